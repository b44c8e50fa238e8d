// A tube page: the player (its frames with the mask on the full frame; play/pause, ←/→),
// the strip of all its frames, the score components, the class posterior's top entries,
// and the bird's-eye track (world x/z of the tube and of the camera) as SVG.
"use strict";

const params = new URLSearchParams(location.search);
const tubeId = params.get("id");
const FPS = 10;  // KITTI's frame rate; the player shows frames, not real time
const PRELOAD = 4;  // frames fetched ahead while playing
const SVG_NS = "http://www.w3.org/2000/svg";
let frames = [], current = 0, timer = null, marker = null, toSvg = null, follow = false, zoom = 1;
const FOLLOW_CONTEXT = 0.6;  // the crop around the object: its box plus this fraction on each side
const MAX_ZOOM = 8;
const AUTO_FOLLOW_AREA = 0.01;  // a box under 1 % of the frame opens followed
const cache = new Map();

function frameUrl(f, size) { return `/img/frame?id=${encodeURIComponent(tubeId)}&frame=${f.frame}&size=${size}`; }

function preload(k) {
  if (k < 0 || k >= frames.length || cache.has(k)) return;
  const img = new Image();
  img.src = frameUrl(frames[k], "full");
  cache.set(k, img);
}

function show(k) {
  if (!frames.length) return;
  current = (k + frames.length) % frames.length;
  const f = frames[current];
  document.getElementById("frame").src = frameUrl(f, "full");
  place();
  document.getElementById("scrub").value = current;
  document.getElementById("frame-label").textContent =
    `frame ${f.frame} (${current + 1} of ${frames.length}) · ${f.observed ? "observed" : "predicted (gap)"}` +
    (f.objectness === null ? "" : ` · objectness ${fmt(f.objectness)}`) +
    (f.mask_iou === null ? "" : ` · mask IoU ${fmt(f.mask_iou)}`);
  for (const [i, t] of document.querySelectorAll("#strip img").entries()) t.classList.toggle("current", i === current);
  const strip = document.querySelectorAll("#strip img")[current];
  if (strip) strip.scrollIntoView({ block: "nearest", inline: "nearest" });
  if (marker && toSvg) {
    const [x, y] = toSvg(f.position_world);
    marker.setAttribute("cx", x); marker.setAttribute("cy", y);
  }
  for (let d = 1; d <= PRELOAD; d++) preload(current + d);
}

// Follow the object: scale and shift the full frame so that its box (with context) fills the view.
function place() {
  const img = document.getElementById("frame"), f = frames[current];
  if (!follow || !f || !f.bbox) { img.style.transform = ""; return; }
  const W = f.rle_w, H = f.rle_h, [x1, y1, x2, y2] = f.bbox;
  const d = img.clientWidth / W;  // displayed pixels per image pixel
  let cw = Math.max((x2 - x1) * (1 + 2 * FOLLOW_CONTEXT), (y2 - y1) * (1 + 2 * FOLLOW_CONTEXT) * W / H, W / MAX_ZOOM) / zoom;
  cw = Math.min(W, Math.max(W / MAX_ZOOM, cw));
  const ch = cw * H / W, s = W / cw;
  const x0 = Math.min(W - cw, Math.max(0, (x1 + x2) / 2 - cw / 2)), y0 = Math.min(H - ch, Math.max(0, (y1 + y2) / 2 - ch / 2));
  img.style.transform = `scale(${s.toFixed(3)}) translate(${(-x0 * d).toFixed(1)}px, ${(-y0 * d).toFixed(1)}px)`;
  document.body.dataset.zoom = s.toFixed(2);
}

function setFollow(on) {
  follow = on;
  const b = document.getElementById("follow");
  b.setAttribute("aria-pressed", String(on));
  b.classList.toggle("on", on);
  if (!on) document.body.dataset.zoom = "1";
  place();
}

function play(on) {
  const button = document.getElementById("play");
  if (on === undefined) on = timer === null;
  clearInterval(timer); timer = null;
  if (on) {
    timer = setInterval(() => {
      const next = cache.get((current + 1) % frames.length);
      if (next && !next.complete) return;  // wait for the next frame rather than skip it
      show(current + 1);
    }, 1000 / FPS);
  }
  button.textContent = on ? "❚❚ pause" : "▶ play";
}

function rows(table, items) {
  table.replaceChildren(...items.map(([k, v]) => el("tr", {}, el("th", { text: k }), el("td", { text: v }))));
}

