// Fleet map: machine locations on a basemap served with the page (Natural Earth 1:110m country
// outlines from the vendored world-atlas package, decoded by the vendored topojson-client), drawn
// in SVG with an equirectangular projection scaled by cos(latitude) at the map's centre. No
// tiles, no network. The map shows the machines the table shows (same filter); a click on a
// marker opens the machine; hovering a table row highlights its marker and back.

const SVG = "http://www.w3.org/2000/svg";
const W = 600, H = 420;

let countries = null; // GeoJSON features
let loading = null;

function loadBasemap() {
  if (loading) return loading;
  loading = fetch("/static/lib/world-atlas/countries-110m.json").then((r) => {
    if (!r.ok) throw new Error(`basemap: HTTP ${r.status}`);
    return r.json();
  }).then((topo) => {
    countries = topojson.feature(topo, topo.objects.countries).features;
    return countries;
  });
  return loading;
}

// The view: the machines' bounding box, padded (at least 4° across), or the whole world.
export function mapView(points) {
  if (points.length === 0) return { lon0: -180, lon1: 180, lat0: -60, lat1: 80 };
  let lon0 = Math.min(...points.map((p) => p.lon)), lon1 = Math.max(...points.map((p) => p.lon));
  let lat0 = Math.min(...points.map((p) => p.lat)), lat1 = Math.max(...points.map((p) => p.lat));
  const padLon = Math.max(2, 0.3 * (lon1 - lon0)), padLat = Math.max(1.5, 0.3 * (lat1 - lat0));
  lon0 -= padLon; lon1 += padLon; lat0 -= padLat; lat1 += padLat;
  // keep the map's aspect: widen the shorter side
  const k = Math.cos(((lat0 + lat1) / 2) * Math.PI / 180);
  const wDeg = (lon1 - lon0) * k, hDeg = lat1 - lat0;
  const want = W / H;
  if (wDeg / hDeg < want) { const add = (hDeg * want / k - (lon1 - lon0)) / 2; lon0 -= add; lon1 += add; }
  else { const add = ((wDeg / want) - hDeg) / 2; lat0 -= add; lat1 += add; }
  return { lon0, lon1, lat0: Math.max(lat0, -85), lat1: Math.min(lat1, 85) };
}

export function project(view, lon, lat) {
  return [W * (lon - view.lon0) / (view.lon1 - view.lon0), H * (view.lat1 - lat) / (view.lat1 - view.lat0)];
}

function ringPath(view, ring) {
  let d = "";
  let prev = null;
  for (const [lon, lat] of ring) {
    const [x, y] = project(view, lon, lat);
    // a jump across the antimeridian starts a new piece instead of a line across the map
    d += (prev === null || Math.abs(lon - prev) > 180 ? "M" : "L") + x.toFixed(1) + "," + y.toFixed(1);
    prev = lon;
  }
  return d + "Z";
}

function featurePath(view, f) {
  const g = f.geometry;
  if (!g) return "";
  const polys = g.type === "Polygon" ? [g.coordinates] : g.type === "MultiPolygon" ? g.coordinates : [];
  return polys.map((poly) => poly.map((ring) => ringPath(view, ring)).join("")).join("");
}

export class FleetMap {
  constructor(el) {
    this.el = el;
    this.svg = document.createElementNS(SVG, "svg");
    this.svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
    this.svg.setAttribute("role", "img");
    this.svg.setAttribute("aria-label", "Map of machine locations");
    this.land = document.createElementNS(SVG, "g");
    this.land.setAttribute("class", "map-land");
    this.marks = document.createElementNS(SVG, "g");
    this.svg.append(this.land, this.marks);
    el.appendChild(this.svg);
    this.viewKey = null;
    this.error = null;
  }

  async update(machines) {
    const pts = machines.filter((m) => m.location && Number.isFinite(m.location.lat) && Number.isFinite(m.location.lon))
      .map((m) => ({ m, lat: m.location.lat, lon: m.location.lon }));
    const view = mapView(pts);
    this.view = view;
    const key = JSON.stringify(view);
    try {
      await loadBasemap();
    } catch (err) {
      this.error = String(err);
    }
    if (key !== this.viewKey && countries) {
      this.viewKey = key;
      this.land.innerHTML = "";
      for (const f of countries) {
        const p = document.createElementNS(SVG, "path");
        p.setAttribute("d", featurePath(view, f));
        p.setAttribute("data-country", (f.properties && f.properties.name) || "");
        this.land.appendChild(p);
      }
    }
    this.marks.innerHTML = "";
    for (const { m, lat, lon } of pts) {
      const [x, y] = project(view, lon, lat);
      const a = document.createElementNS(SVG, "a");
      a.setAttribute("href", `/machines/${encodeURIComponent(m.machine_id)}`);
      a.setAttribute("class", `map-machine ${m.status || ""}`);
      a.dataset.machineId = m.machine_id;
      const c = document.createElementNS(SVG, "circle");
      c.setAttribute("cx", x.toFixed(1)); c.setAttribute("cy", y.toFixed(1)); c.setAttribute("r", "7");
      const title = document.createElementNS(SVG, "title");
      title.textContent = `${m.name || m.machine_id} · ${m.status} · ${lat.toFixed(4)}°, ${lon.toFixed(4)}°`;
      const t = document.createElementNS(SVG, "text");
      t.setAttribute("x", (x + 10).toFixed(1)); t.setAttribute("y", (y + 4).toFixed(1));
      t.textContent = m.name || m.machine_id;
      a.append(c, t, title);
      a.addEventListener("mouseenter", () => this.highlight(m.machine_id));
      a.addEventListener("mouseleave", () => this.highlight(null));
      this.marks.appendChild(a);
    }
    const unplaced = machines.length - pts.length;
    const note = this.el.parentElement.querySelector(".map-note");
    if (note) {
      note.textContent = (this.error ? `Basemap unavailable (${this.error}). ` : "")
        + (unplaced > 0 ? `${unplaced} machine${unplaced > 1 ? "s" : ""} without a location.` : "");
    }
    return pts.length;
  }

  // Highlights a machine's marker and table row (null: none).
  highlight(id) {
    for (const el of document.querySelectorAll(".map-machine.hl, #rows tr.hl")) el.classList.remove("hl");
    if (!id) return;
    for (const el of document.querySelectorAll(`.map-machine[data-machine-id="${CSS.escape(id)}"], #rows tr[data-machine-id="${CSS.escape(id)}"]`)) el.classList.add("hl");
  }
}
