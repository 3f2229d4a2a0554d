// Replay data: twin results fetched in chunks around the time cursor, interpolated per frame.
// No imports (inlined into exported replays).

export const CHUNK_S = 60;

export class ReplayStore {
  // source.twin(from, to) -> Promise of a twin JSON result (contract v1); chunks[i] and the
  // primer are {state, data, a, b}: [a, b] the window asked for [s]
  constructor(source, from, to, rateHz) {
    this.source = source;
    this.from = from;
    this.to = to;
    this.rateHz = rateHz;
    this.chunks = new Map(); // index -> {state: "loading"|"ready"|"empty"|"error", data}
    this.onLoaded = null;
    this.frame = { poses: {}, cylinder_pins: {}, utilisation: {}, cylinder_forces: {}, q: [0, 0, 0, 0], tip: [0, 0, 0], payload_kg: 0, t: from };
  }

  chunkIndex(t) { return Math.max(0, Math.floor((t - this.from) / CHUNK_S)); }

  // A one-second window around t, fetched first so the crane is drawn before its chunk arrives.
  prime(t) {
    const a = Math.max(this.from, t - 0.5);
    const b = Math.min(this.to, a + 1);
    this.primer = { state: "loading", data: null, a, b };
    const entry = this.primer;
    this.source.twin(a, b, this.rateHz).then((data) => {
      if (data && data.t && data.t.length > 0) { entry.data = prepare(data); entry.state = "ready"; }
      else entry.state = "empty";
      if (this.onLoaded) this.onLoaded(-1, entry);
    }).catch(() => { entry.state = "error"; });
  }

  ensure(t) {
    const i = this.chunkIndex(t);
    this.load(i);
    // prefetch the next chunk once past the middle of this one
    if (t - (this.from + i * CHUNK_S) > CHUNK_S / 2 && this.from + (i + 1) * CHUNK_S < this.to) this.load(i + 1);
    return this.chunks.get(i);
  }

  load(i) {
    if (this.chunks.has(i)) return;
    const a = this.from + i * CHUNK_S;
    const b = Math.min(this.to, a + CHUNK_S + 1 / this.rateHz);
    const entry = { state: "loading", data: null, a, b };
    this.chunks.set(i, entry);
    this.source.twin(a, b, this.rateHz).then((data) => {
      if (!data || !data.t || data.t.length === 0) { entry.state = "empty"; }
      else { entry.state = "ready"; entry.data = prepare(data); }
      if (this.onLoaded) this.onLoaded(i, entry);
    }).catch((err) => {
      entry.state = "error";
      entry.error = err;
      if (this.onLoaded) this.onLoaded(i, entry);
    });
  }

  // Fills this.frame for time t; returns null when the chunk is not there (yet), or "empty"
  // after the chunk's last sample when the data stop before the chunk's end (a silence).
  frameAt(t) {
    let entry = this.ensure(t);
    if ((!entry || entry.state !== "ready") && this.primer && this.primer.state === "ready"
        && t >= this.primer.a && t <= this.primer.b) entry = this.primer;
    if (!entry || entry.state !== "ready") return entry ? entry.state : null;
    const d = entry.data;
    const n = d.t.length;
    const tol = 4 / this.rateHz; // a longer step between frames is a silence [s]
    if (t > d.t[n - 1] + tol && entry.b > d.t[n - 1] + tol) return "empty";
    let i = upperBound(d.t, t) - 1;
    if (i < 0) i = 0;
    const j = Math.min(i + 1, n - 1);
    const span = d.t[j] - d.t[i];
    const a = span > 0 ? Math.min(Math.max((t - d.t[i]) / span, 0), 1) : 0;
    const f = this.frame;
    f.t = t;
    // inside a silence of the data (or before the chunk's first sample): where data resume
    if (t < d.t[0]) f.gapTo = d.t[0];
    else if (t > d.t[i] && j > i && span > tol) f.gapTo = d.t[j];
    else f.gapTo = undefined;
    f.index = i;
    f.chunk = entry;
    for (const body in d.poses) f.poses[body] = lerpArr(d.poses[body][i], d.poses[body][j], a, f.poses[body]);
    for (const c in d.pins) f.cylinder_pins[c] = lerpArr(d.pins[c][i], d.pins[c][j], a, f.cylinder_pins[c]);
    for (const c in d.util) f.utilisation[c] = d.util[c][i] + a * (d.util[c][j] - d.util[c][i]);
    for (const c in d.forces) f.cylinder_forces[c] = d.forces[c][i] + a * (d.forces[c][j] - d.forces[c][i]);
    f.q = lerpArr(d.q[i], d.q[j], a, f.q);
    f.tip = d.tip ? lerpArr(d.tip[i], d.tip[j], a, f.tip) : null;
    f.payload_kg = d.payloadAt(t);
    f.joint_torques = d.torques ? d.torques[i] : null;
    // the verdicts of this chunk's window; none from the primer (one second says nothing
    // about a force's range)
    f.observability = entry === this.primer ? null : d.observability;
    f.consistency = entry === this.primer ? null : d.consistency;
    return f;
  }

