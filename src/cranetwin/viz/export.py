"""Self-contained replay HTML: the machine page with its scripts, styles and data inlined.

The file opens from disk with no server and no internet: meshcat's viewer bundle
(``main.min.js``, three.js inside) and plotly.js come from their Python packages, the page's own ES
modules are joined into one module, and the data (machine, scene commands, twin result, load
history, events) becomes ``window.CRANETWIN_EMBED``; the page's script sees the embedded data and
replays it instead of calling the API. All four are stored gzip-compressed and base64-encoded in
``<script type="text/plain">`` blocks and unpacked by a small bootstrap with the browser's
``DecompressionStream`` (Chromium 80+, Firefox 113+, Safari 16.4+).

Size: ≈ 2.2 MB of packed libraries plus the data; the twin is thinned to at most
:data:`EXPORT_MAX_FRAMES` frames and rounded to 1e-4, so any window (≤ 10 min) stays ≈ 3 MB,
small enough to e-mail.
"""

from __future__ import annotations

import base64
import gzip
import json
import re
from importlib import resources
from pathlib import Path
from typing import Any

from cranetwin.errors import CraneTwinError, MissingExtraError

EXPORT_MAX_SECONDS = 600.0
"""Longest window an export holds [s]."""
EXPORT_MAX_FRAMES = 3000
"""Most animation frames embedded in one export."""

MODULE_ORDER = ("api.js", "crane3d.js", "replay.js", "timeline.js", "charts.js", "schedule.js",
                "source.js", "playback.js", "live.js", "chartpanel.js", "nowcard.js", "machine.js")
"""The page's ES modules in dependency order (each imports only earlier ones)."""


class ExportError(CraneTwinError):
    """A replay export could not be produced."""


def export_rate_hz(seconds: float) -> float:
    """Frame rate [Hz] of an export of ``seconds``: 25 Hz, lowered so frames ≤ the maximum."""
    if seconds <= 0:
        raise ExportError(f"export window of {seconds} s: expected a positive duration")
    return float(min(25.0, EXPORT_MAX_FRAMES / seconds))


