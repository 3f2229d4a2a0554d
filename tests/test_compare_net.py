"""The known-payload comparison (``payload_column="compare"``) puts the twin's own lift payload
next to the gross estimate: per known lift, the twin's lift that overlaps it longest, grab and
release left out and net of the empty reading next to it (:mod:`cranetwin.twin.lifts`), with
its σ. A pressure sensor's zero offset moves the gross figure and not the net one; without an
offset the two agree; the chunked notes give exactly what the whole result gives."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from typer.testing import CliRunner

from conftest import offset_pressures
from cranetwin.importer.payload import LiftError, lift_errors, summary_line
from cranetwin.importer.replay import ReplayNotes, iter_replay_table, replay_table
from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays
from cranetwin.twin import TwinResult
from cranetwin.twin.lifts import Lift

F64 = npt.NDArray[np.float64]
T0 = 1_767_225_600.0
Sim = tuple[SampleArrays, F64]


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def sim(machine: Machine) -> Sim:
    """30 s of the simulated log-loading scenario (one 312 kg lift from 9 to 23 s, the grapple
    empty before and after) and the true payload at the sample times."""
    from cranetwin.sim import builtin_scenario, simulate

    rec = simulate(machine, builtin_scenario("log-loading", duration_s=30.0), wrenches=False)
    return rec.samples, np.interp(rec.samples.t_s, rec.truth.t_s, rec.truth.payload_kg)


def _lift(samples: SampleArrays, machine: Machine, truth: F64) -> LiftError:
    table = replay_table(samples, machine, known_payload_kg=truth, payload_column="compare")
    assert table.lifts is not None and len(table.lifts) == 1, table.lifts
    return table.lifts[0]


@pytest.mark.timeout(300)
@pytest.mark.parametrize("seed", [0, 2])
def test_a_pressure_offset_moves_the_gross_estimate_not_the_net(machine: Machine, sim: Sim,
                                                                seed: int) -> None:
    """Every pressure sensor with a constant offset within ±1 % of its range (the draws of
    seeds 0 and 2 move the estimate up and down by 7–8 kg): the gross error is over 2 %, the
    net one under 0.5 % and within 3σ, and the tare is the gross error's sign."""
    samples, truth = sim
    lift = _lift(offset_pressures(samples, machine, 0.01, seed), machine, truth)
    assert abs(lift.known_kg - 312.3) < 0.1
    assert abs(lift.error_pct) > 2.0, lift.line()
    assert abs(lift.net_error_pct) < 0.5, lift.line()
    assert abs(lift.net_error_kg) < 3.0 * lift.net_std_kg, lift.line()
    assert np.sign(lift.tare_kg) == np.sign(lift.error_kg) and abs(lift.tare_kg) > 5.0


@pytest.mark.timeout(300)
def test_without_an_offset_net_and_gross_agree(machine: Machine, sim: Sim) -> None:
    samples, truth = sim
    lift = _lift(samples, machine, truth)
    assert np.isfinite(lift.net_kg) and 0.0 < lift.net_std_kg < 5.0
    assert abs(lift.net_kg - lift.estimate_kg) <= 2.0 * lift.net_std_kg, lift.line()
    assert abs(lift.error_pct) < 0.5 and abs(lift.net_error_pct) < 0.5, lift.line()


def _rows(res: TwinResult, i: int, j: int) -> TwinResult:
    """Rows i:j of a replay's result (every array field, the smoothing choices kept)."""
    return dataclasses.replace(res, **{f.name: getattr(res, f.name)[i:j]
                                       for f in dataclasses.fields(res)
                                       if f.name != "smoothing"})


def _same_lifts(a: list[Lift] | list[LiftError], b: list[Lift] | list[LiftError]) -> None:
    assert len(a) == len(b) > 0
    for x, y in zip(a, b, strict=True):  # bit for bit, NaN equal to NaN
        np.testing.assert_array_equal(np.array(tuple(x) if isinstance(x, tuple)
                                               else dataclasses.astuple(x), dtype=float),
                                      np.array(tuple(y) if isinstance(y, tuple)
                                               else dataclasses.astuple(y), dtype=float))


