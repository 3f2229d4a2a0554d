// Machine page: 3D crane, live and replay modes, charts on one time cursor, events, share/export.
// The page wires these modules together: source (API or embedded data), crane3d (the scene),
// replay + playback (chunks, play clock), live (websocket, buffers), chartpanel (channel
// picker and load history), timeline.
import { ApiError, askSignIn, download, setupSignIn, isoSeconds, parseTime, relTime } from "./api.js";
import { Crane3D } from "./crane3d.js";
import { ReplayStore } from "./replay.js";
import { Charts } from "./charts.js";
import { Timeline, coverageFromHistory } from "./timeline.js";
import { apiSource, embeddedSource, loadScript } from "./source.js";
import { FRAME_S, REPLAY_RATE_HZ, drawReplay, playStep } from "./playback.js";
import { LiveBuffer, LiveFeed, drawLive } from "./live.js";
import { ChartPanel } from "./chartpanel.js";
import { buildForceRows, showNow } from "./nowcard.js";
import { showSchedule } from "./schedule.js";

const $ = (id) => document.getElementById(id);
const SPEEDS = [0.25, 0.5, 1, 2, 4, 8, 16];

// Measurements read by the browser tests and benchmarks.
const metrics = window.cranetwin = {
  moduleStartMs: performance.now(),
  ready: false, firstFrameMs: null, sceneMs: null, framesRendered: 0, rafIntervals: [],
  liveLatencyMs: [], liveFrames: 0, lastLiveT: null, mode: null, cursor: null, drawnT: null, errors: [],
};

// ---- page state ---------------------------------------------------------------------------------
const embed = window.CRANETWIN_EMBED || null;
const machineId = embed ? embed.machine.machine_id : decodeURIComponent(window.location.pathname.split("/").filter(Boolean).pop());
const source = embed ? embeddedSource(embed) : apiSource(machineId);
const params = new URLSearchParams(window.location.search);
const state = {
  machine: null, model: null, crane: null, charts: null, groups: null,
  mode: null, from: null, to: null, cursor: null, playing: false, view: null, coverage: [],
  panel: null, charts: null, timeline: null,
  speed: Math.min(16, Math.max(0.25, parseFloat(params.get("speed")) || 1)),
  store: null, events: [], live: null, liveFrame: null, liveDirty: false,
  liveBuffer: new LiveBuffer(), liveTrail: [], lastWall: null, lastUrlUpdate: 0,
};

function banner(text, kind = "info") {
  const b = $("banner");
  if (!text) { b.hidden = true; return; }
  b.hidden = false;
  b.className = `banner ${kind}`;
  b.textContent = text;
}

function fmtTime(t) {
  if (t === null || t === undefined) return "–";
  return new Date(t * 1000).toISOString().replace("T", " ").replace(/\.(\d)\d\dZ$/, ".$1");
}
function toLocalInput(t) { return new Date(t * 1000).toISOString().slice(0, 19); }
function fromLocalInput(v) { return v ? Date.parse(v + "Z") / 1000 : null; }