def join_twin(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Join consecutive twin results (contract v1 JSON) into one, dropping repeated seam samples.

    Per-time lists (``t``, ``q``, ``tip``, ``joint_torques`` and each entry of ``poses``,
    ``cylinder_pins``, ``cylinder_forces``, ``utilisation``) are concatenated; ``payload``
    series (own ``t``) likewise. Other keys come from the first part, but for the window
    verdicts (``force_observability``, ``model_consistency``): each part's are kept in
    ``notes``, one ``{"from", "to", "force_observability", "model_consistency"}`` per part
    (its first and last sample time [s]), so a replay of the joined result shows the verdicts
    of the window it is in.
    """
    parts = [p for p in parts if p and p.get("t")]
    if not parts:
        return {"t": [], "q": [], "tip": [], "poses": {}, "cylinder_pins": {},
                "cylinder_forces": {}, "utilisation": {}, "payload": {"t": [], "kg": []}}
    out: dict[str, Any] = dict(parts[0])
    per_time = ("q", "tip", "joint_torques")
    per_name = ("poses", "cylinder_pins", "cylinder_forces", "utilisation")
    out["t"] = list(parts[0]["t"])
    for k in per_time:
        if k in out:
            out[k] = list(out[k])
    for k in per_name:
        out[k] = {name: list(v) for name, v in (parts[0].get(k) or {}).items()}
    pay = parts[0].get("payload") or {}
    out["payload"] = {"t": list(pay.get("t", [])), "kg": list(pay.get("kg", []))}
    out.pop("wrenches", None)
    out.pop("force_observability", None)
    out.pop("model_consistency", None)
    out["notes"] = [{"from": p["t"][0], "to": p["t"][-1],
                     "force_observability": list(p.get("force_observability") or []),
                     "model_consistency": list(p.get("model_consistency") or [])}
                    for p in parts]
    for p in parts[1:]:
        last = out["t"][-1]
        keep = [i for i, t in enumerate(p["t"]) if t > last + 1e-9]
        out["t"] += [p["t"][i] for i in keep]
        for k in per_time:
            if k in out and k in p:
                out[k] += [p[k][i] for i in keep]
        for k in per_name:
            for name, v in (p.get(k) or {}).items():
                out[k].setdefault(name, [])
                out[k][name] += [v[i] for i in keep]
        pay = p.get("payload") or {}
        lastp = out["payload"]["t"][-1] if out["payload"]["t"] else float("-inf")
        for t, kg in zip(pay.get("t", []), pay.get("kg", []), strict=False):
            if t > lastp + 1e-9:
                out["payload"]["t"].append(t)
                out["payload"]["kg"].append(kg)
    return out


def _round(obj: Any, digits: int = 4) -> Any:
    if isinstance(obj, float):
        r = round(obj, digits)
        return 0.0 if r == 0 else r
    if isinstance(obj, list):
        return [_round(x, digits) for x in obj]
    if isinstance(obj, dict):
        return {k: _round(v, digits) for k, v in obj.items()}
    return obj


def _script_safe(text: str) -> str:
    """Text that can sit inside <script>…</script>: no closing tag, no HTML comment opener."""
    return text.replace("</script", "<\\/script").replace("<!--", "<\\!--")


BOOTSTRAP = """
(async function () {
  async function unpack(id) {
    const b64 = document.getElementById(id).textContent;
    const bin = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
    const stream = new Blob([bin]).stream().pipeThrough(new DecompressionStream("gzip"));
    return await new Response(stream).text();
  }
  function run(code, type) {
    const s = document.createElement("script");
    if (type) s.type = type;
    s.textContent = code;
    document.body.appendChild(s);
  }
  try {
    run(await unpack("ct-meshcat"));
    run(await unpack("ct-plotly"));
    window.CRANETWIN_EMBED = JSON.parse(await unpack("ct-data"));
    run(await unpack("ct-app"), "module");
  } catch (err) {
    const b = document.getElementById("banner");
    b.hidden = false; b.className = "banner error";
    b.textContent = "This browser cannot open the export (needs DecompressionStream): " + err;
  }
})();
"""
"""Unpacks the gzip+base64 blocks of an export (vendor bundles, data, app) and runs them."""


def _gzip_b64(text: str) -> str:
    return base64.b64encode(gzip.compress(text.encode("utf-8"), compresslevel=9, mtime=0)
                            ).decode("ascii")


def _vendor(package: str, *parts: str) -> str:
    """Text of a browser library shipped in an installed wheel (the ``web`` extra)."""
    try:
        root = resources.files(package)
    except ModuleNotFoundError as exc:
        raise MissingExtraError("web", "the HTML export") from exc
    return root.joinpath(*parts).read_text("utf-8")


_IMPORT = re.compile(r"^import\s.*?from\s+['\"].*?['\"];\s*$", re.MULTILINE)
_EXPORT = re.compile(r"^export\s+(?=(async\s+)?(function|class|const|let)\b)", re.MULTILINE)


def bundle_modules(web_dir: Path) -> str:
    """The page's ES modules joined into one module (imports removed, ``export`` dropped)."""
    chunks = []
    for name in MODULE_ORDER:
        path = web_dir / "js" / name
        try:
            src = path.read_text("utf-8")
        except OSError as exc:
            raise ExportError(f"{path}: cannot read ({exc}); expected the web/ folder") from exc
        src = _IMPORT.sub("", src)
        src = _EXPORT.sub("", src)
        chunks.append(f"// ---- {name}\n{src}")
    return "\n".join(chunks)


def render_export(web_dir: Path, data: dict[str, Any]) -> str:
    """The self-contained HTML text of a replay.

    Args:
        web_dir: The ``web/`` folder (machine.html, css/app.css, js/*.js).
        data: ``machine``, ``model``, ``scene``, ``twin``, ``history``, ``events``, ``from``,
            ``to`` (epoch s) as the API returns them.

    Raises:
        ExportError: web files missing.
    """
    try:
        page = (web_dir / "machine.html").read_text("utf-8")
        css = (web_dir / "css" / "app.css").read_text("utf-8")
    except OSError as exc:
        raise ExportError(f"web files under {web_dir} unreadable: {exc}") from exc
    embed = {
        "machine": data["machine"], "model": data["model"], "scene": data["scene"],
        "twin": _round(data["twin"]), "history": _round(data.get("history") or {}, 3),
        "events": data.get("events") or [],
        "from": float(data["from"]), "to": float(data["to"]),
    }
    t0, t1 = float(data["from"]), float(data["to"])
    meta = (f'<meta name="cranetwin-export" content="machine={data["machine"].get("machine_id")};'
            f'from={t0};to={t1}">')
    blobs = {
        "ct-meshcat": _vendor("meshcat", "viewer", "dist", "main.min.js"),
        "ct-plotly": _vendor("plotly", "package_data", "plotly.min.js"),
        "ct-data": json.dumps(embed, separators=(",", ":")),
        "ct-app": bundle_modules(web_dir),
    }
    packed = "\n".join(
        f'<script type="text/plain" id="{k}">{_gzip_b64(v)}</script>' for k, v in blobs.items())
    page = re.sub(r'<link rel="stylesheet" href="/static/css/app.css">', lambda _: "", page)
    page = re.sub(r'<link rel="modulepreload" href="[^"]*">\n?', lambda _: "", page)
    page = re.sub(r'<script src="/static/vendor/meshcat.min.js"[^>]*></script>', lambda _: "", page)
    page = page.replace("</head>", f"<style>{css}</style>\n{meta}\n</head>", 1)
    page, n = re.subn(r'<script type="module" src="/static/js/machine.js"></script>',
                      lambda _: f"{packed}\n<script>{BOOTSTRAP}</script>", page)
    if n != 1:
        raise ExportError("machine.html has no machine.js module tag to inline")
    return page
