"""How hard the thesis's Cascade PID gains toggle the counter chamber, by vane angle (docs/controllers.md).

Runs SC-1 with the Cascade PID (Eq 3.26 gains) at both targets and in both
directions and measures, over each run's evaluation window, the
period-2 toggle of both chamber pressures: a ±A square wave at the control
rate has second differences of ±4A, so A = |P[k+1] − 2P[k] + P[k−1]| / 4
[bar]. Prints one JSON object: per case and chamber, the median amplitude
over the window and per band of |θ| [rad]. The chamber the vane turns
towards shrinks (V = V_dead + A_v·r·(θ_max ∓ θ)), so the pressure loop's
gain grows as 1/V; the toggle follows it.

Run: ``python bench/pid_chatter.py [--seed 0]`` inside the project
environment (a few seconds).
"""

from __future__ import annotations

import argparse
import itertools
import json
from typing import Any

import numpy as np

from app.engine.scenarios import main_cases, run_case

BANDS_RAD = (0.0, 0.1, 0.3, 0.5, 0.7, 1.0, np.inf)
"""Edges of the |θ| bands [rad]."""


def toggle_amplitude(p: np.ndarray) -> np.ndarray:
    """Period-2 amplitude at each inner sample [bar]: |second difference| / 4."""
    return np.abs(p[2:] - 2.0 * p[1:-1] + p[:-2]) / 4.0


def measure(seed: int) -> list[dict[str, Any]]:
    """SC-1 with the Cascade PID: the toggle per case, chamber and |θ| band."""
    out = []
    for case in (c for c in main_cases() if c.scenario == "SC-1"):
        run = run_case(case, "pid", seed=seed)
        t, theta = run.result.column("t")[1:-1], run.result.column("theta")[1:-1]
        inside = (t >= run.window[0]) & (t <= run.window[1])
        band = np.digitize(np.abs(theta), BANDS_RAD[1:-1])
        row: dict[str, Any] = {"scenario": case.scenario, "target_nm": case.target, "direction": case.direction}
        for ch in ("p_a", "p_b"):
            amp = toggle_amplitude(run.result.column(ch))
            per_band = {f"{lo:g}-{hi:g}": (float(np.median(amp[inside & (band == k)]))
                                           if np.any(inside & (band == k)) else None)
                        for k, (lo, hi) in enumerate(itertools.pairwise(BANDS_RAD))}
            row[ch] = {"median_bar": float(np.median(amp[inside])), "by_abs_theta_rad": per_band}
        out.append(row)
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=0)
    print(json.dumps(measure(ap.parse_args().seed), indent=1))