// ---- start ------------------------------------------------------------------------------------
async function start() {
  const t0 = performance.now();
  const machineP = source.machine();
  const modelP = source.model();
  const sceneP = source.scene();
  let machine, model, scene;
  try {
    machine = await machineP;
    // the replay range is known now: fetch the first frame while the scene is still on its way
    planReplay(machine);
    [model, scene] = await Promise.all([modelP, sceneP]);
  } catch (err) {
    return fail(err);
  }
  state.machine = machine;
  state.model = model;
  document.title = `cranetwin · ${machine.name || machine.machine_id}`;
  $("title").textContent = machine.name || machine.machine_id;
  setStatus(machine);
  state.crane = new Crane3D($("view3d"), scene);
  window.__crane = state.crane;
  metrics.sceneMs = performance.now() - t0;
  buildForceRows($("force-rows"), state.crane.spec.cylinders);
  state.panel = new ChartPanel(source, model, { list: $("channel-list"), count: $("channel-count"), charts: $("charts"), msg: $("charts-msg") },
    (params.get("ch") || "").split(","));
  state.panel.buildPicker(pickChannels);
  state.timeline = new Timeline($("timeline"), { onView: (a, b) => setView(a, b, "timeline"), onSeek: (t) => { state.playing = false; updatePlayButton(); seek(t, true); } });
  if (!embed) setupSignIn(() => window.location.reload());
  if (embed) { $("mode-live").disabled = true; $("share").hidden = true; $("export").hidden = true; $("report").hidden = true; $("report-fmt").hidden = true; $("back-link").hidden = true; }
  wireControls();
  if (!embed) showSchedule(machineId, $("schedule-card"), $("schedule-rows")).catch(() => {});
  requestAnimationFrame(loop);
  // plotly (4.6 MB to parse) is loaded once the crane is drawn, so it never delays that paint
  const afterPaint = Promise.race([firstFrame, new Promise((r) => setTimeout(r, 3000))]);
  const chartsReady = afterPaint.then(() => (embed ? null : loadScript("/static/vendor/plotly.min.js"))).then(() => {
    state.panel.attach((groups) => new Charts($("charts"), groups, (t) => { if (state.mode === "replay") seek(t, true); },
      (a, b) => { if (state.mode === "replay") setView(a ?? state.from, b ?? state.to, "chart"); }));
    state.charts = state.panel.charts;
    if (state.view) state.charts.setXRange(state.view.a, state.view.b);
    $("charts").addEventListener("wheel", (ev) => {
      if (state.mode !== "replay" || !state.timeline || state.from === null) return;
      state.timeline.wheel(ev);
    }, { passive: false });
  }).catch((err) => { $("charts-msg").hidden = false; $("charts-msg").textContent = `Charts unavailable: ${err.message}`; });
  state.chartsReady = chartsReady;
  const plan = state.plan;
  if (plan.mode === "live") {
    setMode("live");
  } else if (plan.from !== null) {
    setMode("replay", plan.from, plan.to, plan.t);
  } else {
    setMode("replay", null, null);
    banner("No stored data for this machine yet. When it starts sending, switch to Live.", "warn");
  }
  if (state.mode === "replay" && state.store) drawReplayFrame(); // without waiting for a tick
}

// Mode and range from the URL (or the embedded export, or the machine's stored data range).
function planReplay(machine) {
  const range = machine.data_range || {};
  const dataFrom = parseTime(range.from);
  const dataTo = parseTime(range.to);
  const mode = params.get("mode") || (embed ? "replay" : (machine.status === "live" ? "live" : "replay"));
  const from = embed ? embed.from : parseTime(params.get("from")) ?? (dataTo !== null ? Math.max(dataFrom ?? dataTo - 600, dataTo - 600) : null);
  const to = embed ? embed.to : parseTime(params.get("to")) ?? dataTo;
  const ok = from !== null && to !== null && to > from;
  let t = parseTime(params.get("t"));
  if (ok) t = t !== null && t >= from && t <= to ? t : from;
  state.plan = { mode: mode === "live" && !embed ? "live" : "replay", from: ok ? from : null, to: ok ? to : null, t };
  if (state.plan.mode === "replay" && ok) {
    state.store = new ReplayStore(source, from, to, REPLAY_RATE_HZ);
    if (!source.embedded) state.store.prime(t);
    state.store.ensure(t);
  }
}

function fail(err) {
  metrics.errors.push(String(err));
  if (err instanceof ApiError && err.status === 401) { askKey(err); return; }
  if (err instanceof ApiError && err.status === 404) { banner(`Unknown machine “${machineId}”. ${err.detail || ""}`, "error"); return; }
  if (err instanceof ApiError && err.status === 403) { banner(`This key may not view this machine (${err.detail || "forbidden"}).`, "error"); return; }
  banner(`Could not load the machine: ${err.message}`, "error");
}

