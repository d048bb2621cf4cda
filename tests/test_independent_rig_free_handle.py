"""The diagnosis on the independently written rig's free handle (``bench/independent_rig.py --free-handle``).

A file of its own: the parallel run hands out whole files (``./dev test``), and beside the tube's
diagnosis in ``test_independent_rig.py`` (the suite's longest test) this one would run after it on the
same worker instead of on another."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.engine.diagnosis.logs import read_logdir


@pytest.mark.slow
def test_a_free_handle_thrown_to_the_stops_does_not_bend_the_recalibration(tmp_path: Path) -> None:
    """``--free-handle``: PRV steps with nobody at the handle throw the vane from stop to stop, where
    the stop takes the pneumatic torque unseen. With the torque there scored, the effect-free rig's
    friction was fitted at 2.0 × and the pressure gains at 1.03 (E 0.12, pre-sliding named); left
    unscored near the stops, the baseline stays near the rig (docs/diagnosis-record.md).

    Pre-sliding is the one candidate tried: the recalibration, which this test is about, does not
    depend on the candidates, and the other eight took over half the test's CPU time (180 CPU-s
    in all against 81, on the fiftieth session's VM)."""
    from app.engine.diagnosis.run import diagnose_dir
    from bench import independent_rig as ir

    ir.run_rig_other(tmp_path, 0, "none", free=True)
    theta = {e.name: e.channels["theta"] for e in read_logdir(tmp_path)}
    assert np.max(np.abs(theta["free_steps_1"])) == pytest.approx(ir.THETA_MAX, abs=0.002)  # on the stops
    r = diagnose_dir(tmp_path, candidates=["presliding_friction"])
    fit = r["baseline"]["identifiability"]["params"]
    assert 0.7 < fit["friction_scale"] < 1.4, fit
    assert abs(fit["gain_a"] - 1.0) < 0.015 and abs(fit["gain_b"] - 1.0) < 0.015, fit
    assert r["how_far"]["e_before"] < 0.04, r["how_far"]
    assert [c["effect"] for c in r["ranking"]] == ["presliding_friction"]
    assert "presliding_friction" not in r["verdict"]["effects"], r["verdict"]
