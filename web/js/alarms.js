// Alarms panel of the fleet page: every machine's events with filters (machine, severity, kind,
// state, time) and paging, acknowledged and cleared by the signed-in user (role fleet or admin).
import { ApiError, getJSON, postJSON } from "./api.js";

const $ = (id) => document.getElementById(id);
const PAGE = 20;
const state = { offset: 0, total: 0, kinds: [], busy: false };

function fromLocal(v) {
  if (!v) return "";
  const ms = new Date(v).getTime();
  return Number.isNaN(ms) ? "" : String(ms / 1000);
}

function params() {
  return {
    machine: $("f-machine").value, severity: $("f-severity").value, kind: $("f-kind").value,
    state: $("f-state").value, from: fromLocal($("f-from").value), to: fromLocal($("f-to").value),
    limit: PAGE, offset: state.offset,
  };
}

function stateText(a) {
  const at = (x) => new Date(x.at).toLocaleString();
  if (a.cleared) return `cleared by ${a.cleared.by}, ${at(a.cleared)}`;
  if (a.acknowledged) return `acknowledged by ${a.acknowledged.by}, ${at(a.acknowledged)}`;
  return "new";
}

function note(text, kind = "error") {
  const n = $("alarm-note");
  n.hidden = !text;
  n.className = `banner ${kind}`;
  n.textContent = text || "";
}

async function act(id, action) {
  try {
    await postJSON(`/api/v1/alarms/${id}/${action}`);
    note(null);
    await refreshAlarms();
  } catch (err) {
    if (err instanceof ApiError && err.status === 403) {
      note("Acknowledging and clearing need a fleet or admin key; sign out and sign in with one.");
    } else {
      note(`Could not ${action} the alarm: ${err.message}`);
    }
  }
}

function render(body) {
  const rows = $("alarm-rows");
  rows.innerHTML = "";
  for (const a of body.items) {
    const tr = document.createElement("tr");
    tr.className = `alarm ${a.severity}${a.cleared ? " cleared" : ""}`;
    tr.dataset.alarmId = String(a.id);
    tr.innerHTML = "<td></td><td><a></a></td><td><span class=\"badge\"></span></td><td></td><td class=\"state\"></td><td class=\"actions\"></td>";
    tr.children[0].textContent = new Date(a.t * 1000).toLocaleString();
    const link = tr.querySelector("a");
    link.href = `/machines/${encodeURIComponent(a.machine_id)}?mode=replay&from=${a.t - 60}&to=${a.t + 60}&t=${a.t}`;
    link.textContent = a.machine_id;
    const badge = tr.querySelector(".badge");
    badge.textContent = a.severity;
    badge.classList.add(`sev-${a.severity}`);
    tr.children[3].textContent = a.message;
    tr.children[4].textContent = stateText(a);
    const actions = tr.children[5];
    if (!a.acknowledged) {
      const b = document.createElement("button");
      b.type = "button"; b.className = "ack"; b.textContent = "Acknowledge";
      b.onclick = () => act(a.id, "acknowledge");
      actions.appendChild(b);
    }
    if (!a.cleared) {
      const b = document.createElement("button");
      b.type = "button"; b.className = "clear"; b.textContent = "Clear";
      b.onclick = () => act(a.id, "clear");
      actions.appendChild(b);
    }
    rows.appendChild(tr);
  }
  state.total = body.total;
  const last = Math.min(state.offset + body.items.length, body.total);
  $("alarm-count").textContent = `${body.total} ${$("f-state").value === "all" ? "" : $("f-state").value + " "}`.trim();
  $("page-info").textContent = body.total ? `${state.offset + 1}–${last} of ${body.total}` : "none";
  $("alarm-prev").disabled = state.offset === 0;
  $("alarm-next").disabled = last >= body.total;
  $("alarms-empty").hidden = body.items.length > 0;
  const kinds = body.kinds || [];
  if (kinds.join() !== state.kinds.join()) {
    state.kinds = kinds;
    const sel = $("f-kind");
    const keep = sel.value;
    sel.innerHTML = "<option value=\"\">any kind</option>";
    for (const k of kinds) {
      const o = document.createElement("option");
      o.value = k; o.textContent = k.replaceAll("_", " ");
      sel.appendChild(o);
    }
    sel.value = keep;
  }
}

export async function refreshAlarms() {
  if (state.busy) return;
  state.busy = true;
  try {
    render(await getJSON("/api/v1/alarms", params()));
    window.cranetwin.alarmsReady = true;
  } catch (err) {
    if (!(err instanceof ApiError && err.status === 401)) note(`Alarms unavailable: ${err.message}`);
  } finally {
    state.busy = false;
  }
}

// Machines for the machine filter (kept as chosen when the list refreshes).
export function setMachines(machines) {
  const sel = $("f-machine");
  const ids = machines.map((m) => m.machine_id);
  const have = [...sel.options].slice(1).map((o) => o.value);
  if (ids.join() === have.join()) return;
  const keep = sel.value;
  sel.innerHTML = "<option value=\"\">all machines</option>";
  for (const m of machines) {
    const o = document.createElement("option");
    o.value = m.machine_id; o.textContent = m.name || m.machine_id;
    sel.appendChild(o);
  }
  sel.value = keep;
}

export function initAlarms() {
  for (const id of ["f-machine", "f-severity", "f-kind", "f-state", "f-from", "f-to"]) {
    $(id).onchange = () => { state.offset = 0; refreshAlarms(); };
  }
  $("alarm-prev").onclick = () => { state.offset = Math.max(0, state.offset - PAGE); refreshAlarms(); };
  $("alarm-next").onclick = () => { state.offset += PAGE; refreshAlarms(); };
}