function bar(name, p) {
  const w = Math.max(0, Math.min(1, p || 0)) * 100;
  return el("div", { class: "prob" }, el("span", { class: "prob-name", text: name }),
    el("span", { class: "prob-bar" }, el("span", { style: `width:${w.toFixed(1)}%` })),
    el("span", { class: "prob-val", text: (p || 0).toFixed(3) }));
}

function svg(tag, attrs) {
  const e = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  return e;
}

function drawTrack(tubeFrames, ego, call) {
  const box = document.getElementById("track");
  box.replaceChildren();
  const pts = tubeFrames.map(f => f.position_world).filter(p => p);
  const cam = ego.map(e => [e.x, e.y, e.z]);
  const all = pts.concat(cam);
  if (!all.length) return;
  const size = 320, pad = 24;
  let x0 = Math.min(...all.map(p => p[0])), x1 = Math.max(...all.map(p => p[0]));
  let z0 = Math.min(...all.map(p => p[2])), z1 = Math.max(...all.map(p => p[2]));
  const span = Math.max(x1 - x0, z1 - z0, 4);  // at least 4 m across, equal scale on both axes
  const cx = (x0 + x1) / 2, cz = (z0 + z1) / 2;
  const s = (size - 2 * pad) / span;
  toSvg = p => [(size / 2 + (p[0] - cx) * s).toFixed(1), (size / 2 - (p[2] - cz) * s).toFixed(1)];  // forward (z) up
  // Grid every 1, 2, 5, 10, … metres: about five lines across.
  const step = [1, 2, 5, 10, 20, 50, 100, 200, 500].find(g => span / g <= 6) || 1000;
  for (let g = Math.ceil((cx - span / 2) / step) * step; g <= cx + span / 2; g += step) {
    const [x] = toSvg([g, 0, cz]);
    box.append(svg("line", { x1: x, y1: 0, x2: x, y2: size, class: "grid" }));
  }
  for (let g = Math.ceil((cz - span / 2) / step) * step; g <= cz + span / 2; g += step) {
    const [, y] = toSvg([cx, 0, g]);
    box.append(svg("line", { x1: 0, y1: y, x2: size, y2: y, class: "grid" }));
  }
  const label = svg("text", { x: 4, y: size - 6, class: "grid-label" });
  label.textContent = `grid ${step} m`;
  box.append(label);
  if (cam.length) {
    box.append(svg("polyline", { points: cam.map(p => toSvg(p).join(",")).join(" "), class: "ego" }));
    const [ex, ey] = toSvg(cam[cam.length - 1]);
    box.append(svg("circle", { cx: ex, cy: ey, r: 3, class: "ego-end" }));
  }
  box.append(svg("polyline", { points: pts.map(p => toSvg(p).join(",")).join(" "), class: `tube c-${call}` }));
  for (const f of tubeFrames) {
    const [x, y] = toSvg(f.position_world);
    box.append(svg("circle", { cx: x, cy: y, r: f.observed ? 2.2 : 1.4, class: f.observed ? "obs" : "gap" }));
  }
  marker = svg("circle", { cx: 0, cy: 0, r: 5, class: "now" });
  box.append(marker);
}

// Motion only where it exceeds its own uncertainty (stereo noise at the tube's depth: speed_sigma_mps).
function motionText(t) {
  if (t.moving_speed_mps !== null && t.moving_speed_mps !== undefined)
    return `moving ${fmt(t.moving_speed_mps, 1)} ± ${fmt(t.speed_sigma_mps, 1)} m/s · path ${fmt(t.path_length, 1)} ± ${fmt(t.path_sigma_m, 1)} m`;
  if (t.speed_sigma_mps === null || t.speed_sigma_mps === undefined) return "not measurable (under 3 observations)";
  return `static: ${fmt(t.speed, 1)} m/s is within 3 × its ±${fmt(t.speed_sigma_mps, 1)} m/s noise`;
}

function showLabels(r) {
  document.getElementById("tube-labels").replaceChildren(labelChips(r),
    el("span", { class: "muted small", text: r.labelled_by ? ` by ${r.labelled_by}` : " none yet" }));
}

async function label(body) {
  body.tubes = [tubeId];
  try {
    const answer = await postLabels(body);
    showLabels(answer.labelled[0]);
    document.getElementById("label-status").textContent = "saved";
    if (body.tag) document.getElementById("tag").value = "";  // the next tag starts afresh (not joined onto this one)
    document.body.dataset.labelled = String(Number(document.body.dataset.labelled || 0) + 1);
  } catch (e) { document.getElementById("label-status").textContent = `not saved: ${e.message}`; }
}

