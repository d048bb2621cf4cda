"""Issue 6 on the CWRR rig: protocol logs, the replay family, withheld effects, the CLI on station logs."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.engine.diagnosis import rotary
from app.engine.diagnosis.core import (
    _residuals,
    channel_scales,
    diagnose,
    fit,
    held_form,
    recalibrate,
    recalibrate_forms,
)
from app.engine.diagnosis.logs import Experiment, LogFormatError, read_logdir
from app.engine.diagnosis.protocol import PREROLL_S, VISIBLE, effect_experiments, run_protocol
from app.engine.diagnosis.rotary import RotaryFamily, _phase_lost
from app.engine.diagnosis.run import (
    PROTOCOL,
    SHOWN_BY,
    _split_station,
    diagnose_dir,
    excites,
    split_by_coverage,
    unshown,
)
from app.engine.diagnosis.suite import MAGNITUDES, STRUCTURAL, perturbed, perturbed_each, run_case, true_params
from app.engine.params import EFFECT_NAMES, PlantParams, ValveDynamicsEffect
from app.engine.physics.flow import null_scale
from app.engine.physics.plant import area_frac
from tests.conftest import REFDATA


@pytest.fixture(scope="module")
def nominal_logs() -> list:
    return run_protocol(PlantParams(), seed=4, repetitions=1, scale=0.6)


def test_protocol_table_covers_every_effect() -> None:
    # every candidate is made visible by at least one experiment the station runs (issue 6 §6)
    assert set(effect_experiments()) == set(EFFECT_NAMES)
    assert all(PROTOCOL[e] for e in EFFECT_NAMES)
    assert set(MAGNITUDES) == set(EFFECT_NAMES)


def test_protocol_logs_are_in_the_station_format(tmp_path: Path) -> None:
    run_protocol(PlantParams(), seed=1, repetitions=2, scale=0.3, kinds=["hold_closed", "prv_steps"], outdir=tmp_path)
    exps = read_logdir(tmp_path)  # the format checks pass
    assert sorted(e.name for e in exps) == ["hold_closed-1", "hold_closed-2", "prv_steps-1", "prv_steps-2"]
    calib, held, _ = _split_station(exps, None)
    # whole experiments are held out: the second repetition of each kind
    assert sorted(e.name for e in held) == ["hold_closed-2", "prv_steps-2"]
    assert sorted(e.name for e in calib) == ["hold_closed-1", "prv_steps-1"]


def test_a_diagnosis_asked_for_an_effect_the_family_lacks_names_the_ones_it_has(tmp_path: Path) -> None:
    """``diagnose_dir(candidates=...)`` tries the effects it is given; a name the rotary family has no
    add-on for is refused before anything is fitted, with the names it knows."""
    from app.engine.diagnosis.run import diagnose_dir

    run_protocol(PlantParams(), seed=1, repetitions=2, scale=0.3, kinds=["hold_closed"], outdir=tmp_path)
    with pytest.raises(ValueError, match=r"the rotary family has no candidate stiction; known: inertia, "):
        diagnose_dir(tmp_path, candidates=["vane_leakage", "stiction"])
    with pytest.raises(ValueError, match=r"no candidate effect given; known: inertia, "):
        diagnose_dir(tmp_path, candidates=[])
    # before a log is read: an adapter's family has effects of its own
    with pytest.raises(ValueError, match=r"the drive family has no candidate vane_leakage; known: inertia, "
                                         r"sensor_bias, presliding_friction"):
        diagnose_dir(REFDATA / "emps", candidates=["vane_leakage"])


def test_cwrr_diagnose_refuses_an_effect_the_logs_family_lacks(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """``cwrr diagnose --effects`` with a name the logs' family has no add-on for exits 2 naming the ones
    it has, and writes no report (the effects it has are tried in the side-by-side test below)."""
    from app.cli import main

    logs, out = tmp_path / "logs", tmp_path / "report.json"
    run_protocol(PlantParams(), seed=1, repetitions=2, scale=0.3, kinds=["hold_closed"], outdir=logs)
    assert main(["diagnose", str(logs), "--effects", "vane_leakage", "stiction", "--json", str(out)]) == 2
    assert "the rotary family has no candidate stiction; known: inertia, vane_leakage," in capsys.readouterr().err
    assert not out.exists()


def test_logs_run_once_are_held_out_only_where_other_logs_excite_the_same(nominal_logs: list) -> None:
    """Without repetitions a third of the logs is still withheld whole, but never the only one with
    motion at speed or the only shut after a fast fill: the last third of the protocol (friction
    sweep, sine sweep, isotonic) left the fit no motion at all, and inertia, supply droop and valve
    dynamics went unnamed on the protocol run once (docs/diagnosis-record.md)."""
    calib, held, why = _split_station(nominal_logs, None)
    assert len(held) == math.ceil(len(nominal_logs) / 3) and len(calib) + len(held) == len(nominal_logs)
    fitted = set().union(*(excites(e) for e in calib))
    assert {"motion", "fast motion", "shut", "shut after a fast fill or vent", "prv steps"} <= fitted
    for e in held:
        assert excites(e) <= fitted, (e.name, excites(e) - fitted)
    kinds = {e.meta["experiment"] for e in calib}
    assert {"fill_shut", "friction_sweep"} <= kinds, kinds
    assert "run once each" in why


def _log(name: str, t: np.ndarray, u: float | np.ndarray, p_a: np.ndarray, omega: float | np.ndarray = 0.0,
         z: float = 2.0) -> Experiment:
    n = len(t)
    full = np.broadcast_to
    return Experiment(name, t, {"z_a": full(z, n).copy(), "z_b": full(z, n).copy(), "u_a": full(u, n).copy(),
                                "u_b": full(u, n).copy()},
                      {"p_a": p_a, "p_b": np.full(n, 2.0), "p_s": np.full(n, 7.0),
                       "theta": np.cumsum(full(omega, n)) * (t[1] - t[0]), "omega": full(omega, n).copy(),
                       "torque": np.zeros(n)}, {"experiment": name})


def test_what_a_log_excites_is_read_from_its_commands_and_measurements() -> None:
    t = np.arange(0.0, 6.0, 0.005)
    shut_at = t >= 2.0
    u = np.where(shut_at, 5.0, 0.0)
    fast = np.where(t < 1.6, 2.0, np.minimum(2.0 + (t - 1.6) * 5.0, 4.0))  # +2 bar in 0.4 s, then shut
    slow = np.minimum(2.0 + t * 0.5, 3.0)  # settled a second before the shut
    assert excites(_log("fast", t, u, fast)) >= {"shut", "shut after a fast fill or vent", "dcv steps"}
    assert "shut after a fast fill or vent" not in excites(_log("slow", t, u, slow))
    still = excites(_log("still", t, 10.0, np.full(len(t), 2.0), omega=0.05))
    assert still == {"pressure ≤ 3 bar"}  # a handle twitching at 0.05 rad/s is no motion
    sweep = excites(_log("sweep", t, 10.0, np.full(len(t), 3.5), omega=1.2 * np.sign(np.sin(t))))
    assert sweep == {"motion", "fast motion", "pressure > 3 bar"}


def test_a_valve_held_partly_open_is_a_regime_of_its_own_that_stays_fitted() -> None:
    """The flow through a partly open DCV is the valve model's shape, not just its capacity: on logs of a
    protocol other than ours (a DCV chirp among PRV steps, holds and swings, on the independent rig of
    bench/independent_rig.py) the chirp was held out, the valve's shape never fitted, and 98 % of the
    effect-free rig's pressure error lay there (E 0.049 against 0.014 with the chirp fitted)."""
    t = np.arange(0.0, 4.0, 0.005)
    chirp = 5.0 - 2.5 * np.sin(2.0 * np.pi * (0.2 + 0.3 * t) * t)
    assert "dcv partly open" in excites(_log("chirp", t, chirp, np.full(len(t), 2.0)))
    assert "dcv partly open" not in excites(_log("full", t, np.where(t < 2.0, 0.0, 10.0), np.full(len(t), 2.0)))
    assert "dcv partly open" not in excites(_log("shut", t, 5.1, np.full(len(t), 2.0)))  # within 0.2 V of centre
    logs = [_log(n, t, 10.0, np.full(len(t), 2.0)) for n in ("a", "b")]
    calib, held, _ = split_by_coverage([logs[0], _log("chirp", t, chirp, np.full(len(t), 2.0)), logs[1]])
    assert [e.name for e in held] == ["b"] and "chirp" in [e.name for e in calib]


def test_what_shows_each_effect_is_what_the_protocols_experiments_excite(nominal_logs: list) -> None:
    """The regimes that show each candidate (run.SHOWN_BY) are the protocol table's rows read as
    regimes: every experiment named for an effect makes it visible (VISIBLE) and its log excites one
    of them. A candidate the held-out logs cannot show is reported as not ruled out."""
    by_kind = {e.meta["experiment"]: excites(e) for e in nominal_logs}
    assert set(SHOWN_BY) == set(EFFECT_NAMES)
    for effect, (regimes, kinds) in SHOWN_BY.items():
        assert bool(regimes) == bool(kinds), effect
        for k in kinds:
            assert effect in VISIBLE[k] and by_kind[k].intersection(regimes), (effect, k, by_kind[k])
    every = set().union(*by_kind.values())
    assert unshown(every, every) == {}
    u = unshown(every, {"prv steps", "pressure > 3 bar"})
    assert set(u) == {"inertia", "presliding_friction", "vane_leakage", "external_leakage", "heat_transfer"}
    assert u["heat_transfer"]["experiments"] == ["fill_shut"] and u["heat_transfer"]["fitted"]
    assert u["heat_transfer"]["why"].startswith("no held-out log has what shows it best (shut after a fast fill")
    assert not unshown(set(), set())["inertia"]["fitted"] and "sensor_bias" not in unshown(set(), set())
    assert u["heat_transfer"]["why"].endswith("the protocol's fill_shut would")
    # fill_shut run at 0.3 × its length: its shut (1.5 s) is under the 2 s that shows heat exchange; it is
    # named as run and too short, not recommended as if it had not run
    short = unshown(every - {"shut after a fast fill or vent"}, set(), {"fill_shut": 0.3, "prv_steps": 0.3})
    assert short["heat_transfer"]["why"].endswith(
        "the fill_shut logs here lack it (run at 0.3 × the protocol's length; at full length it shows it)")
    unknown = unshown(set(), set(), {"fill_shut": None})["heat_transfer"]["why"]
    assert unknown.endswith("the fill_shut logs here lack it")


def test_when_every_log_excites_something_alone_the_last_is_held_out_and_that_is_said() -> None:
    t = np.arange(0.0, 4.0, 0.005)
    logs = [_log("a", t, 10.0, np.full(len(t), 2.0)), _log("b", t, 10.0, np.full(len(t), 3.5), omega=1.2)]
    calib, held, why = split_by_coverage(logs)
    assert [e.name for e in calib] == ["a"] and [e.name for e in held] == ["b"]
    assert "no other does" in why
    # and three alike: one (the last) is held out, its regimes fitted on the other two
    three = [_log(n, t, 10.0, np.full(len(t), 3.5), omega=1.2) for n in ("x", "y", "z")]
    calib, held, why = split_by_coverage(three)
    assert [e.name for e in held] == ["z"] and "other logs also excite" in why
    (one,), (_rest,), why = split_by_coverage(three[:1])
    assert one.duration < three[0].duration and "first 60 %" in why
    with pytest.raises(ValueError, match="once = 'twice': must be 'coverage' or 'last_third'"):
        run_case(None, once="twice")  # the bench's switch (bench/withheld.py --once)


