// Charts of pressures, cylinder forces, payload and joint loads, linked to the one time cursor.
// Long ranges come from min/max buckets (/history): each series is a min-max band plus its mean.
// Plotly (served locally from the plotly Python package) is the global `Plotly`.
import { bucketGap } from "./timeline.js";

const PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#17becf", "#e377c2"];

// Every channel the charts can show: raw ones of the machine description (pressures, rod
// positions, angles, drive torques) and the twin worker's derived ones (cylinder forces, payload,
// joint reaction moments, joint torques). {name, label, kind, title, scale, live}: `kind` groups
// channels sharing a chart (one unit), `live` says whether the live stream carries it.
const KINDS = {
  pressure: { title: "Pressure [bar]", scale: 1e-5 },
  position: { title: "Rod position [mm]", scale: 1e3 },
  angle: { title: "Angle [°]", scale: 180 / Math.PI },
  drive: { title: "Drive torque [kN·m]", scale: 1e-3 },
  force: { title: "Cylinder force [kN]", scale: 1e-3 },
  payload: { title: "Payload [kg]", scale: 1 },
  moment: { title: "Joint reaction moment [kN·m]", scale: 1e-3 },
  torque: { title: "Joint torque [kN·m]", scale: 1e-3 },
  torqueP: { title: "Joint force (prismatic) [kN]", scale: 1e-3 },
};
export const DEFAULT_KINDS = ["pressure", "force", "payload", "moment", "torque"];

export function channelCatalog(model) {
  const out = [];
  const add = (name, label, kind, live) => out.push({ name, label, kind, live, ...KINDS[kind] });
  const raw = { pressure_a: "pressure", pressure_b: "pressure", position: "position", angle: "angle", torque: "drive" };
  for (const c of model.channels || []) {
    const kind = raw[c.quantity];
    if (kind) add(c.name, c.name, kind, kind === "pressure");
  }
  for (const c of model.cylinders || []) add(`force:${c.name}`, c.name, "force", true);
  add("payload", "payload", "payload", true);
  for (const j of model.joints || []) if (j.kind === "revolute") add(`moment:${j.name}`, j.name, "moment", false);
  for (const j of model.joints || []) add(`torque:${j.name}`, j.name, j.kind === "revolute" ? "torque" : "torqueP", true);
  return out;
}

// Chart groups (one chart per kind, in catalogue order) of the selected channel names.
export function chartGroups(catalog, selected) {
  const sel = new Set(selected);
  const groups = [];
  for (const c of catalog) {
    if (!sel.has(c.name)) continue;
    let g = groups.find((x) => x.key === c.kind);
    if (!g) { g = { key: c.kind, title: c.title, scale: c.scale, channels: [], labels: {} }; groups.push(g); }
    g.channels.push(c.name);
    g.labels[c.name] = c.label;
  }
  for (const g of groups) g.label = (n) => g.labels[n] || n;
  return groups;
}

export class Charts {
  // onSeek(t): a click on a chart; onView(a, b): a range brushed on a chart (null, null: reset)
  constructor(div, groups, onSeek, onView) {
    this.div = div;
    this.groups = groups;
    this.onSeek = onSeek;
    this.onView = onView;
    this.xRange = null;
    this.fitHeight();
    this.cursor = document.createElement("div");
    this.cursor.className = "chart-cursor";
    this.cursor.setAttribute("aria-hidden", "true");
    this.div.parentElement.appendChild(this.cursor);
    this.ready = false;
    this.liveMode = false;
  }

