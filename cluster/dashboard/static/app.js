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

function clock(t) {
  return new Date(t * 1000).toTimeString().slice(0, 8);
}

function fixed(v, digits) {
  return v === null || v === undefined ? "–" : Number(v).toFixed(digits);
}

// The run's end, in words: finished (its summary's final numbers) or stopped.
function runBanner(run) {
  const box = document.getElementById("run");
  const ended = run && run.ended;
  box.hidden = !ended;
  box.dataset.state = ended ? ended.state : "running";
  if (!ended) return;
  if (ended.state === "finished") {
    const s = ended.summary;
    box.textContent = `Run finished at ${clock(ended.finished_at)}: ${s.algo} on ${s.env}, ` +
      `${Number(s.t_env).toLocaleString("en")} env steps in ${fixed(s.wall_s, 0)} s. ` +
      `Final test win rate ${fixed(s.final_test_won_mean, 2)}, ` +
      `test return ${fixed(s.final_test_return_mean, 2)}. The charts end at its last scrape.`;
  } else {
    box.textContent = `The run's exporters stopped answering at ${clock(ended.last_seen)} ` +
      "and it wrote no summary.json: it was stopped or it crashed. " +
      "The charts end at its last scrape.";
  }
}

function render(data) {
  document.getElementById("source").textContent = "source: " + data.source;
  document.getElementById("updated").textContent = "updated " + clock(data.end);
  const errors = document.getElementById("errors");
  errors.hidden = data.errors.length === 0;
  errors.textContent = data.errors.join("\n");
  runBanner(data.run);
  const shown = new Set(data.panels.map(p => p.id));
  for (const node of grid.querySelectorAll(".panel")) {
    if (!shown.has(node.dataset.panel)) node.remove();  // not this run's algorithm
  }
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
