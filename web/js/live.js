// Live mode: the websocket of /api/v1/machines/{id}/live with reconnection, the rolling chart
// buffer and the tip-path trail of the frames received. Shared by the machine and compare pages.

export const LIVE_WINDOW_S = 60; // rolling charts [s]
const TRAIL_POINTS = 600;

// One machine's live stream. `on`: {open(), frame(f), error(text), refused(code), lost(ms)}.
// Reconnects after 0.5 s, doubling up to 10 s; close() ends it.
export class LiveFeed {
  constructor(url, on) {
    this.url = url;
    this.on = on;
    this.ws = null;
    this.timer = null;
    this.backoff = 500;
    this.closed = false;
    this.lastFrameWall = Date.now();
    this.connect();
  }

  connect() {
    const ws = new WebSocket(this.url);
    this.ws = ws;
    ws.onopen = () => { this.backoff = 500; this.lastFrameWall = Date.now(); if (this.on.open) this.on.open(); };
    ws.onmessage = (msg) => {
      let f;
      try { f = JSON.parse(msg.data); } catch (_) { return; }
      if (f.type === "hello") return;
      if (f.type === "error") {
        // a rate-limit refusal (close 4429) says when to retry: reconnect no sooner
        if (f.retry_after) this.backoff = Math.max(this.backoff, f.retry_after * 1000);
        if (this.on.error) this.on.error(f.detail || f.title || "Live stream error");
        return;
      }
      this.lastFrameWall = Date.now();
      f.receivedAt = performance.now();
      this.on.frame(f);
    };
    ws.onclose = (ev) => {
      if (this.closed || this.ws !== ws) return;
      if ([4401, 4403, 1008, 4404].includes(ev.code)) { if (this.on.refused) this.on.refused(ev.code); return; }
      if (this.on.lost) this.on.lost(this.backoff);
      this.timer = setTimeout(() => this.connect(), this.backoff);
      this.backoff = Math.min(this.backoff * 2, 10000);
    };
  }

  get connected() { return !!this.ws && this.ws.readyState === 1; }

  // Seconds since the last frame (or since connecting).
  quietS() { return (Date.now() - this.lastFrameWall) / 1000; }

  close() {
    this.closed = true;
    clearTimeout(this.timer);
    if (this.ws) { const ws = this.ws; this.ws = null; ws.close(); }
  }
}

// The last LIVE_WINDOW_S of the channels a live frame carries, as the charts read them:
// {t: [...], series: {name: [...]}}.
export class LiveBuffer {
  constructor() { this.t = []; this.series = {}; }

  push(f) {
    this.t.push(f.t);
    const add = (name, v) => { (this.series[name] ||= []).push(v ?? null); };
    for (const [k, v] of Object.entries(f.pressures || {})) add(k, v);
    for (const [k, v] of Object.entries(f.cylinder_forces || {})) add(`force:${k}`, v);
    for (const [k, v] of Object.entries(f.joint_torques || {})) add(`torque:${k}`, v);
    add("payload", f.payload_kg);
    while (this.t.length > 0 && this.t[0] < f.t - LIVE_WINDOW_S) {
      this.t.shift();
      for (const k in this.series) this.series[k].shift();
    }
  }
}

// Draws live frame `f` on `crane` with the tip-path trail of the frames before it (`trail`: a
// flat [x, y, z, ...] array kept by the caller).
export function drawLive(crane, f, trail) {
  const tip = crane.tipFromPoses(f.poses || {});
  if (tip) { trail.push(tip[0], tip[1], tip[2]); if (trail.length > 3 * TRAIL_POINTS) trail.splice(0, 3); }
  crane.apply(f);
  crane.setTrail(trail);
}
