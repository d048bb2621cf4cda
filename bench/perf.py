"""Simulator speed against scipy's solve_ivp on the same closed loop.

Run: ``./dev bench perf --json`` (or ``python bench/perf.py``). Prints one JSON
object with ``sim_rtf`` and ``solve_ivp_rtf`` (real-time factors measured in
the same run) and their ratio.
"""

from __future__ import annotations

import json

from app.benchmarks import perf

if __name__ == "__main__":
    print(json.dumps(perf()))
