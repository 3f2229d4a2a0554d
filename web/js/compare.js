// Compare page: 2–4 machines' 3D scenes side by side, live or replaying one time range with one
// shared timeline and time cursor: /compare?machines=a,b[,c,d]&mode=replay&from&to&t&speed.
// Each machine keeps its own data (scene, replay chunks, live stream, charts panel); time is the
// same for all, and play skips the stretches where none of the machines has data.
import { ApiError, askSignIn, setupSignIn, isoSeconds, parseTime, relTime } from "./api.js";
import { Crane3D } from "./crane3d.js";
import { ReplayStore } from "./replay.js";
import { Charts } from "./charts.js";
import { Timeline, coverageFromHistory, unionCoverage } from "./timeline.js";
import { apiSource, loadScript } from "./source.js";
import { FRAME_S, REPLAY_RATE_HZ, drawReplay, playStep } from "./playback.js";
import { LiveBuffer, LiveFeed, drawLive } from "./live.js";
import { ChartPanel } from "./chartpanel.js";
import { loadLine, utilClass } from "./nowcard.js";

const el = (id) => document.getElementById(id);
const SPEED_STEPS = [0.25, 0.5, 1, 2, 4, 8, 16];
const MAX_MACHINES = 4;
const DEFAULT_SPAN_S = 600;
const CHART_KINDS = ["payload", "force"]; // charted per machine unless the link's ch= says

// Read by the browser tests and benchmarks.
const stats = window.cranetwin = {
  ready: false, firstFrameMs: null, mode: null, cursor: null, view: null, errors: [], rafIntervals: [],
  coverage: [], gapsSkipped: 0, historyLoads: 0,
  cells: {}, // machine id -> {drawnT, frames, liveFrames, liveLatencyMs, envelope, state, channels}
};

const query = new URLSearchParams(window.location.search);
const wanted = [...new Set((query.get("machines") || "").split(",").map((s) => s.trim()).filter(Boolean))];
const page = {
  cells: [], mode: null, from: null, to: null, cursor: null, view: null, playing: false, coverage: [],
  speed: Math.min(16, Math.max(0.25, parseFloat(query.get("speed")) || 1)),
  timeline: null, lastWall: null, lastUi: 0, needsFrame: false, chartsReady: null, viewTimer: null,
  wantedChannels: (query.get("ch") || "").split(",").filter(Boolean),
};

function note(text, kind = "info") {
  const b = el("banner");
  b.hidden = !text;
  if (text) { b.className = `banner ${kind}`; b.textContent = text; }
}

function hhmmss(t) { return t === null ? "–" : new Date(t * 1000).toISOString().slice(11, 21); }
function toInput(t) { return new Date(t * 1000).toISOString().slice(0, 19); }
function fromInput(v) { return v ? Date.parse(v + "Z") / 1000 : null; }

// ---- cells -----------------------------------------------------------------------------------
function makeCell(id) {
  const sec = document.createElement("section");
  sec.className = "cmp-cell";
  sec.dataset.machineId = id;
  sec.setAttribute("aria-label", `3D view of ${id}`);
  sec.innerHTML = `<header><a href="/machines/${encodeURIComponent(id)}"></a><span class="badge">…</span></header>`
    + `<div class="view3d"></div><span class="cell-note muted"></span><div class="overlay-readout" aria-live="off"></div>`;
  sec.querySelector("a").textContent = id;
  el("cells").appendChild(sec);
  const box = document.createElement("section");
  box.className = "cmp-charts";
  box.dataset.machineId = id;
  box.setAttribute("aria-label", `Charts of ${id}`);
  box.innerHTML = `<header><span class="cmp-name"></span><details class="channel-picker"><summary>Channels (<span class="channel-count">0</span>)</summary>`
    + `<div class="channel-list"></div></details></header><div class="charts-box"><div class="charts"></div><p class="muted charts-msg" hidden></p></div>`;
  box.querySelector(".cmp-name").textContent = id;
  el("charts-grid").appendChild(box);
  const cell = {
    id, source: apiSource(id), el: sec, chartsEl: box, view: sec.querySelector(".view3d"), machine: null, crane: null,
    store: null, live: null, liveFrame: null, liveDirty: false, trail: [], drawnT: null, state: "loading",
    panel: null, charts: null, events: [], liveBuffer: new LiveBuffer(),
  };
  stats.cells[id] = { drawnT: null, frames: 0, liveFrames: 0, liveLatencyMs: [], envelope: null, state: "loading", channels: [] };
  return cell;
}

