// The gallery: the address's query is the filter (so a filter can be bookmarked or shared).
// It goes to /api/tubes as it is, every parameter of it, so the page shows exactly what the
// address names, or the server's error saying which parameter it cannot use; the form mirrors
// it, and a change in the form writes a new address. The server filters, sorts and pages; this
// draws the cards.
"use strict";

const RANGES = [
  ["score", "score"], ["score_motion", "motion"], ["score_mask", "mask"],
  ["score_objectness", "objectness"], ["n_frames", "frames"], ["n_observed", "frames seen"],
  ["category_prob", "class prob."], ["object_prob", "P(object)"],
  ["class_evidence", "class evidence"], ["moving_speed_mps", "moving m/s"],
  ["path_length", "path m"],
];
const form = document.getElementById("filters");
const PAGE = 48;  // the page size when the address gives no limit
let request = 0;  // only the latest answer is drawn
let facetsFor = null, facets = null;

function address() { return new URLSearchParams(location.search); }

function buildRanges() {
  const box = document.getElementById("ranges");
  for (const [col, label] of RANGES) {
    const row = el("div", { class: "range" }, el("span", { text: label }),
      el("input", { type: "number", step: "any", name: `min_${col}`, id: `min_${col}`, placeholder: "min" }),
      el("input", { type: "number", step: "any", name: `max_${col}`, id: `max_${col}`, placeholder: "max" }));
    box.append(row);
  }
}

function formToParams() {
  const p = new URLSearchParams();
  const checked = form.querySelector("input[name=set]:checked");
  const set = checked ? checked.value : address().get("set");  // none checked: the address's (bad) value stays
  if (set !== null && set !== "selected") p.set("set", set);
  for (const c of form.querySelectorAll("input[name=call]:checked")) p.append("call", c.value);
  for (const o of document.getElementById("category").selectedOptions) p.append("category", o.value);
  for (const o of document.getElementById("seq").selectedOptions) p.append("seq", o.value);
  for (const c of form.querySelectorAll("input[name=verdict]:checked")) p.append("verdict", c.value);
  for (const o of document.getElementById("tagfilter").selectedOptions) p.append("tag", o.value);
  for (const [col] of RANGES) {
    for (const b of ["min", "max"]) {
      const v = document.getElementById(`${b}_${col}`).value;
      if (v !== "") p.set(`${b}_${col}`, v);
    }
  }
  const sort = document.getElementById("sort").value, order = document.getElementById("order").value;
  if (sort !== "score") p.set("sort", sort);
  if (order !== "desc") p.set("order", order);
  for (const g of address().getAll("group")) p.append("group", g);  // a group chosen on /groups stays
  const limit = address().get("limit");  // the page size the address chose stays
  if (limit !== null) p.set("limit", limit);
  return p;
}

// Select ``value`` in ``select``, adding it when the form does not offer it (the server judges it).
function choose(select, value) {
  if (![...select.options].some(o => o.value === value)) select.append(el("option", { value, text: value }));
  select.value = value;
}

function paramsToForm(p) {
  const set = p.get("set") || "selected";
  for (const r of form.querySelectorAll("input[name=set]")) r.checked = r.value === set;
  const calls = p.getAll("call");
  for (const c of form.querySelectorAll("input[name=call]")) c.checked = calls.includes(c.value);
  const verdicts = p.getAll("verdict");
  for (const c of form.querySelectorAll("input[name=verdict]")) c.checked = verdicts.includes(c.value);
  for (const [col] of RANGES) {
    for (const b of ["min", "max"]) document.getElementById(`${b}_${col}`).value = p.get(`${b}_${col}`) || "";
  }
  choose(document.getElementById("sort"), p.get("sort") || "score");
  choose(document.getElementById("order"), p.get("order") || "desc");
  if (facets) fillSelects(p);
}

function fillSelect(select, items, wanted) {
  select.replaceChildren();
  for (const [value, text] of items) {
    const o = el("option", { value, text });
    o.selected = wanted.includes(value);
    select.append(o);
  }
  // Keep a wanted value the facets do not list (e.g. from a shared link), so the filter shows.
  for (const w of wanted) {
    if (!items.some(([v]) => v === w)) select.append(Object.assign(el("option", { value: w, text: `${w} (0)` }), { selected: true }));
  }
}

