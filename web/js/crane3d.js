// The 3D crane: a meshcat viewer filled with the scene commands of /api/v1/machines/{id}/scene,
// animated by frames {q, poses, cylinder_pins, utilisation, payload_kg, tip}.
// No imports: this file is also inlined into exported replay HTML files.

export function utilisationColor(u) {
  // 0 -> green, 0.6 -> amber, 1 -> red, above 1 -> magenta (over rating)
  if (!(u >= 0)) return [0.45, 0.5, 0.58];
  if (u > 1.0) return [0.85, 0.1, 0.75];
  const stops = [[0, [0.16, 0.65, 0.3]], [0.6, [0.95, 0.7, 0.1]], [1, [0.86, 0.15, 0.12]]];
  for (let i = 1; i < stops.length; i++) {
    const [u1, c1] = stops[i];
    const [u0, c0] = stops[i - 1];
    if (u <= u1) {
      const a = (u - u0) / (u1 - u0);
      return [0, 1, 2].map((k) => c0[k] + a * (c1[k] - c0[k]));
    }
  }
  return stops[2][1];
}

// Column-major 4x4 taking a unit mesh along +z (z in [0, 1]) onto p0 -> p0 + n*len.
export function segmentMatrix(p0, dir, len) {
  const n = dir;
  const helper = Math.abs(n[1]) < 0.9 ? [0, 1, 0] : [1, 0, 0];
  let u = cross(helper, n);
  const un = Math.hypot(u[0], u[1], u[2]) || 1;
  u = [u[0] / un, u[1] / un, u[2] / un];
  const w = cross(n, u);
  return [u[0], u[1], u[2], 0, w[0], w[1], w[2], 0,
    n[0] * len, n[1] * len, n[2] * len, 0, p0[0], p0[1], p0[2], 1];
}
function cross(a, b) {
  return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
}
function transformPoint(m, p) {
  // m: column-major 4x4, p: [x, y, z] in the body frame -> world
  return [0, 1, 2].map((i) => m[i] * p[0] + m[4 + i] * p[1] + m[8 + i] * p[2] + m[12 + i]);
}
function setSegment(node, a, b) {
  const d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
  const len = Math.hypot(d[0], d[1], d[2]) || 1e-9;
  node.set_transform(segmentMatrix(a, [d[0] / len, d[1] / len, d[2] / len], len));
}
function flatPins(p) {
  // accepts [[bx,by,bz],[rx,ry,rz]] or [bx,by,bz,rx,ry,rz]
  if (!p) return null;
  return Array.isArray(p[0]) ? [p[0][0], p[0][1], p[0][2], p[1][0], p[1][1], p[1][2]] : p;
}

export function logRadius(kg, spec) {
  const m = Math.max(kg || 0, 0);
  return Math.sqrt(m / (spec.log_density_kgm3 * Math.PI * spec.log_length_m));
}

export function softwareGL(gl) {
  try {
    const ext = gl.getExtension("WEBGL_debug_renderer_info");
    const name = ext ? String(gl.getParameter(ext.UNMASKED_RENDERER_WEBGL)) : "";
    return /swiftshader|llvmpipe|software|softpipe/i.test(name);
  } catch (_) {
    return true;
  }
}

// Rated payload [kg] at horizontal reach r [m]: linear in between, held beyond the chart's ends
// (as RatedLoad.payload_at on the server).
export function ratedAt(chart, r) {
  const xs = chart.reach_m, ys = chart.payload_kg;
  if (r <= xs[0]) return ys[0];
  if (r >= xs[xs.length - 1]) return ys[ys.length - 1];
  let i = 1;
  while (xs[i] < r) i++;
  const a = (r - xs[i - 1]) / (xs[i] - xs[i - 1]);
  return ys[i - 1] + a * (ys[i] - ys[i - 1]);
}