function askKey(err) {
  setupSignIn(() => window.location.reload());
  askSignIn(err && err.title === "Signed out" ? "Your session has ended. Enter a key to sign in again." : null);
}

function setStatus(machine) {
  const s = $("status");
  const st = machine.status || "unknown";
  s.textContent = st === "live" ? "live" : `${st}${machine.last_seen ? " · " + relTime(machine.last_seen) : ""}`;
  s.className = `badge ${st}`;
}


// ---- modes --------------------------------------------------------------------------------------
function setMode(mode, from, to, t) {
  state.playing = false;
  stopLive();
  state.mode = metrics.mode = mode;
  $("mode-live").setAttribute("aria-pressed", String(mode === "live"));
  $("mode-replay").setAttribute("aria-pressed", String(mode === "replay"));
  document.body.dataset.mode = mode;
  $("export").setAttribute("aria-disabled", String(mode !== "replay"));
  banner(null);
  if (mode === "live") { startLive(); } else { startReplay(from ?? state.from, to ?? state.to, t); }
  updatePlayButton();
  updateUrl(true);
}

function startReplay(from, to, t) {
  if (from === null || to === null || !(to > from)) {
    $("slider").disabled = true; $("play").disabled = true;
    return;
  }
  state.from = from; state.to = to;
  $("from").value = toLocalInput(from);
  $("to").value = toLocalInput(to);
  $("slider").disabled = false; $("play").disabled = false;
  for (const id of ["frame-back", "frame-fwd", "zoom-out"]) $(id).disabled = false;
  state.coverage = [];
  state.timeline.setRange(from, to);
  const vf = parseTime(params.get("vfrom")), vt = parseTime(params.get("vto"));
  params.delete("vfrom"); params.delete("vto"); // only the first range of the page
  setView(vf !== null && vt !== null && vt > vf ? vf : from, vf !== null && vt !== null && vt > vf ? vt : to, "range");
  if (!state.store || state.store.from !== from || state.store.to !== to) {
    state.store = new ReplayStore(source, from, to, REPLAY_RATE_HZ);
    if (!source.embedded) state.store.prime(t ?? from);
  }
  state.store.onLoaded = (i, entry) => {
    if (entry.state === "empty" && state.store.chunkIndex(state.cursor) === i) banner("No data in this part of the range.", "warn");
    else if (entry.state === "error") banner(`Could not load the replay: ${entry.error.message}`, "error");
    else if (entry.state === "ready") { if (i >= 0 && $("banner").classList.contains("warn")) banner(null); state.needsFrame = true; }
  };
  const t0 = t !== null && t !== undefined && t >= from && t <= to ? t : from;
  seek(t0, false);
  // the cursor's chunk may have been fetched with the scene and settled before this handler
  // existed (a fast "no data" answer): report it now instead of never
  const i0 = state.store.chunkIndex(t0);
  const settled = state.store.chunks.get(i0);
  if (settled && settled.state !== "loading") state.store.onLoaded(i0, settled);
  source.events(from, to).then((events) => { state.events = events || []; state.timeline.setEvents(state.events); renderEvents(); })
    .catch(() => { state.events = []; renderEvents(); });
  state.chartsReady.then(() => loadHistory(from, to));
  loadCoverage(from, to);
}

