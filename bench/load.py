"""Does the engine keep its period while clients watch and script it? (issue 5; issue 7 scales it up)

Starts the station in this process (uvicorn + viser, simulator paced at
``--rate`` Hz), runs the same SC-1 workout twice — first with no client (the
peer), then with N headless Chromium pages (half the dashboard, half the
viser live plots) and ``--rps`` REST requests per second from another
process — and reads ``/api/health`` over the same 8 s of each run. Prints one
JSON object: jitter p50/p99/max and overruns for both phases, their ratio,
and the REST latencies.

Run inside the project environment: ``python bench/load.py 20 --rate 500 --rps 50``
(issue 7's load), ``python bench/load.py 10`` (issue 5's), or the slow test
``tests/test_load.py``.
"""

from __future__ import annotations

import argparse
import json

from app.benchmarks import load

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clients", type=int, nargs="?", default=10, help="browser pages (half dashboards, half viser)")
    ap.add_argument("--rate", type=float, default=200.0, help="control rate [Hz]")
    ap.add_argument("--rps", type=float, default=0.0, help="REST requests per second during the watched phase")
    ap.add_argument("--seconds", type=float, default=8.0, help="length of each measured phase [s]")
    ap.add_argument("--viser", type=int, default=None, help="how many of the pages are viser pages (default half)")
    a = ap.parse_args()
    print(json.dumps(load(a.clients, seconds=a.seconds, rate_hz=a.rate, rps=a.rps, viser_clients=a.viser), indent=1))
