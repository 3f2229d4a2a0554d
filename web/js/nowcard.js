// The "Now" readout of a crane frame: payload, reach, rated payload there, utilisation and the
// cylinder forces (machine page) with the replayed window's verdicts on them (force not
// resolved by the pressures, pressures inconsistent with the motion), and the one-line load
// summary written over a 3D view.

const byId = (id) => document.getElementById(id);

// "load 250 kg · 61 % of the rated 410 kg at 5.2 m" (env: Crane3D.envelopeState), or "".
export function loadLine(kg, env) {
  if (kg === null || kg === undefined || !env) return "";
  return `load ${Math.round(kg)} kg · ${Math.round(100 * env.utilisation)} % of the rated ${Math.round(env.rated_kg)} kg at ${env.reach_m.toFixed(1)} m`;
}

// CSS class of a utilisation (fraction of the rating).
export function utilClass(u) { return u > 1 ? "over" : u > 0.8 ? "high" : ""; }

// The limits the service judges a replayed window by (docs/ACCURACY.md; the same numbers as
// cranetwin.twin.observability and cranetwin.twin.consistency).
export const RESOLVABLE_SHARE = 0.1; // pressure error / force range above this: not resolved
export const FORCE_ACCURACY_TARGET = 0.04; // systematic floor / force range above this: not resolved
export const CONSISTENCY_SHARE = 0.1; // residual / force the motion needs, above this ...
export const CONSISTENCY_NOISE = 3; // ... and this many times the noise: inconsistent

// A force [N] as people write it: "850 N", "12.3 kN".
export function newtons(x) {
  if (x === null || x === undefined || !Number.isFinite(x)) return "–";
  return Math.abs(x) >= 1000 ? `${(x / 1000).toFixed(1)} kN` : `${Math.round(x)} N`;
}
const pct = (x, digits = 0) => `${(100 * x).toFixed(digits)} %`;

// Why the replayed window's pressures cannot resolve a cylinder's force (one
// force_observability entry of the twin result), or "" when they can; `brief`: the short line
// under the table, else the full reason (the badge's tooltip).
export function observabilityNote(v, brief = false) {
  if (!v || v.observable !== false) return "";
  const causes = Array.isArray(v.causes) && v.causes.length ? ` (${v.causes.join(", ")})` : "";
  const constant = v.share === null || v.share === undefined;
  if (brief) {
    const floor = v.systematic_n > 0 ? `, systematic floor ±${newtons(v.systematic_n)}` : "";
    return `${v.cylinder}: force not resolved${causes}: error ±${newtons(v.sigma_n)}${floor}`
      + (constant ? " on a force that does not change here" : ` against a ${newtons(v.range_n)} range (${pct(v.share)})`);
  }
  const range = constant
    ? "a force that does not change in this window"
    : `a force range of ${newtons(v.range_n)} (${pct(v.share)}; limit ${pct(RESOLVABLE_SHARE)})`;
  let text = `${v.cylinder}: force not resolved${causes}: pressure error ±${newtons(v.sigma_n)}`
    + ` (1σ, ${v.source || "unknown source"}) against ${range}`;
  if (v.systematic_n > 0) {
    const share = v.systematic_share === null || v.systematic_share === undefined ? "" : ` = ${pct(v.systematic_share, 1)}`;
    text += `; systematic floor ±${newtons(v.systematic_n)} (stated accuracy beyond the noise)${share}`
      + ` (limit ${pct(FORCE_ACCURACY_TARGET)})`;
  }
  return text;
}

// Why a cylinder's pressures disagree with the motion's inverse dynamics (one
// model_consistency entry), or "" when they agree; `brief` as above.
export function consistencyNote(v, brief = false) {
  if (!v || v.consistent !== false) return "";
  if (brief) {
    let text = `${v.cylinder}: pressures disagree with the motion: residual ${newtons(v.typical_n)}`;
    if (Number.isFinite(v.share)) text += ` = ${pct(v.share)} of the force needed`;
    if (Number.isFinite(v.noise_ratio)) text += `, ${v.noise_ratio.toFixed(1)}× the noise`;
    return v.hint ? `${text}; likely ${v.hint}` : text;
  }
  let text = `${v.cylinder}: pressures disagree with the motion (machine file, mapping or sensor calibration):`
    + ` force residual ${newtons(v.typical_n)}`;
  if (Number.isFinite(v.share)) text += ` = ${pct(v.share)} of the force the motion needs (${newtons(v.level_n)} RMS; limit ${pct(CONSISTENCY_SHARE)})`;
  if (Number.isFinite(v.noise_ratio)) text += ` and ${v.noise_ratio.toFixed(1)}× what sensor noise explains (±${newtons(v.noise_n)}; limit ${CONSISTENCY_NOISE}×)`;
  if (v.hint) text += `; likely ${v.hint}`;
  return text;
}

