"""Analytics and reports of a stored range: replay → :mod:`cranetwin.analytics` → JSON or file.

The range is merged from the analytics parts the twin worker stored per minute, hour and day
(:mod:`cranetwin.service.history`); only minutes without a part are replayed. The result is
an :class:`cranetwin.analytics.AnalyticsState` (rainflow
spectra per load channel, Miner damage and remaining life per fatigue detail, ISO 4301 duty
classification, events, work cycles and productivity), and the report is returned as JSON, or
rendered as CSV / HTML / PDF.
"""

from __future__ import annotations

import csv
import dataclasses
import html
import io
import math
from typing import Any

import numpy as np

from cranetwin.errors import AnalyticsError, MissingExtraError
from cranetwin.model import Machine
from cranetwin.service.replayer import Replayer
from cranetwin.service.timerange import TimeRange, iso

MARGIN_S = 2.0


def _jsonable(x: Any) -> Any:
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: _jsonable(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def lift_payload(res: Any, threshold_kg: float | None = None,
                 sample_period_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A replay's payload as the analytics read it: where it is a steady estimate of a lift's
    load, shape (n,) bool — inside each lift (:func:`cranetwin.twin.lifts.result_lifts`) with
    the grab and release ramps the estimate's window smears left out; a work cycle's payload
    is the mean over these instants (:mod:`cranetwin.analytics.productivity`) — and the
    estimate net of each lift's empty reading from its grab to its release (the lift's
    ``tare_kg``: a sensor offset read where the grapple is empty), shape (n,) [kg].

    Args:
        res: A :class:`cranetwin.twin.TwinResult` (computed over the whole replay, margins
            included, so a lift is found the same way in every window that holds it; its
            empty reading is what the replay holds of the empty stretches next to it).
        threshold_kg: A lift is where the estimate exceeds this [kg] (None: the work cycles'
            ``grab_kg``).
        sample_period_s: Period of the replayed samples [s] (None: the median step of the
            result's grid, which the replay puts at the sample rate).
    """
    from cranetwin.analytics import ProductivityConfig
    from cranetwin.analytics.history import median_step
    from cranetwin.twin.lifts import result_lifts, steady_mask

    net = np.array(res.payload_kg, dtype=np.float64, copy=True)
    if res.t_s.shape[0] < 2:
        return np.zeros(res.t_s.shape, dtype=bool), net
    thr = ProductivityConfig().grab_kg if threshold_kg is None else threshold_kg
    dt = median_step(res.t_s) if sample_period_s is None else sample_period_s
    lifts = result_lifts(res, dt, thr)
    for lf in lifts:  # the grid is increasing: each lift a slice (time linear in its length)
        if lf.tare_kg != 0.0:
            net[np.searchsorted(res.t_s, lf.grab_s, "left"):
                np.searchsorted(res.t_s, lf.release_s, "right")] -= lf.tare_kg
    return steady_mask(res.t_s, lifts), net


def cylinder_loads(machine: Machine, q: np.ndarray, id_torque: np.ndarray,
                   cyl_force: np.ndarray) -> np.ndarray:
    """Axial load of each cylinder by inverse dynamics, F = τ_ID / (ds/dq) [N], shape
    (n, n_cyl): the force the reconstructed motion needs along the cylinder, pressures and end
    stop together (virtual work, as ``actuator_torque = F·ds/dq``). Where the lever vanishes
    (|ds/dq| < 1e-6) or τ_ID is not finite, the pressures' force ``cyl_force`` is kept.

    Args:
        machine: The machine.
        q: Joint positions, shape (n, n_joints) [rad or m].
        id_torque: Inverse-dynamics joint loads, shape (n, n_joints) [N·m or N].
        cyl_force: Cylinder forces of the pressures (Eq. 1–2), shape (n, n_cyl) [N].
    """
    from cranetwin.physics import moment_arms

    if q.shape[0] == 0 or not machine.cylinders:
        return np.array(cyl_force, dtype=float, copy=True)
    arm = moment_arms(machine, q)
    tau = id_torque[:, [machine.joint_index(c.joint) for c in machine.cylinders]]
    ok = (np.abs(arm) >= 1e-6) & np.isfinite(tau)
    return np.where(ok, tau / np.where(ok, arm, 1.0), cyl_force)


def load_history(machine: Machine, res: Any, keep: np.ndarray,
                 reach_m: np.ndarray | None = None) -> Any:
    """:class:`cranetwin.analytics.LoadHistory` of the kept instants of a replay result, with
    where its payload is steady and the payload net of each lift's empty reading
    (:func:`lift_payload`) and the cylinders' load forces by inverse dynamics
    (:func:`cylinder_loads`: at a stroke end, what shock loads are taken from).
    ``reach_m``: the kept instants' horizontal reach [m], shape (k,), when the caller has it
    (None: computed here)."""
    from cranetwin.analytics import LoadHistory
    from cranetwin.physics import horizontal_reach

    q = res.q[keep]
    steady, net = lift_payload(res)
    return LoadHistory.from_arrays(
        machine, t_s=res.t_s[keep], cyl_force=res.cyl_force[keep], q=q, qd=res.qd[keep],
        payload_kg=np.maximum(net[keep], 0.0),
        reach_m=horizontal_reach(machine, q) if reach_m is None else reach_m,
        joint_wrench=res.joint_wrench[keep], rod_s=res.rod_s[keep], rod_v=res.rod_v[keep],
        p_a=res.p_a[keep], p_b=res.p_b[keep], payload_steady=steady[keep],
        cyl_load=cylinder_loads(machine, q, res.id_torque[keep], res.cyl_force[keep]))


def stored_events(machine_id: str, events: list[Any]) -> list[Any]:
    """Analytics events as storage events (message and details in the evidence)."""
    from cranetwin.storage import Event as StoredEvent

    def finite(v: float) -> float | None:  # what :func:`_jsonable` makes of a float
        return v if math.isfinite(v) else None

    out = []
    for e in events:
        msg = (f"{e.kind.replace('_', ' ')} on {e.component}: {e.value:.4g} {e.unit} "
               f"(limit {e.limit:.4g} {e.unit})")
        evidence = {"message": msg, "component": str(e.component),
                    "value": finite(float(e.value)), "limit": finite(float(e.limit)),
                    "unit": str(e.unit), "t_end": finite(float(e.t_end)),
                    **{str(k): finite(float(v)) for k, v in e.evidence.items()}}
        out.append(StoredEvent(machine_id, float(e.t_start), e.kind, e.severity, evidence))
    return out


def analytics_report(backend: Any, replayer: Replayer, machine: Machine, machine_id: str,
                     rng: TimeRange, margin_s: float = MARGIN_S,
                     max_replay_s: float | None = None) -> Any:
    """The :class:`cranetwin.analytics.AnalyticsReport` of [from, to), or None without data.

    Merged from the parts the twin worker stored (:func:`cranetwin.service.history.range_state`);
    only minutes without a stored part are replayed, the way the worker replays a minute
    (``margin_s``: the worker's ``twin_margin_s``)."""
    from cranetwin.service.history import range_state, window_history

    prog = backend.progress(machine_id)

    def edge(a: float, b: float) -> Any:
        return window_history(backend, replayer, machine, machine_id, a, b, margin_s)

    engine = backend.store.engine_for(machine_id)
    state = range_state(engine, machine, machine_id, rng.t0_s, rng.t1_s, edge,
                        prog.watermark_s if prog is not None else None, max_replay_s,
                        next_sample=lambda t: backend.next_sample_time(machine_id, t))
    if state.n_samples == 0:
        return None
    op, cal = history_usage(backend, machine_id)
    return state.report(rng.t0_s, rng.t1_s, op, cal)


def direct_report(backend: Any, replayer: Replayer, machine: Machine, machine_id: str,
                  rng: TimeRange, margin_s: float = MARGIN_S) -> Any:
    """The same report by replaying every minute of the range (no stored part used): the
    baseline the merged report must equal, and the benchmark's direct figure."""
    from cranetwin.analytics import AnalyticsState
    from cranetwin.service.history import MINUTE_S, window_history

    state = AnalyticsState(machine)
    a = math.floor(rng.t0_s / MINUTE_S) * MINUTE_S
    while a < rng.t1_s:
        h = window_history(backend, replayer, machine, machine_id, a, a + MINUTE_S, margin_s)
        if h is not None:
            i, j = np.searchsorted(h.t_s, [rng.t0_s, rng.t1_s])
            if j > i:
                state.update(h.slice(int(i), int(j)))
        a += MINUTE_S
    if state.n_samples == 0:
        return None
    op, cal = history_usage(backend, machine_id)
    return state.report(rng.t0_s, rng.t1_s, op, cal)


def history_usage(backend: Any, machine_id: str) -> tuple[float | None, float | None]:
    """(operating s, calendar s) of the machine's whole recorded history, the rate basis of
    remaining life (:class:`cranetwin.analytics.RateBasis`): the twin worker's operating time
    from the first stored sample to its progress mark; (None, None) before the worker
    processed anything."""
    prog = backend.progress(machine_id)
    dr = backend.data_range(machine_id)
    if prog is None or dr is None or not prog.operating_s > 0 or not prog.watermark_s > dr[0]:
        return None, None
    return float(prog.operating_s), float(prog.watermark_s - dr[0])


def analytics_json(report: Any, rng: TimeRange) -> dict[str, Any]:
    """JSON of an analytics report (null figures when the range held no data)."""
    out: dict[str, Any] = {"from": iso(rng.t0_s), "to": iso(rng.t1_s)}
    if report is None:
        out.update({"n_samples": 0, "spectra": [], "life": [], "classification": None,
                    "duty": None, "events": [], "cycles": [], "productivity": None})
        return out
    data = _jsonable(report)
    data.pop("days", None)
    out.update(data)
    out["productivity"] = {
        "recorded_s": report.recorded_s, "idle_s": report.idle_s,
        "working_s": report.working_s, "utilisation": report.utilisation,
        "work_cycles": len(report.cycles),
        "payload_per_working_hour_kg": _jsonable(report.payload_per_working_hour_kg),
        "mean_cycle_time_s": _jsonable(report.mean_cycle_time_s),
    }
    return out


def render(data: dict[str, Any], fmt: str, machine_id: str) -> tuple[bytes, str, str]:
    """``(body, media type, file name)`` of a report in ``csv``, ``html`` or ``pdf``."""
    rows: list[tuple[str, str]] = [("machine", machine_id), ("from", str(data["from"])),
                                   ("to", str(data["to"])),
                                   ("samples", str(data.get("n_samples", 0)))]
    prod = data.get("productivity") or {}
    for k, v in prod.items():
        rows.append((f"productivity.{k}", str(v)))
    for life in data.get("life", []):
        rows.append((f"damage.{life.get('name')}", str(life.get("damage"))))
    cls = data.get("classification")
    if cls:
        rows += [(f"classification.{k}", str(v)) for k, v in cls.items()]
    rows.append(("events", str(len(data.get("events", [])))))
    stem = f"cranetwin-{machine_id}-report"
    if fmt == "csv":
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["quantity", "value"])
        w.writerows(rows)
        return buf.getvalue().encode(), "text/csv", f"{stem}.csv"
    if fmt == "html":
        body = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
                       for k, v in rows)
        page = (f"<!doctype html><meta charset=utf-8><title>{html.escape(stem)}</title>"
                f"<h1>cranetwin report: {html.escape(machine_id)}</h1><table>{body}</table>")
        return page.encode(), "text/html", f"{stem}.html"
    if fmt == "pdf":
        try:
            from reportlab.lib.pagesizes import A4  # type: ignore[import-untyped]
            from reportlab.pdfgen import canvas  # type: ignore[import-untyped]
        except ImportError as exc:
            raise MissingExtraError("reports", "PDF reports") from exc

        buf_b = io.BytesIO()
        c = canvas.Canvas(buf_b, pagesize=A4)
        y = A4[1] - 60
        c.setFont("Helvetica-Bold", 14)
        c.drawString(50, y, f"cranetwin report: {machine_id}")
        c.setFont("Helvetica", 9)
        for k, v in rows:
            y -= 14
            if y < 50:
                c.showPage()
                c.setFont("Helvetica", 9)
                y = A4[1] - 50
            c.drawString(50, y, k[:60])
            c.drawString(300, y, v[:60])
        c.save()
        return buf_b.getvalue(), "application/pdf", f"{stem}.pdf"
    raise AnalyticsError(f"unknown report format {fmt!r}; expected pdf, csv or html")
