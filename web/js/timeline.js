// Timeline strip under the 3D view: the whole replay range, the zoomed view as a window on it,
// where data exist, the events and the time cursor.
// Drag on the strip = brush a range to zoom into; drag the view window = pan; click = seek;
// wheel = pan (Ctrl/Shift + wheel = zoom around the pointer). No imports (inlined into exports).

export const MIN_VIEW_S = 2;

// The bucket width w (median step) of /history bucket start times `ts` [s], and the silence
// threshold: a step longer than gap = max(3 w, 5 s) is a stretch without data.
export function bucketGap(ts) {
  const steps = [];
  for (let i = 1; i < ts.length; i++) steps.push(ts[i] - ts[i - 1]);
  steps.sort((x, y) => x - y);
  const w = steps.length ? steps[steps.length >> 1] : 1;
  return { w, gap: Math.max(3 * w, 5) };
}

// Intervals [[a, b], ...] covered by data, from /history buckets {t: [...]} (bucket start times):
// a silence (bucketGap) splits them.
export function coverageFromHistory(history) {
  let ts = null;
  for (const s of Object.values((history && history.channels) || {})) {
    if (s && s.t && s.t.length > (ts ? ts.length : 0)) ts = s.t;
  }
  if (!ts || ts.length === 0) return [];
  const { w, gap } = bucketGap(ts);
  const out = [[ts[0], ts[0] + w]];
  for (let i = 1; i < ts.length; i++) {
    const last = out[out.length - 1];
    if (ts[i] - last[1] > gap) out.push([ts[i], ts[i] + w]);
    else last[1] = ts[i] + w;
  }
  return out;
}

// The union of interval lists (each [[a, b], ...]): sorted, overlapping ones merged.
export function unionCoverage(...lists) {
  const all = lists.flat().slice().sort((x, y) => x[0] - y[0]);
  const out = [];
  for (const [a, b] of all) {
    const last = out[out.length - 1];
    if (last && a <= last[1]) last[1] = Math.max(last[1], b);
    else out.push([a, b]);
  }
  return out;
}

// The next time >= t inside a covered interval (t itself when covered; null after the last).
export function nextCovered(coverage, t) {
  for (const [a, b] of coverage) {
    if (t < a) return a;
    if (t <= b) return t;
  }
  return null;
}

export class Timeline {
  constructor(el, { onView, onSeek }) {
    this.el = el;
    this.onView = onView;
    this.onSeek = onSeek;
    this.from = null; this.to = null; this.a = null; this.b = null;
    el.innerHTML = '<div class="tl-track"><div class="tl-cover"></div><div class="tl-events"></div>'
      + '<div class="tl-view" title="Drag to pan the zoomed range"></div><div class="tl-brush" hidden></div>'
      + '<div class="tl-cursor"></div></div>';
    this.track = el.querySelector(".tl-track");
    this.viewEl = el.querySelector(".tl-view");
    this.brushEl = el.querySelector(".tl-brush");
    this.cursorEl = el.querySelector(".tl-cursor");
    this.coverEl = el.querySelector(".tl-cover");
    this.eventsEl = el.querySelector(".tl-events");
    this.coverage = [];
    this.track.addEventListener("pointerdown", (ev) => this.down(ev));
    this.track.addEventListener("wheel", (ev) => this.wheel(ev), { passive: false });
  }

  tAt(clientX) {
    const r = this.track.getBoundingClientRect();
    const x = Math.min(Math.max(clientX - r.left, 0), r.width);
    return this.from + (x / Math.max(r.width, 1)) * (this.to - this.from);
  }

  pct(t) { return `${(100 * (t - this.from)) / (this.to - this.from)}%`; }

  setRange(from, to) {
    this.from = from; this.to = to;
    this.a = from; this.b = to;
    this.draw();
  }

  // Sets the view (clamped into the range, at least MIN_VIEW_S long); returns [a, b].
  clampView(a, b) {
    const span = Math.min(Math.max(b - a, MIN_VIEW_S), this.to - this.from);
    let lo = a;
    if (lo < this.from) lo = this.from;
    if (lo + span > this.to) lo = this.to - span;
    return [lo, lo + span];
  }

