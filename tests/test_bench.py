"""The perf benchmark's contract (short durations; numbers live in bench/)."""

from __future__ import annotations

import pytest

from app.benchmarks import perf


@pytest.mark.slow
def test_perf_reports_both_real_time_factors() -> None:
    r = perf(duration=1.0, ivp_duration=0.05)
    assert isinstance(r["sim_rtf"], float) and isinstance(r["solve_ivp_rtf"], float)
    assert r["sim_rtf"] > r["solve_ivp_rtf"]