// The cell's charts panel (channel picker, load history on the shared cursor), once its model is known.
function makePanel(cell, model) {
  const q = (sel) => cell.chartsEl.querySelector(sel);
  cell.panel = new ChartPanel(cell.source, model, { list: q(".channel-list"), count: q(".channel-count"), charts: q(".charts"), msg: q(".charts-msg") },
    page.wantedChannels, CHART_KINDS);
  stats.cells[cell.id].channels = cell.panel.selected.slice();
  cell.panel.buildPicker(() => {
    stats.cells[cell.id].channels = cell.panel.selected.slice();
    saveUrl();
    if (!cell.charts) return;
    if (page.mode === "replay") loadCellHistory(cell);
    else cell.charts.setLive(cell.liveBuffer);
  });
}

function attachCharts(cell) {
  if (!cell.panel) return;
  cell.panel.attach((groups) => new Charts(cell.chartsEl.querySelector(".charts"), groups,
    (t) => { if (page.mode === "replay") { page.playing = false; playButton(); seek(t); saveUrl(); } },
    (a, b) => { if (page.mode === "replay") setView(a ?? page.from, b ?? page.to); }));
  cell.charts = cell.panel.charts;
  if (page.view) cell.charts.setXRange(page.view.a, page.view.b);
  cell.chartsEl.querySelector(".charts").addEventListener("wheel", (ev) => {
    if (page.mode === "replay" && page.from !== null) page.timeline.wheel(ev);
  }, { passive: false });
}

// Min/max history of the cell's charted channels over the view (or the range).
async function loadCellHistory(cell) {
  if (!cell.charts || page.from === null) return;
  const a = page.view ? page.view.a : page.from, b = page.view ? page.view.b : page.to;
  if (await cell.panel.loadHistory(a, b, () => cell.events, () => page.cursor)) stats.historyLoads += 1;
}

function loadAllHistory() { for (const c of page.cells) loadCellHistory(c); }

function cellNote(cell, text) { cell.el.querySelector(".cell-note").textContent = text || ""; }

function showFrame(cell, f) {
  const s = stats.cells[cell.id];
  cell.drawnT = s.drawnT = f.t;
  s.frames += 1;
  const env = cell.crane.envelopeState;
  s.envelope = env ? { reach_m: env.reach_m, rated_kg: env.rated_kg, utilisation: env.utilisation } : null;
  const line = cell.el.querySelector(".overlay-readout");
  line.textContent = loadLine(f.payload_kg, env);
  line.className = `overlay-readout ${env ? utilClass(env.utilisation) : ""}`;
  if (stats.firstFrameMs === null) { stats.firstFrameMs = performance.now(); setTimeout(firstFrameDone, 50); }
}

let firstFrameDone;
const firstFrame = new Promise((r) => { firstFrameDone = r; });

function setState(cell, st) {
  cell.state = stats.cells[cell.id].state = st;
  cellNote(cell, st === "empty" ? "no data at this time" : st === "loading" ? "loading…" : st === "error" ? "could not load" : "");
  checkReady();
}

function checkReady() {
  if (stats.ready) return;
  if (page.cells.length && page.cells.every((c) => c.state !== "loading")) {
    stats.ready = true;
    document.body.dataset.ready = "1";
  }
}