def test_parameter_sets_that_replay_alike_are_replayed_once_per_log(nominal_logs: list,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A torque-side candidate's grid (inertia here) leaves the pneumatic network alone: its points
    share one replay per log, in one batch and after it."""
    fam = RotaryFamily()
    preps = [fam.prepare(e) for e in nominal_logs[:3]]
    calls: list[str] = []
    real = fam._replay

    def counted(p: Any, x: dict[str, float], eff: tuple[str, ...]) -> Any:
        calls.append(p.name)
        return real(p, x, eff)

    monkeypatch.setattr(fam, "_replay", counted)
    x = {p.name: p.x0 for p in fam.baseline()}
    grid = [x | {"inertia.extra": v} for v in (0.0, 0.01, 0.02, 0.04)]
    fam.prefetch(preps, grid, ("inertia",))
    assert sorted(calls) == sorted(p.name for p in preps)
    fam.prefetch(preps, [x | {"prv_c_scale": 1.1}, *grid], ("inertia",))  # only the new pneumatic point
    assert len(calls) == 2 * len(preps)


def test_a_jacobians_points_are_replayed_in_one_batch(nominal_logs: list, monkeypatch: pytest.MonkeyPatch) -> None:
    """Least squares' difference quotients reach the replay as one batch per Jacobian (all cores
    busy to its end), not one parameter set at a time."""
    fam = RotaryFamily()
    fam.max_nfev = 2
    preps = [fam.prepare(e) for e in nominal_logs[:2]]
    sizes: list[int] = []
    real = fam.prefetch

    def counted(p: Any, xs: list[dict[str, float]], eff: tuple[str, ...]) -> None:
        sizes.append(len(xs))
        real(p, xs, eff)

    monkeypatch.setattr(fam, "prefetch", counted)
    fit(fam, preps, ())
    assert len(fam.baseline()) in sizes, sizes


def test_replay_of_the_model_that_made_the_logs_is_near_the_floor(nominal_logs: list) -> None:
    """Replaying a log with the parameters that generated it: the pressures stay within the PRV's
    rest band (its hysteresis makes the exact chatter history-dependent) and the torque balance
    closes in steady motion."""
    fam = RotaryFamily()
    x = {p.name: p.x0 for p in fam.baseline()}
    for e in nominal_logs:
        prep = fam.prepare(e)
        y, m = fam.predict(prep, x, ()), fam.measured(prep)
        for c in ("p_a", "p_b"):
            assert np.sqrt(np.mean((y[c] - m[c]) ** 2)) < 0.03, (e.name, c)
        steady = prep.regimes["steady motion 0.3–1 rad/s"]
        if steady.sum() > 50:
            assert np.sqrt(np.mean((y["torque"] - m["torque"])[steady] ** 2)) < 0.05, e.name


@pytest.mark.slow
def test_the_torque_floor_is_what_the_sensors_noise_adds_to_a_right_models_error() -> None:
    """E_floor is the error the sensors' noise alone leaves a right model. The same protocol is run
    twice on one rig, once with its torque sensor noise-free: the difference of the true model's
    torque errors is the noise's part, exactly. Where static friction holds, the replay's torque is
    the measured one, so the noise cancels there; counting it everywhere had read the floor 1.4–1.75
    times too high (1.38 on this rig), which lowered every gap closure."""
    from app.engine.diagnosis.core import noise_floor

    rig = perturbed(3, 0.2)
    quiet = replace(rig, sensors=replace(rig.sensors, torque_noise_nm=0.0))
    x = true_params(rig, None)
    fam = RotaryFamily()
    noisy = [fam.prepare(e) for e in run_protocol(rig, seed=4, repetitions=1, scale=0.3)]
    clean = [fam.prepare(e) for e in run_protocol(quiet, seed=4, repetitions=1, scale=0.3)]
    assert all(np.array_equal(n.theta, c.theta) for n, c in zip(noisy, clean, strict=True))  # the same run
    part = np.concatenate([(fam.predict(n, x, ())["torque"] - fam.measured(n)["torque"])
                           - (fam.predict(c, x, ())["torque"] - fam.measured(c)["torque"])
                           for n, c in zip(noisy, clean, strict=True)])
    noise_part = float(np.sqrt(np.nanmean(part**2)))
    floor = float(noise_floor(fam, noisy, [fam.measured(p) for p in noisy])[fam.channels.index("torque")])
    full = float(np.median([fam.noise(p)["torque"] for p in noisy]))
    assert 0.85 < floor / noise_part < 1.15, (floor, noise_part)
    assert full / noise_part > 1.3  # what the floor was: the check can tell the two apart
    # the other channels' predictions do not carry their measurement: each keeps its whole noise
    assert all(fam.noise_shows(p).keys() == {"torque"} for p in noisy)


def test_a_replay_starts_from_what_the_sensors_read_whatever_was_replayed_before(nominal_logs: list) -> None:
    """The chambers' first pressures are the first readings taken back through the sensors' gains
    and offsets, so those are part of what a replay is cached under. Keyed on the flows and
    volumes alone, a replay made at one gain had been served at another: the chambers then
    started from another pressure, which a shut chamber keeps (by 0.015–0.04 bar RMS over a
    protocol log for gains of 0.94 / 0.97), and a prediction depended on what was replayed first."""
    fam = RotaryFamily()
    log = next(e for e in nominal_logs if e.name.startswith("hold_closed"))
    x = {p.name: p.x0 for p in fam.baseline()}
    xs = [x | {"gain_a": 0.94, "gain_b": 1.03},
          x | {"sensor_bias.p_a_bar": 0.1, "sensor_bias.p_b_bar": -0.05, "sensor_bias.torque_nm": 0.0}]
    effects: list[tuple[str, ...]] = [(), ("sensor_bias",)]
    used = fam.prepare(log)
    fam.predict(used, x, ())  # the same flows and volumes, replayed at gain 1 and no offset first
    for xi, eff in zip(xs, effects, strict=True):
        fresh = fam.predict(fam.prepare(log), xi, eff)
        again = fam.predict(used, xi, eff)
        for c in ("p_a", "p_b"):
            np.testing.assert_array_equal(again[c], fresh[c])
            assert fresh[c][0] == pytest.approx(log.channels[c][0], abs=1e-9)  # the replay starts at the reading


def test_the_sensors_gains_and_offsets_start_from_their_straight_line_fit() -> None:
    """sensor_bias's descent starts from the gains and offsets fitted as straight lines to the
    replays (gain and offset trade along a narrow valley a descent from offset 0 does not leave):
    from sensors at gain 1 and offset 0 that line lands near the rig's (offsets 0.05 bar and
    0.1 N·m; the replay's own wander biases the line by ≈ 0.01 bar on half-length logs)."""
    rig = perturbed(100).with_effects(sensor_bias=MAGNITUDES["sensor_bias"][0])
    fam = RotaryFamily()
    preps = [fam.prepare(e) for e in run_protocol(rig, seed=100, repetitions=1, scale=0.5)]
    truth = true_params(rig, "sensor_bias")
    start = truth | {"gain_a": 1.0, "gain_b": 1.0, "sensor_bias.p_a_bar": 0.0, "sensor_bias.p_b_bar": 0.0,
                     "sensor_bias.torque_nm": 0.0}
    lin = fam.linear_start(preps, start, ("sensor_bias",))
    assert lin is not None
    for name, tol in (("gain_a", 0.005), ("gain_b", 0.005), ("sensor_bias.p_a_bar", 0.015),
                      ("sensor_bias.p_b_bar", 0.015), ("sensor_bias.torque_nm", 0.02)):
        assert lin[name] == pytest.approx(truth[name], abs=tol), name
    assert fam.linear_start(preps, start, ("inertia",)) is None  # nothing linear to profile