  setView(a, b) {
    [this.a, this.b] = this.clampView(a, b);
    this.draw();
    return [this.a, this.b];
  }

  setCursor(t) {
    if (this.from === null || t === null) return;
    this.cursorEl.style.left = this.pct(Math.min(Math.max(t, this.from), this.to));
  }

  setCoverage(intervals) {
    this.coverage = intervals || [];
    this.coverEl.innerHTML = "";
    for (const [a, b] of this.coverage) {
      const d = document.createElement("div");
      d.className = "tl-span";
      d.style.left = this.pct(Math.max(a, this.from));
      d.style.width = `${(100 * (Math.min(b, this.to) - Math.max(a, this.from))) / (this.to - this.from)}%`;
      this.coverEl.appendChild(d);
    }
  }

  setEvents(events) {
    this.eventsEl.innerHTML = "";
    for (const ev of events || []) {
      if (ev.t < this.from || ev.t > this.to) continue;
      const d = document.createElement("div");
      d.className = `tl-event ${ev.severity || ""}`;
      d.style.left = this.pct(ev.t);
      this.eventsEl.appendChild(d);
    }
  }

  draw() {
    if (this.from === null) return;
    this.viewEl.style.left = this.pct(this.a);
    this.viewEl.style.width = `${(100 * (this.b - this.a)) / (this.to - this.from)}%`;
    this.viewEl.hidden = this.a <= this.from && this.b >= this.to;
  }

  zoomed() { return !(this.a <= this.from && this.b >= this.to); }

  down(ev) {
    if (this.from === null || ev.button !== 0) return;
    ev.preventDefault();
    this.track.setPointerCapture(ev.pointerId);
    const t0 = this.tAt(ev.clientX);
    const x0 = ev.clientX;
    const pan = ev.target === this.viewEl;
    const a0 = this.a, b0 = this.b;
    const move = (e) => {
      if (pan) {
        const dt = this.tAt(e.clientX) - t0;
        this.onView(...this.setView(a0 + dt, b0 + dt));
        return;
      }
      const t1 = this.tAt(e.clientX);
      this.brushEl.hidden = Math.abs(e.clientX - x0) < 4;
      this.brushEl.style.left = this.pct(Math.min(t0, t1));
      this.brushEl.style.width = `${(100 * Math.abs(t1 - t0)) / (this.to - this.from)}%`;
    };
    const up = (e) => {
      this.track.removeEventListener("pointermove", move);
      this.track.removeEventListener("pointerup", up);
      this.brushEl.hidden = true;
      if (pan) return;
      const t1 = this.tAt(e.clientX);
      if (Math.abs(e.clientX - x0) >= 4) this.onView(...this.setView(Math.min(t0, t1), Math.max(t0, t1)));
      else this.onSeek(t1);
    };
    this.track.addEventListener("pointermove", move);
    this.track.addEventListener("pointerup", up);
  }

  // Wheel: pan by a tenth of the view per notch; Ctrl/Shift + wheel zooms around the pointer.
  wheel(ev) {
    if (this.from === null) return;
    ev.preventDefault();
    const d = Math.abs(ev.deltaX) > Math.abs(ev.deltaY) ? ev.deltaX : ev.deltaY;
    if (ev.ctrlKey || ev.shiftKey) this.zoomBy(d > 0 ? 1.25 : 0.8, this.tAt(ev.clientX));
    else this.panBy(Math.sign(d) * 0.1);
  }

  // Pans the view by `fraction` of its width (negative: earlier).
  panBy(fraction) {
    const w = this.b - this.a;
    this.onView(...this.setView(this.a + fraction * w, this.b + fraction * w));
  }

  // Zooms the view by `factor` (> 1: out) around time `t`.
  zoomBy(factor, t) {
    const c = t ?? (this.a + this.b) / 2;
    this.onView(...this.setView(c - (c - this.a) * factor, c + (this.b - c) * factor));
  }
}