// ---- start -------------------------------------------------------------------------------------
async function start() {
  setupSignIn(() => window.location.reload());
  if (wanted.length < 2 || wanted.length > MAX_MACHINES) {
    note(`Compare shows 2 to ${MAX_MACHINES} machines: open /compare?machines=crane-1,crane-2 (${wanted.length} given).`, "error");
    stats.errors.push("machines");
    return;
  }
  el("subtitle").textContent = wanted.join(" · ");
  el("cells").classList.add(`n${wanted.length}`);
  page.cells = wanted.map(makeCell);
  let infos;
  try {
    infos = await Promise.all(page.cells.map((c) => c.source.machine().catch((err) => {
      if (err instanceof ApiError && err.status === 404) return { missing: true, detail: err.detail };
      throw err;
    })));
  } catch (err) {
    stats.errors.push(String(err));
    if (err instanceof ApiError && err.status === 401) { askSignIn(null); return; }
    note(`Could not load the machines: ${err.message}`, "error");
    return;
  }
  const scenes = page.cells.map((c, i) => (infos[i].missing ? Promise.resolve(null) : c.source.scene().catch(() => null)));
  const models = page.cells.map((c, i) => (infos[i].missing ? Promise.resolve(null) : c.source.model().catch(() => null)));
  infos.forEach((m, i) => {
    const cell = page.cells[i];
    if (m.missing) { cell.state = "error"; cellNote(cell, `unknown machine “${cell.id}”`); return; }
    cell.machine = m;
    cell.el.querySelector("a").textContent = m.name || m.machine_id;
    cell.chartsEl.querySelector(".cmp-name").textContent = m.name || m.machine_id;
    const badge = cell.el.querySelector(".badge");
    badge.textContent = m.status === "live" ? "live" : `${m.status || "unknown"}${m.last_seen ? " · " + relTime(m.last_seen) : ""}`;
    badge.className = `badge ${m.status || ""}`;
  });
  const known = page.cells.filter((c) => c.machine);
  for (const c of page.cells) if (!c.machine) c.chartsEl.hidden = true;
  if (known.length === 0) { note("None of these machines is known.", "error"); stats.errors.push("unknown"); return; }
  // one range for all: the URL's, else the last 10 min up to the newest stored sample of any
  const ends = known.map((c) => parseTime((c.machine.data_range || {}).to)).filter((x) => x !== null);
  const starts = known.map((c) => parseTime((c.machine.data_range || {}).from)).filter((x) => x !== null);
  const to = parseTime(query.get("to")) ?? (ends.length ? Math.max(...ends) : null);
  const from = parseTime(query.get("from")) ?? (to !== null ? Math.max(Math.min(...starts), to - DEFAULT_SPAN_S) : null);
  const mode = query.get("mode") || (known.every((c) => c.machine.status === "live") ? "live" : "replay");
  page.timeline = new Timeline(el("timeline"), { onView: (a, b) => setView(a, b), onSeek: (t) => { page.playing = false; playButton(); seek(t); } });
  wire();
  if (mode === "replay" && from !== null && to !== null && to > from) primeStores(from, to, parseTime(query.get("t")));
  const built = await Promise.all(scenes);
  built.forEach((scene, i) => {
    const cell = page.cells[i];
    if (!scene) { if (cell.machine) setState(cell, "error"); return; }
    cell.crane = new Crane3D(cell.view, scene);
  });
  (await Promise.all(models)).forEach((model, i) => { if (model) makePanel(page.cells[i], model); });
  // plotly (4.6 MB to parse) is loaded once a crane is drawn, so it never delays that paint
  page.chartsReady = Promise.race([firstFrame, new Promise((r) => setTimeout(r, 3000))])
    .then(() => loadScript("/static/vendor/plotly.min.js"))
    .then(() => {
      for (const c of page.cells) attachCharts(c);
      if (page.mode === "replay") loadAllHistory(); else for (const c of page.cells) if (c.charts) c.charts.setLive(c.liveBuffer);
    })
    .catch((err) => { for (const c of page.cells) { const m = c.chartsEl.querySelector(".charts-msg"); m.hidden = false; m.textContent = `Charts unavailable: ${err.message}`; } });
  requestAnimationFrame(loop);
  if (mode === "live") setMode("live");
  else if (from !== null && to !== null && to > from) setMode("replay", from, to, parseTime(query.get("t")));
  else { setMode("replay"); note("No stored data for these machines yet. When they send, switch to Live.", "warn"); }
}

// The replay chunks of every machine, asked for as soon as the range is known.
function primeStores(from, to, t) {
  const t0 = t !== null && t >= from && t <= to ? t : from;
  for (const cell of page.cells) {
    if (!cell.machine) continue;
    cell.store = new ReplayStore(cell.source, from, to, REPLAY_RATE_HZ);
    cell.store.prime(t0);
    cell.store.ensure(t0);
  }
}