// The zoomed part of the replay range [a, b]: slider, timeline window and the charts' x axis.
// `by` says who asked ("timeline", "chart", "range", "follow", "keys"): the others follow.
function setView(a, b, by) {
  if (state.from === null || !state.timeline) return;
  [a, b] = state.timeline.setView(a, b);
  state.view = { a, b };
  const slider = $("slider");
  slider.min = "0"; slider.max = String(b - a); slider.step = String(FRAME_S);
  if (state.cursor !== null) slider.value = String(Math.min(Math.max(state.cursor, a), b) - a);
  $("zoom-out").setAttribute("aria-disabled", String(!state.timeline.zoomed()));
  $("view-label").textContent = state.timeline.zoomed() ? `zoom ${fmtDuration(b - a)} of ${fmtDuration(state.to - state.from)}` : "";
  metrics.view = [a, b];
  if (state.charts) state.charts.setXRange(a, b);
  // a cursor outside the view moves into it (a pan or brush is where the user wants to look)
  if (state.cursor !== null && by !== "follow" && (state.cursor < a || state.cursor > b)) seek(a, false);
  // finer history for a zoomed view, once the user stops
  clearTimeout(state.viewTimer);
  if (by !== "range") state.viewTimer = setTimeout(() => loadHistory(a, b), 250);
  updateUrl(false);
}

function fmtDuration(s) {
  if (s < 90) return `${s.toFixed(s < 10 ? 1 : 0)} s`;
  if (s < 5400) return `${(s / 60).toFixed(s < 600 ? 1 : 0).replace(/\.0$/, "")} min`;
  return `${(s / 3600).toFixed(1).replace(/\.0$/, "")} h`;
}

// Where data exist in the range (for the timeline and for play to skip silences).
async function loadCoverage(from, to) {
  try {
    const hist = await source.history(from, to, [state.panel.coverageChannel()], 600);
    if (state.from !== from || state.to !== to) return;
    state.coverage = coverageFromHistory(hist);
    metrics.coverage = state.coverage;
    state.timeline.setCoverage(state.coverage);
  } catch (_) { state.coverage = []; }
}

function pickChannels() {
  metrics.channels = state.panel.selected.slice();
  if (!state.charts) return;
  if (state.mode === "replay") loadHistory(state.view ? state.view.a : state.from, state.view ? state.view.b : state.to);
  else state.charts.setLive(state.liveBuffer);
  updateUrl(true);
}

async function loadHistory(from, to) {
  if (!state.charts) return;
  if (await state.panel.loadHistory(from, to, () => state.events, () => state.cursor)) metrics.historyLoads = (metrics.historyLoads || 0) + 1;
}

function renderEvents() {
  const ol = $("events");
  ol.innerHTML = "";
  $("events-empty").hidden = state.events.length > 0;
  for (const ev of state.events) {
    const li = document.createElement("li");
    const b = document.createElement("button");
    b.type = "button";
    b.className = `event ${ev.severity || ""}`;
    b.textContent = `${fmtTime(ev.t).slice(11)} ${ev.kind}: ${ev.message || ""}`;
    b.onclick = () => { if (state.mode !== "replay") setMode("replay"); seek(ev.t, true); };
    li.appendChild(b);
    ol.appendChild(li);
  }
  if (state.charts && state.mode === "replay") loadHistory(state.view ? state.view.a : state.from, state.view ? state.view.b : state.to);
}

function seek(t, userAction) {
  if (state.from === null) return;
  state.cursor = metrics.cursor = Math.min(Math.max(t, state.from), state.to);
  followCursor();
  $("slider").value = String(state.cursor - state.view.a);
  state.timeline.setCursor(state.cursor);
  state.needsFrame = true;
  if (userAction) updateUrl(true);
}

// ---- live ---------------------------------------------------------------------------------------
// Keeps the cursor inside the view: the view moves on by its width when the cursor leaves it.
function followCursor() {
  const v = state.view;
  if (!v || (state.cursor >= v.a && state.cursor <= v.b)) return;
  const w = v.b - v.a;
  const a = state.cursor > v.b ? state.cursor : state.cursor - w;
  setView(a, a + w, "follow");
}

// One frame (1/25 s) forward or back, on the twin's frame grid; pauses play.
function frameStep(dir) {
  if (state.mode !== "replay" || state.from === null) return;
  state.playing = false;
  updatePlayButton();
  const k = Math.round((state.cursor - state.from) / FRAME_S);
  seek(state.from + (k + dir) * FRAME_S, true);
}

