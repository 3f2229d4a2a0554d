"""Calibration recovers friction and mass that differ from the machine file."""

from __future__ import annotations

import pytest

from cranetwin.model import Friction, load_machine
from cranetwin.twin.calibration import calibrate
from cranetwin.twin.synthetic import make


def test_calibration_recovers_friction_and_mass() -> None:
    m = load_machine("patu655")
    true = {"lift": Friction(coulomb=600.0, coulomb_velocity=0.01, viscous=900.0),
            "jib": Friction(coulomb=400.0, coulomb_velocity=0.003, viscous=500.0),
            "extension": Friction(coulomb=300.0, coulomb_velocity=0.006, viscous=700.0)}
    # motion at 0.3x the synthetic's default frequencies: joint speeds like the crane's
    syn = make(m, duration_s=240.0, payload=220.0, fine_hz=None, friction=true, scale=0.3,
               quantize=True)
    cal = calibrate(syn.samples, m)
    assert cal.extra_mass_kg == pytest.approx(220.0, rel=0.02)
    for fit in cal.cylinders:
        ref = true[fit.name]
        assert fit.coulomb == pytest.approx(ref.coulomb, rel=0.1), fit
        assert fit.viscous == pytest.approx(ref.viscous, rel=0.1), fit
        # vc is seen only in the few instants near zero velocity: weakly determined
        assert fit.coulomb_velocity == pytest.approx(ref.coulomb_velocity, rel=0.3), fit
        assert fit.rms_after_n < 0.05 * fit.rms_before_n


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_calibration_recovers_viscous_friction_on_a_simulated_ten_minute_run(seed: int) -> None:
    """The issue's check: a 10-minute simulated ``random`` run (hydraulics, default sensor model
    with noise, bias, dropouts and jitter; the seed changes the sensors) with friction and tool
    mass different from the machine file; every Fc, vc and b and the extra mass within 10 %."""
    from cranetwin.sim import builtin_scenario, simulate

    m = load_machine("patu655")
    true = {"lift": Friction(coulomb=500.0, coulomb_velocity=0.008, viscous=800.0),
            "jib": Friction(coulomb=400.0, coulomb_velocity=0.004, viscous=600.0),
            "extension": Friction(coulomb=250.0, coulomb_velocity=0.006, viscous=500.0)}
    truth = m.model_copy(update={
        "cylinders": [c.model_copy(update={"friction": true[c.name]}) for c in m.cylinders],
        "load_point": m.load_point.model_copy(update={"tool_mass_kg": 120.0})})
    rec = simulate(truth, builtin_scenario("random", duration_s=600.0), seed=seed,
                   wrenches=False)
    cal = calibrate(rec.samples, m)
    assert cal.extra_mass_kg == pytest.approx(30.0, rel=0.1)
    for fit in cal.cylinders:
        ref = true[fit.name]
        assert fit.viscous == pytest.approx(ref.viscous, rel=0.1), fit
        assert fit.coulomb == pytest.approx(ref.coulomb, rel=0.1), fit
        assert fit.coulomb_velocity == pytest.approx(ref.coulomb_velocity, rel=0.1), fit
        assert fit.rms_after_n < 0.02 * fit.rms_before_n


def test_correlation_time_of_white_and_averaged_noise() -> None:
    import numpy as np

    from cranetwin.twin.calibration import correlation_time

    rng = np.random.default_rng(3)
    white = rng.normal(size=200_000)
    assert correlation_time(white) == pytest.approx(1.0, abs=0.05)
    # a moving average of w samples: τ = w (triangular autocorrelation)
    w = 25
    avg = np.convolve(white, np.ones(w) / w, mode="valid")
    assert correlation_time(avg) == pytest.approx(w, rel=0.1)
    assert correlation_time(np.zeros(10)) == 1.0


def test_cli_warns_about_unphysical_friction(monkeypatch: pytest.MonkeyPatch,
                                              tmp_path: object) -> None:
    """A short recording can fit a negative b; the command says so instead of printing it
    as a result."""
    from pathlib import Path

    from typer.testing import CliRunner

    import cranetwin.twin.calibration as calmod
    from cranetwin.cli import app
    from cranetwin.sim import Recording
    from cranetwin.twin.calibration import Calibration, CylinderFit

    fits = tuple(CylinderFit(name=n, coulomb_file=300.0, coulomb=310.0,
                             coulomb_velocity_file=0.005, coulomb_velocity=0.005,
                             viscous_file=400.0, viscous=b, rms_before_n=100.0,
                             rms_after_n=5.0)
                 for n, b in (("lift", 420.0), ("jib", -46.0), ("extension", 390.0)))
    fake = Calibration(fits, 0.1, 0.02, 90.0, 1000, (0.0, 0.0, 0.0), (1, 100))
    monkeypatch.setattr(calmod, "calibrate", lambda samples, machine: fake)
    monkeypatch.setattr(Recording, "load", staticmethod(lambda path: Recording.__new__(Recording)))
    monkeypatch.setattr(Recording, "samples", None, raising=False)
    out = CliRunner().invoke(app, ["calibrate", str(Path(str(tmp_path)) / "r.npz")],
                             terminal_width=200)
    assert out.exit_code == 0, out.output
    assert "b of jib came out ≤ 0" in out.output
    assert "of lift" not in out.output
