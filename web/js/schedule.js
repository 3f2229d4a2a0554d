// Service schedule card of the machine page: each maintenance item, when it is due and its state.
import { getJSON } from "./api.js";

const SCHEDULE_UNIT = { operating_hours: "h", lifts: "lifts", damage_fraction: "D", calendar_days: "d" };

function scheduleNumber(v) {
  if (v === null || v === undefined) return "–";
  return Math.abs(v) >= 100 ? v.toFixed(0) : Math.abs(v) >= 1 ? v.toFixed(1) : v.toPrecision(2);
}

function scheduleRow(it) {
  const tr = document.createElement("tr");
  tr.className = `schedule-${it.status}`;
  const unit = SCHEDULE_UNIT[it.basis] || "";
  const due = it.due_at.at ? it.due_at.at.slice(0, 10) : "–";
  const cells = [it.item + (it.detail ? ` (${it.detail})` : ""), `${scheduleNumber(it.due_at.value)} ${unit}`,
    `${scheduleNumber(it.current)} ${unit}`, due, it.status];
  for (const text of cells) {
    const td = document.createElement("td");
    td.textContent = text;
    tr.append(td);
  }
  tr.title = `every ${it.interval} ${unit} (${it.basis.replace("_", " ")}); last done ${it.last_done.at}` +
    (it.rate_per_day ? `; ${scheduleNumber(it.rate_per_day)} ${unit} per day lately` : "");
  return tr;
}

/** Fill the table `tbody` with the machine's service schedule; hide `card` when it has none. */
export async function showSchedule(machineId, card, tbody) {
  const data = await getJSON(`/api/v1/machines/${encodeURIComponent(machineId)}/schedules`);
  const items = data.items || [];
  tbody.replaceChildren(...items.map(scheduleRow));
  card.hidden = items.length === 0;
  return items.length;
}
