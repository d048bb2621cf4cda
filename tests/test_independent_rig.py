"""The second, independently written rig model of ``bench/independent_rig.py`` behaves as its docstring says
(the diagnosis's figures on it live in docs/diagnosis.md, "A rig model written apart from ours")."""

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