// The category and sequence lists: the facets' values, the address's chosen.
function fillSelects(p) {
  const cats = document.getElementById("category");
  fillSelect(cats, facets.categories.map(c => [c.category, `${c.category} (${c.n})`]), p.getAll("category"));
  if (!cats.options.length) cats.append(el("option", { disabled: "", text: "none: no tube is classified" }));
  fillSelect(document.getElementById("seq"), facets.sequences.map(s => [`${s.dataset}/${s.sequence}`, `${s.dataset}/${s.sequence} (${s.n})`]), p.getAll("seq"));
  const tags = document.getElementById("tagfilter");
  fillSelect(tags, facets.tags.map(t => [t.tag, `${t.tag} (${t.n})`]), p.getAll("tag"));
  if (!tags.options.length) tags.append(el("option", { disabled: "", text: "no tags yet" }));
  document.getElementById("tag-list").replaceChildren(...facets.tags.map(t => el("option", { value: t.tag })));
}

async function loadFacets(p) {
  const set = p.get("set") || "selected";
  if (facetsFor !== set) {
    facets = await getJSON(`/api/facets?set=${encodeURIComponent(set)}`);
    facetsFor = set;
  }
  const f = facets;
  document.getElementById("catalogue").textContent = f.catalogue;
  document.getElementById("totals").textContent = `${f.selected} selected of ${f.tubes} candidate tubes`;
  for (const s of document.querySelectorAll("span.n[data-call]")) s.textContent = `(${f.calls[s.dataset.call] || 0})`;
  for (const s of document.querySelectorAll("span.n[data-verdict]")) s.textContent = `(${f.verdicts[s.dataset.verdict] || 0})`;
  document.getElementById("author").textContent = `· you label as ${f.author}`;
  fillSelects(p);
  for (const [col] of RANGES) {
    const [lo, hi] = f.ranges[col] || [null, null];
    // The catalogue's range as the hint, rounded outwards so typing it back keeps every tube.
    if (lo !== null) document.getElementById(`min_${col}`).placeholder = String(Math.floor(lo * 100) / 100);
    if (hi !== null) document.getElementById(`max_${col}`).placeholder = String(Math.ceil(hi * 100) / 100);
  }
}

function facetsNote() {
  if (facets && facets.tubes === 0) return "This catalogue has no tubes yet (is a job still running? `mine status` says).";
  return facets && facets.frames_unavailable ? `Pictures are placeholders: ${facets.frames_unavailable}` : "";
}

function card(t, back) {
  const id = encodeURIComponent(t.tube_id);
  const img = el("img", { src: `/img/thumb?id=${id}`, alt: `tube ${t.tube_id}`, width: "240", height: "180", loading: "lazy" });
  const badge = el("span", { class: `badge c-${t.call}`, text: classLabel(t) });
  const moving = t.moving_speed_mps === null || t.moving_speed_mps === undefined ? "" : ` · moving ${fmt(t.moving_speed_mps, 1)} m/s`;
  const a = el("a", { class: "card", href: `/tube?id=${id}&back=${encodeURIComponent(back)}`, "data-tube": t.tube_id },
    img,
    el("div", { class: "card-head" }, badge, el("span", { class: "muted prob-text", text: probLabel(t) }),
      el("span", { class: "score", title: "score (see the tube page for its terms)", text: fmt(t.score, 1) })),
    el("div", { class: "card-id", text: t.tube_id }),
    el("div", { class: "card-facts muted",
      text: `${t.n_frames} frames (${t.n_observed} seen) · ${t.frame_start}–${t.frame_end}${moving}` }),
    t.selected ? "" : el("div", { class: "card-facts unselected-note", text: "candidate, not selected" }));
  const pick = el("input", { type: "checkbox", class: "pick", title: "pick for labelling (x)", "aria-label": `pick tube ${t.tube_id}` });
  const cell = el("div", { class: `cell${t.selected ? "" : " unselected"}`, "data-id": t.tube_id }, a, pick, labelChips(t));
  pick.addEventListener("change", () => { cell.classList.toggle("picked", pick.checked); pickedChanged(); });
  return cell;
}