function startLive() {
  $("slider").disabled = true;
  $("play").disabled = true;
  for (const id of ["frame-back", "frame-fwd", "zoom-out"]) $(id).disabled = true;
  state.liveBuffer = new LiveBuffer();
  state.liveTrail = [];
  state.live = new LiveFeed(source.liveURL(), {
    open: () => banner("Connected — waiting for data from the machine…", "info"),
    error: (text) => { state.liveError = true; banner(text, "error"); },
    frame: (f) => {
      state.liveFrame = f;
      state.liveDirty = true;
      metrics.liveFrames += 1;
      state.liveBuffer.push(f);
    },
    refused: (code) => banner(code === 4404 ? `Unknown machine “${machineId}”.` : "The live stream refused this key.", "error"),
    lost: (ms) => banner(`Live connection lost — reconnecting in ${(ms / 1000).toFixed(1)} s…`, "error"),
  });
  state.liveWatch = setInterval(() => {
    if (state.mode !== "live") return;
    const quiet = state.live.quietS();
    if (quiet > 3 && state.live.connected) {
      const seen = state.machine && state.machine.last_seen ? ` Last seen ${relTime(state.machine.last_seen)}.` : "";
      banner(`No live data for ${Math.round(quiet)} s — the machine is idle or offline.${seen} Use Replay to see stored data.`, "warn");
    } else if (quiet <= 1 && $("banner").classList.contains("warn")) {
      banner(null);
    } else if (quiet <= 1 && $("banner").textContent.startsWith("Connected")) {
      banner(null);
    }
    if (state.charts) state.charts.setLive(state.liveBuffer);
  }, 1000);
}

function stopLive() {
  if (state.live) { state.live.close(); state.live = null; }
  clearInterval(state.liveWatch);
}

// ---- rendering loop -----------------------------------------------------------------------------
function loop(now) {
  requestAnimationFrame(loop);
  if (state.lastWall !== null && (state.playing || state.mode === "live")) {
    metrics.rafIntervals.push(now - state.lastWall);
    if (state.crane) state.crane.frameTime(now - state.lastWall);
  }
  const dt = state.lastWall === null ? 0 : (now - state.lastWall) / 1000;
  state.lastWall = now;
  if (!state.crane) return;
  if (state.mode === "live") {
    if (!state.liveDirty) return;
    state.liveDirty = false;
    const f = state.liveFrame;
    drawLive(state.crane, f, state.liveTrail);
    readout(f);
    metrics.lastLiveT = f.t;
    metrics.liveLatencyMs.push(Date.now() - f.t * 1000);
    rendered();
    return;
  }
  if (state.mode !== "replay" || !state.store) return;
  if (state.playing) {
    const step = playStep(state.store, state.coverage, state.cursor, dt, state.speed, state.to);
    // silences (no data) are skipped, not played through in real time
    if (step.gapsSkipped) metrics.gapsSkipped = (metrics.gapsSkipped || 0) + step.gapsSkipped;
    if (step.kind === "frame") {
      state.cursor = metrics.cursor = step.cursor;
      followCursor();
      if (now - (state.lastSliderPaint || 0) > 100) {
        state.lastSliderPaint = now;
        $("slider").value = String(state.cursor - state.view.a);
        state.timeline.setCursor(state.cursor);
      }
      state.needsFrame = true;
      if (state.cursor >= state.to) { state.playing = false; updatePlayButton(); updateUrl(true); }
    } else if (step.kind === "chunk-skipped") {
      // a whole chunk without data: on to the next chunk at once
      state.cursor = metrics.cursor = step.cursor;
      followCursor();
      $("slider").value = String(state.cursor - state.view.a);
      state.timeline.setCursor(state.cursor);
      $("time-label").textContent = `${fmtTime(state.cursor).slice(11)} (skipping a stretch without data)`;
      if (state.cursor >= state.to) { state.playing = false; updatePlayButton(); }
    }
  }
  if (state.needsFrame) drawReplayFrame();
}

