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
