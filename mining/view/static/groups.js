// The groups page: one tile per group of the unknown set (/api/groups), each opening the gallery
// on that group's tubes (?group=G: the unknown set is selected tubes, the gallery's default set).
"use strict";

function tile(g) {
  const id = encodeURIComponent(g.exemplar);
  const noise = g.group < 0;
  const a = el("a", { class: "card", href: `/?group=${g.group}`, "data-group": String(g.group) },
    el("img", { src: `/img/thumb?id=${id}`, alt: `group ${g.group}: tube ${g.exemplar}`, width: "240", height: "180",
      loading: "lazy" }),
    el("div", { class: "card-head" }, el("span", { class: `badge c-${g.call}`, text: noise ? "in no group" : `group ${g.group}` }),
      el("span", { class: "score", text: `${g.size} tubes` })),
    el("div", { class: "card-facts muted", text: noise ? "the tubes HDBSCAN left out of every group"
      : `spread ${g.spread.toFixed(3)} · exemplar ${g.exemplar}` }));
  return a;
}

async function main() {
  let d;
  try { d = await getJSON("/api/groups"); }
  catch (e) { showBanner(`Error: ${e.message}`); document.body.dataset.state = "error"; return; }
  if (d.note) showBanner(d.note);
  const grouped = d.groups.filter(g => g.group >= 0).length;
  document.getElementById("totals").textContent = `${grouped} groups · ${d.tubes} unknown tubes`;
  document.getElementById("groups").replaceChildren(...d.groups.map(tile));
  document.body.dataset.state = "ready";
}

main();