function drawReplayFrame() {
  const f = drawReplay(state.crane, state.store, state.cursor);
  if ((f === "loading" || f === "empty") && !state.playing) $("time-label").textContent = `${fmtTime(state.cursor).slice(11)} (${f === "empty" ? "no data" : "loading…"})`;
  if (!f || typeof f !== "object") return;
  state.needsFrame = false;
  metrics.drawnT = f.t;
  readout(f);
  rendered();
}

let firstFrameDone;
const firstFrame = new Promise((r) => { firstFrameDone = r; });

function rendered() {
  metrics.framesRendered += 1;
  if (metrics.firstFrameMs === null) {
    // draw the first frame now (the first render also compiles the shaders), so the time
    // recorded is when the posed crane is really on the canvas
    const r0 = performance.now();
    state.crane.viewer.render();
    metrics.firstRenderMs = performance.now() - r0;
    metrics.firstFrameMs = performance.now();
    setTimeout(firstFrameDone, 50); // let the frame reach the screen first
    metrics.ready = true;
    document.body.dataset.ready = "1";
  }
}

let lastReadout = 0;
function readout(f) {
  const now = performance.now();
  if (now - lastReadout < 100 && state.playing) return;
  if (state.charts) state.charts.setCursor(state.mode === "replay" ? state.cursor : null);
  lastReadout = now;
  $("now-time").textContent = fmtTime(f.t);
  $("time-label").textContent = state.mode === "replay" ? `${fmtTime(state.cursor).slice(11)} (${state.speed}×)`
    : `live · ${Math.max(0, Math.round(Date.now() - f.t * 1000))} ms behind`;
  const env = showNow(f, state.crane);
  if (env) metrics.envelope = env;
}

// ---- controls -----------------------------------------------------------------------------------
function updatePlayButton() {
  const b = $("play");
  b.textContent = state.playing ? "❚❚" : "▶";
  b.setAttribute("aria-label", state.playing ? "Pause" : "Play");
  $("speed").value = String(state.speed);
}

function togglePlay() {
  if (state.mode !== "replay" || state.from === null) return;
  if (!state.playing && state.cursor >= state.to) seek(state.from, false);
  state.playing = !state.playing;
  updatePlayButton();
  if (!state.playing) updateUrl(true);
}

function setSpeed(s) {
  state.speed = s;
  updatePlayButton();
  updateUrl(true);
}

function shareURL() {
  const url = new URL(window.location.origin + window.location.pathname);
  url.searchParams.set("mode", state.mode);
  if (state.mode === "replay" && state.from !== null) {
    url.searchParams.set("from", isoSeconds(state.from));
    url.searchParams.set("to", isoSeconds(state.to));
    if (state.cursor !== null) url.searchParams.set("t", state.cursor.toFixed(2));
    url.searchParams.set("speed", String(state.speed));
    if (state.timeline && state.timeline.zoomed()) {
      url.searchParams.set("vfrom", state.view.a.toFixed(2));
      url.searchParams.set("vto", state.view.b.toFixed(2));
    }
  }
  const sel = state.panel ? state.panel.selected : [];
  if (sel.length && sel.join(",") !== state.panel.defaults().join(",")) url.searchParams.set("ch", sel.join(","));
  return url.toString();
}

function updateUrl(force) {
  if (embed) return;
  const now = performance.now();
  if (!force && now - state.lastUrlUpdate < 1000) return;
  state.lastUrlUpdate = now;
  const u = new URL(shareURL());
  window.history.replaceState(null, "", u.pathname + u.search);
}

