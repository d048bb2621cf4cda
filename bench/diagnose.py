"""Diagnosing ten minutes of logs with all nine candidates (issue 6 goal: under 2 minutes here).

Generates the diagnosis protocol on the simulated rig (±20 % parameter
errors, a vane leak) long enough for ``--minutes`` of logs in total, then
times the full diagnosis (baseline recalibration, nine candidates, greedy
combinations, bootstrap, where). Prints one JSON object: the log length,
the diagnosis time, its ratio to the 120 s goal, and — as the peer measured
in the same run — the time the simulator took to produce the same logs.

Run: ``python bench/diagnose.py [--minutes 10] [--rate 200]`` inside the project environment
(``--rate``: the logs' sample rate [Hz]; faster logs are scored at 200 Hz, so the time should not grow
with it).
"""

from __future__ import annotations

import argparse
import json
import time

from app.engine.diagnosis import protocol
from app.engine.diagnosis.core import diagnose
from app.engine.diagnosis.protocol import run_protocol
from app.engine.diagnosis.rotary import RotaryFamily
from app.engine.diagnosis.run import PROTOCOL
from app.engine.diagnosis.suite import MAGNITUDES, perturbed

if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=protocol.RATE_HZ, help="the logs' sample rate [Hz]")
    a = ap.parse_args()
    protocol.RATE_HZ = a.rate
    rig = perturbed(1).with_effects(vane_leakage=MAGNITUDES["vane_leakage"][1])
    run_protocol(rig, seed=0, repetitions=1, scale=0.1)  # compile the simulator outside the timing
    probe = run_protocol(rig, seed=0, repetitions=2, scale=1.0)
    scale = a.minutes * 60.0 / sum(e.duration for e in probe)
    # parts of the protocol do not stretch with the scale (sweep speeds): correct once
    scale *= a.minutes * 60.0 / sum(e.duration for e in run_protocol(rig, seed=0, repetitions=2, scale=scale))
    t0 = time.perf_counter()
    exps = run_protocol(rig, seed=0, repetitions=2, scale=scale)
    t_sim = time.perf_counter() - t0
    logs_s = sum(e.duration for e in exps)
    calib = [e for e in exps if e.meta["repetition"] == 1]
    held = [e for e in exps if e.meta["repetition"] == 2]
    diagnose(RotaryFamily(), probe[:1], probe[1:2], candidates=["vane_leakage"])  # compile the replay
    t0 = time.perf_counter()
    rep = diagnose(RotaryFamily(), calib, held, protocol=PROTOCOL)
    t_diag = time.perf_counter() - t0
    print(json.dumps({"log_minutes": logs_s / 60.0, "sample_rate_hz": a.rate, "diagnosis_s": t_diag, "goal_s": 120.0,
                      "diagnosis_over_goal": t_diag / 120.0, "simulation_s": t_sim,
                      "diagnosis_over_simulation": t_diag / t_sim, "verdict": rep["verdict"]["effects"]}))