// ---- modes ---------------------------------------------------------------------------------------
function setMode(mode, from, to, t) {
  page.playing = false;
  for (const c of page.cells) { if (c.live) { c.live.close(); c.live = null; } }
  clearInterval(page.liveCharts);
  page.mode = stats.mode = mode;
  el("mode-live").setAttribute("aria-pressed", String(mode === "live"));
  el("mode-replay").setAttribute("aria-pressed", String(mode === "replay"));
  document.body.dataset.mode = mode;
  note(null);
  if (mode === "live") startLive(); else startReplay(from ?? page.from, to ?? page.to, t);
  playButton();
  saveUrl();
}

function startReplay(from, to, t) {
  const ok = from !== null && to !== null && to > from;
  for (const id of ["slider", "play", "frame-back", "frame-fwd", "zoom-out"]) el(id).disabled = !ok;
  if (!ok) { for (const c of page.cells) if (c.crane) setState(c, "empty"); return; }
  page.from = from; page.to = to;
  el("from").value = toInput(from);
  el("to").value = toInput(to);
  if (!page.cells.some((c) => c.store && c.store.from === from && c.store.to === to)) primeStores(from, to, t);
  for (const cell of page.cells) {
    if (!cell.store) continue;
    cell.store.onLoaded = () => { page.needsFrame = true; };
  }
  page.coverage = stats.coverage = [];
  page.timeline.setRange(from, to);
  setView(from, to);
  seek(t !== null && t !== undefined && t >= from && t <= to ? t : from);
  loadCoverage(from, to).then(() => { if (page.chartsReady && page.from === from && page.to === to) loadAllHistory(); });
}

// Where any of the machines has data (for the timeline and for play to skip the silences of
// all of them), and the events of all of them, on the one timeline.
async function loadCoverage(from, to) {
  const covs = [];
  const events = [];
  await Promise.all(page.cells.filter((c) => c.machine).map(async (c) => {
    const ch = c.panel ? c.panel.coverageChannel() : "payload";
    try { covs.push(coverageFromHistory(await c.source.history(from, to, [ch], 600))); } catch (_) { /* no history */ }
    try { c.events = (await c.source.events(from, to)) || []; } catch (_) { c.events = []; }
    events.push(...c.events);
  }));
  if (page.from !== from || page.to !== to) return;
  page.coverage = stats.coverage = unionCoverage(...covs);
  page.timeline.setCoverage(page.coverage);
  page.timeline.setEvents(events);
}

function setView(a, b) {
  if (page.from === null) return;
  [a, b] = page.timeline.setView(a, b);
  page.view = stats.view = { a, b };
  const s = el("slider");
  s.min = "0"; s.max = String(b - a); s.step = String(FRAME_S);
  if (page.cursor !== null) s.value = String(Math.min(Math.max(page.cursor, a), b) - a);
  el("zoom-out").setAttribute("aria-disabled", String(!page.timeline.zoomed()));
  el("view-label").textContent = page.timeline.zoomed() ? `zoom ${Math.round(b - a)} s of ${Math.round(page.to - page.from)} s` : "";
  for (const c of page.cells) if (c.charts) c.charts.setXRange(a, b);
  if (page.cursor !== null && (page.cursor < a || page.cursor > b)) seek(a);
  // finer history for a zoomed view, once the user stops
  clearTimeout(page.viewTimer);
  page.viewTimer = setTimeout(loadAllHistory, 250);
}

function seek(t) {
  if (page.from === null) return;
  page.cursor = stats.cursor = Math.min(Math.max(t, page.from), page.to);
  const v = page.view;
  if (v && (page.cursor < v.a || page.cursor > v.b)) {
    const w = v.b - v.a;
    const a = page.cursor > v.b ? page.cursor : page.cursor - w;
    setView(a, a + w);
  }
  el("slider").value = String(page.cursor - page.view.a);
  page.timeline.setCursor(page.cursor);
  for (const c of page.cells) if (c.charts) c.charts.setCursor(page.cursor);
  el("time-label").textContent = `${hhmmss(page.cursor)} (${page.speed}×)`;
  page.needsFrame = true;
}

