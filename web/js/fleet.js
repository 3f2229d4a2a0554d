// Fleet page: every machine with status, last seen, payload and alarms; refreshed every 5 s.
import { ApiError, askSignIn, getJSON, relTime, setupSignIn } from "./api.js";
import { initAlarms, refreshAlarms, setMachines } from "./alarms.js";

const $ = (id) => document.getElementById(id);
let machines = [];
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
  const shown = machines.filter((m) => !q || [m.machine_id, m.name, m.model, m.status].join(" ").toLowerCase().includes(q));
  for (const m of shown) {
    const tr = document.createElement("tr");
    tr.className = `machine ${m.status}`;
    tr.dataset.machineId = m.machine_id;
    const link = `/machines/${encodeURIComponent(m.machine_id)}`;
    const payload = m.payload_kg === null || m.payload_kg === undefined ? "–" : `${Math.round(m.payload_kg)} kg`;
    tr.innerHTML = `<td><a href="${link}"></a></td><td></td><td><span class="badge ${m.status}"></span></td>`
      + `<td title="${m.last_seen || ""}"></td><td class="num"></td><td class="num"></td>`;
    tr.querySelector("a").textContent = m.name || m.machine_id;
    tr.children[1].textContent = m.model || "";
    tr.querySelector(".badge").textContent = m.status || "unknown";
    tr.children[3].textContent = relTime(m.last_seen);
    tr.children[4].textContent = payload;
    tr.children[5].textContent = String(m.alarms ?? 0);
    if (m.alarms > 0) tr.children[5].classList.add("alarm");
    tr.onclick = (ev) => { if (ev.target.tagName !== "A") window.location.href = link; };
    rows.appendChild(tr);
  }
  $("empty").hidden = machines.length > 0;
}

async function refresh() {
  try {
    machines = await getJSON("/api/v1/machines");
    machines.sort((a, b) => (a.status === "live" ? 0 : 1) - (b.status === "live" ? 0 : 1) || String(a.name || a.machine_id).localeCompare(String(b.name || b.machine_id)));
    banner(null);
    $("updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
    render();
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

$("filter").oninput = render;
initAlarms();
setupSignIn(() => refresh());
refresh();
setInterval(refresh, 5000);