  layout(events) {
    const n = Math.max(this.groups.length, 1);
    const gap = 0.04;
    const h = (1 - gap * (n - 1)) / n;
    const layout = {
      margin: { l: 58, r: 10, t: 8, b: 28 },
      showlegend: true,
      hovermode: "x",
      paper_bgcolor: "rgba(0,0,0,0)",
      plot_bgcolor: "#fff",
      font: { size: 11 },
      // the x axis shows the timeline's view (not just where data are), so the chart cursor
      // and the slider line up; a drag on a chart brushes the x range only
      xaxis: { type: "date", anchor: "free", position: 0, showgrid: true, gridcolor: "#eee",
        ...(this.xRange ? { range: this.xRange.map((t) => t * 1000), autorange: false } : {}) },
      dragmode: "zoom",
      shapes: [],
      annotations: [],
    };
    this.groups.forEach((g, k) => {
      const name = k === 0 ? "yaxis" : `yaxis${k + 1}`;
      const top = 1 - k * (h + gap);
      layout[name] = { domain: [top - h, top], title: { text: g.title, font: { size: 10 } }, gridcolor: "#eee", zeroline: false, fixedrange: true };
      // one small legend per chart, in its top-right corner
      layout[legendId(k)] = { x: 1, xanchor: "right", y: top, yanchor: "top", orientation: "h",
        bgcolor: "rgba(255,255,255,0.7)", font: { size: 10 }, itemclick: "toggle" };
    });
    for (const ev of events || []) {
      layout.shapes.push({ type: "line", xref: "x", yref: "paper", x0: ev.t * 1000, x1: ev.t * 1000, y0: 0, y1: 1,
        line: { color: ev.severity === "critical" || ev.severity === "alarm" ? "#d62728" : "#ff9f1a", width: 1, dash: "dot" } });
    }
    return layout;
  }

  // history: {channels: {name: {t, min, max, mean}}}
  setHistory(history, events) {
    const traces = [];
    this.groups.forEach((g, k) => {
      const yaxis = k === 0 ? "y" : `y${k + 1}`;
      g.channels.forEach((name, c) => {
        const raw = history.channels ? history.channels[name] : null;
        if (!raw || !raw.t || raw.t.length === 0) return;
        const color = PALETTE[c % PALETTE.length];
        const sc = (v) => (v === null ? null : v * g.scale);
        const ms = (ts) => ts.map((t) => t * 1000);
        const group = `${g.key}:${name}`;
        // the min-max band: one filled pair per stretch with data (a fill would span a silence)
        for (const seg of splitAtSilences(raw)) {
          traces.push({ x: ms(seg.t), y: seg.max.map(sc), yaxis, type: "scatter", mode: "lines", line: { width: 0, color }, hoverinfo: "skip", showlegend: false, legendgroup: group });
          traces.push({ x: ms(seg.t), y: seg.min.map(sc), yaxis, type: "scatter", mode: "lines", line: { width: 0, color }, fill: "tonexty", fillcolor: hexAlpha(color, 0.18), hoverinfo: "skip", showlegend: false, legendgroup: group });
        }
        const s = withBreaks(raw);
        traces.push({ x: ms(s.t), y: s.mean.map(sc), yaxis, type: "scatter", mode: "lines", line: { width: 1.2, color }, name: g.label(name), legend: legendId(k), legendgroup: group });
      });
    });
    this.liveMode = false;
    this.draw(traces, this.layout(events));
    return traces.length > 0;
  }

  // live: rolling buffers {t: [], series: {name: []}} -> one line per channel
  setLive(buffer) {
    const traces = [];
    this.groups.forEach((g, k) => {
      const yaxis = k === 0 ? "y" : `y${k + 1}`;
      g.channels.forEach((name, c) => {
        const ys = buffer.series[name];
        if (!ys || ys.length === 0) return;
        traces.push({ x: buffer.t.map((t) => t * 1000), y: ys.map((v) => (v === null ? null : v * g.scale)), yaxis, type: "scatter", mode: "lines",
          line: { width: 1.2, color: PALETTE[c % PALETTE.length] }, name: g.label(name), legend: legendId(k) });
      });
    });
    this.liveMode = true;
    const keep = this.xRange;
    this.xRange = null; // live: the rolling window's own range
    const layout = this.layout([]);
    this.xRange = keep;
    this.draw(traces, layout);
  }

  setGroups(groups) { this.groups = groups; this.fitHeight(); }

  // about 95 px per chart (at least 300 px)
  fitHeight() {
    const h = `${Math.max(300, 95 * this.groups.length + 40)}px`;
    if (this.div.style.height !== h) this.div.style.height = h;
  }

