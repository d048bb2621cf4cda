"""The second, independently written rig model of ``bench/independent_rig.py`` behaves as its docstring says
(the diagnosis's figures on it live in docs/diagnosis-record.md, "A rig model written apart from ours")."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.engine.diagnosis.logs import read_logdir


@pytest.mark.slow
def test_the_independent_rig_holds_a_shut_chamber_and_leaks_only_with_its_leak(tmp_path: Path) -> None:
    from bench import independent_rig as ir

    held = {}
    for effect, mag in (("none", 1), ("external_leakage", 2)):
        d = tmp_path / effect
        ir.run_rig(d, 0, effect, 0.3, centre_leak=0.0, magnitude=mag)  # write_log checks the station format
        exps = {e.name: e for e in read_logdir(d)}
        assert len(exps) == 12  # six open-loop experiments, two repetitions
        e = exps["hold_closed-1"]
        shut = e.t >= ir.PREROLL_S + 2.0 * 0.3 + 0.2  # the DCVs at 5 V, settled
        held[effect] = e.channels["p_a"][shut]
        # the supply reads 8 bar; the handle is held near neutral
        assert np.median(e.channels["p_s"]) == pytest.approx(8.0, abs=0.01)
    # shut, the chamber holds within its sensor's noise; with a 0.06 l/(s·bar) orifice it sags
    none, leak = held["none"], held["external_leakage"]
    assert abs(np.mean(none[-20:]) - np.mean(none[:20])) < 0.005
    assert np.mean(leak[:20]) - np.mean(leak[-20:]) > 0.1


@pytest.mark.slow
def test_another_labs_protocol_is_split_with_the_valves_partial_openings_fitted(tmp_path: Path) -> None:
    """``--protocol other``: five experiments written apart from ours, each run once. The DCV chirp is the
    only log with the valves partly open, so it stays fitted (held out, it had left 98 % of the
    effect-free rig's pressure error unfitted); the one log held out cannot show a leak or the gas's
    heat exchange, which the report then names as not ruled out."""
    from app.engine.diagnosis.run import _split_station, excites, unshown
    from bench import independent_rig as ir

    ir.run_rig_other(tmp_path, 0, "none")
    exps = read_logdir(tmp_path)
    assert sorted(e.name for e in exps) == ["blocked_hold", "pulses", "staircase", "swing", "valve_chirp"]
    sig = {e.name: excites(e) for e in exps}
    assert [n for n, s in sig.items() if "dcv partly open" in s] == ["valve_chirp"]
    assert not any("shut after a fast fill or vent" in s for s in sig.values())
    calib, held, why = _split_station(exps, None)
    assert "valve_chirp" in {e.name for e in calib} and "run once each" in why
    scored = set().union(*(sig[e.name] for e in held))
    assert {"external_leakage", "heat_transfer"} <= set(unshown(set().union(*sig.values()), scored))


def _run(effect: str, mag: int, cmd: tuple[float, float, float, float], step_at_s: float, step_to: float,
         angle: tuple[float, float], dur_s: float = 2.0) -> np.ndarray:
    """One experiment on the independent rig: PRV-a stepped to ``step_to`` at ``step_at_s``, the user's
    program ramping from ``angle[0]`` to ``angle[1]`` over the first second and holding; the log's rows."""
    from bench import independent_rig as ir

    n = int(dur_s * ir.RATE_HZ)
    cmds = np.tile(np.array(cmd, dtype=float), (n, 1))
    cmds[int(step_at_s * ir.RATE_HZ):, 0] = step_to
    out = np.empty((n, 11))
    ir._simulate(cmds, np.array([0.0, 1.0, dur_s]), np.array([angle[0], angle[1], angle[1]]),
                 ir.rig_constants(0, effect, 0.0, mag), np.zeros((n, 4)), 3.0 * ir.BAR, out)
    return out


@pytest.mark.slow
def test_the_independent_rigs_tube_delays_the_chamber_and_its_bristle_yields_before_breakaway() -> None:
    """Its two effects written since the twenty-ninth session do what they stand for: 5 m of 4 mm tube
    slow the chamber's answer to a PRV step without changing where it settles, and with the bristle
    the handle yields elastically to a push below breakaway that Karnopp's stick holds exactly."""
    fill = (2.0, 2.0, 0.0, 10.0)  # both DCVs open to their PRVs
    bare, tube = (_run(e, 2, fill, 0.5, 3.5, (0.0, 0.0))[:, 5] for e in ("none", "tube_dynamics"))
    k = round(0.51 * 200)  # 10 ms after the step: the bare chamber is most of the way (3.00 → 4.35 of 4.49 bar abs)
    assert bare[k] - tube[k] > 0.3, (bare[k], tube[k])
    assert abs(bare[-1] - tube[-1]) < 0.02
    shut = (2.0, 2.0, 5.0, 5.0)  # equal pressures: no pneumatic torque; the user pushes 20·0.05 = 1 N·m < T_s
    held, yields = (_run(e, 2, shut, 9.0, 2.0, (0.0, 0.05))[:, 8] for e in ("none", "presliding_friction"))
    assert np.all(held == 0.0)
    assert yields[-1] == pytest.approx(1.0 / (50.0 + 20.0), abs=0.003)  # σ0 = 50 N·m/rad against the user's 20


@pytest.mark.slow
def test_logs_whose_torque_cannot_be_scored_anywhere_leave_it_out_and_say_so(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A free handle under a steady pressure difference rests on its end stop from the start: no sample
    of its torque is scored (the stop takes what the balance leaves). With only such logs, the torque
    had read NaN into every E and the summary ("E nan against a floor of nan"); now the channel leaves
    the diagnosis and the report names it."""
    import json

    from app.cli import main
    from app.engine.diagnosis.logs import write_log
    from bench import independent_rig as ir

    k = ir.rig_constants(0, "none", 0.0, 1)
    for j in (1, 2):
        n = 1600
        log = np.empty((n, 11))
        ir._simulate(np.tile([3.0, 0.5, 0.0, 10.0], (n, 1)), np.array([0.0, 8.0]), np.zeros(2), k,
                     np.random.default_rng(j).standard_normal((n, 4)), 3.0 * ir.BAR, log, 200.0, False)
        meta = {"rig": "rotary", "sample_rate_hz": 200.0, "p_atm_bar": ir.P_ATM / ir.BAR,
                "working_pressure_bar": 3.0, "experiment": "pinned", "human": False}
        write_log(tmp_path, f"pinned-{j}", log, meta)
    assert main(["diagnose", str(tmp_path), "--json", str(tmp_path / "r.json")]) == 0
    r = json.loads((tmp_path / "r.json").read_text())
    assert r["experiments"]["unscored_channels"] == ["torque"]
    assert set(r["baseline"]["nrmse"]) == {"p_a", "p_b", "p_s"} and np.isfinite(r["how_far"]["e_before"])
    assert "nan" not in r["verdict"]["summary"]
    assert "not scored: torque" in capsys.readouterr().out


@pytest.mark.slow
def test_a_tube_behind_a_valve_of_another_form_is_fitted_beside_that_form(tmp_path: Path) -> None:
    """5 m of 4 mm tube on the rig written apart from ours, whose DCVs are shut at their centre and
    whose regulators have no hysteresis. Recalibrated without the tube, the baseline takes that form
    and 4.8 × the dead volume. The tube's grid, run under the nominal form alone, chose 10 cm of
    12 mm bore (GC 0.14, not significant); run again beside the form the recalibration found, the fit
    recovers the tube and gives the dead volume back (docs/diagnosis-record.md, "A tube beside a form").

    The protocol runs at half length (``--scale 0.5``): at full length the suite's longest test took
    208 CPU-s, at half 142, on the fiftieth session's VM, and every check below held on both (the
    tube's GC 0.74 at full length, 0.69 at half)."""
    from app.engine.diagnosis.run import diagnose_dir
    from bench import independent_rig as ir

    ir.run_rig(tmp_path, 0, "tube_dynamics", 0.5, centre_leak=0.0, magnitude=2)
    r = diagnose_dir(tmp_path)
    base = r["baseline"]["identifiability"]["params"]
    assert r["baseline"]["form"]["kept"] and base["dead_volume_scale"] > 3.0, base  # the tube absorbed
    tube = next(c for c in r["ranking"] if c["effect"] == "tube_dynamics")
    assert tube["params"]["tube_dynamics.length"] == pytest.approx(5.0, rel=0.3), tube["params"]
    assert tube["baseline_params"]["dead_volume_scale"] < 2.0, tube["baseline_params"]
    assert tube["significant"] and r["verdict"]["effects"] == ["tube_dynamics"], r["verdict"]
    # and the report says the recalibration had moved the dead volume past any tolerance, and that
    # the verdict's tube gives it back
    recal = r["baseline"]["recalibration"]
    assert "dead_volume_scale" in recal["far"], recal["far"]
    assert "With tube_dynamics in the model, " in recal["note"]
    assert "chamber dead volumes × nominal comes back to" in recal["note"], recal["note"]


def test_on_another_labs_experiments_swapped_pressures_with_a_valve_wired_the_other_way_are_read_right(
        tmp_path: Path) -> None:
    """With DCV-b mirrored no settled fill of both chambers is left to show their order, and the swapped
    pressures passed for a reversed torque and angle; they are now read swapped from the start, which the
    fills, the torque and the angle then all bear out (run.read_conventions)."""
    from app.engine.diagnosis.rotary import RotaryFamily
    from app.engine.diagnosis.run import read_conventions
    from bench import independent_rig as ir

    ir.run_rig_other(tmp_path, 0, "none")
    right = {e.name: e for e in read_logdir(tmp_path)}
    exps = read_logdir(tmp_path)
    for e in exps:
        e.channels["p_a"], e.channels["p_b"] = e.channels["p_b"], e.channels["p_a"]
        e.inputs["u_b"] = 10.0 - e.inputs["u_b"]
    conv = read_conventions(RotaryFamily(), exps)
    assert conv.pressure_swapped and conv.dcv_mirrored == ("b",), conv
    assert not conv.torque_reversed and not conv.angle_reversed, conv
    for e in exps:  # undone: the logs as written right
        for c in ("p_a", "p_b", "torque", "theta"):
            np.testing.assert_array_equal(e.channels[c], right[e.name].channels[c])
        np.testing.assert_allclose(e.inputs["u_b"], right[e.name].inputs["u_b"], atol=1e-12)
    # written right, nothing is undone
    clean = read_conventions(RotaryFamily(), list(right.values()))
    assert not (clean.pressure_swapped or clean.dcv_mirrored or clean.torque_reversed or clean.angle_reversed)
