"""Issue 5: the engine keeps its 200 Hz period while 10 browser clients watch the live plots.

Runs :func:`app.benchmarks.load` (the same as ``python bench/load.py 10``): one
SC-1 workout with no client (the peer), one with five dashboards and five
viser pages open in Debian's Chromium, jitter and overruns read from
``/api/health`` over the same 8 s of each. "Keeps its period" is checked as the
measured rate within 1 % of 200 Hz and p99 start jitter under 1 ms (issue 7's
goal); overruns are printed and reported in the README, not asserted: on this
2-core machine a few (0–3 in 1600 periods) remain, see README.
"""

from __future__ import annotations

import json
import os

import pytest

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not os.path.exists("/usr/bin/chromium"), reason="Debian chromium not installed")]


def test_the_engine_keeps_its_period_while_ten_browsers_watch() -> None:
    from app.benchmarks import load
    from app.engine.loop import make_realtime

    r = load(10)
    print(json.dumps(r, indent=1))
    assert r["dashboards_drawing"] == 5  # the dashboards really drew live data
    w = r["watched"]
    if not w["realtime"]:
        pytest.skip(f"no real-time scheduling here ({make_realtime()}); figures: {json.dumps(w)}")
    assert abs(w["measured_rate_hz"] - 200.0) < 2.0, w
    assert w["jitter_p99_ms"] < 1.0, w
