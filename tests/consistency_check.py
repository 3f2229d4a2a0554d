"""The model-consistency check (:mod:`cranetwin.twin.consistency`) on data with and without model
errors: false alarms and misses (docs/ACCURACY.md, "Model consistency").

``python tests/consistency_check.py family`` replays cases of the noise family (correct machine
file; :mod:`cranetwin.sim.family`, error models of :mod:`cranetwin.sim.sensor_error`) and
``python tests/consistency_check.py indep`` the independent crane (``tests/indep_check.py``)
without and with each crane variant and mapping error, at 0–5 % uniform error. Each prints one
JSON line per replay with every cylinder's verdict, and a summary (``--summary FILE`` reads the
lines back). Lives with the tests: it drives the importer.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _rows(kind: str, spec: dict[str, Any], verdicts: tuple[Any, ...]) -> dict[str, Any]:
    return {"kind": kind, **spec, "cylinders": [v.as_json() for v in verdicts]}


def family(rates: tuple[float, ...], level: float, cranes: int) -> None:
    """Noise-family cases: every crane × fig3 / log-loading × ``rates`` × 4 error models × 2
    normalisations at e = ``level``, and without error."""
    from cranetwin.model import load_machine
    from cranetwin.sim import SensorModel, builtin_scenario, simulate
    from cranetwin.sim.family import crane_family, decimate, variant_machine
    from cranetwin.sim.sensor_error import DISTRIBUTIONS, inject_error
    from cranetwin.twin.replay import replay

    base = load_machine("patu655")
    top = max(rates)
    for variant in crane_family(8)[:cranes]:
        m = variant_machine(base, variant)
        for name, dur in (("fig3", 20.0), ("log-loading", 60.0)):
            payload = 300.0 * variant.force_scale if name == "log-loading" else 0.0
            sc = builtin_scenario(name, duration_s=dur, payload_kg=payload or None)
            rec = simulate(m, sc, seed=0, sensors=SensorModel.ideal(top), wrenches=False)
            for rate in rates:
                clean = decimate(rec.samples, int(round(top / rate)))
                cases = [("none", "full", 0.0)] + [(e, s, level) for e in DISTRIBUTIONS
                                                   for s in ("full", "recorded")]
                for error, scale, lv in cases:
                    noisy = clean if lv == 0 else inject_error(clean, m, lv, 0, error,  # type: ignore[arg-type]
                                                               scale)  # type: ignore[arg-type]
                    res = replay(noisy, m, grid_hz=rate)
                    spec = {"crane": variant.name, "scenario": name, "rate": rate,
                            "error": error, "scale": scale, "level": lv, "bad": None}
                    print(json.dumps(_rows("family", spec, res.model_consistency(m))),
                          flush=True)


def indep(seeds: int, scales: tuple[str, ...]) -> None:
    """The independent crane: as simulated (no model error) and each variant / mapping error,
    valve-steps and log-cycle, noise-free and uniform 1/2/5 % of ``scales``."""
    import tempfile

    import indep_check as ic
    from cranetwin.importer import read_file
    from cranetwin.importer.replay import ReplayNotes, iter_replay_table
    from cranetwin.model import load_machine
    from cranetwin.sim.sensor_error import inject_error
    from cranetwin.testing.indep_crane import PATU655

    machine = load_machine("patu655")
    setups: list[tuple[str | None, str | None]] = [(None, None)]
    setups += [(v, None) for v in sorted(ic.VARIANTS)]
    setups += [(None, e) for e in sorted(ic.MAPPING_ERRORS)]
    with tempfile.TemporaryDirectory() as tmp:
        for variant, error in setups:
            p = PATU655 if variant is None else ic.VARIANTS[variant](PATU655)
            wd = Path(tmp) / (variant or "patu655")
            wd.mkdir(exist_ok=True)
            for name in ic.SCENARIOS:
                run = ic.simulated(name, p)
                csv, toml = wd / f"{name}.csv", wd / f"{name}-{error or 'ok'}.toml"
                if not csv.exists():
                    ic.write_logger_csv(run, csv)
                toml.write_text(ic.mapping_toml(error=error))
                got = read_file(csv, machine, toml)
                levels = [(0.0, "full", 0)] + [(lv, s, seed) for s in scales
                                               for lv in ic.LEVELS[1:] for seed in range(seeds)]
                for lv, scale, seed in levels:
                    samples = got.samples if lv == 0 else inject_error(
                        got.samples, machine, lv, seed, "uniform", scale)  # type: ignore[arg-type]
                    notes = ReplayNotes.empty()
                    for _ in iter_replay_table(samples, machine, notes=notes,
                                               known_payload_kg=got.payload_kg):
                        pass
                    spec = {"crane": variant or "patu655", "mapping": error or "ok",
                            "scenario": name, "error": "uniform", "scale": scale,
                            "level": lv, "seed": seed,
                            "bad": variant or error}
                    print(json.dumps(_rows("indep", spec, notes.model_consistency(machine))),
                          flush=True)


BAD_CYLINDER = {"telescope-63mm": ("extension",), "friction-x4": ("extension",),
                "light": ("lift", "jib", "extension"), "ext-offset+200mm": ("extension",),
                "lift-offset+50mm": ("lift",), "ext-pA-pB-swapped": ("extension",)}
"""The cylinder(s) each model error concerns (friction ×4: the telescope, whose force it
changes by 8 %; the lift's and jib's by < 1 %)."""


def summary(path: str) -> None:
    """False alarms (no model error, any cylinder flagged) per error model, the statistic's
    quantiles, and per model error: replays with any cylinder flagged, and with its own."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines()
            if line.startswith("{")]
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        if not r["bad"]:
            groups.setdefault(f"{r['kind']} {r['error']}/{r['scale']}", []).append(r)
    print("no model error: replays with any cylinder flagged (false alarms)")
    for key, rs in sorted(groups.items()):
        alarms = [r for r in rs if any(not c["consistent"] for c in r["cylinders"])]
        sh = np.array([c["share"] or 0 for r in rs for c in r["cylinders"]])
        nr = np.array([c["noise_ratio"] or 0 for r in rs for c in r["cylinders"]])
        print(f"  {key}: {len(alarms)}/{len(rs)}; share median {np.median(sh):.3f} max "
              f"{sh.max():.3f}; noise ratio median {np.median(nr):.2f} max {nr.max():.1f}")
    print("model error: replays flagged on any cylinder / on its own cylinder(s)")
    bad: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        if r["bad"]:
            bad.setdefault(r["bad"], []).append(r)
    for key, rs in bad.items():
        cyls = BAD_CYLINDER[key]
        anyc = sum(any(not c["consistent"] for c in r["cylinders"]) for r in rs)
        own = sum(all(not c["consistent"] for c in r["cylinders"] if c["cylinder"] in cyls)
                  for r in rs)
        sh = [c["share"] for r in rs for c in r["cylinders"] if c["cylinder"] in cyls]
        hints = sorted({c["hint"] for r in rs for c in r["cylinders"] if c["hint"]})
        print(f"  {key}: any {anyc}/{len(rs)}, own {own}/{len(rs)}; own share "
              f"{min(sh):.3f}–{max(sh):.3f}; hints {hints}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("what", choices=("family", "indep", "summary"))
    ap.add_argument("--rates", default="100,50")
    ap.add_argument("--level", type=float, default=0.05)
    ap.add_argument("--cranes", type=int, default=8)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--scale", action="append", default=None)
    ap.add_argument("--file", default="-")
    a = ap.parse_args(argv)
    if a.what == "family":
        family(tuple(float(x) for x in a.rates.split(",")), a.level, a.cranes)
    elif a.what == "indep":
        indep(a.seeds, tuple(a.scale or ("full", "recorded")))
    else:
        summary(a.file)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