// Reach [m] of point p from the slew axis, and the unit horizontal direction to it.
export function reachOf(axis, p) {
  const o = axis.origin_m, n = axis.axis;
  const d = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
  const along = d[0] * n[0] + d[1] * n[1] + d[2] * n[2];
  const perp = [d[0] - along * n[0], d[1] - along * n[1], d[2] - along * n[2]];
  const r = Math.hypot(perp[0], perp[1], perp[2]);
  return { r, dir: r > 1e-9 ? perp.map((x) => x / r) : [1, 0, 0] };
}

const SOFTWARE_RATIO = 0.7; // pixel ratio of a software rasteriser
const MIN_SOFTWARE_RATIO = 0.5; // ... while its frames are slow
const SLOW_FRAME_MS = 25; // below 40 fps
const FAST_FRAME_MS = 18; // 55 fps and more
export const ENVELOPE_HEIGHT_M = 2.5; // the chart's largest rated payload drawn this high [m]
const ENVELOPE_N = 48;

export class Crane3D {
  constructor(element, sceneData) {
    // Our own renderer: no multisampling (software WebGL, e.g. SwiftShader in headless Chromium,
    // spends most of a frame on it; on real GPUs the device pixel ratio smooths edges) and no
    // shadow passes. Software rasterisers also draw at 0.7× resolution: measured 30 → 60 fps.
    const THREE = MeshCat.THREE;
    const renderer = new THREE.WebGLRenderer({ antialias: false, alpha: false, powerPreference: "high-performance" });
    const software = softwareGL(renderer.getContext());
    renderer.shadowMap.enabled = false;
    element.appendChild(renderer.domElement);
    this.viewer = new MeshCat.Viewer(element, true, renderer);
    this.software = software;
    renderer.setPixelRatio(software ? SOFTWARE_RATIO : Math.min(window.devicePixelRatio || 1, 2));
    window.addEventListener("resize", () => this.resize()); // after meshcat's own (window height)
    this.spec = sceneData.spec;
    this.viewer.handle_command({ type: "set_property", path: "/Background", property: "top_color", value: [0.87, 0.9, 0.94] });
    this.viewer.handle_command({ type: "set_property", path: "/Background", property: "bottom_color", value: [0.63, 0.69, 0.77] });
    this.viewer.handle_command({ type: "set_property", path: "/Axes", property: "visible", value: false });
    if (software) {
      // meshcat draws its gradient background as a full-screen textured quad every frame; a
      // software rasteriser pays for every pixel of it, so it gets a plain clear colour (the
      // gradient's middle) instead: no extra pass, one shader less to compile for the first frame
      this.viewer.scene.background = new THREE.Color(0.75, 0.795, 0.855);
    }
    for (const cmd of sceneData.commands) this.viewer.handle_command(cmd);
    this.nodes = {};
    const find = (path) => this.viewer.scene_tree.find(path.split("/").filter((x) => x.length));
    for (const body of this.spec.bodies) this.nodes[body] = find(this.spec.body_paths[body]);
    this.cyl = {};
    for (const c of this.spec.cylinders) {
      this.cyl[c] = {
        barrel: find(`/cranetwin/cylinders/${c}/barrel`),
        rod: find(`/cranetwin/cylinders/${c}/rod`),
        barrelMesh: find(`/cranetwin/cylinders/${c}/barrel/<object>`),
        barrelLen: this.spec.barrel_lengths_m[c],
        linkage: (this.spec.linkages || {})[c] || null,
      };
      if (this.cyl[c].linkage) {
        this.cyl[c].pivotLink = find(`/cranetwin/cylinders/${c}/pivot_link`);
        this.cyl[c].couplerLink = find(`/cranetwin/cylinders/${c}/coupler_link`);
      }
    }
    this.tool = find(this.spec.tool_path);
    this.payload = find(this.spec.payload_path);
    this.trailObj = find(`${this.spec.trail_path}/<object>`);
    this.trailN = this.spec.trail_points;
    this.lastUtil = {};
    this.setCamera([-1.0, -9.0, 4.5], [2.0, 0, 1.4]);
    if (typeof ResizeObserver !== "undefined") {
      new ResizeObserver(() => this.resize()).observe(element);
    }
    this.element = element;
    this.resize();
    this.follow = false;
    this.buildEnvelope();
    // parked pose until data arrives (no log on the grapple)
    if (this.spec.rest_frame) this.apply(this.spec.rest_frame);
  }