// ------------------------------------------------------------------ labelling: selection, keys, the one write

let cursor = -1;  // the focused cell (keys act on it when nothing is selected)
function cells() { return [...document.querySelectorAll("#grid .cell")]; }
function picked() { return cells().filter(c => c.querySelector(".pick").checked); }

function pickedChanged() {
  const n = picked().length;
  document.getElementById("picked").textContent = n ? `${n} picked` : (cursor >= 0 ? "1 focused" : "none picked");
}

function focusCell(k) {
  const all = cells();
  if (!all.length) return;
  cursor = Math.max(0, Math.min(all.length - 1, k));
  all.forEach((c, i) => c.classList.toggle("focused", i === cursor));
  all[cursor].scrollIntoView({ block: "nearest" });
  pickedChanged();
}

function columns() {
  const all = cells();
  if (!all.length) return 1;
  const top = all[0].offsetTop;
  return Math.max(1, all.filter(c => c.offsetTop === top).length);
}

function targets() {
  const chosen = picked();
  if (chosen.length) return chosen;
  const all = cells();
  return cursor >= 0 && cursor < all.length ? [all[cursor]] : [];
}

async function applyLabel(body) {
  const chosen = targets();
  const status = document.getElementById("label-status");
  if (!chosen.length) { status.textContent = "pick tubes first (their boxes, or x / a)"; return; }
  body.tubes = chosen.map(c => c.dataset.id);
  try {
    const answer = await postLabels(body);
    const byId = new Map(answer.labelled.map(r => [r.tube_id, r]));
    for (const c of cells()) {
      const r = byId.get(c.dataset.id);
      if (r) c.querySelector(".labels").replaceWith(labelChips(r));
    }
    status.textContent = `${answer.labelled.length} labelled`;
    if (body.tag) document.getElementById("tag").value = "";  // the next tag starts afresh (not joined onto this one)
    facetsFor = null;  // the counts changed
    await loadFacets(address());
    document.body.dataset.labelled = String(Number(document.body.dataset.labelled || 0) + 1);
  } catch (e) {
    status.textContent = `not labelled: ${e.message}`;
    document.body.dataset.labelError = e.message;
  }
}

function tagValue() { return document.getElementById("tag").value.trim(); }

function wireLabelling() {
  const bar = document.getElementById("verdicts");
  for (const [v, name, key] of VERDICTS) {
    const b = el("button", { type: "button", "data-verdict": v, title: `${name} (${key})` }, name + " ", el("kbd", { text: key }));
    b.addEventListener("click", () => applyLabel({ verdict: v }));
    bar.append(b);
  }
  document.getElementById("clear-verdict").addEventListener("click", () => applyLabel({ verdict: null }));
  document.getElementById("add-tag").addEventListener("click", () => { if (tagValue()) applyLabel({ tag: tagValue() }); });
  document.getElementById("remove-tag").addEventListener("click", () => { if (tagValue()) applyLabel({ untag: tagValue() }); });
  document.getElementById("tag").addEventListener("keydown", e => {
    if (e.key === "Enter") { e.preventDefault(); if (tagValue()) applyLabel({ tag: tagValue() }); e.target.blur(); }
    else if (e.key === "Escape") e.target.blur();
    e.stopPropagation();
  });
  const keyed = Object.fromEntries(VERDICTS.map(([v, , key]) => [key, v]));
  document.addEventListener("keydown", e => {
    if (e.ctrlKey || e.metaKey || e.altKey) return;
    const t = e.target;
    if (t.tagName === "INPUT" && t.type !== "checkbox" || t.tagName === "SELECT" || t.tagName === "TEXTAREA") return;
    const all = cells();
    let handled = true;
    if (e.key === "ArrowRight") focusCell(cursor + 1);
    else if (e.key === "ArrowLeft") focusCell(cursor - 1);
    else if (e.key === "ArrowDown") focusCell(cursor < 0 ? 0 : cursor + columns());
    else if (e.key === "ArrowUp") focusCell(cursor - columns());
    else if (e.key === "x" || e.key === " ") {
      if (cursor < 0) focusCell(0);
      const box = all[cursor] && all[cursor].querySelector(".pick");
      if (box) { box.checked = !box.checked; box.dispatchEvent(new Event("change")); }
    }
    else if (e.key === "a") { for (const c of all) { const b = c.querySelector(".pick"); b.checked = true; c.classList.add("picked"); } pickedChanged(); }
    else if (e.key === "Escape") { for (const c of all) { c.querySelector(".pick").checked = false; c.classList.remove("picked"); } pickedChanged(); }
    else if (keyed[e.key]) applyLabel({ verdict: keyed[e.key] });
    else if (e.key === "u") applyLabel({ verdict: null });
    else if (e.key === "t") document.getElementById("tag").focus();
    else if (e.key === "Enter" && cursor >= 0 && all[cursor]) location.href = all[cursor].querySelector("a.card").href;
    else handled = false;
    if (handled) e.preventDefault();
  });
}

