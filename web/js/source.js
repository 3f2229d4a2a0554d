// Where a machine page's data come from: the API (every request carries the session cookie),
// or the data embedded in an exported file. Both answer the same calls.
import { getJSON, wsURL } from "./api.js";

export function apiSource(id) {
  const base = `/api/v1/machines/${encodeURIComponent(id)}`;
  return {
    embedded: false,
    machine: () => getJSON(base),
    model: () => getJSON(`${base}/model`),
    scene: () => getJSON(`${base}/scene`),
    twin: (a, b, rate) => getJSON(`${base}/twin`, { from: a, to: b, rate_hz: rate }),
    history: (a, b, channels, maxPoints) => getJSON(`${base}/history`, { from: a, to: b, channels: channels.join(","), max_points: maxPoints }),
    events: (a, b) => getJSON(`${base}/events`, { from: a, to: b }),
    liveURL: () => wsURL(`${base}/live`),
  };
}

export function embeddedSource(e) {
  return {
    embedded: true,
    machine: async () => e.machine,
    model: async () => e.model,
    scene: async () => e.scene,
    twin: async (a, b) => sliceTwin(e.twin, a, b),
    history: async () => e.history,
    events: async () => e.events || [],
    liveURL: () => null,
  };
}

// The frames of an embedded twin result inside [a, b] (and the verdicts of its part there).
export function sliceTwin(tw, a, b) {
  const idx = [];
  tw.t.forEach((t, i) => { if (t >= a - 1e-9 && t <= b + 1e-9) idx.push(i); });
  const pick = (arr) => idx.map((i) => arr[i]);
  const out = { t: pick(tw.t), q: pick(tw.q), tip: tw.tip ? pick(tw.tip) : null, poses: {}, cylinder_pins: {}, utilisation: {}, cylinder_forces: {}, payload: tw.payload };
  for (const k in tw.poses) out.poses[k] = pick(tw.poses[k]);
  for (const k in tw.cylinder_pins || {}) out.cylinder_pins[k] = pick(tw.cylinder_pins[k]);
  for (const k in tw.utilisation || {}) out.utilisation[k] = pick(tw.utilisation[k]);
  for (const k in tw.cylinder_forces || {}) out.cylinder_forces[k] = pick(tw.cylinder_forces[k]);
  // the verdicts of the exported window (part) [a, b] overlaps most
  let best = null, most = 0;
  for (const n of tw.notes || []) {
    const overlap = Math.min(b, n.to) - Math.max(a, n.from);
    if (overlap > most) { most = overlap; best = n; }
  }
  if (best) { out.force_observability = best.force_observability; out.model_consistency = best.model_consistency; }
  return out;
}

// A classic script (plotly), loaded once.
export function loadScript(src) {
  return new Promise((resolve, reject) => {
    if (typeof Plotly !== "undefined") { resolve(); return; }
    const s = document.createElement("script");
    s.src = src; s.onload = resolve; s.onerror = () => reject(new Error(`cannot load ${src}`));
    document.head.appendChild(s);
  });
}