function wireLabels() {
  const box = document.getElementById("label-buttons");
  for (const [v, name, key] of VERDICTS) {
    const b = el("button", { type: "button", title: `${name} (${key})` }, name + " ", el("kbd", { text: key }));
    b.addEventListener("click", () => label({ verdict: v }));
    box.append(b);
  }
  const clear = el("button", { type: "button", title: "take the verdict back (u)" }, "no verdict ", el("kbd", { text: "u" }));
  clear.addEventListener("click", () => label({ verdict: null }));
  box.append(clear);
  const tag = document.getElementById("tag");
  document.getElementById("add-tag").addEventListener("click", () => { if (tag.value.trim()) label({ tag: tag.value.trim() }); });
  document.getElementById("remove-tag").addEventListener("click", () => { if (tag.value.trim()) label({ untag: tag.value.trim() }); });
  tag.addEventListener("keydown", e => {
    if (e.key === "Enter" && tag.value.trim()) { label({ tag: tag.value.trim() }); tag.blur(); }
    else if (e.key === "Escape") tag.blur();
    e.stopPropagation();
  });
}

// The nearest tubes by descriptor (`mine describe` made them) or by image embedding (`mine embed`),
// each a thumbnail linking to its page.
function showSimilar(similar, note, id = "similar") {
  const box = document.getElementById(id);
  if (!similar.length) { box.replaceChildren(el("p", { class: "muted small", text: note || "No other tube." })); return; }
  box.replaceChildren(...similar.map(s => {
    const a = el("a", { href: `/tube?id=${encodeURIComponent(s.tube_id)}`, title: s.tube_id, class: `c-${s.call}` });
    a.append(el("img", { src: `/img/thumb?id=${encodeURIComponent(s.tube_id)}`, alt: `tube ${s.tube_id}`, width: "120",
      height: "90", loading: "lazy" }), el("span", { class: "small", text: `${s.category || s.call} · ${s.distance.toFixed(3)}` }));
    return a;
  }));
}

