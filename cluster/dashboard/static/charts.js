// A small SVG line-chart drawer for the credit dashboard (no dependencies, no network).
// drawChart(svg, series, opts): series = [{name, points: [[unixSeconds, value], ...]}],
// opts = {start, end, unit, yMin, yMax}. Draws axes with "nice" ticks, one polyline per series and an
// empty-state text. Returns the number of points drawn.
"use strict";

const COLORS = ["#2563eb", "#dc2626", "#059669", "#d97706", "#7c3aed", "#0891b2",
  "#db2777", "#4b5563", "#65a30d", "#9333ea"];
const SVG_NS = "http://www.w3.org/2000/svg";

function el(name, attrs, text) {
  const node = document.createElementNS(SVG_NS, name);
  for (const [k, v] of Object.entries(attrs || {})) node.setAttribute(k, v);
  if (text !== undefined) node.textContent = text;
  return node;
}

function niceStep(span, count) {
  const raw = span / Math.max(1, count);
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const norm = raw / mag;
  const nice = norm <= 1 ? 1 : norm <= 2 ? 2 : norm <= 2.5 ? 2.5 : norm <= 5 ? 5 : 10;
  return nice * mag;
}

function formatValue(v) {
  const a = Math.abs(v);
  if (a === 0) return "0";
  if (a >= 1e9) return (v / 1e9).toFixed(a >= 1e10 ? 0 : 1) + "G";
  if (a >= 1e6) return (v / 1e6).toFixed(a >= 1e7 ? 0 : 1) + "M";
  if (a >= 1e4) return (v / 1e3).toFixed(a >= 1e5 ? 0 : 1) + "k";
  if (a >= 100) return v.toFixed(0);
  if (a >= 1) return String(Number(v.toFixed(a >= 10 ? 1 : 2)));  // 5, 2.5, 12.3
  if (a >= 0.001) return v.toFixed(3).replace(/0+$/, "").replace(/\.$/, "");
  return v.toExponential(1);
}

function formatClock(t) {
  const d = new Date(t * 1000);
  return d.toTimeString().slice(0, 8);
}

function yRange(series, yMin, yMax) {
  let lo = Infinity, hi = -Infinity;
  for (const s of series) for (const [, v] of s.points) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  if (lo === Infinity) return [0, 1, 0.25];
  // Rates, counts and fractions read best against their natural bounds (0, 1).
  if (yMin !== null && yMin !== undefined) lo = Math.min(lo, yMin);
  if (yMax !== null && yMax !== undefined) hi = Math.max(hi, yMax);
  if (hi === lo) {
    const pad = Math.abs(hi) * 0.1 || 1;
    if (yMin !== null && yMin !== undefined && lo === yMin) hi += pad; else { lo -= pad; hi += pad; }
  }
  const step = niceStep(hi - lo, 4);
  return [Math.floor(lo / step) * step, Math.ceil(hi / step) * step, step];
}

function drawChart(svg, series, opts) {
  while (svg.firstChild) svg.removeChild(svg.firstChild);
  const W = svg.clientWidth || 420, H = svg.clientHeight || 190;
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  const m = {l: 52, r: 10, t: 8, b: 22};
  const pw = W - m.l - m.r, ph = H - m.t - m.b;
  const total = series.reduce((n, s) => n + s.points.length, 0);
  svg.appendChild(el("line", {x1: m.l, y1: m.t + ph, x2: m.l + pw, y2: m.t + ph, class: "axis"}));
  if (total === 0) {
    svg.appendChild(el("text", {x: m.l + pw / 2, y: m.t + ph / 2, "text-anchor": "middle",
      class: "empty"}, "no data yet"));
    return 0;
  }
  const [lo, hi, step] = yRange(series, opts.yMin, opts.yMax);
  // Zoom to the data while they cover less than the window (at least 30 s shown).
  let first = opts.end;
  for (const s of series) if (s.points.length) first = Math.min(first, s.points[0][0]);
  const x0 = Math.max(opts.start, Math.min(first, opts.end - 30));
  const x = t => m.l + ((t - x0) / (opts.end - x0)) * pw;
  const y = v => m.t + ph - ((v - lo) / (hi - lo)) * ph;
  for (let v = lo; v <= hi + step / 2; v += step) {
    svg.appendChild(el("line", {x1: m.l, x2: m.l + pw, y1: y(v), y2: y(v), class: "gridline"}));
    svg.appendChild(el("text", {x: m.l - 6, y: y(v) + 4, "text-anchor": "end"}, formatValue(v)));
  }
  const tstep = niceStep(opts.end - x0, 4);
  for (let t = Math.ceil(x0 / tstep) * tstep; t <= opts.end; t += tstep) {
    svg.appendChild(el("text", {x: x(t), y: H - 5, "text-anchor": "middle"}, formatClock(t)));
  }
  series.forEach((s, i) => {
    const color = COLORS[i % COLORS.length];
    const pts = s.points.map(([t, v]) => `${x(t).toFixed(1)},${y(v).toFixed(1)}`).join(" ");
    if (s.points.length === 1) {
      const [t, v] = s.points[0];
      svg.appendChild(el("circle", {cx: x(t), cy: y(v), r: 3, fill: color}));
    } else {
      svg.appendChild(el("polyline", {points: pts, fill: "none", stroke: color,
        "stroke-width": 2, "stroke-linejoin": "round"}));
    }
  });
  return total;
}

window.creditCharts = {drawChart, formatValue, COLORS};