function startLive() {
  for (const id of ["slider", "play", "frame-back", "frame-fwd", "zoom-out"]) el(id).disabled = true;
  for (const cell of page.cells) {
    if (!cell.machine) continue;
    cell.trail = [];
    cell.liveBuffer = new LiveBuffer();
    setState(cell, "loading");
    cellNote(cell, "waiting for live data…");
    cell.live = new LiveFeed(cell.source.liveURL(), {
      frame: (f) => { cell.liveFrame = f; cell.liveDirty = true; stats.cells[cell.id].liveFrames += 1; cell.liveBuffer.push(f); },
      refused: () => cellNote(cell, "the live stream refused this key"),
      lost: (ms) => cellNote(cell, `connection lost — retrying in ${(ms / 1000).toFixed(1)} s`),
    });
  }
  // the rolling live charts, redrawn once a second
  page.liveCharts = setInterval(() => { for (const c of page.cells) if (c.charts && page.mode === "live") c.charts.setLive(c.liveBuffer); }, 1000);
  // a machine that sends nothing does not hold the page back
  setTimeout(() => { for (const c of page.cells) if (c.state === "loading" && page.mode === "live") { setState(c, "empty"); cellNote(c, "no live data — idle or offline"); } }, 3000);
}

// ---- drawing -------------------------------------------------------------------------------------
function loop(now) {
  requestAnimationFrame(loop);
  if (page.lastWall !== null && (page.playing || page.mode === "live")) {
    stats.rafIntervals.push(now - page.lastWall);
    for (const c of page.cells) if (c.crane) c.crane.frameTime(now - page.lastWall);
  }
  const dt = page.lastWall === null ? 0 : (now - page.lastWall) / 1000;
  page.lastWall = now;
  if (page.mode === "live") {
    for (const cell of page.cells) {
      if (!cell.crane || !cell.liveDirty) continue;
      cell.liveDirty = false;
      drawLive(cell.crane, cell.liveFrame, cell.trail);
      showFrame(cell, cell.liveFrame);
      stats.cells[cell.id].liveLatencyMs.push(Date.now() - cell.liveFrame.t * 1000);
      if (cell.state !== "ready") setState(cell, "ready");
      cellNote(cell, "");
    }
    return;
  }
  if (page.mode !== "replay" || page.from === null) return;
  if (page.playing) {
    // one clock for all machines: time runs on through one machine's silence (it shows "no
    // data"); a stretch where none of them has data is skipped
    const stores = page.cells.filter((c) => c.crane && c.store).map((c) => c.store);
    const step = stores.length ? playStep(stores, page.coverage, page.cursor, dt, page.speed, page.to)
      : { kind: "frame", cursor: Math.min(page.cursor + dt * page.speed, page.to), gapsSkipped: 0 };
    stats.gapsSkipped += step.gapsSkipped;
    if (step.kind !== "wait") {
      const jumped = step.kind === "chunk-skipped" || step.gapsSkipped > 0;
      page.cursor = stats.cursor = step.cursor;
      if (page.cursor > page.view.b || page.cursor < page.view.a) { const w = page.view.b - page.view.a; setView(page.cursor, page.cursor + w); }
      if (jumped || now - page.lastUi > 100) {
        page.lastUi = now;
        el("slider").value = String(page.cursor - page.view.a);
        page.timeline.setCursor(page.cursor);
        for (const c of page.cells) if (c.charts) c.charts.setCursor(page.cursor);
        el("time-label").textContent = `${hhmmss(page.cursor)} (${jumped ? "skipping a stretch without data" : `${page.speed}×`})`;
      }
      page.needsFrame = true;
      if (page.cursor >= page.to) { page.playing = false; playButton(); saveUrl(); }
    }
  }
  if (!page.needsFrame) return;
  let waiting = false;
  for (const cell of page.cells) {
    if (!cell.crane || !cell.store) continue;
    const f = drawReplay(cell.crane, cell.store, page.cursor);
    if (f && typeof f === "object") {
      showFrame(cell, f);
      if (cell.state !== "ready") setState(cell, "ready");
    } else {
      if (f === "loading" || f === null) waiting = true;
      if (f !== cell.state && f !== null) setState(cell, f);
    }
  }
  page.needsFrame = waiting;
}

// ---- controls ------------------------------------------------------------------------------------
function playButton() {
  const b = el("play");
  b.textContent = page.playing ? "❚❚" : "▶";
  b.setAttribute("aria-label", page.playing ? "Pause" : "Play");
  el("speed").value = String(page.speed);
}

function togglePlay() {
  if (page.mode !== "replay" || page.from === null) return;
  if (!page.playing && page.cursor >= page.to) seek(page.from);
  page.playing = !page.playing;
  playButton();
  if (!page.playing) saveUrl();
}