  // Adaptive resolution on software rasterisers: `frameMs` is the interval of the animation
  // frame just drawn. Slow frames for half a second lower the pixel ratio (0.7 → 0.5), fast ones
  // for two seconds raise it again; real GPUs keep their ratio.
  frameTime(frameMs) {
    if (!this.software || !(frameMs > 0)) return;
    const a = this.frameEma === undefined ? frameMs : this.frameEma;
    this.frameEma = a + 0.1 * (frameMs - a);
    const now = performance.now();
    if (this.ratioChanged !== undefined && now - this.ratioChanged < 500) return;
    const ratio = this.viewer.renderer.getPixelRatio();
    let next = ratio;
    if (this.frameEma > SLOW_FRAME_MS && ratio > MIN_SOFTWARE_RATIO + 1e-6) next = MIN_SOFTWARE_RATIO;
    else if (this.frameEma < FAST_FRAME_MS && ratio < SOFTWARE_RATIO - 1e-6 && now - (this.ratioChanged || 0) > 2000) next = SOFTWARE_RATIO;
    if (next !== ratio) {
      this.ratioChanged = now;
      this.viewer.renderer.setPixelRatio(next);
      this.resize();
      this.viewer.set_dirty();
    }
  }

  resize() {
    const w = this.element.clientWidth;
    const h = this.element.clientHeight;
    if (w > 0 && h > 0) this.viewer.set_3d_pane_size(w, h);
  }

  setCamera(eye, target) {
    // meshcat turns its scene -90° about x so that content is z-up inside a y-up three.js world;
    // the camera and OrbitControls work in that y-up world: (x, y, z) z-up is (x, z, -y) there.
    const v = this.viewer;
    const w = (p) => [p[0], p[2], -p[1]];
    const e = w(eye), t = w(target);
    v.camera.fov = 45;
    v.camera.position.set(e[0], e[1], e[2]);
    v.controls.target.set(t[0], t[1], t[2]);
    v.controls.update();
    v.camera.updateProjectionMatrix();
    v.set_dirty();
  }

  apply(frame) {
    const poses = frame.poses || {};
    for (const body of this.spec.bodies) {
      const m = poses[body];
      if (m) this.nodes[body].set_transform(m);
    }
    const pins = frame.cylinder_pins || {};
    const util = frame.utilisation || {};
    for (const c of this.spec.cylinders) {
      const p = flatPins(pins[c]);
      const parts = this.cyl[c];
      if (p) {
        const d = [p[3] - p[0], p[4] - p[1], p[5] - p[2]];
        const len = Math.hypot(d[0], d[1], d[2]) || 1e-9;
        const n = [d[0] / len, d[1] / len, d[2] / len];
        const bl = Math.min(parts.barrelLen, len);
        parts.barrel.set_transform(segmentMatrix([p[0], p[1], p[2]], n, bl));
        const nr = [-n[0], -n[1], -n[2]];
        parts.rod.set_transform(segmentMatrix([p[3], p[4], p[5]], nr, Math.max(len - 0.5 * bl, 0.01)));
        const lk = parts.linkage;
        if (lk && poses[lk.parent_body] && poses[lk.child_body]) {
          const e = [p[3], p[4], p[5]];
          const d = transformPoint(poses[lk.parent_body], lk.pivot_m);
          const f = transformPoint(poses[lk.child_body], lk.coupler_m);
          setSegment(parts.pivotLink, d, e);
          setSegment(parts.couplerLink, e, f);
        }
      }
      const u = util[c];
      if (u !== undefined && u !== null && this.lastUtil[c] !== Math.round(u * 100)) {
        this.lastUtil[c] = Math.round(u * 100);
        const mat = parts.barrelMesh.object.material;
        if (mat && mat.color) {
          const rgb = utilisationColor(Math.abs(u));
          mat.color.setRGB(rgb[0], rgb[1], rgb[2]);
        }
      }
    }
    const tip = frame.tip || this.tipFromPoses(poses);
    if (tip) {
      const th = frame.q ? frame.q[0] : 0;
      const c = Math.cos(th), s = Math.sin(th);
      this.tool.set_transform([c, s, 0, 0, -s, c, 0, 0, 0, 0, 1, 0, tip[0], tip[1], tip[2], 1]);
      const r = logRadius(frame.payload_kg, this.spec);
      const L = r > 0.005 ? this.spec.log_length_m : 0;
      const rr = L > 0 ? r : 0;
      this.payload.set_transform([rr, 0, 0, 0, 0, L, 0, 0, 0, 0, rr, 0, 0, 0, -this.spec.tool_drop_m - rr, 1]);
      this.envelopeState = this.updateEnvelope(tip, frame.payload_kg);
      this.followTo(tip);
    }
    this.viewer.set_dirty();
  }