async function main() {
  const back = params.get("back");
  if (back && back.startsWith("?")) document.getElementById("back").href = `/${back}`;
  if (!tubeId) { showBanner("No tube id in the address (?id=…)."); document.body.dataset.state = "error"; return; }
  let d;
  const asked = params.get("frame");
  try { d = await getJSON(`/api/tube?id=${encodeURIComponent(tubeId)}` + (asked ? `&frame=${encodeURIComponent(asked)}` : "")); }
  catch (e) { showBanner(`Error: ${e.message}`); document.body.dataset.state = "error"; return; }
  const t = d.tube;
  frames = d.frames;
  document.title = `Tube Miner · ${t.tube_id}`;
  document.getElementById("title").textContent = t.tube_id;
  const badge = document.getElementById("badge");
  badge.textContent = classLabel(t) + (t.selected ? "" : " · candidate, not selected");
  showLabels(t);
  wireLabels();
  badge.classList.add(`c-${t.call}`);
  if (d.frames_unavailable) showBanner(`Pictures are placeholders: ${d.frames_unavailable}`);
  document.getElementById("score-model").textContent = `score: ${d.score_model}`;
  const scoreRows = [["score", fmt(t.score, 2)]];
  if (t.score_model === "calibrated") {
    for (const g of ["prior", "motion", "mask", "objectness", "shape", "class"]) scoreRows.push([`  θ ${g}`, fmt(t[`theta_${g}`], 2)]);
    scoreRows.push(["REFERENCE terms", "(not in this score)"]);
  }
  scoreRows.push(["motion LLR", fmt(t.score_motion, 1)], ["mask LLR", fmt(t.score_mask, 1)],
    ["objectness LLR", fmt(t.score_objectness, 1)], ["selected", t.selected ? "yes" : "no: a candidate co-selection did not choose"]);
  rows(document.getElementById("scores"), scoreRows);
  rows(document.getElementById("class"), [
    ["call", t.call + (t.call_from_known ? " (read from known: written before the call column)" : "")],
    ["category", fmt(t.category)],
    [t.call === "unclassified" ? "probability" : `P(${t.call === "known" ? t.category : "unknown"})`,
      t.category_prob === null ? "–" : t.category_prob.toFixed(3)],
    ["P(object)", t.object_prob === null ? "– (not judged by the object gate)" : t.object_prob.toFixed(3)],
    ["best COCO class", fmt(t.best_known)], ["classified frames", fmt(t.classified_frames)],
    ["evidence", fmt(t.class_evidence, 2)]]);
  document.getElementById("class-rule").textContent = d.class_rule.text;
  const top = document.getElementById("top-classes");
  top.replaceChildren(...d.top_classes.map(c => bar(c.name, c.p)));
  if (!d.top_classes.length) top.append(el("p", { class: "muted", text: "No classifier looked at this tube." }));
  rows(document.getElementById("facts"), [
    ["sequence", `${t.dataset}/${t.sequence}`], ["frames", `${t.frame_start}–${t.frame_end} (${t.n_frames}, ${t.n_observed} observed)`],
    ["size (w, h, l)", (t.size || []).map(v => fmt(v, 2)).join(" × ") + " m"],
    ["motion", motionText(t)], ["segment", fmt(t.segment)], ["windows stitched", fmt(t.n_windows)]]);
  document.getElementById("export").textContent = d.export_command;
  drawTrack(frames, d.ego, t.call);
  showSimilar(d.similar, d.similar_note);
  if (d.similar_looks.length || d.similar_looks_note) {  // no strip where nothing was embedded
    document.getElementById("similar-looks-box").hidden = false;
    document.getElementById("similar-looks-model").textContent = d.similar_looks_model || "mine embed";
    showSimilar(d.similar_looks, d.similar_looks_note, "similar-looks");
  }
  document.querySelector(".swatch.tube").classList.add(`c-${t.call}`);

  const strip = document.getElementById("strip");
  strip.replaceChildren(...frames.map((f, k) => {
    // Sized before it loads, so the lazy strip lays out (and scrolls to the current frame) at once.
    const img = el("img", { src: frameUrl(f, "strip"), alt: `frame ${f.frame}`, title: `frame ${f.frame}`, loading: "lazy",
      class: f.observed ? "" : "gap", height: "64", width: String(Math.round(64 * f.rle_w / Math.max(1, f.rle_h))) });
    img.addEventListener("click", () => { play(false); show(k); });
    return img;
  }));
  const scrub = document.getElementById("scrub");
  scrub.max = Math.max(0, frames.length - 1);
  scrub.addEventListener("input", () => { play(false); show(Number(scrub.value)); });
  document.getElementById("play").addEventListener("click", () => play());
  document.getElementById("step-back").addEventListener("click", () => { play(false); show(current - 1); });
  document.getElementById("step-fwd").addEventListener("click", () => { play(false); show(current + 1); });
  document.getElementById("follow").addEventListener("click", () => setFollow(!follow));
  document.getElementById("zoom-in").addEventListener("click", () => { zoom = Math.min(4, zoom * 1.5); if (!follow) setFollow(true); else place(); });
  document.getElementById("zoom-out").addEventListener("click", () => { zoom = Math.max(0.25, zoom / 1.5); place(); });
  document.getElementById("frame").addEventListener("load", place);
  window.addEventListener("resize", place);
  const keyed = Object.fromEntries(VERDICTS.map(([v, , key]) => [key, v]));
  document.addEventListener("keydown", e => {
    if (e.target.tagName === "INPUT" && e.target.type !== "range") return;
    if (e.key === "ArrowRight") { play(false); show(current + 1); e.preventDefault(); }
    else if (e.key === "ArrowLeft") { play(false); show(current - 1); e.preventDefault(); }
    else if (e.key === " ") { play(); e.preventDefault(); }
    else if (e.key === "f") setFollow(!follow);
    else if (e.key === "+" || e.key === "=") { zoom = Math.min(4, zoom * 1.5); if (!follow) setFollow(true); else place(); }
    else if (e.key === "-") { zoom = Math.max(0.25, zoom / 1.5); place(); }
    else if (keyed[e.key]) label({ verdict: keyed[e.key] });
    else if (e.key === "u") label({ verdict: null });
    else if (e.key === "t") { document.getElementById("tag").focus(); e.preventDefault(); }
  });
  wireCopyButtons();
  const start = frames.findIndex(f => f.frame === d.start_frame);
  // A small object (a speck on the full frame) opens followed: cropped to it, `f` shows the whole frame.
  const first = frames[start < 0 ? 0 : start];
  if (first && first.bbox && (first.bbox[2] - first.bbox[0]) * (first.bbox[3] - first.bbox[1]) < AUTO_FOLLOW_AREA * first.rle_w * first.rle_h) setFollow(true);
  else document.body.dataset.zoom = "1";
  show(start < 0 ? 0 : start);
  document.body.dataset.state = "ready";
}

main();
