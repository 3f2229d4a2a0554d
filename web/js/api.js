// HTTP access to the cranetwin API (contract v1): sign-in and problem-JSON errors.
// The browser signs in once (POST /api/v1/session with a key): the server answers with an
// HttpOnly, SameSite=Strict session cookie that every later request and websocket carries. No
// key is ever put in a URL, in localStorage or in a request header by this page. A key found in
// the address bar (`?key=`, an old demo link) or in localStorage (older versions kept it there)
// is exchanged for the cookie once and removed.

const OLD_KEY_STORE = "cranetwin.key";

export class ApiError extends Error {
  constructor(status, title, detail) {
    super(detail ? `${title}: ${detail}` : title);
    this.status = status;
    this.title = title;
    this.detail = detail;
  }
}

async function problem(resp, fallback) {
  let title = resp.statusText || fallback;
  let detail = "";
  try {
    const body = await resp.json();
    title = body.title || title;
    detail = body.detail || "";
  } catch (_) { /* not JSON */ }
  return new ApiError(resp.status, title, detail);
}

// Sign in with `key`: resolves to {key_id, name, role, expires}; rejects with an ApiError whose
// message says why the key was refused.
export async function signIn(key) {
  let resp;
  try {
    resp = await fetch(new URL("/api/v1/session", window.location.origin), {
      method: "POST", credentials: "same-origin",
      headers: { "Content-Type": "application/json", Accept: "application/json" },
      body: JSON.stringify({ key: String(key || "").trim() }),
    });
  } catch (_) {
    throw new ApiError(0, "Service unreachable", "the cranetwin service does not answer; check the network");
  }
  if (!resp.ok) throw await problem(resp, "Sign-in failed");
  return resp.json();
}

export async function signOut() {
  try {
    await fetch(new URL("/api/v1/session", window.location.origin), { method: "DELETE", credentials: "same-origin" });
  } catch (_) { /* offline: the cookie expires on its own */ }
}

// Who is signed in (null when nobody is).
export async function whoAmI() {
  try { return await getJSON("/api/v1/session"); } catch (err) {
    if (err instanceof ApiError && err.status === 401) return null;
    throw err;
  }
}

// A key left in the address bar or in localStorage: taken out at once, then exchanged for the
// session cookie before the page's first API call.
function legacyKey() {
  let k = "";
  const url = new URL(window.location.href);
  if (url.searchParams.has("key")) {
    k = url.searchParams.get("key") || "";
    url.searchParams.delete("key");
    window.history.replaceState(null, "", url.pathname + url.search + url.hash);
  }
  try {
    const stored = localStorage.getItem(OLD_KEY_STORE);
    if (stored) { localStorage.removeItem(OLD_KEY_STORE); k = k || stored; }
  } catch (_) { /* private mode */ }
  return k;
}
const pendingKey = legacyKey();
let linkFailure = null;
const ready = pendingKey ? signIn(pendingKey).catch((e) => { linkFailure = e; return null; }) : Promise.resolve(null);

// Wires a page's sign-in dialog (#key-dialog, #key-form, #key-input, #key-error) and its
// sign-out button (#sign-out, with #who showing who is signed in). `onSignedIn` runs after a
// successful sign-in from the dialog.
export function setupSignIn(onSignedIn) {
  const $ = (id) => document.getElementById(id);
  const form = $("key-form");
  if (form) {
    form.onsubmit = async (ev) => {
      ev.preventDefault();
      const err = $("key-error");
      const button = form.querySelector("button[type=submit]");
      button.disabled = true;
      try {
        const who = await signIn($("key-input").value);
        err.hidden = true;
        $("key-input").value = "";
        $("key-dialog").close();
        showWho(who);
        onSignedIn(who);
      } catch (e) {
        err.textContent = e.status === 401
          ? `This key was not accepted: ${e.detail || e.title}. Check that it was copied whole (it starts with ctk_).`
          : `Could not sign in: ${e.message}`;
        err.hidden = false;
        $("key-input").select();
      } finally {
        button.disabled = false;
      }
    };
  }
  const out = $("sign-out");
  if (out) {
    out.onclick = async () => {
      await signOut();
      showWho(null);
      askSignIn("Signed out. Enter a key to sign in again.");
    };
  }
  ready.then(() => whoAmI()).then(showWho).catch(() => {});
}