def test_a_faster_log_is_scored_at_the_station_rate(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 1 kHz log is replayed sample by sample but scored on every fifth sample (200 Hz, SPEC's HIL
    rate): least squares carries the rows of a 200 Hz log and ΔBIC counts what it would there; the
    scored channels, regimes and inputs stay aligned, and the true model still replays near the floor."""
    monkeypatch.setattr("app.engine.diagnosis.protocol.RATE_HZ", 1000.0)
    fast = run_protocol(PlantParams(), seed=4, repetitions=1, scale=0.3, kinds=["hold_closed", "friction_sweep"])
    fam = RotaryFamily()
    x = {p.name: p.x0 for p in fam.baseline()}
    for e in fast:
        assert e.meta["sample_rate_hz"] == 1000.0
        prep = fam.prepare(e)
        n = (len(e.t) + 4) // 5
        y, m = fam.predict(prep, x, ()), fam.measured(prep)
        assert {len(v) for v in (*y.values(), *m.values(), *prep.regimes.values(), *prep.inputs.values())} == {n}
        assert np.allclose(m["p_a"], e.channels["p_a"][::5])
        for c in ("p_a", "p_b"):
            assert np.sqrt(np.mean((y[c] - m[c]) ** 2)) < 0.03, (e.name, c)
        steady = prep.regimes["steady motion 0.3–1 rad/s"]
        if steady.sum() > 50:
            assert np.sqrt(np.nanmean((y["torque"] - m["torque"])[steady] ** 2)) < 0.05, e.name


@pytest.mark.parametrize("rate_hz", [150.0, 2000.0])
def test_a_replay_keeps_the_logs_clock_at_any_sample_rate(rate_hz: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """A sample is replayed in whole substeps of exactly its length, none longer than the replay's
    1 ms. A leaking closed chamber shows it: its decay is as fast as the rig's clock says. Rounding
    to whole 1 ms substeps had replayed a 2 kHz log at twice the speed (0.38 bar RMS off) and a
    150 Hz one 5 % fast (7 ms per 6.7 ms sample: 0.034 bar); now 0.004–0.012."""
    monkeypatch.setattr("app.engine.diagnosis.protocol.RATE_HZ", rate_hz)
    rig = PlantParams().with_effects(external_leakage=MAGNITUDES["external_leakage"][1])
    (e,) = run_protocol(rig, seed=4, repetitions=1, scale=0.3, kinds=["hold_closed"])
    fam = RotaryFamily()
    prep = fam.prepare(e)
    y, m = fam.predict(prep, true_params(rig, "external_leakage"), ("external_leakage",)), fam.measured(prep)
    for c in ("p_a", "p_b"):
        assert np.sqrt(np.mean((y[c] - m[c]) ** 2)) < 0.02, c


def test_a_log_with_skipped_periods_replays_on_the_rigs_clock() -> None:
    """A station log with gaps (the engine skips the periods it overran) is replayed on a uniform
    grid with the commands held through each gap, and the made-up pressures are not scored. Before,
    each gap put every later sample that much early: a leaking closed chamber with 2 % of its
    samples and one 50 ms stretch gone replayed 0.064 bar RMS off with the true parameters (now
    0.008; the PRV-step log 0.015 either way)."""
    rig = PlantParams().with_effects(external_leakage=MAGNITUDES["external_leakage"][1])
    x = true_params(rig, "external_leakage")
    fam = RotaryFamily()
    for e in run_protocol(rig, seed=4, repetitions=1, scale=0.3, kinds=["hold_closed", "prv_steps"]):
        keep = np.random.default_rng(1).uniform(size=len(e.t)) > 0.02
        keep[len(e.t) // 3: len(e.t) // 3 + 10] = False
        keep[0] = True
        gapped = type(e)(e.name, e.t[keep], {k: v[keep] for k, v in e.inputs.items()},
                         {k: v[keep] for k, v in e.channels.items()}, dict(e.meta))
        prep = fam.prepare(gapped)
        y, m = fam.predict(prep, x, ("external_leakage",)), fam.measured(prep)
        assert len(m["p_a"]) == len(e.t) and np.isnan(m["p_a"]).sum() == (~keep).sum()
        for c in ("p_a", "p_b"):
            assert np.sqrt(np.nanmean((y[c] - m[c]) ** 2)) < 0.02, (e.name, c)


def test_the_torque_balance_follows_stick_slip_transitions(nominal_logs: list) -> None:
    """Within 0.1 s of every stick↔slip switch the true model's torque stays within 0.08 N·m RMS.
    Static friction used to be computed from the already filtered balance and filtered again,
    and the friction law saw a 10 Hz speed: 0.26 N·m in prv_steps, 0.23 in dcv_steps."""
    fam = RotaryFamily()
    x = {p.name: p.x0 for p in fam.baseline()}
    for e in nominal_logs:
        prep = fam.prepare(e)
        r = fam.predict(prep, x, ())["torque"] - fam.measured(prep)["torque"]
        w = int(round(0.1 / prep.dt))
        near = np.zeros(r.size, dtype=bool)
        for i in np.flatnonzero(np.diff(prep.stuck.astype(int))):
            near[max(0, i - w): i + w + 1] = True
        if near.any():
            assert np.sqrt(np.nanmean(r[near] ** 2)) < 0.08, e.name
        # the zero-phase filter's first and last 0.1 s are left out, not scored
        assert np.isnan(r[:w]).all() and np.isnan(r[-w:]).all() and np.isfinite(r[w:-w]).all()


def test_the_supply_level_is_profiled_out(nominal_logs: list) -> None:
    # the shop regulator set 0.2 bar higher that day: the supply channel's residual is unchanged
    fam = RotaryFamily()
    x = {p.name: p.x0 for p in fam.baseline()}
    e = nominal_logs[0]
    r0 = fam.predict(fam.prepare(e), x, ())["p_s"] - e.channels["p_s"]
    e.channels["p_s"] = e.channels["p_s"] + 0.2
    try:
        r1 = fam.predict(fam.prepare(e), x, ())["p_s"] - e.channels["p_s"]
    finally:
        e.channels["p_s"] = e.channels["p_s"] - 0.2
    assert abs(float(np.mean(r1))) < 1e-9
    np.testing.assert_allclose(r1, r0, atol=2e-3)  # the network sees the supply 0.2 bar higher


def test_protocol_logs_begin_at_rest_so_a_lagging_valve_replays_from_the_start() -> None:
    """Every protocol log opens with PREROLL_S of the rest commands (PRVs holding the start
    pressure, DCVs shut), so its first step is inside it. A replay starts the valves at the
    log's first command: on logs that began with a step, valves lagging 10/30 ms put the true
    model up to 1 bar off for the first 50 ms (90 % of its held-out error)."""
    rig = PlantParams().with_effects(valve_dynamics=ValveDynamicsEffect(0.03, 0.1))
    e = run_protocol(rig, seed=2, repetitions=1, kinds=["dcv_steps"])[0]
    n0 = int(round(PREROLL_S / e.dt))
    rest = np.column_stack([e.inputs[c][:n0] for c in ("z_a", "z_b", "u_a", "u_b")])
    assert (rest == rest[0]).all() and (rest[0, 2:] == 5.0).all()
    assert e.inputs["u_a"][n0] != 5.0  # the first step comes right after
    fam = RotaryFamily()
    x = {p.name: p.x0 for p in fam.baseline()} | {"valve_dynamics.tau_dcv": 0.03, "valve_dynamics.tau_prv": 0.1}
    prep = fam.prepare(e)
    y, m = fam.predict(prep, x, ("valve_dynamics",)), fam.measured(prep)
    for c in ("p_a", "p_b"):
        assert np.sqrt(np.mean((y[c] - m[c])[: n0 + 200] ** 2)) < 0.01, c  # bar, through the first second


def test_the_regulators_phase_counts_as_lost_from_half_a_second_after_a_chambers_step() -> None:
    """A chamber's prediction is the replay's cycle mean only where its averaging window lies
    wholly :data:`~rotary.PHASE_KEPT_S` or more after that chamber's last command step, or after
    the log's start (the replay starts in phase, from what the sensors read)."""
    dt, n = 0.005, 1000
    cmds = np.full((n, 2), 5.0)
    cmds[400:, 0] = 6.0  # a PRV step at sample 400
    cmds[700:, 1] = 5.0 + 0.5 * rotary.STEP_V  # a change below a step
    lost = _phase_lost(cmds, dt)
    before, after = round(rotary.PHASE_KEPT_S / dt), round(0.5 * rotary.CYCLE_MEAN_S / dt) + 1
    assert not lost[: before + 1].any()  # the start
    assert lost[before + 1: 400 - after].all()
    assert not lost[400 - after: 400 + before + 1].any()  # the step's window, either side
    assert lost[400 + before + 1:].all()


def test_a_command_step_is_read_alike_at_every_sample_rate() -> None:
    """A chirp on the DCVs (another lab's valve_chirp, bench/independent_rig.py) moves ≥ 0.016 V per
    5 ms but 0.003 V per 1 ms where it turns slowly: sampled at 200 Hz it read as stepping throughout
    (the regulator's phase kept), at 1 kHz a quarter of it as held (the phase lost), and that log's
    recalibration took another form. A step is now a change over 5 ms: the same at both rates, and at
    200 Hz the change between neighbouring samples, as before."""
    def chirp(rate: float) -> np.ndarray:
        t = np.arange(int(15.0 * rate)) / rate
        u = 5.0 - 2.5 * np.sin(2.0 * np.pi * (0.2 + 0.06 * t) * t)
        return np.column_stack([np.full_like(t, 2.0), u])

    slow, fast = chirp(200.0), chirp(1000.0)
    np.testing.assert_array_equal(rotary.command_changes(slow, 0.005)[1:], np.abs(np.diff(slow, axis=0)))
    lost_slow, lost_fast = _phase_lost(slow, 0.005), _phase_lost(fast, 0.001)
    assert not lost_slow.any() and not lost_fast.any()
    # a step of a 1 kHz log is still one step, seen over the next 5 ms only
    held = np.full((3000, 2), 5.0)
    held[1000:, 0] = 6.0
    ch = rotary.command_changes(held, 0.001)
    assert (np.flatnonzero(ch[:, 0] > rotary.STEP_V) == np.arange(1000, 1005)).all()
    # and what a log excites does not hang on its rate: a PRV ramp of 0.4 V/s…
    for rate in (200.0, 1000.0):
        t = np.arange(int(10.0 * rate)) / rate
        z = np.column_stack([1.0 + 0.4 * t, np.full_like(t, 2.0)])
        assert not (rotary.command_changes(z, 1.0 / rate) > rotary.PRV_STEP_V).any(), rate
        z[int(5.0 * rate):, 0] += 0.5  # …with one step in it
        assert (rotary.command_changes(z, 1.0 / rate) > rotary.PRV_STEP_V).any(), rate


def test_where_the_phase_is_lost_the_cycles_mean_predicts_the_rig_better() -> None:
    """A PRV that acts cycles in a sawtooth whose phase the replay loses a few cycles after a step:
    two sawtooths out of phase differ by about their size, a mean by less. On a noise-free rig
    replayed with its true parameters (heat exchange, the second draw's larger: the replay_floor
    bench's case), the mean lowers the friction sweep's chamber pressure error by a quarter
    (0.021 → 0.015 bar RMS on this half-length log), and where the phase holds the prediction is the
    replay's."""
    noisy = perturbed(101).with_effects(heat_transfer=MAGNITUDES["heat_transfer"][1])
    rig = replace(noisy, sensors=replace(noisy.sensors, pressure_noise_bar=0.0, torque_noise_nm=0.0))
    x = true_params(rig, "heat_transfer")
    logs = run_protocol(rig, seed=101, repetitions=1, scale=0.5, kinds=["prv_steps", "friction_sweep"])

    def rms(fam: RotaryFamily) -> dict[str, tuple[float, np.ndarray, np.ndarray]]:
        out = {}
        for e in logs:
            prep = fam.prepare(e)
            y, m = fam.predict(prep, x, ("heat_transfer",)), fam.measured(prep)
            out[e.name.split("-")[0]] = (float(np.sqrt(np.mean((y["p_a"] - m["p_a"]) ** 2))), y["p_a"],
                                         prep.phase_lost[0])
        return out

    mean, raw = rms(RotaryFamily()), rms(RotaryFamily(cycle_mean_s=0.0))
    assert mean["friction_sweep"][0] < 0.85 * raw["friction_sweep"][0]
    assert mean["prv_steps"][0] <= raw["prv_steps"][0]
    for k in mean:
        kept = ~mean[k][2]
        assert kept.any() and mean[k][2].any()
        np.testing.assert_array_equal(mean[k][1][kept], raw[k][1][kept])


def test_the_replay_takes_the_atmosphere_each_log_was_taken_in() -> None:
    """A lab at 1000 m (0.90 bar abs), its logs saying so: the PRVs regulate to z + P_atm and exhaust
    into it. The replay had used the sea-level 1.013 bar whatever the log said, so such a rig's
    pressures read 0.1 bar off (a protocol at 0.95 bar doubled the baseline's error, and
    sensor_bias closed half of it)."""
    from app.engine.constants import BAR

    quiet = PlantParams()
    quiet = replace(quiet, p_atm=0.90 * BAR, sensors=replace(quiet.sensors, pressure_noise_bar=0.0,
                                                             torque_noise_nm=0.0))
    (log,) = run_protocol(quiet, repetitions=1, scale=0.3, kinds=["prv_steps"])
    assert log.meta["p_atm_bar"] == pytest.approx(0.90)
    fam = RotaryFamily()
    x = {p.name: p.x0 for p in fam.baseline()}

    def rms(e: Experiment) -> float:
        prep = fam.prepare(e)
        y, m = fam.predict(prep, x, ()), fam.measured(prep)
        return float(np.sqrt(np.mean((y["p_a"] - m["p_a"]) ** 2)))

    told = rms(log)
    untold = rms(replace(log, meta=log.meta | {"p_atm_bar": 1.01325}))
    assert told < 0.02 and untold > 0.08, (told, untold)  # bar RMS: 0.007 and 0.11 when written


def test_a_wrong_atmosphere_in_the_logs_is_read_off_the_vented_chambers() -> None:
    """A wrong p_atm_bar reads as an offset of both chamber sensors, which sensor_bias would take; where
    a DCV has vented its chamber, the chamber stands at the atmosphere, so the report says which."""
    from app.engine.diagnosis.run import ATMOSPHERE_TOL_BAR, VENT_MIN_SAMPLES, vented_atmosphere

    logs = run_protocol(PlantParams(), seed=5, repetitions=1, scale=0.5, kinds=["fill_shut", "prv_steps"])
    right = vented_atmosphere(logs)
    for c in ("p_a", "p_b"):  # the venting's own: 0.001–0.003 bar above the atmosphere
        assert right[c]["samples"] >= VENT_MIN_SAMPLES and abs(right[c]["offset_bar"]) < 0.5 * ATMOSPHERE_TOL_BAR
    assert right["note"] == "" and right["p_atm_bar"] == pytest.approx(1.01325)
    # the logs written at sea level, the rig at 1000 m: both chambers read 0.11 bar under it
    high = vented_atmosphere([replace(e, meta=e.meta | {"p_atm_bar": 1.125}) for e in logs])
    assert high["p_a"]["offset_bar"] == pytest.approx(-0.11, abs=0.01), high
    assert high["note"].startswith("where a DCV vented its chamber, p_a and p_b read -0.11")
    assert "the atmosphere written in the logs looks wrong" in high["note"]
    # one sensor's zero off: only that chamber is named
    off_b = vented_atmosphere([replace(e, channels=e.channels | {"p_b": e.channels["p_b"] + 0.05}) for e in logs])
    assert off_b["note"].startswith("where its DCV vented it, p_b reads +0.05") and "p_a " not in off_b["note"]
    # logs that never vent a chamber say nothing either way
    none = vented_atmosphere([e for e in logs if e.name.startswith("prv_steps")])
    assert none["p_a"]["samples"] == 0 and math.isnan(none["p_a"]["offset_bar"]) and none["note"] == ""


def test_replay_sees_an_effect_where_it_acts(nominal_logs: list) -> None:
    # the same replay with a vane leak switched on departs from the leak-free logs in the hold
    fam = RotaryFamily()
    x = {p.name: p.x0 for p in fam.baseline()} | {"vane_leakage.c": 0.06}
    hold = next(e for e in nominal_logs if e.name.startswith("hold_closed"))
    prep = fam.prepare(hold)
    y = fam.predict(prep, x, ("vane_leakage",))
    gap = np.abs(y["p_a"] - fam.measured(prep)["p_a"])[-200:]
    assert gap.mean() > 0.05  # bar: a leak across the vane drains the high chamber into the low one


@pytest.mark.parametrize("effect", ["heat_transfer", "tube_dynamics", "vane_leakage", "external_leakage",
                                    "valve_dynamics"])
def test_an_effect_at_its_off_values_replays_as_the_baseline_itself(nominal_logs: list, effect: str) -> None:
    # a candidate's fit starts from its "off" values, and promises never to end worse than the model
    # without it: there its replay must be the baseline's. At their bounds a tube (5 cm of 12 mm) and a
    # wall's exchange (20 W/K) were still there, and on a rig written apart from ours logged at 1 kHz
    # the heat exchange's fit ended above the baseline (GC -0.72)
    fam = RotaryFamily()
    specs = fam.effect(effect)
    base = {p.name: p.x0 for p in fam.baseline()}
    off = base | {p.name: p.off for p in specs if p.off is not None}
    near = base | {p.name: (p.off * (0.97 if p.off == p.hi else 1.03)) if p.log and p.off is not None else p.x0
                   for p in specs}
    for log in (e for e in nominal_logs if e.name.startswith(("hold_closed", "prv_steps"))):
        prep = fam.prepare(log)
        without = fam.predict(prep, base, ())
        at_off = fam.predict(prep, off, (effect,))
        for c in ("p_a", "p_b"):
            assert np.array_equal(at_off[c], without[c], equal_nan=True), (log.name, c)
        # and just inside its range the effect is there: the replay did not drop it everywhere
        if effect in ("heat_transfer", "tube_dynamics") and log.name.startswith("prv_steps"):
            moved = fam.predict(prep, near, (effect,))
            assert np.nanmax(np.abs(moved["p_a"] - without["p_a"])) > 1e-3


def test_perturbed_rig_stays_within_twenty_percent() -> None:
    p, q = PlantParams(), perturbed(7)
    assert 0.8 <= q.prv.c_supply / p.prv.c_supply <= 1.2
    assert 0.8 <= q.vane.dead_volume_a / p.vane.dead_volume_a <= 1.2
    assert q.prv.c_supply != p.prv.c_supply


def test_diagnose_refuses_linear_rig_station_logs(tmp_path: Path) -> None:
    from app.engine.diagnosis.logs import write_log
    from app.engine.sim import LOG_COLUMNS

    n = 50
    data = np.zeros((n, len(LOG_COLUMNS)))
    data[:, 0] = np.arange(n) / 200.0
    data[:, 5:8] = 2.0
    meta = {"rig": "linear", "sample_rate_hz": 200.0, "p_atm_bar": 1.013, "working_pressure_bar": 3.0,
            "experiment": "x", "human": False}
    write_log(tmp_path, "lin", data, meta)
    with pytest.raises(LogFormatError, match="lin come from the linear rig"):
        diagnose_dir(tmp_path)


@pytest.mark.parametrize(("args", "words"), [
    (["--effect", "wobble"], "unknown effect 'wobble'"),
    (["--effect", "inertia:3"], "magnitude must be 1 (smaller) or 2 (larger)"),
    (["--scale", "0"], "--scale 0.0 is outside"),
    (["--param-error", "2"], "--param-error 2.0 is outside"),
])
def test_cwrr_protocol_refuses_bad_arguments_and_writes_nothing(tmp_path: Path, args: list[str], words: str,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    from app.cli import main

    assert main(["protocol", str(tmp_path / "logs"), *args]) == 2
    assert words in capsys.readouterr().err
    assert not (tmp_path / "logs").exists()


def test_a_simulated_rig_is_off_by_group_or_parameter_by_parameter() -> None:
    """``errors='grouped'`` scales every friction level by one factor, as the baseline recalibrates;
    ``'each'`` gives each table entry and each PRV capacity an error of its own."""
    from app.engine.diagnosis.suite import simulated_rig

    nom = PlantParams()

    def ratios(rig: PlantParams) -> np.ndarray:
        return np.array([*(np.array(rig.friction.ts_ccw) / nom.friction.ts_ccw),
                         *(np.array(rig.friction.ts_cw) / nom.friction.ts_cw),
                         rig.prv.c_supply / nom.prv.c_supply, rig.prv.c_exhaust / nom.prv.c_exhaust])

    grouped, each = ratios(simulated_rig(5, 0.2)), ratios(simulated_rig(5, 0.2, "each"))
    assert np.ptp(grouped[:-2]) < 1e-12 and abs(grouped[-1] - grouped[-2]) < 1e-12
    assert np.ptp(each[:-2]) > 0.02 and abs(each[-1] - each[-2]) > 1e-6
    assert np.all(np.abs(each - 1.0) <= 0.2 + 1e-12)
    assert simulated_rig(5, 0.0, "each") == nom  # no error: the nominal rig either way
    assert simulated_rig(5, 0.2, effects={"vane_leakage": 2}).effects.active() == ["vane_leakage"]
    with pytest.raises(ValueError, match="errors = 'every'"):
        simulated_rig(5, 0.2, "every")


def test_cwrr_protocol_draws_errors_parameter_by_parameter(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    from app.cli import main

    assert main(["protocol", str(tmp_path), "--param-error", "0.2", "--errors", "each", "--scale", "0.2",
                 "--effect", "vane_leakage"]) == 0
    out = capsys.readouterr().out
    assert "14 logs written" in out and len(list(tmp_path.glob("*.csv"))) == 14
    # a short protocol is said to pin the nominal values down less where its length is chosen
    assert "a protocol 0.2 × as long pins the model's nominal values down less" in out
    # run again into the same folder: refused before anything runs, naming the logs in the way, and the
    # folder as it was (the writer never overwrites a log, and used to fail at the first clash with a
    # traceback); a file where the folder should be is refused in words too
    before = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
    (tmp_path / "dcv_steps-1.csv").unlink()
    (tmp_path / "dcv_steps-1.json").unlink()
    del before["dcv_steps-1.csv"], before["dcv_steps-1.json"]
    assert main(["protocol", str(tmp_path), "--scale", "0.2"]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path} already holds prv_steps-1.csv, prv_steps-1.json, hold_closed-1.csv" in err, err
    assert "and 22 more: the protocol writes its logs under those names and never overwrites one" in err, err
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == before
    assert main(["protocol", str(tmp_path / "prv_steps-1.csv"), "--scale", "0.2"]) == 2
    assert "prv_steps-1.csv is a file, not a directory for the protocol's logs" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["protocol", str(tmp_path / "x"), "--errors", "every"])
    assert "invalid choice: 'every'" in capsys.readouterr().err and not (tmp_path / "x").exists()


@pytest.mark.slow
def test_withheld_sensor_bias_through_the_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """End to end as a researcher would: run the protocol on a rig with offsets on its sensors and
    ±20 % parameter errors, diagnose the logs, read the report."""
    from app.cli import main

    logs = tmp_path / "logs"
    assert main(["protocol", str(logs), "--effect", "sensor_bias:2", "--param-error", "0.2", "--seed", "5",
                 "--scale", "0.5"]) == 0
    assert len(list(logs.glob("*.csv"))) == 2 * len(VISIBLE)
    out = tmp_path / "report.json"
    assert main(["diagnose", str(logs), "--json", str(out)]) == 0

    def no_bare_tokens(token: str) -> float:
        raise AssertionError(f"{token} in a report strict JSON readers must parse")

    # strict JSON: the form parameters the recalibration held have no SD, and Python's json would
    # write those as the bare token NaN, which JSON.parse and jq refuse
    r = json.loads(out.read_text(), parse_constant=no_bare_tokens)
    assert set(r["baseline"]["nrmse"]) == {"p_a", "p_b", "p_s", "torque"}
    assert r["verdict"]["effects"][:1] == ["sensor_bias"], r["verdict"]
    top = r["ranking"][0]
    assert top["effect"] == "sensor_bias" and top["significant"]
    assert r["verdict"]["alternatives"] == [], r["alternatives"]  # real offsets: not a friction error per direction
    # the offsets the rig had (MAGNITUDES["sensor_bias"][1]: +0.15 bar, +0.10 bar, −0.3 N·m), recovered.
    # A pressure sensor's offset trades against its gain (fitted too, the rig's are off by up to ±2 %)
    # when the logs stay near P_w, so what the data pin down is the sensor's reading over the pressures
    # the protocol visits: compare the recovered line g·p + b with the rig's over 2–4 bar abs.
    truth = MAGNITUDES["sensor_bias"][1]
    rig = perturbed(5, 0.2)
    fitted = top["params"] | top["baseline_params"]
    for side, bias in (("a", truth.p_a_bar), ("b", truth.p_b_bar)):
        g_rig = getattr(rig.sensors, f"pressure_gain_{side}")
        for p in (2.0, 3.0, 4.0):
            reading = fitted[f"gain_{side}"] * p + fitted[f"sensor_bias.p_{side}_bar"]
            assert reading == pytest.approx(g_rig * p + bias, abs=0.03), (side, p, fitted)
        # and the offset itself within the ±2 % gain's worth at P_w (3 bar · 2 % ≈ 0.06 bar)
        assert fitted[f"sensor_bias.p_{side}_bar"] == pytest.approx(bias, abs=0.06)
    assert top["params"]["sensor_bias.torque_nm"] == pytest.approx(truth.torque_nm, abs=0.06)
    assert r["how_far"]["e_after"] < r["how_far"]["e_before"]
    assert {w["channel"] for w in r["where"]} == {"p_a", "p_b", "p_s", "torque"}
    # "where" reads each RMS against the floor the report's E is read against: for the torque, the
    # part of its sensor's noise a right model's error carries (it cancels at standstill)
    spread = {w["channel"]: w["floor"] / r["noise_floor"]["nrmse"][w["channel"]] for w in r["where"]}
    assert all(w["floor"] > 0 for w in r["where"]) and len({round(v, 9) for v in spread.values()}) <= 2, spread
    tq = next(w for w in r["where"] if w["channel"] == "torque")
    assert tq["floor"] < 0.8 * tq["noise"], tq
    assert sorted(r["experiments"]["held_out"]) == sorted(f"{k}-2" for k in VISIBLE)
    assert r["experiments"]["split"] == "the last repetition of every experiment run more than once"
    for w in r["where"]:  # and per held-out log, whose shares of the squared error add up
        assert set(w["experiments"]) == set(r["experiments"]["held_out"]), w["experiments"]
        assert sum(e["share"] for e in w["experiments"].values()) == pytest.approx(1.0)
    assert "motion" in r["experiments"]["excites"]["friction_sweep-1"]
    assert "shut after a fast fill or vent" in r["experiments"]["excites"]["fill_shut-2"]
    assert r["experiments"]["unshown"] == {} and r["verdict"]["untested"] == []  # the protocol shows every one
    printed = capsys.readouterr().out
    assert "held out: " in printed  # which logs scored the verdict, and why those
    assert "\n  sensor_bias: pressure or torque sensors reading off zero\n" in printed  # the verdict in plain words


@pytest.mark.slow
def test_withheld_presliding_is_found_and_an_effect_free_rig_is_left_alone() -> None:
    r = run_case("presliding_friction", 1, seed=11, scale=0.5)
    assert r["verdict"][:1] == ["presliding_friction"], (r["verdict"], r["rank"])
    p = r["report"]["ranking"][0]["params"]
    assert p["presliding_friction.sigma0"] == pytest.approx(MAGNITUDES["presliding_friction"][1].sigma0, rel=0.3)
    null = run_case(None, seed=12, scale=0.5)
    assert null["verdict"] == [], null["report"]["ranking"][0]


@pytest.mark.slow
def test_a_rig_that_differs_in_form_is_left_as_unexplained_gap_not_blamed_on_an_effect() -> None:
    # a rig model written by someone else differs from ours in form, not only in scale (issue 6): here
    # the PRVs' critical pressure ratio, 0.45 against the model's 0.30, which is no candidate effect
    r = run_case(None, seed=300, structural="prv_b_0.45", scale=0.5)
    hf = r["report"]["how_far"]
    assert r["verdict"] == [], r["report"]["ranking"][:3]
    assert hf["e_before"] > 2 * hf["e_floor"] and hf["unexplained_share"] == 1.0  # a gap, said to be unexplained
    with pytest.raises(ValueError, match=r"no structural variant 'prv_b'; known: dcv_b_0\.40"):
        run_case(None, structural="prv_b")


def test_fill_shut_shows_the_gas_cooling_that_a_dead_volume_cannot_mimic() -> None:
    """After a 0.4 s fill the DCVs shut at 5 V: on the isothermal rig only the null zone's leak
    moves the chamber, towards the valve's equilibrium at 5 V (a ≈ 0.97 of the line, ≈ 0.15 bar
    below; 0.11 bar in the first second); with wall heat exchange (h·A = 0.3 W/K, τ ≈ 1 s) the
    compression-warmed gas cools and the pressure sags ≥ 0.15 bar more (0.34 bar) — at constant
    volume, so no dead volume can explain it."""
    sags = {}
    for name, rig in (("isothermal", PlantParams()),
                      ("heat", PlantParams().with_effects(heat_transfer=MAGNITUDES["heat_transfer"][0]))):
        e = run_protocol(rig, seed=3, repetitions=1, kinds=["fill_shut"])[0]
        shut = int(np.argmax((e.inputs["u_a"] == 5.0) & (e.t > 1.0)))  # the first shut
        assert e.channels["p_a"][shut] > 4.0  # filled from the line (z = 3.5 V) before the shut
        sags[name] = float(e.channels["p_a"][shut] - e.channels["p_a"][shut + 200])  # over the next 1 s
    assert 0.0 <= sags["isothermal"] < 0.15, sags
    assert sags["heat"] > sags["isothermal"] + 0.15, sags


@pytest.mark.slow
def test_withheld_heat_transfer_heads_the_ranking() -> None:
    """With fill_shut in the protocol the smaller heat-exchange magnitude (h·A = 0.3 W/K) ranks
    first (it was sixth without it: the dead volume absorbed it). On the full protocol it is
    named, GC 0.70 against the true model's 0.69 (docs/diagnosis-record.md; 0.52 and not significant before the
    baseline's grid in pneumatic fits); the half-length protocol here keeps CI time down."""
    r = run_case("heat_transfer", 0, seed=100, scale=0.5)
    assert r["rank"] == 1, [x["effect"] for x in r["report"]["ranking"]]
    assert r["gap_closure"] > 0.2


@pytest.mark.slow
def test_a_slow_heat_exchange_is_fitted_from_the_nominal_dead_volumes() -> None:
    """At h·A = 0.05 W/K the baseline, recalibrated without heat exchange, puts the dead volumes
    at 0.72–0.80 × nominal (true 1.19 ×; 0.80 since the recalibration's grid start). A fit started
    there ended at h·A = 0.9 W/K and nothing was significant (GC 0.12); the grid and descent from
    the nominal volumes (RotaryFamily.rebase) find the exchange (0.055 W/K) and name it.

    The dead volumes are not asserted: on these logs they trade with the exchange, below the
    truth's calibration cost. Once replays started from the readings at the fit's own gains, the
    fit ended at 0.80 × nominal (0.92 × the truth's cost); with the grid's second refinement at
    1.03 × (0.82 ×). Either way its held-out GC is the true model's."""
    eff, mag, seed = "heat_transfer", 1, 100
    r = run_case(eff, mag, seed=seed)
    assert r["verdict"][:1] == [eff], (r["verdict"], r["rank"])
    heat = next(x for x in r["report"]["ranking"] if x["effect"] == eff)
    assert 0.025 < heat["params"]["heat_transfer.h_a"] < 0.1, heat["params"]
    assert r["gap_closure"] > 0.3
    assert r["gap_closure"] > r["oracle_gap_closure"] - 0.05
    rig = perturbed(seed).with_effects(heat_transfer=MAGNITUDES[eff][mag])
    fam = RotaryFamily()
    preps = [fam.prepare(e) for e in run_protocol(rig, seed=seed) if e.meta["repetition"] == 1]
    meas, scales = [fam.measured(p) for p in preps], channel_scales(fam, preps)

    def cost(x: dict[str, float]) -> float:
        res = _residuals(fam, preps, meas, x, (eff,), scales)
        return float(res @ res)

    assert cost(heat["baseline_params"] | heat["params"]) < 1.1 * cost(true_params(rig, eff))


def _calibration_once(rig: PlantParams, seed: int) -> tuple[list[Experiment], RotaryFamily, list, dict[str, float]]:
    """The protocol run once on ``rig``, split as ``cwrr diagnose`` splits it: its calibration logs, the
    family, their preparations and channel scales."""
    calib, _, _ = split_by_coverage(run_protocol(rig, seed=seed, repetitions=1))
    fam = RotaryFamily()
    preps = [fam.prepare(e) for e in calib]
    return calib, fam, preps, channel_scales(fam, preps)


def test_the_recalibration_grids_again_with_the_gains_and_friction_it_fitted() -> None:
    """An effect-free rig (seed 211: PRV capacity, DCV capacity and dead volume 0.88 / 1.06 / 0.93 ×
    nominal, pressure gains 1.020 / 1.017), logged once. The recalibration's grid, run with the
    gains and friction at nominal, chose the PRV capacity 1.25 ×; the descent stayed in that basin
    at 1.6 × the calibration cost of a descent from the truth, and tube_dynamics, refitting the
    flows from nominal, closed 0.38 of a gap that was the baseline's own (a false positive). The
    grid again at the fitted gains and friction (docs/diagnosis-record.md, "The recalibration's second
    grid") finds the valley a descent from the truth ends in."""
    rig = perturbed(211)
    _, fam, preps, scales = _calibration_once(rig, 211)
    base = recalibrate(fam, preps, scales)
    from_truth = fit(fam, preps, (), scales=scales, starts=[true_params(rig, None)])
    assert base.rss < 1.1 * from_truth.rss, (base.params, base.rss / from_truth.rss)


def test_a_valve_shut_at_its_centre_is_recalibrated_not_left_as_gap() -> None:
    """An effect-free rig whose DCVs are shut at 5 V and open past a 0.2 V dead band with no null
    zone (suite.STRUCTURAL's dcv_closed_centre), logged once. With the thesis's centre (underlaps
    0.7 / 0.3 V, a 1.6 V null zone) held, the replay fills a vented, shut chamber from the line and
    sags a full one: on such a rig written apart from ours (bench/independent_rig.py) that had left
    E at 18 × the noise floor. The recalibration takes the valve's centre as it is."""
    rig = STRUCTURAL["dcv_closed_centre"][1](perturbed(212))
    calib, fam, preps, scales = _calibration_once(rig, 212)
    base = recalibrate(fam, preps, scales)
    truth = true_params(rig, None)
    assert truth["dcv_centre_closure"] == 1.0 and truth["dcv_dead_band_v"] == pytest.approx(0.2)
    assert base.params["dcv_centre_closure"] > 0.8, base.params
    from_truth = fit(fam, preps, (), scales=scales, starts=[truth])
    assert base.rss < 1.2 * from_truth.rss, (base.params, base.rss / from_truth.rss)
    # the thesis's centre held (its range narrowed to it): what the recalibration did before
    thesis = RotaryFamily(bounds={"dcv_centre_closure": (0.0, 1e-6)})
    held = recalibrate(thesis, [thesis.prepare(e) for e in calib], scales)
    assert held.rss > 3 * base.rss, (held.rss / base.rss, held.params)


def test_the_valves_centre_moves_both_paths_together_and_never_leaks_more_than_the_thesiss() -> None:
    fam = RotaryFamily()
    d = fam.nominal.dcv
    assert fam.dcv_centre(0.0, 0.3) == {"ul_f": d.underlap_fill_v, "ul_e": d.underlap_exh_v, "null_w": d.null_width_v}
    assert fam.dcv_centre(1.0, 0.3) == pytest.approx({"ul_f": -0.3, "ul_e": -0.3, "null_w": 0.0})
    # the flow at 5 V falls with the closure on both paths: no form drains a shut chamber faster
    k0 = fam.kernel
    for c0, c1 in [(0.0, 0.3), (0.3, 0.7), (0.7, 1.0)]:
        a, b = fam.dcv_centre(c0, 0.2), fam.dcv_centre(c1, 0.2)
        for ul in ("ul_f", "ul_e"):
            s_a = null_scale(5.0, k0.null_s0, a["null_w"]) * area_frac(a[ul], k0.mp)
            s_b = null_scale(5.0, k0.null_s0, b["null_w"]) * area_frac(b[ul], k0.mp)
            assert s_b <= s_a, (c0, c1, ul)


def test_the_prv_regulators_form_maps_to_the_kernel_and_the_suites_answer_key_reproduces_a_rig() -> None:
    fam = RotaryFamily()
    r, k = fam.nominal.prv, fam.kernel
    assert fam.prv_regulator(1.0, 1.0, 0.0) == pytest.approx(
        {"prv_db_on": k.prv_db_on, "prv_db_off": k.prv_db_off, "prv_dz": k.prv_dz})
    # no hysteresis: it wakes and rests at the band's middle; a dead zone as wide as the rest band
    mid = 0.5 * (r.deadband_on_bar + r.deadband_off_bar) * 1e5
    assert fam.prv_regulator(1.0, 0.0, 1.0) == pytest.approx({"prv_db_on": mid, "prv_db_off": mid, "prv_dz": mid})
    # never a negative rest band, however wide the hysteresis
    assert fam.prv_regulator(0.5, 2.0, 1.0)["prv_db_off"] >= 0.0
    # the answer key's form gives the rig's own regulator
    for rig in (STRUCTURAL["prv_deadband_half"][1](PlantParams()), STRUCTURAL["prv_dead_zone"][1](PlantParams())):
        x = true_params(rig, None)
        got, own = fam.kernel_for(x, (), 8.0), rotary.pl.build_kernel(rig)
        assert (got.prv_db_on, got.prv_db_off, got.prv_dz) == pytest.approx((own.prv_db_on, own.prv_db_off, own.prv_dz))
        assert got.prv_gain == own.prv_gain
    x = {p.name: p.x0 for p in fam.baseline()}
    assert fam._key(x, ()) != fam._key(x | {"prv_dead_zone": 0.5}, ())  # not the nominal's cached replay


def test_the_prv_spool_opens_past_its_dead_zone() -> None:
    assert rotary.pl.spool_error(3000.0, 1000.0) == 2000.0 and rotary.pl.spool_error(-3000.0, 1000.0) == -2000.0
    assert rotary.pl.spool_error(500.0, 1000.0) == 0.0 and rotary.pl.spool_error(500.0, 0.0) == 500.0
    with pytest.raises(ValueError, match="dead_zone"):
        PlantParams(prv=replace(PlantParams().prv, dead_zone=1.5))


def test_a_prv_regulator_of_another_form_is_recalibrated_where_it_matters() -> None:
    """An effect-free rig whose PRV regulators wake and rest at 0.02 bar (no hysteresis) and open
    their spools in proportion to the error past that (suite.STRUCTURAL's prv_dead_zone), logged
    once. The nominal regulator (wakes at 0.03 bar, rests below 0.01, opens in proportion to the
    whole error) overshoots each fill and rests off: on such a rig written apart from ours
    (bench/independent_rig.py) the pressure error had stayed at 0.017 / 0.018 bar RMS with the
    valve's centre recalibrated. On ours the form costs less (0.013 / 0.016 bar) and taking it
    gains 0.005 / 0.008 bar: under the family's relevance (0.01 bar), so it is left nominal, as any
    form is that gains less than what matters (core.recalibrate_forms). Where a finer error
    matters (half that relevance), the recalibration takes the regulator's form: no hysteresis
    and a dead zone, though only half the rig's (its coordinate grids stop in a valley where the
    dead volumes and the dead zone trade, at 1.8 × the calibration cost of a descent from the
    truth, 0.45 × the nominal form's)."""
    rig = STRUCTURAL["prv_dead_zone"][1](perturbed(213))
    _, fam, preps, scales = _calibration_once(rig, 213)
    truth = true_params(rig, None)
    assert truth["prv_hysteresis_scale"] == 0.0 and truth["prv_dead_zone"] == 1.0
    held, base = recalibrate_forms(fam, preps, scales)
    assert base is held and all(held.params[n] == v for n, v in rotary.PRV_FORM_NOMINAL.items()), base.params
    fam.relevance = {c: v / 2 for c, v in fam.relevance.items()}
    base = recalibrate(fam, preps, scales)
    assert base.params["prv_hysteresis_scale"] < 0.5 and base.params["prv_dead_zone"] > 0.25, base.params
    from_truth = fit(fam, preps, (), scales=scales, starts=[truth])
    assert base.rss < 2.0 * from_truth.rss, (base.params, base.rss / from_truth.rss)
    assert held.rss > 2 * base.rss, (held.rss / base.rss, held.params)


def test_friction_that_does_not_follow_the_pressures_is_recalibrated() -> None:
    """An effect-free rig whose friction is Table 4.2's 3 bar row at every pressure, logged once.
    Read at the lower chamber's pressure, the table's rows (ω_s 0.55 rad/s at 2 bar, 0.92 at 3)
    bend the friction the replay predicts; the recalibration reads it at 3 bar throughout."""
    base_rig = perturbed(214)
    fr = base_rig.friction
    i = fr.pw_bar.index(3.0)
    row: dict[str, Any] = {n: (getattr(fr, n)[i],)
                           for n in ("ts_ccw", "tc_ccw", "ws_ccw", "b_ccw", "ts_cw", "tc_cw", "ws_cw", "b_cw")}
    rig = replace(base_rig, friction=replace(fr, pw_bar=(3.0,), **row))
    _, fam, preps, scales = _calibration_once(rig, 214)
    base = recalibrate(fam, preps, scales)
    assert base.params["friction_pressure_weight"] < 0.3, base.params
    levels = true_params(base_rig, None)
    truth = base.params | {"friction_pressure_weight": 0.0, "friction_scale": levels["friction_scale"],
                           "viscous_scale": levels["viscous_scale"]}
    following = base.params | {"friction_pressure_weight": 1.0}

    def torque_rms(x: dict[str, float]) -> float:
        r = np.concatenate([fam.measured(p)["torque"] - fam.predict(p, x, ())["torque"] for p in preps])
        return float(np.sqrt(np.nanmean(r**2)))

    assert torque_rms(base.params) < 1.2 * torque_rms(truth), (torque_rms(base.params), torque_rms(truth))
    assert torque_rms(following) > 1.5 * torque_rms(base.params), (torque_rms(following), torque_rms(base.params))


def test_a_tubes_static_part_is_its_restriction_with_a_hundredth_of_its_volume() -> None:
    fam = RotaryFamily()
    part = fam.static_part("tube_dynamics")
    assert part is not None
    extra, words = part
    eff = ("tube_dynamics",)
    x = {p.name: p.x0 for p in fam.baseline()} | {"tube_dynamics.length": 2.0, "tube_dynamics.diameter": 0.004}
    k, k_static = fam.kernel_for(x, eff, 8.0), fam.kernel_for(x | extra, eff, 8.0)
    assert k_static.tube_vol == pytest.approx(0.01 * k.tube_vol) and k_static.tube_g == k.tube_g
    assert fam._key(x, eff) != fam._key(x | extra, eff)  # not the tube's cached replay
    assert "restriction" in words and fam.static_part("vane_leakage") is None


def test_a_form_the_recalibration_kept_nominal_is_held_in_every_candidates_fit() -> None:
    fam = RotaryFamily()
    dcv, prv = set(rotary._DCV_FORM), set(rotary._PRV_FORM)
    form = dcv | prv
    nominal = {p.name: p.x0 for p in fam.baseline()}
    assert set(held_form(fam, nominal)) == form
    # each group is held or moved as a whole, apart from the other
    assert set(held_form(fam, nominal | {"dcv_centre_closure": 0.9})) == prv
    assert set(held_form(fam, nominal | {"prv_dead_zone": 0.5})) == dcv
    assert held_form(fam, nominal | {"dcv_centre_closure": 0.9, "prv_hysteresis_scale": 0.0}) == []
    for eff in ("inertia", "presliding_friction", "sensor_bias"):
        assert form <= fam.frozen((eff,)), eff  # they leave the pneumatic network alone
    assert form <= fam.frozen(("vane_leakage", "heat_transfer"))  # a greedy round keeps the reference's
    assert not form & fam.frozen(("vane_leakage",))
    for eff in ("vane_leakage", "external_leakage", "tube_dynamics", "sensor_bias"):
        assert form <= fam.rebase((eff,)), eff  # a moved form may stand in for the effect: restarted
    assert not form & fam.rebase(("inertia",))
    assert form <= {p.name for p in fam.baseline()}
    assert [{p.name for p in g} for g in fam.form_grids] == [dcv, prv]
    # a bound narrows the form's grid as it does the range
    narrowed = RotaryFamily(bounds={"dcv_centre_closure": (0.0, 0.5), "prv_band_scale": (0.5, 1.5)})
    grids = {p.name: (p.lo, p.hi) for g in narrowed.form_grids for p in g}
    assert grids["dcv_centre_closure"] == (0.0, 0.5) and grids["prv_band_scale"] == (0.5, 1.5)


@pytest.mark.slow
def test_a_pneumatic_candidate_recalibrates_the_flows_and_volumes_it_restarts_from_nominal() -> None:
    """A vane leak (0.06 l/(s·bar)) on a rig whose PRV capacity, DCV capacity and dead volumes are
    0.92 / 0.82 / 1.19 × nominal. Restarted from nominal for the leak's grid, a descent had left the
    three at 1.00 × and the fit's calibration cost at 5.9 × the truth's (tube_dynamics then entered
    a greedy round to soak up the rest). The baseline's grid over the three, run after the
    effect's, moves them: 2.6 × the truth's cost (docs/diagnosis-record.md, "Fitting on a replayed simulator")."""
    rig = perturbed(100).with_effects(vane_leakage=MAGNITUDES["vane_leakage"][1])
    exps = run_protocol(rig, seed=100)
    calib = [e for e in exps if e.meta["repetition"] == 1]
    fam = RotaryFamily()
    rep = diagnose(fam, calib, [e for e in exps if e.meta["repetition"] == 2], candidates=["vane_leakage"])
    r = rep["ranking"][0]
    fitted = r["baseline_params"] | r["params"]
    assert max(abs(math.log(fitted[k])) for k in ("prv_c_scale", "dcv_c_scale", "dead_volume_scale")) > 0.1
    preps = [fam.prepare(e) for e in calib]
    scales = channel_scales(fam, preps)
    meas = [fam.measured(p) for p in preps]

    def cost(x: dict[str, float]) -> float:
        res = _residuals(fam, preps, meas, x, ("vane_leakage",), scales)
        return float(res @ res)

    assert cost(fitted) < 4.0 * cost(true_params(rig, "vane_leakage")), fitted


def test_sensor_offsets_give_back_the_flows_the_baseline_bent_to_absorb_them() -> None:
    """Pressure sensors reading 0.15 / 0.10 bar high (the larger sensor_bias, second draw's rig:
    PRV capacity, DCV capacity and dead volume 1.11 / 1.04 / 0.92 × nominal). Recalibrated
    without offsets, the baseline bent the flows to absorb them (1.25 / 0.80 / 1.12 ×), and the
    offsets' fit, which kept those frozen, ended at 3.0 × the truth's calibration cost (held-out
    GC 0.63 against the true model's 0.83). Refitted from the nominal flows on the baseline's own
    grid (RotaryFamily.rebase), the offsets find the rig's flows again."""
    eff, mag, seed = "sensor_bias", 1, 101
    rig = perturbed(seed).with_effects(sensor_bias=MAGNITUDES[eff][mag])
    exps = run_protocol(rig, seed=seed)
    calib = [e for e in exps if e.meta["repetition"] == 1]
    fam = RotaryFamily()
    rep = diagnose(fam, calib, [e for e in exps if e.meta["repetition"] == 2], candidates=[eff])
    r = rep["ranking"][0]
    assert r["significant"]
    fitted = r["baseline_params"] | r["params"]
    truth = true_params(rig, eff)
    assert fitted["dcv_c_scale"] == pytest.approx(truth["dcv_c_scale"], rel=0.1)
    assert fitted["prv_c_scale"] == pytest.approx(truth["prv_c_scale"], rel=0.1)
    preps = [fam.prepare(e) for e in calib]
    scales = channel_scales(fam, preps)
    meas = [fam.measured(p) for p in preps]

    def cost(x: dict[str, float]) -> float:
        res = _residuals(fam, preps, meas, x, (eff,), scales)
        return float(res @ res)

    assert cost(fitted) < 1.5 * cost(truth), fitted


@pytest.mark.slow
def test_friction_off_per_direction_is_not_passed_off_as_a_sensor_offset() -> None:
    """An effect-free rig whose CCW static/Coulomb friction is 15 % above and CW 15 % below the
    rest of its error. With one friction scale for both directions the torque balance's misfit
    bent the pressure gains, and sensor_bias won it back (two such rigs: GC 0.69 and 0.66, a
    torque offset of 0.16 N·m, verdict sensor_bias). The offsets are now weighed against friction
    per direction: the verdict either drops them or names the alternative beside them."""
    r = run_case(None, seed=13, structural="friction_per_direction", scale=0.5)
    rep = r["report"]
    v = rep["verdict"]
    bias = next(c for c in rep["ranking"] if c["effect"] == "sensor_bias")
    assert bias["significant"], bias  # on its own, the offsets would have been the verdict
    (alt,) = rep["alternatives"]
    assert alt["explanation"] == "friction_per_direction" and alt["instead_of"] == "sensor_bias"
    assert alt["params"]["friction_per_direction.asymmetry"] == pytest.approx(0.15, abs=0.05), alt
    assert (alt["confusable"] or alt["better"]) and alt["effect_gap_closure"] == bias["gap_closure"], alt
    assert v["alternatives"] == ["friction_per_direction"] and "tare the sensors" in v["summary"]
    # dropped when the friction explains more and the offsets add nothing beside it; kept, and
    # said to be confusable, when the logs cannot tell
    assert v["effects"] == ([] if alt["dropped"] else ["sensor_bias"]), v
    # how far the gap shrinks is told for the model the verdict describes
    hf = rep["how_far"]
    assert hf["model"] == (["friction_per_direction"] if alt["dropped"] else
                           ["friction_per_direction", "sensor_bias"] if alt["better"] else ["sensor_bias"]), hf
    if alt["dropped"]:
        closed = (hf["e_before"] - hf["e_after"]) / (hf["e_before"] - hf["e_floor"])
        assert closed == pytest.approx(alt["gap_closure"]), hf


def test_every_parameter_off_by_its_own_error_stays_within_the_spread_and_physical() -> None:
    """suite.perturbed_each: each table entry and capacity has its own error within ±20 %, the
    Coulomb level never exceeds the static one, and the groups' averages are the answer key."""
    n = PlantParams()
    rig = perturbed_each(3)
    fr, nf = rig.friction, n.friction
    ratios = [np.asarray(getattr(fr, k)) / np.asarray(getattr(nf, k)) for k in ("ts_ccw", "ws_cw", "b_ccw")]
    assert all(np.all((r > 0.8 - 1e-12) & (r < 1.2 + 1e-12)) for r in ratios)
    assert len({round(float(v), 9) for r in ratios for v in r}) > 10  # not one factor per group
    assert np.all(np.abs(fr.tc_ccw) <= np.abs(fr.ts_ccw)) and np.all(np.abs(fr.tc_cw) <= np.abs(fr.ts_cw))
    assert rig.prv.c_supply / n.prv.c_supply != pytest.approx(rig.prv.c_exhaust / n.prv.c_exhaust)
    truth = true_params(rig, None)
    assert 0.8 <= truth["prv_c_scale"] <= 1.2 and 0.8 <= truth["friction_scale"] <= 1.2
    grouped = perturbed(3)  # one factor per group: its answer key is that factor
    assert true_params(grouped, None)["friction_scale"] == pytest.approx(grouped.friction.ts_ccw[0]
                                                                        / n.friction.ts_ccw[0])
    with pytest.raises(ValueError, match="no parameter-error kind 'per-entry'; known: grouped, each"):
        run_case(None, seed=3, errors="per-entry")
    with pytest.raises(ValueError, match=r"friction_asymmetry = 0.7: outside its allowed range \[-0.5, 0.5\]"):
        run_case(None, seed=3, friction_asymmetry=0.7)


def test_the_recalibrations_ranges_can_be_narrowed_and_a_bad_range_is_refused() -> None:
    fam = RotaryFamily(bounds={"dead_volume_scale": (0.9, 1.1), "gain_a": (0.95, 1.05)})
    specs = {p.name: p for p in fam.baseline()}
    assert (specs["dead_volume_scale"].lo, specs["dead_volume_scale"].hi) == (0.9, 1.1)
    assert (specs["gain_a"].lo, specs["gain_a"].hi) == (0.95, 1.05)
    default = {p.name: p for p in RotaryFamily().baseline()}
    assert specs["prv_c_scale"] == default["prv_c_scale"]  # the others keep the wide defaults
    grid = {p.name: (p.lo, p.hi) for p in fam.base_grid}
    assert grid["dead_volume_scale"] == (0.9, 1.1) and grid["prv_c_scale"] == (0.8, 1.25)  # the grid clipped
    assert {p.name: (p.lo, p.hi) for p in RotaryFamily().base_grid}["dead_volume_scale"] == (0.8, 1.25)
    for bounds, words in [({"dead_volume": (0.9, 1.1)}, "the baseline has no such parameter; known: prv_c_scale"),
                          ({"gain_b": (1.1, 0.9)}, "1.1 … 0.9 is not a range"),
                          ({"gain_b": (0.9, math.inf)}, "is not a range"),
                          ({"dcv_c_scale": (0.0, 2.0)}, "0 … 2 reaches outside the default range 0.3 … 3"),
                          ({"dead_volume_scale": (0.9, 6.0)}, "which a bound may only narrow"),
                          ({"dead_volume_scale": (1.5, 2.0)}, "leaves out its nominal value 1")]:
        with pytest.raises(ValueError) as e:
            RotaryFamily(bounds=bounds)
        assert words in str(e.value), e.value


@pytest.mark.slow
def test_cwrr_diagnose_fits_within_the_ranges_it_is_given(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from app.cli import main

    logs, out = tmp_path / "logs", tmp_path / "report.json"
    assert main(["protocol", str(logs), "--param-error", "0.2", "--seed", "3", "--scale", "0.2"]) == 0
    for bad, words in [("dead_volume_scale:0.9:1.1", "expected NAME=LO:HI"), ("dead_volume_scale=0.9", "NAME=LO:HI"),
                       ("dead_volume_scale=a:b", "NAME=LO:HI"), ("volume=0.9:1.1", "no such parameter")]:
        assert main(["diagnose", str(logs), "--json", str(out), "--bound", bad]) == 2
        assert words in capsys.readouterr().err and not out.exists()
    assert main(["diagnose", str(logs), "--adapter", "emps", "--bound", "gain_a=0.9:1.1"]) == 2
    assert "bounds apply to the rotary rig's station logs" in capsys.readouterr().err
    assert main(["diagnose", str(logs), "--json", str(out), "--bound", "dead_volume_scale=0.95:1.05",
                 "--bound", "friction_scale=0.9:1.1"]) == 0
    r = json.loads(out.read_text())
    # the rig's dead volumes and friction are 0.84 and 0.83 × nominal (perturbed(3)): outside these
    # ranges, so only the ranges hold the fits inside them
    assert r["baseline"]["bounds"]["dead_volume_scale"] == [0.95, 1.05]
    assert r["baseline"]["bounds"]["prv_c_scale"] == [0.3, 3.0]
    fitted = r["baseline"]["identifiability"]["params"]
    assert 0.95 <= fitted["dead_volume_scale"] <= 1.05 and 0.9 <= fitted["friction_scale"] <= 1.1
    for c in r["ranking"]:  # a candidate refitting the baseline beside it keeps to the ranges too
        assert 0.95 <= c["baseline_params"]["dead_volume_scale"] <= 1.05, c["effect"]


def test_the_torque_is_not_scored_where_an_end_stop_takes_part_of_it(nominal_logs: list) -> None:
    """A free handle thrown to an end stop rests there under the pressures' torque, which the stop
    takes and no sensor sees: the balance cannot tell that from a model error. Within 2° of a stop,
    and as far as the torque's filter spreads it, the torque is left unscored; elsewhere nothing
    changes (bench/independent_rig.py --free-handle: an effect-free rig had pre-sliding named, E 0.12)."""
    fam = RotaryFamily()
    e = next(x for x in nominal_logs if x.meta["experiment"] == "prv_steps")
    before = fam.measured(fam.prepare(e))["torque"]
    th_max = PlantParams().vane.theta_max
    n = len(e.t)
    theta = np.where(np.arange(n) < n // 2, e.channels["theta"], th_max)  # thrown to the CCW stop halfway
    at_stop = replace(e, channels=e.channels | {"theta": theta, "omega": np.gradient(theta, e.t)})
    prep = fam.prepare(at_stop)
    after = fam.measured(prep)["torque"]
    t = e.t[prep.keep]
    edge = rotary.EDGE_S
    assert np.all(np.isnan(after[t >= e.t[n // 2] - edge + 1e-9]))  # at the stop, and the filter's reach before
    early = t < e.t[n // 2] - edge - 0.05
    assert np.array_equal(np.isnan(after[early]), np.isnan(before[early]))
    assert fam.at_stops(np.array([0.0, th_max - 0.03, -th_max + 0.03, th_max - 0.04])).tolist() == [
        False, True, True, False]  # 2° = 0.0349 rad


def test_a_single_station_log_is_split_in_time_and_diagnosed(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    # one log, as a lab might hand over: fitted on its first 60 %, scored on the rest. The regimes
    # each part shows are read off the parts (the whole log's had been looked up for them: KeyError)
    from app.cli import main

    run_protocol(PlantParams(), seed=2, repetitions=1, scale=0.3, kinds=["hold_closed"], outdir=tmp_path)
    out = tmp_path / "r.json"
    assert main(["diagnose", str(tmp_path), "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["experiments"]["split"] == "one log: fitted on its first 60 %, scored on the rest"
    assert r["experiments"]["held_out"] == ["hold_closed-1[held-out]"]
    assert list(r["experiments"]["excites"]) == ["hold_closed-1"]
    assert "held out: hold_closed-1[held-out]" in capsys.readouterr().out


def _leak_logs(d: Path, rewrite: Any, kinds: tuple[str, ...] = ("hold_closed", "fill_shut", "friction_sweep")) -> None:
    """A short protocol on a rig with the larger vane leak, each log's columns rewritten by
    ``rewrite(columns)`` (a dict of the CSV's columns by name, changed in place)."""
    rig = PlantParams().with_effects(vane_leakage=MAGNITUDES["vane_leakage"][1])
    run_protocol(rig, seed=6, scale=0.4, kinds=list(kinds), outdir=d)
    for csv in d.glob("*.csv"):
        head, *rows = csv.read_text().splitlines()
        names = head.split(",")
        data = np.array([[float(v) for v in r.split(",")] for r in rows])
        cols = {n: data[:, j].copy() for j, n in enumerate(names)}
        rewrite(cols)
        data = np.column_stack([cols[n] for n in names])
        csv.write_text(head + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in data) + "\n")


def _leak_logs_with_torque(d: Path, torque: Any) -> None:
    """:func:`_leak_logs` with the torque column rewritten by ``torque``."""

    def rewrite(cols: dict[str, np.ndarray]) -> None:
        cols["torque"] = torque(cols["torque"])

    _leak_logs(d, rewrite)


@pytest.mark.slow
def test_a_torque_that_reads_one_value_in_every_log_is_taken_as_not_measured(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # a lab without a torque sensor, or a rig model that writes zeros there: fitted as a measured
    # constant, the zeros bent the baseline until a large vane leak went unnamed (GC 0.97 without them)
    _leak_logs_with_torque(tmp_path, np.zeros_like)
    out = tmp_path / "r.json"
    from app.cli import main

    assert main(["diagnose", str(tmp_path), "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["experiments"]["unmeasured_channels"] == {"torque": 0.0}
    assert set(r["baseline"]["nrmse"]) == {"p_a", "p_b", "p_s"}  # left out of every fit and of E
    assert r["verdict"]["effects"][:1] == ["vane_leakage"], r["verdict"]
    # what only the torque shows is not ruled out, and the report says why
    assert {"inertia", "presliding_friction"} <= set(r["verdict"]["untested"])
    why = {c["effect"]: c["not_significant_because"] for c in r["ranking"]}["inertia"]
    assert "no log measures the torque (it reads 0 in every log), so these logs cannot rule it out" in why
    assert "torque read one value in every log, taken as not measured and left out" in r["verdict"]["summary"]
    assert "not measured: torque (reads 0 in every log)" in capsys.readouterr().out


@pytest.mark.slow
def test_a_torque_written_with_the_other_sign_convention_is_read_reversed_and_said_to_be(tmp_path: Path) -> None:
    # the torque on the user rather than the user's on the handle: fitted as it came, the balance's
    # mirror image had presliding friction named beside a vane leak
    from app.engine.diagnosis.run import diagnose_dir

    _leak_logs_with_torque(tmp_path, np.negative)
    r = diagnose_dir(tmp_path)
    sign = r["experiments"]["torque_sign"]
    assert sign["reversed"] and sign["agreement"] < 0.02 and sign["samples"] > 500, sign
    assert r["verdict"]["effects"] == ["vane_leakage"], r["verdict"]
    assert "the torque was read with its sign reversed (it opposed the sign the chamber pressures give it in" in \
        r["verdict"]["summary"]


def test_the_torques_sign_is_read_where_the_pressures_alone_set_it() -> None:
    fam = RotaryFamily()
    t = np.arange(0.0, 4.0, 0.005)
    dp = np.where(t < 2.0, 2.0, -1.5)  # P_a − P_b [bar]: 3.9 and −2.9 N·m of pneumatic torque
    held = -fam.nominal.vane.torque_per_pa * dp * 1e5 + 0.3 * np.sin(7 * t)  # the user's, holding the handle

    def log(torque: np.ndarray, theta: float = 0.0) -> Experiment:
        n = len(t)
        return Experiment("x", t, {}, {"p_a": 3.0 + dp / 2, "p_b": 3.0 - dp / 2, "p_s": np.full(n, 7.0),
                                       "theta": np.full(n, theta), "omega": np.zeros(n), "torque": torque}, {})

    assert fam.torque_sign_agreement([log(held)]) == (1.0, len(t))
    assert fam.torque_sign_agreement([log(-held)]) == (0.0, len(t))
    # at an end stop the stop, not the sensor, takes the pneumatic torque; below the pressures' say, nothing
    assert fam.torque_sign_agreement([log(-held, theta=fam.nominal.vane.theta_max)]) == (1.0, 0)
    assert fam.torque_sign_agreement([log(0.1 * np.ones_like(t))]) == (1.0, 0)


def _held_log(fam: RotaryFamily, z_a: float, z_b: float, p_a: float, p_b: float, omega: float = 0.0,
              torque: float = 0.0, human: bool = True) -> Experiment:
    """2 s of both DCVs filling from PRVs commanded to ``z_a`` / ``z_b`` [V], the chambers at ``p_a`` /
    ``p_b`` [bar abs], the vane turning at ``omega`` [rad/s] against ``torque`` [N·m]."""
    t = np.arange(0.0, 2.0, 0.005)
    n = len(t)
    one = np.ones(n)
    return Experiment("x", t, {"z_a": z_a * one, "z_b": z_b * one, "u_a": 0.0 * one, "u_b": 10.0 * one},
                      {"p_a": p_a * one, "p_b": p_b * one, "p_s": 7.0 * one, "theta": omega * t,
                       "omega": omega * one, "torque": torque * one}, {"human": human})


def test_which_chamber_is_which_is_read_off_settled_fills() -> None:
    fam = RotaryFamily()
    # settled for 0.5 s of the 2 s: 300 samples; the chambers stand in their commands' order, or the other
    assert fam.pressure_order_agreement([_held_log(fam, 3.0, 1.0, 4.0, 2.0)]) == (1.0, 300)
    assert fam.pressure_order_agreement([_held_log(fam, 3.0, 1.0, 2.0, 4.0)]) == (0.0, 300)
    # regulators set 0.3 V apart, or a chamber exhausting: nothing decided
    assert fam.pressure_order_agreement([_held_log(fam, 2.0, 1.7, 2.0, 3.0)]) == (1.0, 0)
    ex = _held_log(fam, 3.0, 1.0, 2.0, 4.0)
    ex.inputs["u_a"][:] = 10.0
    assert fam.pressure_order_agreement([ex]) == (1.0, 0)


def test_each_valves_wiring_is_read_off_where_its_chamber_stands() -> None:
    fam = RotaryFamily()
    # DCV-a fully open to fill (0 V), its PRV at 3 V: chamber a at the regulator's 4 bar abs, or at the room
    fills = _held_log(fam, 3.0, 3.0, 4.01, 4.01)
    assert fam.dcv_wiring_agreement([fills], "a") == (1.0, 300)
    assert fam.dcv_wiring_agreement([_held_log(fam, 3.0, 3.0, 1.02, 4.01)], "a") == (0.0, 300)
    assert fam.dcv_wiring_agreement([_held_log(fam, 3.0, 3.0, 4.01, 1.02)], "b") == (0.0, 300)
    # exhausting (DCV-a at 10 V): at the room is right
    vents = _held_log(fam, 3.0, 3.0, 1.02, 4.01)
    vents.inputs["u_a"][:] = 10.0
    assert fam.dcv_wiring_agreement([vents], "a") == (1.0, 300)
    # a PRV commanded under 1 V leaves the two readings too close to tell
    assert fam.dcv_wiring_agreement([_held_log(fam, 0.5, 0.5, 1.02, 1.02)], "a") == (1.0, 0)


def test_the_angles_sign_is_read_off_the_power_friction_takes() -> None:
    fam = RotaryFamily()
    # P_a − P_b = 0.5 bar: 0.98 N·m of pneumatic torque turning the vane at +1 rad/s, the user helping
    right = _held_log(fam, 2.0, 2.0, 3.5, 3.0, omega=1.0, torque=0.2)
    assert fam.dissipation([right]) == (1.0, 400)
    assert fam.dissipation([_held_log(fam, 2.0, 2.0, 3.5, 3.0, omega=-1.0, torque=0.2)]) == (-1.0, 400)
    # a user driving the vane against the chambers: the measured torque decides
    assert fam.dissipation([_held_log(fam, 2.0, 2.0, 3.5, 3.0, omega=-1.0, torque=-1.5)])[0] == 1.0
    # without a measured torque only the logs with nobody at the handle count
    assert fam.dissipation([_held_log(fam, 2.0, 2.0, 3.5, 3.0, omega=-1.0)], torque_measured=False) == (1.0, 0)
    free = _held_log(fam, 2.0, 2.0, 3.5, 3.0, omega=-1.0, human=False)
    assert fam.dissipation([free], torque_measured=False) == (-1.0, 400)
    # a speed not measured (omega flat at 0): read off the angle instead, here and for what a log excites
    free.channels["omega"][:] = 0.0
    assert fam.dissipation([free], torque_measured=False) == (-1.0, 400)
    from app.engine.diagnosis.run import excites

    assert "motion" in excites(free)


def test_each_convention_undone_is_said_and_the_alternative_only_while_the_logs_cannot_rule_it_out() -> None:
    from app.engine.diagnosis.run import Conventions

    none = Conventions(False, 1.0, 2000, False, 1.0, 3000, False, 0.99, 8000)
    assert none.summary() == ""
    both = none._replace(pressure_samples=40, torque_reversed=True, torque_agreement=0.0, angle_reversed=True,
                         dissipation=-0.99)
    said = both.summary()
    assert "the torque was read with its sign reversed (it opposed the sign the chamber pressures give it in " \
           "100 % of 3000 samples where they alone set it; if the torque's sign is right, p_a and p_b are swapped)" \
           in said
    assert "net -0.99 of the power over 8000 samples in motion; with the torque reversed too, this is also what " \
           "p_a and p_b written in each other's columns look like" in said
    settled = both._replace(pressure_samples=2000).summary()
    assert "swapped" not in settled and "the angle and speed were read with their signs reversed" in settled
    assert none._replace(pressure_swapped=True, pressure_agreement=0.0).summary() == (
        "; p_a and p_b were read swapped (with both chambers filling from regulators set ≥ 0.5 V apart, their "
        "pressures stood in the other order in 100 % of 2000 settled samples)")
    assert none.report()["angle_sign"] == {"reversed": False, "dissipation": 0.99, "samples": 8000}
    valve = none._replace(dcv_mirrored=("b",), dcv_agreement=(1.0, 0.002), dcv_samples=(9000, 9100))
    assert valve.summary() == (
        "; DCV-b's command was read mirrored about 5 V (fully open, chamber b stood near the atmosphere where the "
        "format's wiring fills it and near its regulator's pressure where it exhausts it, in 100 % of 9100 settled "
        "samples)")
    assert valve.report()["dcv_wiring"] == {"a": {"mirrored": False, "agreement": 1.0, "samples": 9000},
                                            "b": {"mirrored": True, "agreement": 0.002, "samples": 9100}}


@pytest.mark.slow
def test_pressures_in_each_others_columns_a_valve_wired_the_other_way_and_a_reversed_angle_are_read_right(
        tmp_path: Path) -> None:
    # read as written, the swapped pressures of a large vane leak's logs gave "no significant effect"
    # (E 219 × the floor) and a reversed angle left E after the leak 9 × the right reading's
    from app.engine.diagnosis.run import diagnose_dir

    def rewrite(cols: dict[str, np.ndarray]) -> None:
        cols["p_a"], cols["p_b"] = cols["p_b"], cols["p_a"]
        cols["theta"], cols["omega"] = -cols["theta"], -cols["omega"]
        cols["u_b"] = 10.0 - cols["u_b"]

    _leak_logs(tmp_path, rewrite, kinds=("prv_steps", "hold_closed", "fill_shut", "friction_sweep"))
    r = diagnose_dir(tmp_path)
    ex = r["experiments"]
    assert ex["pressure_order"]["swapped"] and ex["pressure_order"]["samples"] >= 100, ex["pressure_order"]
    assert ex["angle_sign"]["reversed"] and ex["angle_sign"]["dissipation"] < -0.9, ex["angle_sign"]
    assert not ex["torque_sign"]["reversed"], ex["torque_sign"]
    assert [ex["dcv_wiring"][s]["mirrored"] for s in "ab"] == [False, True], ex["dcv_wiring"]
    assert r["verdict"]["effects"] == ["vane_leakage"], r["verdict"]
    assert "; DCV-b's command was read mirrored about 5 V (" in r["verdict"]["summary"]
    assert "; p_a and p_b were read swapped (" in r["verdict"]["summary"]
    assert "; the angle and speed were read with their signs reversed (" in r["verdict"]["summary"]


def test_candidates_fitted_side_by_side_give_the_report_of_one_at_a_time(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Fitting candidates (and the recalibration's descents) two at a time shares the replay caches
    between threads; every fit is still a pure function of its inputs, so the report is the one a
    loop over them gives, to the last digit (on the ten-minute bench as well: 156 s one at a time,
    140 s side by side). Through ``cwrr diagnose --effects``: the ranking holds the effects asked
    for, each once."""
    from app.cli import main
    from app.engine.diagnosis import core

    rig = perturbed(3).with_effects(vane_leakage=MAGNITUDES["vane_leakage"][1])
    run_protocol(rig, seed=2, repetitions=2, scale=0.3, kinds=["hold_closed", "prv_steps"], outdir=tmp_path / "logs")
    asked = ["vane_leakage", "external_leakage", "inertia", "sensor_bias", "vane_leakage"]
    reports = []
    for evaluations in (2, 1):
        monkeypatch.setattr(core, "EVALUATIONS", evaluations)
        out = tmp_path / f"side_by_side_{evaluations}.json"
        assert main(["diagnose", str(tmp_path / "logs"), "--effects", *asked, "--json", str(out)]) == 0
        reports.append(out.read_text())
    rep = json.loads(reports[0])
    assert sorted(c["effect"] for c in rep["ranking"]) == sorted(set(asked))
    assert rep["verdict"]["effects"] == ["vane_leakage"] and rep["ranking"][0]["effect"] == "vane_leakage"
    assert len(rep["combination"]) == 1  # the greedy round's three pairs were fitted, and none was kept
    assert reports[0] == reports[1]