// What the Now card shows of the verdicts (reset when the rows are built).
let shownVerdicts = { obs: undefined, con: undefined };

// One row per cylinder in `tbody`: name, force (with a badge when the window's pressures do
// not resolve it, another when they disagree with the motion), a utilisation bar.
export function buildForceRows(tbody, cylinders) {
  tbody.innerHTML = "";
  for (const c of cylinders) {
    const tr = document.createElement("tr");
    tr.innerHTML = `<th scope="row">${c}</th><td><span id="f-${c}">–</span>`
      + ` <span class="flag" id="fo-${c}" hidden>±&nbsp;not resolved</span>`
      + ` <span class="flag" id="fc-${c}" hidden>≠&nbsp;model</span></td>`
      + `<td><div class="bar"><div id="u-${c}"></div></div></td>`;
    tbody.appendChild(tr);
  }
  shownVerdicts = { obs: undefined, con: undefined };
}

// The badges and the note lines (list `#force-notes`) of the verdicts `obs`, `con` ({cylinder:
// entry} of the replayed window, or null: none known, e.g. live); the DOM is touched only when
// they change (a new chunk).
export function showVerdicts(cylinders, obs, con) {
  obs = obs || null;
  con = con || null;
  if (shownVerdicts.obs === obs && shownVerdicts.con === con) return;
  shownVerdicts = { obs, con };
  const lines = [];
  for (const c of cylinders) {
    for (const [id, note, v] of [[`fo-${c}`, observabilityNote, obs && obs[c]], [`fc-${c}`, consistencyNote, con && con[c]]]) {
      const badge = byId(id);
      if (!badge) continue;
      const text = note(v);
      badge.hidden = !text;
      if (text) { badge.title = text; lines.push([id, note(v, true)]); } else badge.removeAttribute("title");
    }
  }
  const list = byId("force-notes");
  if (!list) return;
  list.innerHTML = "";
  for (const [id, text] of lines) {
    const li = document.createElement("li");
    li.dataset.for = id;
    li.textContent = text;
    list.appendChild(li);
  }
  list.hidden = lines.length === 0;
}

// Writes frame `f` of `crane` into the Now card and the view's overlay line; returns the
// envelope state (or null).
export function showNow(f, crane) {
  const kg = f.payload_kg;
  byId("now-payload").textContent = kg === null || kg === undefined ? "unknown" : `${Math.round(kg)} kg`;
  const env = crane.envelopeState;
  const rated = env ? env.rated_kg : crane.spec.rated_payload_kg;
  byId("payload-bar").style.width = rated ? `${Math.min(100, 100 * (kg || 0) / rated)}%` : "0%";
  if (!env && !rated) { // the machine has no rated-load chart
    byId("now-rated").textContent = "unknown";
    byId("now-util").textContent = "unknown (no rated-load chart)";
  }
  if (env) {
    byId("now-reach").textContent = `${env.reach_m.toFixed(2)} m`;
    byId("now-rated").textContent = `${Math.round(env.rated_kg)} kg`;
    const u = byId("now-util");
    u.textContent = kg === null || kg === undefined ? "–" : `${Math.round(100 * env.utilisation)} % of rated`;
    u.className = utilClass(env.utilisation);
    byId("readout").textContent = loadLine(kg, env);
  }
  for (const c of crane.spec.cylinders) {
    const F = (f.cylinder_forces || {})[c];
    const u = (f.utilisation || {})[c];
    byId(`f-${c}`).textContent = F === undefined || F === null ? "–" : `${(F / 1000).toFixed(1)} kN`;
    const bar = byId(`u-${c}`);
    const uu = u === undefined || u === null ? 0 : Math.abs(u);
    bar.style.width = `${Math.min(100, 100 * uu)}%`;
    bar.className = utilClass(uu);
    bar.parentElement.title = `${Math.round(100 * uu)} % of rating`;
  }
  showVerdicts(crane.spec.cylinders, f.observability, f.consistency);
  return env || null;
}