  // Tip positions of the last `seconds` before t (flat xyz), from loaded chunks.
  trail(t, seconds, maxPoints) {
    const out = [];
    const entry = this.chunks.get(this.chunkIndex(t));
    const prev = this.chunks.get(this.chunkIndex(t) - 1);
    for (const e of [prev, entry]) {
      if (!e || e.state !== "ready" || !e.data.tip) continue;
      const d = e.data;
      const lo = lowerBound(d.t, t - seconds);
      const hi = upperBound(d.t, t);
      for (let k = lo; k < hi; k++) out.push(d.tip[k][0], d.tip[k][1], d.tip[k][2]);
    }
    const n = out.length / 3;
    if (n <= maxPoints) return out;
    const stride = Math.ceil(n / maxPoints);
    const thin = [];
    for (let k = (n - 1) % stride; k < n; k += stride) thin.push(out[3 * k], out[3 * k + 1], out[3 * k + 2]);
    return thin;
  }
}

function flat6(p) { return Array.isArray(p[0]) ? [p[0][0], p[0][1], p[0][2], p[1][0], p[1][1], p[1][2]] : p; }

export function prepare(data) {
  const pins = {};
  for (const c in (data.cylinder_pins || {})) pins[c] = data.cylinder_pins[c].map(flat6);
  const pay = data.payload || {};
  const pt = pay.t || [];
  const pk = pay.kg || [];
  return {
    t: data.t,
    q: data.q,
    tip: data.tip,
    poses: data.poses || {},
    pins,
    util: data.utilisation || {},
    forces: data.cylinder_forces || {},
    torques: data.joint_torques || null,
    observability: byCylinder(data.force_observability),
    consistency: byCylinder(data.model_consistency),
    payloadAt(t) {
      if (pk.length === 0) return 0;
      const k = upperBound(pt, t) - 1;
      if (k < 0) return pk[0];
      if (k >= pk.length - 1) return pk[pk.length - 1];
      const a = (t - pt[k]) / (pt[k + 1] - pt[k]);
      return pk[k] + a * (pk[k + 1] - pk[k]);
    },
  };
}

// The window's per-cylinder verdicts ({cylinder, ...} list) keyed by cylinder, or null.
function byCylinder(list) {
  if (!Array.isArray(list) || list.length === 0) return null;
  const out = {};
  for (const v of list) if (v && v.cylinder) out[v.cylinder] = v;
  return out;
}

function lerpArr(x, y, a, out) {
  const n = x.length;
  if (!out || out.length !== n) out = new Array(n);
  for (let k = 0; k < n; k++) out[k] = x[k] + a * (y[k] - x[k]);
  return out;
}
export function upperBound(arr, v) {
  let lo = 0, hi = arr.length;
  while (lo < hi) { const m = (lo + hi) >> 1; if (arr[m] <= v) lo = m + 1; else hi = m; }
  return lo;
}
function lowerBound(arr, v) {
  let lo = 0, hi = arr.length;
  while (lo < hi) { const m = (lo + hi) >> 1; if (arr[m] < v) lo = m + 1; else hi = m; }
  return lo;
}