function frameStep(dir) {
  if (page.mode !== "replay" || page.from === null) return;
  page.playing = false;
  playButton();
  seek(page.from + (Math.round((page.cursor - page.from) / FRAME_S) + dir) * FRAME_S);
  saveUrl();
}

function shareUrl() {
  const url = new URL(window.location.origin + window.location.pathname);
  url.searchParams.set("machines", wanted.join(","));
  url.searchParams.set("mode", page.mode || "replay");
  if (page.mode === "replay" && page.from !== null) {
    url.searchParams.set("from", isoSeconds(page.from));
    url.searchParams.set("to", isoSeconds(page.to));
    if (page.cursor !== null) url.searchParams.set("t", page.cursor.toFixed(2));
    url.searchParams.set("speed", String(page.speed));
  }
  // the charted channels, when any machine's differ from the defaults: one list for all (each
  // machine charts those it has), so the link compares the same channels
  const panels = page.cells.filter((c) => c.panel).map((c) => c.panel);
  if (panels.some((p) => p.selected.join(",") !== p.defaults().join(","))) {
    url.searchParams.set("ch", [...new Set(panels.flatMap((p) => p.selected))].join(","));
  }
  return url.toString();
}

function saveUrl() {
  const u = new URL(shareUrl());
  window.history.replaceState(null, "", u.pathname + u.search);
}

function wire() {
  el("mode-live").onclick = () => setMode("live");
  el("mode-replay").onclick = () => {
    if (page.from !== null) { setMode("replay"); return; }
    const ends = page.cells.filter((c) => c.machine).map((c) => parseTime((c.machine.data_range || {}).to)).filter((x) => x !== null);
    if (ends.length) { const to = Math.max(...ends); setMode("replay", to - DEFAULT_SPAN_S, to); } else setMode("replay");
  };
  el("play").onclick = togglePlay;
  el("frame-back").onclick = () => frameStep(-1);
  el("frame-fwd").onclick = () => frameStep(1);
  el("slider").oninput = () => { page.playing = false; playButton(); seek(page.view.a + parseFloat(el("slider").value)); };
  el("slider").onchange = saveUrl;
  el("speed").onchange = () => { page.speed = parseFloat(el("speed").value); playButton(); saveUrl(); };
  el("zoom-out").onclick = () => setView(page.from, page.to);
  el("range-form").onsubmit = (ev) => {
    ev.preventDefault();
    const a = fromInput(el("from").value), b = fromInput(el("to").value);
    if (a === null || b === null || !(b > a)) { note("The range must end after it starts.", "error"); return; }
    setMode("replay", a, b, a);
  };
  el("share").onclick = async () => {
    const url = shareUrl();
    try { await navigator.clipboard.writeText(url); note(`Link copied: ${url}`); } catch (_) { note(`Share this link: ${url}`); }
    setTimeout(() => note(null), 4000);
  };
  document.addEventListener("keydown", (ev) => {
    if (ev.target instanceof HTMLInputElement && ev.target.type !== "range") return;
    if (ev.target instanceof HTMLSelectElement || ev.ctrlKey || ev.metaKey || ev.altKey) return;
    switch (ev.key) {
      case " ": ev.preventDefault(); togglePlay(); break;
      case "ArrowRight": if (page.mode === "replay") { ev.preventDefault(); if (ev.shiftKey) seek(page.cursor + 1); else frameStep(1); } break;
      case "ArrowLeft": if (page.mode === "replay") { ev.preventDefault(); if (ev.shiftKey) seek(page.cursor - 1); else frameStep(-1); } break;
      case "+": case "=": page.speed = SPEED_STEPS[Math.min(SPEED_STEPS.length - 1, SPEED_STEPS.indexOf(page.speed) + 1)] || 1; playButton(); break;
      case "-": case "_": page.speed = SPEED_STEPS[Math.max(0, SPEED_STEPS.indexOf(page.speed) - 1)] || 1; playButton(); break;
      case "0": if (page.mode === "replay") setView(page.from, page.to); break;
      case "l": case "L": setMode("live"); break;
      case "r": case "R": el("mode-replay").click(); break;
      case "s": case "S": el("share").click(); break;
      case "Escape": if (!document.querySelector("dialog[open]")) window.location.href = "/"; break;
      default: break;
    }
  });
}

start();
