"""Issues 5 and 7: the engine keeps its 200 Hz period while 10 browsers watch and a script polls the API.

Runs :func:`app.benchmarks.load` (as ``python bench/load.py 10 --rps 50 --viser 2``):
one SC-1 workout with no client (the peer), one with eight dashboards and two
viser pages open in Debian's Chromium — ten pages drawing live plots — and 50
REST requests per second from another process, jitter and overruns read from
``/api/health`` over the same 8 s of each. Two viser pages, not the
benchmark's five: each renders its 3-D scene in software GL and loads in
seconds to minutes on a busy 2-core machine (this test took 2.5–10 minutes
with five), which the 15-minute CI budget cannot carry; the benchmark keeps
the heavier mix.

The timing goals (measured rate within 1 % of 200 Hz, p99 start jitter under
1 ms, no overruns) are the benchmark's to print beside its no-client peer, not
this test's to assert (the developers' brief: speed goals live in ``bench/``; on a
shared 2-core CI machine they hold in most runs, not all — docs/station.md has the
figures). What is asserted is what must always hold: the dashboards really
draw live data, every scripted request is answered, the workout runs to the
end at its rate in both phases, and the figures are reported.
"""

from __future__ import annotations

import json
import os

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.serial,
              pytest.mark.skipif(not os.path.exists("/usr/bin/chromium"), reason="Debian chromium not installed")]


def test_the_engine_keeps_its_period_while_ten_browsers_watch_and_a_script_polls() -> None:
    from app.benchmarks import load
    from app.engine.loop import make_realtime

    r = load(10, rps=50.0, viser_clients=2)
    print(json.dumps(r, indent=1))
    assert r["dashboards_drawing"] == 8  # the dashboards really drew live data
    req = r["requests"]
    assert req["errors"] == 0 and req["requests"] > 0.5 * 50 * 8, req  # a scripted client was served throughout
    for phase in ("quiet", "watched"):
        h = r[phase]
        assert h["state_after"] == "idle" and h["fault_before"] is None, h  # no fault, no stall, ended normally
        # a stalled loop (one that lost whole periods) shows here, however the jitter is spread
        assert 0.5 * 200.0 < h["measured_rate_hz"] < 1.5 * 200.0, h
        assert h["jitter_p50_ms"] <= h["jitter_p99_ms"] <= h["jitter_max_ms"], h
        floor = h["machine_floor"]  # the bare pacing process beside the engine ran the whole phase
        assert floor["periods"] > 0.5 * 200.0 * 8 and floor["jitter_p50_ms"] <= floor["jitter_p99_ms"], floor
        assert 0.0 <= h["steal_pct"] <= 100.0, h
        assert h["live_plots"]["errors"] == 0, h  # the viser publisher never failed a push
    # the two viser pages were counted and fed: at least one chart update a second (25 at best) while
    # the workout ran (before, nobody watched: nothing is encoded then)
    assert r["watched"]["live_plots"]["viewers"] == 2 and r["watched"]["live_plots"]["pushes_per_s"] >= 1.0, r
    assert r["quiet"]["live_plots"]["pushes_per_s"] == 0.0, r
    if not r["watched"]["realtime"]:
        print(f"no real-time scheduling here: {make_realtime()}")