  // The rated-load envelope in the vertical plane through the slew axis and the load: the chart
  // drawn as a curve whose height is the rated payload (ENVELOPE_HEIGHT_M for the largest), on a
  // base line along the reach, and a marker at (current reach, current payload): inside the
  // curve = within rating. Green where the current payload is allowed at that reach, red where not.
  buildEnvelope() {
    const chart = this.spec.rated_load, axis = this.spec.slew_axis;
    this.envelope = null;
    if (!chart || !axis) return;
    const THREE = MeshCat.THREE;
    const root = this.viewer.scene_tree.find(["cranetwin"]).object; // z-up like the crane
    const group = new THREE.Group();
    group.name = "rated-load-envelope";
    const n = ENVELOPE_N;
    const curve = new THREE.BufferGeometry();
    curve.setAttribute("position", new THREE.BufferAttribute(new Float32Array(3 * n), 3));
    curve.setAttribute("color", new THREE.BufferAttribute(new Float32Array(3 * n), 3));
    const curveLine = new THREE.Line(curve, new THREE.LineBasicMaterial({ vertexColors: true, depthTest: false, transparent: true }));
    const baseGeo = new THREE.BufferGeometry();
    baseGeo.setAttribute("position", new THREE.BufferAttribute(new Float32Array(3 * 2 * (n + 1)), 3));
    const base = new THREE.LineSegments(baseGeo, new THREE.LineBasicMaterial({ color: 0x35506b, depthTest: false, transparent: true }));
    const marker = new THREE.Mesh(new THREE.SphereGeometry(0.09, 12, 8), new THREE.MeshBasicMaterial({ color: 0x1e9e4a, depthTest: false, transparent: true }));
    const stemGeo = new THREE.BufferGeometry();
    stemGeo.setAttribute("position", new THREE.BufferAttribute(new Float32Array(6), 3));
    const stem = new THREE.Line(stemGeo, new THREE.LineBasicMaterial({ color: 0x1c2430, depthTest: false, transparent: true }));
    for (const o of [curveLine, base, marker, stem]) { o.renderOrder = 10; o.frustumCulled = false; group.add(o); }
    root.add(group);
    this.envelope = { group, curve, baseGeo, marker, stemGeo, chart, axis, state: null };
  }

  setEnvelopeVisible(v) { if (this.envelope) { this.envelope.group.visible = v; this.viewer.set_dirty(); } }