@pytest.mark.timeout(300)
def test_chunked_notes_equal_the_whole_result(machine: Machine, sim: Sim) -> None:
    """``iter_replay_table`` with :class:`ReplayNotes` (what the CLI prints) gives the lifts
    :func:`cranetwin.twin.lifts.result_lifts` finds in the whole replay, exactly; and the notes
    fed the same result in random chunks give the same lifts again."""
    from cranetwin.importer.payload import MIN_LIFT_KG
    from cranetwin.twin import replay
    from cranetwin.twin.known_payload import at_instants
    from cranetwin.twin.lifts import result_lifts

    samples, truth = offset_pressures(sim[0], machine, 0.01, 0), sim[1]
    notes = ReplayNotes.empty()
    for _ in iter_replay_table(samples, machine, notes=notes, known_payload_kg=truth,
                               payload_column="compare"):
        pass
    chunked = notes.lifts()
    assert chunked is not None and len(notes.payload) >= 2  # the replay came in chunks

    period = float(np.median(np.diff(samples.t_s)))  # as iter_replay_table takes it
    res = replay(samples, machine, float(round(1.0 / period)))
    whole = result_lifts(res, period, MIN_LIFT_KG)
    twin = notes.twin_lifts()
    assert twin is not None
    _same_lifts(twin, whole)
    known = at_instants(res.t_s, samples.t_s, truth, 5.0 * period)
    _same_lifts(chunked, lift_errors(res.t_s, known, res.payload_kg, twin_lifts=whole))
    assert any(lf.tare_kg != 0.0 for lf in whole)  # the offset was taken off

    rng = np.random.default_rng(7)
    again = ReplayNotes.empty()
    i = 0
    while i < res.n:
        j = min(res.n, i + int(rng.integers(1, 400)))
        part = _rows(res, i, j)
        again.add(part, known[i:j], sample_period_s=period)
        i = j
    assert len(again.payload) > 5
    regained = again.lifts()
    assert regained is not None
    _same_lifts(regained, chunked)


@pytest.mark.timeout(60)
def test_the_longest_overlap_is_the_twins_lift_and_both_figures_are_printed() -> None:
    t = np.arange(0.0, 40.0, 0.1)
    known = np.where((t >= 5.0) & (t < 15.0), 400.0, 0.0)
    known[(t >= 25.0) & (t < 35.0)] = 300.0
    est = known + 30.0
    twin = [Lift(4.0, 6.0, 5.0, 5.0, 100.0, 9.0, True),  # overlaps the first lift by 1 s
            Lift(6.5, 15.2, 9.0, 12.0, 401.5, 2.0, True, 30.0, 30.0)]  # by 8.4 s
    first, second = lift_errors(t, known, est, twin_lifts=twin)
    assert (first.net_kg, first.net_std_kg, first.tare_kg) == (401.5, 2.0, 30.0)
    assert first.error_kg == pytest.approx(30.0) and first.net_error_kg == pytest.approx(1.5)
    assert first.net_error_pct == pytest.approx(0.375)
    assert first.line().endswith("known 400.0 kg, estimate 430.0 kg, error +30.0 kg (+7.5 %); "
                                 "net 401.5 ± 2.0 kg (tare +30.0 kg), error +1.5 kg (+0.4 %)")
    # no lift of the twin's over the second: no net figures, none printed
    assert np.isnan(second.net_kg) and np.isnan(second.tare_kg)
    assert second.line().endswith("error +30.0 kg (+10.0 %)")
    line = summary_line([first, second])
    assert "mean |error| 30.0 kg (8.8 %)" in line
    assert line.endswith("; net of the empty reading over the 1 the twin found: mean |error| "
                         "1.5 kg (0.4 %), largest 1.5 kg, 1 of 1 within 2σ")
    # the gross comparison alone (no twin lifts given) is what it was
    alone = lift_errors(t, known, est)
    assert [x.estimate_kg for x in alone] == [first.estimate_kg, second.estimate_kg]
    assert "net" not in summary_line(alone) and "net" not in alone[0].line()
    short = lift_errors(t, known, est, twin_lifts=[Lift(5.0, 15.0, 9.0, 8.0, float("nan"),
                                                        float("inf"), True)])
    assert short[0].line().endswith("net: none (the twin's lift is too short for a steady "
                                    "part)")


