"""The paper's accuracy experiment (Fig. 7): sensor error in, twin error out.

For one simulated recording (quantisation-only sensors, the "client side" of the paper) and
each error level e: add uniform error in [−e, +e] × channel full range to the pressure and
position samples (as the paper, :func:`cranetwin.signal.inject_uniform_noise`), replay, and
measure NRMSE = RMSE / (max − min of the truth) of the lift and jib rod positions (Xc1, Xc2)
and cylinder forces (Fc1, Fc2) against the simulator's fine-step truth on the 1 kHz grid.
Repeated over seeds: mean and standard deviation per level. Also reported: the input NRMSE
(noisy samples against the clean ones, normalised the same way; for forces, Eq. 1 from the
raw noisy pressures at the sample instants) and the payload estimate's RMSE during lifts.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from cranetwin import physics
from cranetwin.errors import MissingExtraError, TwinError
from cranetwin.model import Machine
from cranetwin.signal import inject_uniform_noise, nrmse
from cranetwin.twin.options import ReplayOptions
from cranetwin.twin.replay import replay

F64 = npt.NDArray[np.float64]

METRICS = ("Xc1", "Xc2", "Fc1", "Fc2")


@dataclass
class LevelResult:
    """Statistics over seeds at one error level (fractions, not percent)."""

    level: float
    mean: dict[str, float] = field(default_factory=dict)
    std: dict[str, float] = field(default_factory=dict)
    input_mean: dict[str, float] = field(default_factory=dict)
    payload_rmse_kg: float = float("nan")
    payload_rmse_rated: float = float("nan")
    payload_std_mean_kg: float = float("nan")


def _truth_on_grid(truth_t: F64, t: F64) -> npt.NDArray[np.intp]:
    idx = np.searchsorted(truth_t, t - 1e-9)
    idx = np.clip(idx, 0, truth_t.shape[0] - 1)
    if np.abs(truth_t[idx] - t).max() > 1e-6:
        raise TwinError("the truth grid does not contain the twin's grid instants")
    return idx


def run_levels(recording: Any, machine: Machine, levels: list[float], seeds: int,
               payload_window_s: float = 2.0) -> list[LevelResult]:
    """Run the experiment on a :class:`cranetwin.sim.Recording`.

    Args:
        recording: Simulated recording (samples with quantisation only, and its truth).
        machine: Machine description.
        levels: Error levels e as fractions (0.05 = 5 %).
        seeds: Noise realisations per level (seeds 0 … seeds−1; one run at e = 0).
        payload_window_s: Payload least-squares window [s].
    """
    tr = recording.truth
    clean = recording.samples
    cyl_names = [c.name for c in machine.cylinders]
    li, ji = cyl_names.index("lift"), cyl_names.index("jib")
    pos_ch = ["lift_s", "jib_s"]
    cols = [clean.channels.index(c) for c in pos_ch]
    ts_idx = _truth_on_grid(tr.t_s, clean.t_s)
    truth_pos_s = tr.rod_s[ts_idx][:, [li, ji]]
    truth_f_s = tr.cyl_force[ts_idx][:, [li, ji]]
    reach = physics.horizontal_reach(machine, tr.q)
    rated = (machine.rated_load.payload_at(reach) if machine.rated_load is not None
             else np.full(reach.shape, np.nan))  # no chart: unknown
    out: list[LevelResult] = []
    for e in levels:
        runs: dict[str, list[float]] = {k: [] for k in METRICS}
        inputs: dict[str, list[float]] = {k: [] for k in METRICS}
        pay_sq: list[float] = []
        pay_rated: list[float] = []
        pay_std: list[float] = []
        for seed in range(seeds if e > 0 else 1):
            noisy = inject_uniform_noise(clean, machine, e, seed=seed)
            res = replay(noisy, machine, grid_hz=1000.0, payload=None,
                         options=ReplayOptions(payload_window_s=payload_window_s))
            gi = _truth_on_grid(tr.t_s, res.t_s)
            x = nrmse(res.rod_s[:, [li, ji]], tr.rod_s[gi][:, [li, ji]])
            f = nrmse(res.cyl_force[:, [li, ji]], tr.cyl_force[gi][:, [li, ji]])
            for k, val in zip(METRICS, [*x, *f], strict=True):
                runs[k].append(float(val))
            xin = nrmse(noisy.values[:, cols], truth_pos_s)
            fin: list[float] = []
            for c, name in ((li, "lift"), (ji, "jib")):
                cyl = machine.cylinders[c]
                pa = noisy.column(f"{name}_pA")
                pb = noisy.column(f"{name}_pB")
                raw = physics.cylinder_force(pa, pb, tr.rod_v[ts_idx][:, c], cyl)
                ok = np.isfinite(raw)
                fin.append(float(nrmse(raw[ok], truth_f_s[ok, len(fin)])))
            for k, val in zip(METRICS, [*xin, *fin], strict=True):
                inputs[k].append(float(val))
            # payload during lifts: truth payload > 0 and no change within half a window
            p_true = tr.payload_kg[gi]
            change = np.flatnonzero(np.diff(p_true) != 0)
            steady = np.ones(res.n, dtype=bool)
            half = payload_window_s / 2 + 0.5
            for c in change.tolist():
                steady &= np.abs(res.t_s - res.t_s[c]) > half
            lift = steady & (p_true > 0)
            if lift.any():
                err = res.payload_kg[lift] - p_true[lift]
                pay_sq.append(float(np.mean(err**2)))
                pay_rated.append(float(np.sqrt(np.mean(err**2)) / np.mean(rated[gi][lift])))
                pay_std.append(float(np.mean(res.payload_std_kg[lift])))
        lr = LevelResult(level=e)
        for k in METRICS:
            lr.mean[k] = float(np.mean(runs[k]))
            lr.std[k] = float(np.std(runs[k]))
            lr.input_mean[k] = float(np.mean(inputs[k]))
        if pay_sq:
            lr.payload_rmse_kg = float(np.sqrt(np.mean(pay_sq)))
            lr.payload_rmse_rated = float(np.mean(pay_rated))
            lr.payload_std_mean_kg = float(np.mean(pay_std))
        out.append(lr)
    return out


def as_json(results: list[LevelResult]) -> list[dict[str, Any]]:
    """Plain dicts of the results (NaN -> None)."""
    def clean(x: Any) -> Any:
        if isinstance(x, float) and not np.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        return x
    return [clean(asdict(r)) for r in results]


def plot(results: list[LevelResult], path: str, title: str) -> None:
    """Fig. 7-like plot: NRMSE [%] of positions (a) and forces (b) vs maximum error e [%],
    points with ±1 std over seeds and third-degree polynomial fits (as the paper)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise MissingExtraError("reports", "the accuracy plot") from exc

    e = np.array([r.level for r in results]) * 100
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, keys, label in ((axes[0], ("Xc1", "Xc2"), "(a) positions"),
                            (axes[1], ("Fc1", "Fc2"), "(b) forces")):
        for k, mk in zip(keys, ("o", "s"), strict=True):
            m = np.array([r.mean[k] for r in results]) * 100
            s = np.array([r.std[k] for r in results]) * 100
            line = ax.errorbar(e, m, yerr=s, fmt=mk, label=k, capsize=3)
            if e.shape[0] >= 4:
                c = np.polyfit(e, m, 3)
                xx = np.linspace(e.min(), e.max(), 100)
                ax.plot(xx, np.polyval(c, xx), color=line[0].get_color())
            inp = np.array([r.input_mean[k] for r in results]) * 100
            ax.plot(e, inp, ":", color=line[0].get_color(), label=f"{k} input (raw)")
        ax.set_xlabel("maximum added error e [% of sensor range]")
        ax.set_ylabel("NRMSE [%]")
        ax.set_title(label)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