  // Updates the envelope for the load at `tip` (world [m]) carrying `payloadKg`; returns
  // {reach_m, rated_kg, payload_kg, utilisation, slew_rad} or null.
  updateEnvelope(tip, payloadKg) {
    const e = this.envelope;
    if (!e || !tip) return null;
    const { r, dir } = reachOf(e.axis, tip);
    const o = e.axis.origin_m, up = e.axis.axis;
    const xs = e.chart.reach_m;
    const r0 = 0, r1 = xs[xs.length - 1] * 1.1;
    const maxKg = Math.max(...e.chart.payload_kg);
    const k = ENVELOPE_HEIGHT_M / maxKg;
    const kg = Math.max(payloadKg || 0, 0);
    const at = (rr, h) => [0, 1, 2].map((i) => o[i] + rr * dir[i] + h * up[i]);
    const pos = e.curve.attributes.position.array, col = e.curve.attributes.color.array;
    const bpos = e.baseGeo.attributes.position.array;
    for (let i = 0; i < ENVELOPE_N; i++) {
      const rr = r0 + ((r1 - r0) * i) / (ENVELOPE_N - 1);
      const rated = ratedAt(e.chart, Math.max(rr, xs[0]));
      const p = at(rr, rated * k);
      pos.set(p, 3 * i);
      const ok = rated >= kg;
      col.set(ok ? [0.12, 0.62, 0.29] : [0.86, 0.15, 0.12], 3 * i);
    }
    for (let i = 0; i <= ENVELOPE_N; i++) {
      // the base line, dashed: every other piece
      const a = r0 + ((r1 - r0) * i) / (ENVELOPE_N + 1);
      const b = a + (r1 - r0) / (2 * (ENVELOPE_N + 1));
      bpos.set(at(a, 0), 6 * i);
      bpos.set(at(b, 0), 6 * i + 3);
    }
    e.curve.attributes.position.needsUpdate = true;
    e.curve.attributes.color.needsUpdate = true;
    e.baseGeo.attributes.position.needsUpdate = true;
    const rated = ratedAt(e.chart, r);
    const u = kg / rated;
    const m = at(r, kg * k);
    e.marker.position.set(m[0], m[1], m[2]);
    const rgb = utilisationColor(u);
    e.marker.material.color.setRGB(rgb[0], rgb[1], rgb[2]);
    e.stemGeo.attributes.position.array.set([...at(r, 0), ...m]);
    e.stemGeo.attributes.position.needsUpdate = true;
    e.state = { reach_m: r, rated_kg: rated, payload_kg: kg, utilisation: u, slew_rad: Math.atan2(dir[1], dir[0]), dir };
    return e.state;
  }

  // Camera follow: the orbit target moves with the load (the camera keeps its offset, so the
  // user can still turn and zoom around it).
  setFollow(on) { this.follow = !!on; this.lastFollow = null; }

  followTo(tip) {
    if (!this.follow || !tip) return;
    const v = this.viewer;
    const t = [tip[0], tip[2], -tip[1]]; // z-up -> meshcat's y-up world
    const c = v.controls.target;
    const d = [t[0] - c.x, t[1] - c.y, t[2] - c.z];
    if (Math.abs(d[0]) + Math.abs(d[1]) + Math.abs(d[2]) < 1e-6) return;
    v.controls.target.set(t[0], t[1], t[2]);
    v.camera.position.set(v.camera.position.x + d[0], v.camera.position.y + d[1], v.camera.position.z + d[2]);
    v.controls.update();
    v.set_dirty();
  }

  tipFromPoses(poses) {
    const lp = this.spec.load_point;
    if (!lp || !poses[lp.body]) return null;
    return transformPoint(poses[lp.body], lp.point_m);
  }

  setTrail(points) {
    // points: flat [x, y, z, ...] of at most trail_points points (oldest first)
    const obj = this.trailObj.object;
    if (!obj || !obj.geometry) return;
    const attr = obj.geometry.attributes.position;
    const n = Math.min(points.length / 3, this.trailN);
    const start = points.length - 3 * n;
    for (let i = 0; i < 3 * n; i++) attr.array[i] = points[start + i];
    for (let i = 3 * n; i < 3 * this.trailN; i++) attr.array[i] = n > 0 ? points[points.length - 3 + (i % 3)] : 0;
    attr.needsUpdate = true;
    obj.geometry.setDrawRange(0, n);
    this.viewer.set_dirty();
  }

  snapshot() { return this.viewer.capture_image(); }
}
