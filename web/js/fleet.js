// Fleet page: every machine with status, last seen, payload and alarms; refreshed every 5 s.
import { ApiError, askSignIn, getJSON, relTime, setupSignIn } from "./api.js";
import { initAlarms, refreshAlarms, setMachines } from "./alarms.js";
import { FleetMap } from "./fleetmap.js";

const $ = (id) => document.getElementById(id);
let machines = [];
let figures = { machines: {}, total: null };
const sort = { key: "status", dir: 1 };
const STATUS_ORDER = { live: 0, idle: 1, offline: 2 };
const map = new FleetMap($("map"));
const compareSel = new Set(); // machine ids ticked for the compare page (2 to 4)
const COMPARE_MAX = 4;

function figure(m, k) { return (figures.machines[m.machine_id] || {})[k] ?? null; }

function sortValue(m, key) {
  switch (key) {
    case "name": return String(m.name || m.machine_id).toLowerCase();
    case "model": return String(m.model || "");
    case "status": return STATUS_ORDER[m.status] ?? 3;
    case "last_seen": return m.last_seen ? Date.parse(m.last_seen) : -Infinity;
    case "payload_kg": return m.payload_kg ?? -Infinity;
    case "alarms": return m.alarms ?? 0;
    default: return figure(m, key) ?? -Infinity;
  }
}

function compare(a, b) {
  const va = sortValue(a, sort.key);
  const vb = sortValue(b, sort.key);
  const c = typeof va === "string" ? va.localeCompare(vb) : (va > vb) - (va < vb);
  return c * sort.dir || String(a.name || a.machine_id).localeCompare(String(b.name || b.machine_id));
}

const fmt = (x, digits = 0) => (x === null || x === undefined ? "–" : x.toLocaleString(undefined, { maximumFractionDigits: digits, minimumFractionDigits: digits }));

function renderFigures() {
  const counts = { live: 0, idle: 0, offline: 0 };
  for (const m of machines) counts[m.status] = (counts[m.status] || 0) + 1;
  $("fig-machines").textContent = String(machines.length);
  $("fig-status").textContent = `${counts.live} live · ${counts.idle} idle · ${counts.offline} offline`;
  const t = figures.total;
  if (!t) return;
  $("fig-hours").textContent = `${fmt(t.operating_h, 1)} h`;
  $("fig-lifts").textContent = fmt(t.lifts);
  $("fig-tonnes").textContent = `${fmt(t.tonnes, 1)} t`;
  $("fig-alarms").textContent = fmt(t.alarms_today);
  $("fig-critical").textContent = `${t.critical_today} critical`;
  $("fig-alarms").classList.toggle("alarm", t.critical_today > 0);
}
window.cranetwin = { ready: false, refreshes: 0, alarmsReady: false };

function banner(text, kind = "info") {
  const b = $("banner");
  b.hidden = !text;
  if (text) { b.className = `banner ${kind}`; b.textContent = text; }
}

