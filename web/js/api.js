// HTTP access to the cranetwin API (contract v1): API key handling and problem-JSON errors.
// The key comes from `?key=` (then it is remembered in localStorage and removed from the address
// bar so that screenshots and shared links do not carry it) or from localStorage.

const KEY_STORE = "cranetwin.key";

export class ApiError extends Error {
  constructor(status, title, detail) {
    super(detail ? `${title}: ${detail}` : title);
    this.status = status;
    this.title = title;
    this.detail = detail;
  }
}

export function apiKey() {
  const url = new URL(window.location.href);
  const fromUrl = url.searchParams.get("key");
  if (fromUrl) {
    try { localStorage.setItem(KEY_STORE, fromUrl); } catch (_) { /* private mode */ }
    url.searchParams.delete("key");
    window.history.replaceState(null, "", url.pathname + url.search + url.hash);
    return fromUrl;
  }
  try { return localStorage.getItem(KEY_STORE) || ""; } catch (_) { return ""; }
}

export function setApiKey(key) {
  try { localStorage.setItem(KEY_STORE, key); } catch (_) { /* ignore */ }
}

let cachedKey = null;
function key() {
  if (cachedKey === null) cachedKey = apiKey();
  return cachedKey;
}
export function resetKey(k) { cachedKey = k; setApiKey(k); }

export async function getJSON(path, params = {}) {
  const url = new URL(path, window.location.origin);
  for (const [k, v] of Object.entries(params)) {
    if (v !== undefined && v !== null && v !== "") url.searchParams.set(k, String(v));
  }
  let resp;
  try {
    resp = await fetch(url, { headers: { "X-API-Key": key(), Accept: "application/json" } });
  } catch (err) {
    throw new ApiError(0, "Service unreachable", "the cranetwin service does not answer; check the network");
  }
  if (!resp.ok) {
    let title = resp.statusText || "Request failed";
    let detail = "";
    try {
      const body = await resp.json();
      title = body.title || title;
      detail = body.detail || "";
    } catch (_) { /* not JSON */ }
    throw new ApiError(resp.status, title, detail);
  }
  return resp.json();
}

// Downloads a file with the key in a header (never in a URL that server logs would keep).
export async function download(path, filename) {
  const resp = await fetch(new URL(path, window.location.origin), { headers: { "X-API-Key": key() } });
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

export function wsURL(path) {
  const url = new URL(path, window.location.origin);
  url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
  url.searchParams.set("key", key());
  return url.toString();
}

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