@pytest.mark.timeout(600)
def test_cli_prints_the_net_figures(machine: Machine, sim: Sim, tmp_path: Path) -> None:
    """``cranetwin replay FILE --payload-column compare`` prints the lines of
    :func:`replay_table`'s lifts: the gross and the net figure of each."""
    from cranetwin.cli import app

    samples, truth = offset_pressures(sim[0], machine, 0.01, 0), sim[1]
    f = tmp_path / "logger.csv"
    np.savetxt(f, np.column_stack([samples.t_s + T0, samples.values, truth]), delimiter=",",
               fmt=["%.6f", *["%.10g"] * (len(samples.channels) + 1)],
               header=",".join(["t_s", *samples.channels, "hook_kg"]), comments="")
    m = tmp_path / "map.toml"
    m.write_text('[payload]\ncolumn = "hook_kg"\n')
    r = CliRunner().invoke(app, ["replay", str(f), "--mapping", str(m), "--out",
                                 str(tmp_path / "twin.csv"), "-q", "--payload-column",
                                 "compare"])
    assert r.exit_code == 0, r.output
    table = replay_table(f, machine, m, payload_column="compare")
    assert table.lifts is not None and len(table.lifts) == 1
    lift = table.lifts[0]
    assert abs(lift.net_error_pct) < 0.5 < 2.0 < abs(lift.error_pct), lift.line()
    assert summary_line(table.lifts) in r.output and f"  {lift.line()}" in r.output, r.output
    assert "; net of the empty reading: mean |error|" in r.output


def _one_window_each(t: F64, m: F64, s: F64, sb: F64, smear: float, thr: float,
                     span: float | None) -> list[Lift]:
    """Each lift of :func:`lift_payloads` computed on its own window: from the previous lift's
    last instant above the threshold to the next one's first, where it is the middle lift."""
    from cranetwin.twin.lifts import lift_payloads

    on = np.nan_to_num(m, nan=-np.inf) > thr
    edges = np.flatnonzero(np.diff(on.astype(np.int8)))
    firsts = edges[~on[edges]] + 1
    lasts = edges[on[edges]]
    if on[0]:
        firsts = np.concatenate([[0], firsts])
    if on[-1]:
        lasts = np.concatenate([lasts, [t.size - 1]])
    out: list[Lift] = []
    for i in range(firsts.size):
        lo = int(lasts[i - 1]) if i > 0 else 0
        hi = int(firsts[i + 1]) + 1 if i + 1 < firsts.size else t.size
        got = lift_payloads(t[lo:hi], m[lo:hi], s[lo:hi], smear, thr,
                            payload_sys_std_kg=sb[lo:hi], tare_span_s=span)
        assert len(got) == 1 + (i > 0) + (i + 1 < firsts.size)
        out.append(got[1 if i > 0 else 0])
    return out


@pytest.mark.timeout(120)
@pytest.mark.parametrize("span", [30.0, 5.0, None])
@pytest.mark.parametrize("seed", range(4))
def test_a_lift_depends_only_on_the_window_between_its_neighbours(
        seed: int, span: float | None) -> None:
    """:func:`cranetwin.twin.lifts.lift_payloads` over the whole series equals, bit for bit,
    each lift computed on the window between its neighbours (what lets it read each lift's
    instants as slices, in time linear in the length): lifts of random lengths and gaps
    (some shorter than a steady part), loaded at the first and the last instant, an offset,
    noise, NaN dropouts."""
    from cranetwin.twin.lifts import lift_payloads, steady_mask

    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 900.0, 0.01)
    load = np.zeros_like(t)
    edge = 0.0
    while edge < t[-1]:
        a = edge + rng.uniform(0.5, 60.0)
        b = a + rng.uniform(0.5, 30.0)
        load[(t >= a) & (t < b)] = rng.uniform(100.0, 400.0)
        edge = b
    load[t < 4.0] = 250.0
    load[t > 890.0] = 250.0
    m = load + rng.uniform(-20.0, 20.0) + rng.normal(0.0, 3.0, t.size)
    m[rng.integers(0, t.size, 300)] = np.nan
    s = np.full_like(t, 4.0)
    sb = np.full_like(t, 1.0)
    whole = lift_payloads(t, m, s, 2.06, 50.0, payload_sys_std_kg=sb, tare_span_s=span)
    assert len(whole) > 10 and not whole[0].complete and not whole[-1].complete
    assert any(lf.tare_kg != 0.0 for lf in whole) == (span is not None)
    _same_lifts(_one_window_each(t, m, s, sb, 2.06, 50.0, span), whole)
    # the steady mask: the instants of each lift's steady part, as a per-lift comparison
    want = np.zeros(t.shape, dtype=bool)
    for lf in whole:
        want |= (t >= lf.t0_s) & (t <= lf.t1_s)
    assert np.array_equal(steady_mask(t, whole), want)
