// The credit dashboard page: builds one card per panel, polls /api/panels and redraws.
// Each card carries data-points / data-series attributes (what the browser test reads).
"use strict";

const grid = document.getElementById("grid");
const rangeSel = document.getElementById("range");
let refreshMs = 2000;
let timer = null;

function card(panel) {
  let node = document.getElementById("panel-" + panel.id);
  if (node) return node;
  node = document.createElement("section");
  node.className = "panel";
  node.id = "panel-" + panel.id;
  node.dataset.panel = panel.id;
  node.innerHTML = `<h2></h2><div class="desc"></div>
    <svg xmlns="http://www.w3.org/2000/svg" role="img"></svg><div class="legend"></div>`;
  node.querySelector("h2").textContent = panel.title;
  const unit = document.createElement("span");
  unit.className = "unit";
  unit.textContent = "(" + panel.unit + ")";
  node.querySelector("h2").appendChild(unit);
  node.querySelector(".desc").textContent = panel.description;
  node.querySelector("svg").setAttribute("aria-label", panel.title + " in " + panel.unit);
  grid.appendChild(node);
  return node;
}

function legend(node, series) {
  const box = node.querySelector(".legend");
  box.innerHTML = "";
  series.forEach((s, i) => {
    const item = document.createElement("span");
    item.className = "item";
    const sw = document.createElement("span");
    sw.className = "swatch";
    sw.style.background = creditCharts.COLORS[i % creditCharts.COLORS.length];
    const last = s.points.length ? s.points[s.points.length - 1][1] : NaN;
    const val = document.createElement("span");
    val.className = "value";
    val.textContent = Number.isFinite(last) ? creditCharts.formatValue(last) : "–";
    item.append(sw, document.createTextNode(s.name), val);
    box.appendChild(item);
  });
}

function render(data) {
  document.getElementById("source").textContent = "source: " + data.source;
  document.getElementById("updated").textContent =
    "updated " + new Date(data.end * 1000).toTimeString().slice(0, 8);
  const errors = document.getElementById("errors");
  errors.hidden = data.errors.length === 0;
  errors.textContent = data.errors.join("\n");
  for (const panel of data.panels) {
    const node = card(panel);
    const n = creditCharts.drawChart(node.querySelector("svg"), panel.series,
      {start: data.start, end: data.end, unit: panel.unit, yMin: panel.y_min, yMax: panel.y_max});
    node.dataset.points = String(n);
    node.dataset.series = String(panel.series.length);
    legend(node, panel.series);
  }
  grid.dataset.loaded = "true";
}

async function tick() {
  clearTimeout(timer);
  try {
    const r = await fetch("/api/panels?range=" + rangeSel.value, {cache: "no-store"});
    if (!r.ok) throw new Error("HTTP " + r.status);
    render(await r.json());
  } catch (e) {
    const errors = document.getElementById("errors");
    errors.hidden = false;
    errors.textContent = "dashboard server unreachable: " + e.message;
  }
  timer = setTimeout(tick, refreshMs);
}

fetch("/api/config").then(r => r.json()).then(c => { refreshMs = c.refresh_s * 1000; })
  .catch(() => {}).finally(tick);
rangeSel.addEventListener("change", () => tick());
