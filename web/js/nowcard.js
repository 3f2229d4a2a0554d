// The "Now" readout of a crane frame: payload, reach, rated payload there, utilisation and the
// cylinder forces (machine page), and the one-line load summary written over a 3D view.

const byId = (id) => document.getElementById(id);

// "load 250 kg · 61 % of the rated 410 kg at 5.2 m" (env: Crane3D.envelopeState), or "".
export function loadLine(kg, env) {
  if (kg === null || kg === undefined || !env) return "";
  return `load ${Math.round(kg)} kg · ${Math.round(100 * env.utilisation)} % of the rated ${Math.round(env.rated_kg)} kg at ${env.reach_m.toFixed(1)} m`;
}

// CSS class of a utilisation (fraction of the rating).
export function utilClass(u) { return u > 1 ? "over" : u > 0.8 ? "high" : ""; }

// One row per cylinder in `tbody`: name, force, a utilisation bar.
export function buildForceRows(tbody, cylinders) {
  tbody.innerHTML = "";
  for (const c of cylinders) {
    const tr = document.createElement("tr");
    tr.innerHTML = `<th scope="row">${c}</th><td id="f-${c}">–</td><td><div class="bar"><div id="u-${c}"></div></div></td>`;
    tbody.appendChild(tr);
  }
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
  return env || null;
}
