// Shared by the gallery and the tube page: JSON fetches, small DOM helpers, class labels.
"use strict";

async function getJSON(url) {
  const r = await fetch(url);
  let body;
  try { body = await r.json(); } catch (e) { body = { error: `${r.status} ${r.statusText}` }; }
  if (!r.ok) throw new Error(body.error || `${r.status} ${r.statusText}`);
  return body;
}

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v;
    else if (k === "text") e.textContent = v;
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

function fmt(v, digits = 2) {
  if (v === null || v === undefined) return "–";
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toFixed(digits);
  return String(v);
}

// A tube's call (mining/score/call.py) is the API's `call`, one of known, unknown, clutter, unclassified
// for every row (the server reads a row written before the column from its `known`); each call has its
// colour (app.css: .c-<call>). The badge: a known tube's COCO class, else its call.
function classLabel(t) {
  return t.call === "known" ? t.category : t.call;
}

// The number beside the badge: the posterior of the class the badge names (known: P(class), unknown:
// P(unknown)); for clutter the object gate's P(object), which made it clutter; nothing when unclassified.
function probLabel(t) {
  const call = t.call, num = v => v !== null && v !== undefined && Number.isFinite(v);
  if (call === "clutter") return num(t.object_prob) ? `P(object) ${t.object_prob.toFixed(2)}` : "";
  if (call === "unclassified" || !num(t.category_prob)) return "";
  return `P(${call === "known" ? t.category : "unknown"}) ${t.category_prob.toFixed(2)}`;
}

// Labels: the verdicts' names and keys (catalog/labels.py VERDICTS), and the one write.
const VERDICTS = [["object", "object", "o"], ["not_object", "not an object", "n"], ["part_of", "part of another", "p"],
  ["duplicate", "duplicate", "d"]];
const VERDICT_NAME = Object.fromEntries(VERDICTS.map(([v, name]) => [v, name]));

async function postLabels(body) {
  const r = await fetch("/api/labels", { method: "POST", headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body) });
  let answer;
  try { answer = await r.json(); } catch (e) { answer = { error: `${r.status} ${r.statusText}` }; }
  if (!r.ok) throw new Error(answer.error || `${r.status} ${r.statusText}`);
  return answer;
}

function labelChips(t) {
  const box = el("span", { class: "labels" });
  if (t.verdict) box.append(el("span", { class: `verdict v-${t.verdict}`, text: VERDICT_NAME[t.verdict] || t.verdict }));
  for (const tag of t.tags || []) box.append(el("span", { class: "tag", text: tag }));
  return box;
}

function showBanner(text) {
  const b = document.getElementById("banner");
  if (!text) { b.hidden = true; return; }
  b.textContent = text;
  b.hidden = false;
}

function wireCopyButtons() {
  for (const b of document.querySelectorAll("button.copy")) {
    b.addEventListener("click", async () => {
      const text = document.getElementById(b.dataset.copy).textContent;
      try { await navigator.clipboard.writeText(text); b.textContent = "copied"; }
      catch (e) {  // no clipboard (plain http on another host): select the text instead
        const range = document.createRange();
        range.selectNodeContents(document.getElementById(b.dataset.copy));
        const sel = window.getSelection(); sel.removeAllRanges(); sel.addRange(range);
        b.textContent = "selected: press Ctrl-C";
      }
      setTimeout(() => { b.textContent = "copy"; }, 1500);
    });
  }
}