function render() {
  const q = $("filter").value.trim().toLowerCase();
  const rows = $("rows");
  rows.innerHTML = "";
  const st = $("status-filter").value;
  const shown = machines.filter((m) => (!q || [m.machine_id, m.name, m.model, m.status].join(" ").toLowerCase().includes(q))
    && (!st || m.status === st)).sort(compare);
  for (const th of document.querySelectorAll("#machines th[data-sort]")) {
    th.setAttribute("aria-sort", th.dataset.sort === sort.key ? (sort.dir > 0 ? "ascending" : "descending") : "none");
  }
  for (const m of shown) {
    const tr = document.createElement("tr");
    tr.className = `machine ${m.status}`;
    tr.dataset.machineId = m.machine_id;
    const link = `/machines/${encodeURIComponent(m.machine_id)}`;
    const payload = m.payload_kg === null || m.payload_kg === undefined ? "–" : `${Math.round(m.payload_kg)} kg`;
    tr.innerHTML = `<td><a href="${link}"></a></td><td></td><td><span class="badge ${m.status}"></span></td>`
      + `<td title="${m.last_seen || ""}"></td><td class="num"></td><td class="num"></td><td class="num"></td><td class="num"></td><td class="num"></td>`
      + `<td class="pick"><input type="checkbox" class="compare-pick"></td>`;
    tr.querySelector("a").textContent = m.name || m.machine_id;
    tr.children[1].textContent = m.model || "";
    tr.querySelector(".badge").textContent = m.status || "unknown";
    tr.children[3].textContent = relTime(m.last_seen);
    tr.children[4].textContent = payload;
    tr.children[5].textContent = fmt(figure(m, "operating_h"), 1);
    tr.children[6].textContent = fmt(figure(m, "lifts"));
    tr.children[7].textContent = fmt(figure(m, "tonnes"), 1);
    tr.children[8].textContent = String(m.alarms ?? 0);
    if (m.alarms > 0) tr.children[8].classList.add("alarm");
    const pick = tr.querySelector(".compare-pick");
    pick.checked = compareSel.has(m.machine_id);
    pick.setAttribute("aria-label", `Compare ${m.name || m.machine_id}`);
    pick.onchange = () => { if (pick.checked) compareSel.add(m.machine_id); else compareSel.delete(m.machine_id); compareButton(); };
    tr.children[9].onclick = (ev) => ev.stopPropagation();
    tr.onclick = (ev) => { if (ev.target.tagName !== "A") window.location.href = link; };
    tr.onmouseenter = () => map.highlight(m.machine_id);
    tr.onmouseleave = () => map.highlight(null);
    rows.appendChild(tr);
  }
  // the map shows what the table shows
  map.update(shown).then((n) => { window.cranetwin.mapMarkers = n; window.cranetwin.mapReady = true; })
    .catch((err) => { window.cranetwin.mapError = String(err); });
  $("empty").hidden = machines.length > 0;
  compareButton();
}

function compareButton() {
  for (const id of [...compareSel]) if (!machines.some((m) => m.machine_id === id)) compareSel.delete(id);
  const n = compareSel.size;
  const b = $("compare");
  b.textContent = `Compare (${n})`;
  b.disabled = n < 2 || n > COMPARE_MAX;
  b.title = n > COMPARE_MAX ? `At most ${COMPARE_MAX} machines side by side` : "Open 2 to 4 ticked machines side by side";
}

async function refresh() {
  try {
    machines = await getJSON("/api/v1/machines");
    try { figures = await getJSON("/api/v1/fleet/figures"); } catch (e) { if (e instanceof ApiError && e.status === 401) throw e; }
    banner(null);
    $("updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
    render();
    renderFigures();
    setMachines(machines);
    await refreshAlarms();
    window.cranetwin.ready = true;
    window.cranetwin.refreshes += 1;
    document.body.dataset.ready = "1";
  } catch (err) {
    if (err instanceof ApiError && err.status === 401) {
      askSignIn(err.title === "Signed out" ? "Your session has ended. Enter a key to sign in again." : null);
      return;
    }
    banner(`Cannot reach the service (${err.message}). Showing the last list; retrying.`, "error");
  }
}

$("compare").onclick = () => {
  const ids = machines.map((m) => m.machine_id).filter((id) => compareSel.has(id));
  if (ids.length >= 2 && ids.length <= COMPARE_MAX) window.location.href = `/compare?machines=${ids.map(encodeURIComponent).join(",")}`;
};
$("filter").oninput = render;
$("status-filter").onchange = render;
for (const th of document.querySelectorAll("#machines th[data-sort]")) {
  th.querySelector("button").onclick = () => {
    sort.dir = sort.key === th.dataset.sort ? -sort.dir : 1;
    sort.key = th.dataset.sort;
    render();
  };
}
initAlarms();
setupSignIn(() => refresh());
refresh();
setInterval(refresh, 5000);
