"""Does the engine keep its period while browsers watch? (issue 5; issue 7 scales it up)

Starts the station in this process (uvicorn + viser, simulator at 200 Hz),
runs the same SC-1 workout twice — first with no client (the peer), then with
N headless Chromium pages (half the dashboard, half the viser live plots) —
and reads ``/api/health`` over the same 8 s of each run. Prints one JSON
object: jitter p50/p99/max and overruns for both phases, and their ratios.

Run: ``./dev bench-load`` is not a thing; use ``python bench/load.py [N]``
inside the project environment (``./dev`` prints it), or the slow test
``tests/test_load.py``.
"""

from __future__ import annotations

import json
import sys

from app.benchmarks import load

if __name__ == "__main__":
    print(json.dumps(load(int(sys.argv[1]) if len(sys.argv) > 1 else 10), indent=1))