async function load() {
  const mine = ++request;
  document.body.dataset.state = "loading";
  const p = address();
  try {
    await loadFacets(p);
    const api = new URLSearchParams(p);  // every parameter of the address, so the server judges each
    if (!api.has("limit")) api.set("limit", PAGE);
    const page = await getJSON(`/api/tubes?${api}`);
    if (mine !== request) return;
    const size = page.limit, offset = page.offset;
    showBanner(facetsNote());
    document.getElementById("count").textContent = page.total;
    const pages = Math.max(1, Math.ceil(page.total / size));
    document.getElementById("pageinfo").textContent = page.total > size ? ` · page ${Math.floor(offset / size) + 1} of ${pages}` : "";
    const back = location.search;
    document.getElementById("grid").replaceChildren(...page.tubes.map(t => card(t, back)));
    cursor = -1;
    pickedChanged();
    if (!page.tubes.length) document.getElementById("grid").append(el("p", { class: "muted", text: "No tube matches this filter." }));
    document.getElementById("prev").disabled = offset <= 0;
    document.getElementById("next").disabled = offset + size >= page.total;
    document.getElementById("export").textContent = page.export_command;
    document.body.dataset.total = page.total;
    document.body.dataset.state = "ready";
  } catch (e) {
    if (mine !== request) return;
    // Nothing of another filter stays on screen: no cards, no count, no export line.
    showBanner(`Error: ${e.message}`);
    document.getElementById("count").textContent = "–";
    document.getElementById("pageinfo").textContent = "";
    document.getElementById("grid").replaceChildren(el("p", { class: "muted", text: "The address's filter cannot be used (see above); change it in the form or reset." }));
    document.getElementById("prev").disabled = document.getElementById("next").disabled = true;
    document.getElementById("export").textContent = "";
    document.body.dataset.total = "";
    document.body.dataset.state = "error";
  }
}

function pageSize() { return Number(address().get("limit")) || PAGE; }

function setOffset(offset) {
  const p = address();
  if (offset > 0) p.set("offset", offset); else p.delete("offset");
  history.pushState(null, "", `/?${p}`);
  load();
}

let typing = null;
function changed() {  // a filter changed: the URL says so, and the page starts at the first tube
  const p = formToParams();
  history.replaceState(null, "", p.toString() ? `/?${p}` : "/");
  load();
}

buildRanges();
paramsToForm(address());
form.addEventListener("change", changed);
form.addEventListener("input", e => {
  if (e.target.type !== "number") return;
  clearTimeout(typing);
  typing = setTimeout(changed, 500);
});
form.addEventListener("submit", e => { e.preventDefault(); changed(); });
document.getElementById("reset").addEventListener("click", () => { history.pushState(null, "", "/"); paramsToForm(new URLSearchParams()); facetsFor = null; load(); });
document.getElementById("prev").addEventListener("click", () => setOffset(Math.max(0, Number(address().get("offset") || 0) - pageSize())));
document.getElementById("next").addEventListener("click", () => setOffset(Number(address().get("offset") || 0) + pageSize()));
window.addEventListener("popstate", () => { paramsToForm(address()); facetsFor = null; load(); });
wireCopyButtons();
wireLabelling();
load();