function showWho(who) {
  const w = document.getElementById("who");
  const out = document.getElementById("sign-out");
  if (w) w.textContent = who ? `${who.name || who.key_id} · ${who.role}` : "";
  if (out) out.hidden = !who;
}

// Opens the sign-in dialog (after a 401), with `note` above the key field.
export function askSignIn(note) {
  const d = document.getElementById("key-dialog");
  const n = document.getElementById("key-note");
  if (!note && linkFailure) note = `The key in the link was not accepted (${linkFailure.detail || linkFailure.title}). Enter a valid key.`;
  if (n && note) n.textContent = note;
  if (!d.open) d.showModal();
  document.getElementById("key-input").focus();
}

export async function getJSON(path, params = {}) {
  const url = new URL(path, window.location.origin);
  for (const [k, v] of Object.entries(params)) {
    if (v !== undefined && v !== null && v !== "") url.searchParams.set(k, String(v));
  }
  let resp;
  try {
    await ready;
    resp = await fetch(url, { credentials: "same-origin", headers: { Accept: "application/json" } });
  } catch (err) {
    throw new ApiError(0, "Service unreachable", "the cranetwin service does not answer; check the network");
  }
  if (!resp.ok) throw await problem(resp, "Request failed");
  return resp.json();
}

// POST without a body (actions such as acknowledging an alarm); resolves to the JSON answer.
export async function postJSON(path) {
  await ready;
  let resp;
  try {
    resp = await fetch(new URL(path, window.location.origin), {
      method: "POST", credentials: "same-origin", headers: { Accept: "application/json" },
    });
  } catch (_) {
    throw new ApiError(0, "Service unreachable", "the cranetwin service does not answer; check the network");
  }
  if (!resp.ok) throw await problem(resp, "Request failed");
  return resp.json();
}

// Downloads a file (the session cookie authenticates it; no key in a URL that logs would keep).
export async function download(path, filename) {
  await ready;
  const resp = await fetch(new URL(path, window.location.origin), { credentials: "same-origin" });
  if (!resp.ok) {
    let detail = resp.statusText;
    try { const body = await resp.json(); detail = body.detail || body.title || detail; } catch (_) { /* not JSON */ }
    throw new ApiError(resp.status, "Download failed", detail);
  }
  const blob = await resp.blob();
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob);
  a.download = filename;
  document.body.appendChild(a);
  a.click();
  setTimeout(() => { URL.revokeObjectURL(a.href); a.remove(); }, 1000);
  return blob.size;
}

// A websocket URL (the handshake carries the session cookie: same origin, no key in the URL).
export function wsURL(path) {
  const url = new URL(path, window.location.origin);
  url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
  return url.toString();
}

// Resolves once a key from the address bar (if any) was exchanged for the session cookie.
export function signedInReady() { return ready; }

// Time helpers: the API speaks epoch seconds or ISO 8601.
export function isoSeconds(t) {
  return new Date(t * 1000).toISOString().replace(/\.\d{3}Z$/, "Z");
}
export function parseTime(v) {
  if (v === null || v === undefined || v === "") return null;
  if (typeof v === "number") return v;
  if (/^-?\d+(\.\d+)?$/.test(v)) return parseFloat(v);
  const ms = Date.parse(v);
  return Number.isNaN(ms) ? null : ms / 1000;
}
export function relTime(iso) {
  if (!iso) return "never";
  const t = Date.parse(iso);
  if (Number.isNaN(t)) return iso;
  const s = Math.round((Date.now() - t) / 1000);
  if (s < 5) return "just now";
  if (s < 90) return `${s} s ago`;
  if (s < 5400) return `${Math.round(s / 60)} min ago`;
  if (s < 129600) return `${Math.round(s / 3600)} h ago`;
  return new Date(t).toLocaleString();
}