  // Shows [a, b] on the x axis (the timeline's view); cheap: a relayout, no new data.
  setXRange(a, b) {
    this.xRange = a === null ? null : [a, b];
    if (!this.ready || !this.div._fullLayout) return;
    this.ignoreRelayout = true;
    const upd = this.xRange ? { "xaxis.range": this.xRange.map((t) => t * 1000), "xaxis.autorange": false } : { "xaxis.autorange": true };
    Promise.resolve(Plotly.relayout(this.div, upd)).finally(() => { this.ignoreRelayout = false; });
  }

  draw(traces, layout) {
    const config = { displaylogo: false, responsive: true, scrollZoom: false, doubleClick: "reset",
      modeBarButtonsToRemove: ["lasso2d", "select2d", "zoomIn2d", "zoomOut2d", "autoScale2d"] };
    this.ignoreRelayout = true;
    Promise.resolve(Plotly.react(this.div, traces, layout, config)).finally(() => { this.ignoreRelayout = false; });
    if (!this.ready) {
      this.ready = true;
      this.div.on("plotly_relayout", (ev) => {
        if (this.ignoreRelayout || this.liveMode || !this.onView) return;
        const r0 = ev["xaxis.range[0]"] ?? (ev["xaxis.range"] || [])[0];
        const r1 = ev["xaxis.range[1]"] ?? (ev["xaxis.range"] || [])[1];
        const ms = (x) => (typeof x === "number" ? x : Date.parse(String(x).replace(" ", "T") + "Z"));
        if (r0 !== undefined && r1 !== undefined) this.onView(ms(r0) / 1000, ms(r1) / 1000);
        else if (ev["xaxis.autorange"]) this.onView(null, null);
      });
      this.div.on("plotly_click", (ev) => {
        if (!ev.points || ev.points.length === 0 || this.liveMode) return;
        const x = ev.points[0].x;
        const t = typeof x === "number" ? x / 1000 : Date.parse(x.replace(" ", "T") + "Z") / 1000;
        if (this.onSeek && Number.isFinite(t)) this.onSeek(t);
      });
    }
  }

  setCursor(t) {
    const fl = this.div._fullLayout;
    if (!fl || !fl.xaxis || t === null) { this.cursor.style.display = "none"; return; }
    const xa = fl.xaxis;
    const px = xa._offset + xa.l2p(t * 1000);
    if (!(px >= xa._offset && px <= xa._offset + xa._length)) { this.cursor.style.display = "none"; return; }
    this.cursor.style.display = "block";
    // moved by a compositor transform: no layout, no repaint of the charts
    this.cursor.style.transform = `translate(${this.div.offsetLeft + px}px, ${this.div.offsetTop + fl.margin.t}px)`;
    this.cursor.style.height = `${fl.height - fl.margin.t - fl.margin.b}px`;
  }
}

// The stretches with data of a /history series {t, min, max, mean}: split at each silence
// (bucketGap), as series of the same shape.
export function splitAtSilences(s) {
  const { gap } = bucketGap(s.t);
  const out = [];
  let a = 0;
  for (let i = 1; i <= s.t.length; i++) {
    if (i === s.t.length || s.t[i] - s.t[i - 1] > gap) {
      out.push({ t: s.t.slice(a, i), min: s.min.slice(a, i), max: s.max.slice(a, i), mean: s.mean.slice(a, i) });
      a = i;
    }
  }
  return out;
}

// The series with a null point in each silence, so a line stops where the data stop instead
// of joining across the silence.
export function withBreaks(s) {
  const out = { t: [], min: [], max: [], mean: [] };
  let prev = null;
  for (const seg of splitAtSilences(s)) {
    if (prev !== null) {
      out.t.push((prev + seg.t[0]) / 2);
      out.min.push(null); out.max.push(null); out.mean.push(null);
    }
    for (const k of ["t", "min", "max", "mean"]) for (const v of seg[k]) out[k].push(v);
    prev = seg.t[seg.t.length - 1];
  }
  return out;
}

function legendId(k) { return k === 0 ? "legend" : `legend${k + 1}`; }

function hexAlpha(hex, a) {
  const v = parseInt(hex.slice(1), 16);
  return `rgba(${(v >> 16) & 255},${(v >> 8) & 255},${v & 255},${a})`;
}
