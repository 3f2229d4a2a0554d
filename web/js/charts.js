// Charts of pressures, cylinder forces, payload and joint loads, linked to the one time cursor.
// Long ranges come from min/max buckets (/history): each series is a min-max band plus its mean.
// Plotly (served locally from the plotly Python package) is the global `Plotly`. No imports.

const PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#17becf", "#e377c2"];

export function chartGroups(model) {
  const ch = (model.channels || []);
  const pressures = ch.filter((c) => c.quantity === "pressure_a" || c.quantity === "pressure_b").map((c) => c.name);
  const cyls = (model.cylinders || []).map((c) => c.name);
  const joints = (model.joints || []).filter((j) => j.kind === "revolute").map((j) => j.name);
  return [
    { key: "pressure", title: "Pressure [bar]", scale: 1e-5, channels: pressures, label: (n) => n },
    { key: "force", title: "Cylinder force [kN]", scale: 1e-3, channels: cyls.map((c) => `force:${c}`), label: (n) => n.slice(6) },
    { key: "payload", title: "Payload [kg]", scale: 1, channels: ["payload"], label: () => "payload" },
    { key: "moment", title: "Joint moment [kN·m]", scale: 1e-3, channels: joints.map((j) => `moment:${j}`), label: (n) => n.slice(7) },
  ];
}

export class Charts {
  constructor(div, groups, onSeek) {
    this.div = div;
    this.groups = groups;
    this.onSeek = onSeek;
    this.cursor = document.createElement("div");
    this.cursor.className = "chart-cursor";
    this.cursor.setAttribute("aria-hidden", "true");
    this.div.parentElement.appendChild(this.cursor);
    this.ready = false;
    this.liveMode = false;
  }

  layout(events) {
    const n = this.groups.length;
    const gap = 0.04;
    const h = (1 - gap * (n - 1)) / n;
    const layout = {
      margin: { l: 58, r: 10, t: 8, b: 28 },
      showlegend: true,
      hovermode: "x",
      paper_bgcolor: "rgba(0,0,0,0)",
      plot_bgcolor: "#fff",
      font: { size: 11 },
      xaxis: { type: "date", anchor: "free", position: 0, showgrid: true, gridcolor: "#eee" },
      shapes: [],
      annotations: [],
    };
    this.groups.forEach((g, k) => {
      const name = k === 0 ? "yaxis" : `yaxis${k + 1}`;
      const top = 1 - k * (h + gap);
      layout[name] = { domain: [top - h, top], title: { text: g.title, font: { size: 10 } }, gridcolor: "#eee", zeroline: false };
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
        const s = history.channels ? history.channels[name] : null;
        if (!s || !s.t || s.t.length === 0) return;
        const x = s.t.map((t) => t * 1000);
        const color = PALETTE[c % PALETTE.length];
        const sc = (v) => (v === null ? null : v * g.scale);
        const group = `${g.key}:${name}`;
        traces.push({ x, y: s.max.map(sc), yaxis, type: "scatter", mode: "lines", line: { width: 0, color }, hoverinfo: "skip", showlegend: false, legendgroup: group });
        traces.push({ x, y: s.min.map(sc), yaxis, type: "scatter", mode: "lines", line: { width: 0, color }, fill: "tonexty", fillcolor: hexAlpha(color, 0.18), hoverinfo: "skip", showlegend: false, legendgroup: group });
        traces.push({ x, y: s.mean.map(sc), yaxis, type: "scatter", mode: "lines", line: { width: 1.2, color }, name: g.label(name), legend: legendId(k), legendgroup: group });
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
    this.draw(traces, this.layout([]));
  }

  draw(traces, layout) {
    const config = { displaylogo: false, responsive: true, modeBarButtonsToRemove: ["lasso2d", "select2d"] };
    Plotly.react(this.div, traces, layout, config);
    if (!this.ready) {
      this.ready = true;
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

function legendId(k) { return k === 0 ? "legend" : `legend${k + 1}`; }

function hexAlpha(hex, a) {
  const v = parseInt(hex.slice(1), 16);
  return `rgba(${(v >> 16) & 255},${(v >> 8) & 255},${v & 255},${a})`;
}
