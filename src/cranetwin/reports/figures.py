"""Report figures drawn with matplotlib (Agg backend, no display) as PNG bytes.

matplotlib is the ``reports`` extra: imported on the first figure, not with this module.
"""

from __future__ import annotations

import io
from functools import cache
from typing import Any

import numpy as np

from cranetwin.analytics import KINDS, AnalyticsReport
from cranetwin.errors import MissingExtraError
from cranetwin.model import Machine

DAY_S = 86400.0


@cache
def _plt() -> Any:
    """matplotlib.pyplot on the Agg backend.

    Raises:
        MissingExtraError: matplotlib is not installed (``cranetwin[reports]``).
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise MissingExtraError("reports", "report figures") from exc
    return plt


def _png(fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=110)
    _plt().close(fig)
    return buf.getvalue()


def usage(rep: AnalyticsReport) -> bytes:
    """Working and idle hours and work cycles per day."""
    fig, ax = _plt().subplots(figsize=(7.5, 3.2))
    days = sorted(rep.days)
    x = np.arange(len(days))
    work = np.array([rep.days[d].working_s / 3600 for d in days])
    idle = np.array([(rep.days[d].recorded_s - rep.days[d].working_s) / 3600 for d in days])
    ax.bar(x, work, color="#2f6db5", label="working")
    ax.bar(x, idle, bottom=work, color="#bbbbbb", label="idle")
    ax.set_ylabel("hours")
    ax.set_xlabel("day")
    ax2 = ax.twinx()
    ax2.plot(x, [rep.days[d].cycles for d in days], "o-", color="#d9822b", ms=3,
             label="work cycles")
    ax2.set_ylabel("work cycles")
    ax.legend(loc="upper left", fontsize=8)
    ax2.legend(loc="upper right", fontsize=8)
    ax.set_title("Usage per day")
    return _png(fig)


def spectrum(rep: AnalyticsReport) -> bytes:
    """Cumulative load spectra: cycles with range ≥ x, ranges relative to the largest."""
    fig, axes = _plt().subplots(1, 2, figsize=(7.5, 3.4))
    for ax, kind in zip(axes, (":force", ":moment"), strict=True):
        for s in rep.spectra:
            if not s.channel.endswith(kind) or s.cycles.count.size == 0:
                continue
            r = s.cycles.ranges
            order = np.argsort(r)[::-1]
            cum = np.cumsum(s.cycles.count[order])
            ax.step(cum, r[order] / 1000.0, where="post", label=s.channel.split(":")[1])
        ax.set_xscale("log")
        ax.set_xlabel("cycles exceeding")
        ax.set_ylabel("range [kN]" if kind == ":force" else "range [kN·m]")
        ax.set_title("cylinder forces" if kind == ":force" else "joint moments")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    return _png(fig)


def damage(rep: AnalyticsReport) -> bytes:
    """Miner damage per detail and remaining life."""
    fig, ax = _plt().subplots(figsize=(7.5, 0.5 + 0.45 * max(len(rep.life), 1)))
    names = [e.name for e in rep.life]
    d = [e.damage for e in rep.life]
    y = np.arange(len(names))
    ax.barh(y, d, color="#b53a2f")
    ax.set_yticks(y, names, fontsize=7)
    ax.set_xlabel("Miner damage D (1 = predicted fatigue life)")
    for yi, e in zip(y, rep.life, strict=True):
        yrs = e.remaining_days / 365.25
        label = f"  {yrs:.3g} years left" if np.isfinite(yrs) else "  no damage"
        ax.text(e.damage, float(yi), label, va="center", fontsize=7)
    ax.set_xlim(0, max(d + [1e-12]) * 1.6)
    ax.set_title("Damage and remaining life")
    return _png(fig)


def events(rep: AnalyticsReport) -> bytes:
    """Events over time by kind."""
    fig, ax = _plt().subplots(figsize=(7.5, 2.8))
    t0 = rep.t_start
    for i, k in enumerate(KINDS):
        ev = [e for e in rep.events if e.kind == k]
        if ev:
            ax.scatter([(e.t_start - t0) / DAY_S for e in ev], [i] * len(ev),
                       c=["#b53a2f" if e.severity == "critical" else "#d9a12b" for e in ev],
                       s=18)
    ax.set_yticks(range(len(KINDS)), KINDS, fontsize=7)
    ax.set_xlim(0, max(rep.observed_days, 1e-3))
    ax.set_xlabel("days since start")
    ax.set_title("Events (red: critical, amber: warning)")
    return _png(fig)


def productivity(rep: AnalyticsReport, machine: Machine) -> bytes:
    """Payload per work cycle and load ratio distribution."""
    fig, axes = _plt().subplots(1, 2, figsize=(7.5, 3.0))
    p = np.array([c.payload_kg for c in rep.cycles])
    r = np.array([c.load_ratio for c in rep.cycles])
    known = r[np.isfinite(r)]
    axes[0].hist(p, bins=30, color="#2f6db5")
    axes[0].set_xlabel("payload per work cycle [kg]")
    axes[0].set_ylabel("cycles")
    if r.size and not known.size:  # no rated-load chart
        axes[1].text(0.5, 0.5, "load ratio unknown:\nno rated-load chart", ha="center",
                     va="center", transform=axes[1].transAxes)
    axes[1].hist(known, bins=30, range=(0, max(1.2, float(known.max()) if known.size else 1.2)),
                 color="#4a9a5b")
    axes[1].axvline(1.0, color="#b53a2f", lw=1)
    axes[1].set_xlabel("P_i / P_max (rated at reach)")
    fig.suptitle("Productivity and load spectrum of work cycles", fontsize=10)
    return _png(fig)


def all_figures(rep: AnalyticsReport, machine: Machine) -> dict[str, bytes]:
    """Every figure by section name."""
    return {"usage": usage(rep), "spectrum": spectrum(rep), "damage": damage(rep),
            "events": events(rep), "productivity": productivity(rep, machine)}