function jumpEvent(dir) {
  if (state.events.length === 0) return;
  if (state.mode !== "replay") setMode("replay");
  const evs = state.events.map((e) => e.t).sort((a, b) => a - b);
  const c = state.cursor ?? state.from;
  const t = dir > 0 ? evs.find((x) => x > c + 0.05) : [...evs].reverse().find((x) => x < c - 0.05);
  if (t !== undefined) seek(t, true);
}

function wireControls() {
  $("mode-live").onclick = () => setMode("live");
  $("mode-replay").onclick = () => {
    if (state.from === null) {
      const r = state.machine.data_range || {};
      const to = parseTime(r.to);
      if (to !== null) { setMode("replay", Math.max(parseTime(r.from) ?? to - 600, to - 600), to); return; }
    }
    setMode("replay");
  };
  $("play").onclick = togglePlay;
  $("slider").oninput = () => { state.playing = false; updatePlayButton(); seek(state.view.a + parseFloat($("slider").value), false); };
  $("frame-back").onclick = () => frameStep(-1);
  $("frame-fwd").onclick = () => frameStep(1);
  $("zoom-out").onclick = () => setView(state.from, state.to, "keys");
  $("slider").onchange = () => updateUrl(true);
  $("speed").onchange = () => setSpeed(parseFloat($("speed").value));
  $("range-form").onsubmit = (ev) => {
    ev.preventDefault();
    const from = fromLocalInput($("from").value);
    const to = fromLocalInput($("to").value);
    if (from === null || to === null || !(to > from)) { banner("The range must end after it starts.", "error"); return; }
    setMode("replay", from, to, from);
  };
  $("preset").onchange = () => {
    const v = $("preset").value;
    const r = state.machine.data_range || {};
    const end = parseTime(r.to) ?? Date.now() / 1000;
    const start = parseTime(r.from) ?? end - 600;
    // a preset never reaches before the first stored sample
    if (v === "all") setMode("replay", start, end, null);
    else if (v) {
      const want = parseFloat(v);
      setMode("replay", Math.max(start, end - want), end, null);
      if (end - start < want) banner(`Only ${fmtDuration(end - start)} of data stored: showing all of it.`, "info");
    }
    $("preset").value = "";
  };
  $("share").onclick = async () => {
    const url = shareURL();
    try { await navigator.clipboard.writeText(url); banner(`Link copied: ${url}`, "info"); }
    catch (_) { banner(`Share this link: ${url}`, "info"); }
    setTimeout(() => banner(null), 4000);
  };
  $("help-btn").onclick = () => $("help").showModal();
  $("follow").onclick = () => {
    const on = $("follow").getAttribute("aria-pressed") !== "true";
    $("follow").setAttribute("aria-pressed", String(on));
    state.crane.setFollow(on);
    metrics.follow = on;
    state.needsFrame = true; state.liveDirty = true;
  };
  $("envelope").onclick = () => {
    const on = $("envelope").getAttribute("aria-pressed") !== "true";
    $("envelope").setAttribute("aria-pressed", String(on));
    state.crane.setEnvelopeVisible(on);
  };
  $("export").onclick = async (ev) => {
    ev.preventDefault();
    if (state.mode !== "replay" || state.from === null) { banner("Export needs a replay range: switch to Replay (R) and choose one.", "warn"); return; }
    // the window around the cursor, at most 10 minutes
    const len = Math.min(600, state.to - state.from);
    const a = Math.max(state.from, Math.min(state.cursor - len / 2, state.to - len));
    const b = a + len;
    banner(`Exporting ${fmtTime(a)} – ${fmtTime(b).slice(11)} …`, "info");
    try {
      const size = await download(`/api/v1/machines/${encodeURIComponent(machineId)}/export.html?from=${a}&to=${b}`,
        `cranetwin-${machineId}-${isoSeconds(a).replace(/[:]/g, "")}.html`);
      banner(`Exported (${(size / 1e6).toFixed(1)} MB): one HTML file that replays offline.`, "info");
    } catch (err) {
      banner(`Export failed: ${err.message}`, "error");
    }
  };
  $("report").onclick = async (ev) => {
    ev.preventDefault();
    if (state.mode !== "replay" || state.from === null) { banner("A report needs a replay range: switch to Replay (R) and choose one.", "warn"); return; }
    // the service replays the range for a report: at most one hour, ending at the replay range's end
    const b = state.to;
    const a = Math.max(state.from, b - 3600);
    const fmt = $("report-fmt").value;
    const ext = fmt === "csv" ? "zip" : fmt;
    banner(`Building the ${fmt.toUpperCase()} report of ${fmtTime(a)} – ${fmtTime(b).slice(11)} …`, "info");
    try {
      const size = await download(`/api/v1/machines/${encodeURIComponent(machineId)}/report?from=${a}&to=${b}&format=${fmt}`,
        `cranetwin-report-${machineId}-${isoSeconds(a).replace(/[:]/g, "")}.${ext}`);
      banner(`Report downloaded (${(size / 1e3).toFixed(0)} kB).`, "info");
    } catch (err) {
      const hint = err.status === 403 ? " Reports need a fleet or admin key (cranetwin keys create --role fleet)." : "";
      banner(`Report failed: ${err.message}.${hint}`, "error");
    }
  };
  document.addEventListener("keydown", (ev) => {
    if (ev.target instanceof HTMLInputElement && ev.target.type !== "range") return;
    if (ev.target instanceof HTMLSelectElement || ev.ctrlKey || ev.metaKey || ev.altKey) return;
    const step = ev.shiftKey ? 1 : 10;
    switch (ev.key) {
      case " ": ev.preventDefault(); togglePlay(); break;
      case "ArrowRight": if (state.mode === "replay") { ev.preventDefault(); if (ev.shiftKey) seek(state.cursor + 1, true); else frameStep(1); } break;
      case "ArrowLeft": if (state.mode === "replay") { ev.preventDefault(); if (ev.shiftKey) seek(state.cursor - 1, true); else frameStep(-1); } break;
      case "PageDown": if (state.mode === "replay") { ev.preventDefault(); seek(state.cursor + step, true); } break;
      case "PageUp": if (state.mode === "replay") { ev.preventDefault(); seek(state.cursor - step, true); } break;
      case "z": case "Z": if (state.mode === "replay" && state.timeline) state.timeline.zoomBy(ev.key === "z" ? 0.5 : 2, state.cursor); break;
      case "0": if (state.mode === "replay" && state.from !== null) setView(state.from, state.to, "keys"); break;
      case "Home": if (state.mode === "replay") { ev.preventDefault(); seek(state.from, true); } break;
      case "End": if (state.mode === "replay") { ev.preventDefault(); seek(state.to, true); } break;
      case "+": case "=": setSpeed(SPEEDS[Math.min(SPEEDS.length - 1, SPEEDS.indexOf(state.speed) + 1)] || 1); break;
      case "-": case "_": setSpeed(SPEEDS[Math.max(0, SPEEDS.indexOf(state.speed) - 1)] || 1); break;
      case "n": case "N": jumpEvent(1); break;
      case "p": case "P": jumpEvent(-1); break;
      case "l": case "L": if (!embed) setMode("live"); break;
      case "r": case "R": $("mode-replay").click(); break;
      case "s": case "S": if (!embed) $("share").click(); break;
      case "f": case "F": $("follow").click(); break;
      case "e": case "E": $("envelope").click(); break;
      case "?": $("help").showModal(); break;
      case "Escape": if (!embed && !document.querySelector("dialog[open]")) window.location.href = "/"; break;
      default: break;
    }
  });
  if (!embed) {
    setInterval(async () => {
      try { state.machine = { ...state.machine, ...(await source.machine()) }; setStatus(state.machine); }
      catch (err) { if (err.status === 0) banner("The cranetwin service does not answer — retrying.", "error"); }
    }, 10000);
  }
}

start();
