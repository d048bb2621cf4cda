"""How hard the Cascade PID toggles the counter chamber, by vane angle, with two gain sets (docs/controllers.md).

Runs SC-1 with the Cascade PID at both targets and in both directions,
once with the thesis's hand-set gains (Eq 3.26) and once with the gains
the station's own autotuner (thesis 3.6.2, ``pid_tune.autotune_sim``)
returns for PRV-a and PRV-b on the simulated rig, and measures over each
run's evaluation window the period-2 toggle of both chamber pressures: a
±A square wave at the control rate has second differences of ±4A, so
A = |P[k+1] − 2P[k] + P[k−1]| / 4 [bar]. The chamber the vane turns towards
shrinks (V = V_dead + A_v·r·(θ_max ∓ θ)), so the pressure loop's gain grows
as 1/V; with gains near the loop's limit the toggle follows it.

Prints one JSON object: the gains; per gain set and SC-1 case the six
metrics and, per chamber, the toggle's median over the window and per band
of |θ| [rad]; and the RMSE of all twelve main cases (SC-1–SC-4) with either
gain set, beside Default's and Fuzzy's.

Run: ``python bench/pid_chatter.py [--seed 0]`` inside the project
environment (about fifteen seconds).
"""

from __future__ import annotations

import argparse
import itertools
import json
from typing import Any

import numpy as np

from app.engine.ident.pid_tune import AutotuneSpec, autotune_sim
from app.engine.metrics import toggle_amplitude
from app.engine.scenarios import main_cases, run_case

BANDS_RAD = (0.0, 0.1, 0.3, 0.5, 0.7, 1.0, np.inf)
"""Edges of the |θ| bands [rad]."""

Gains = tuple[tuple[float, float, float], tuple[float, float, float]]


def autotuned(seed: int) -> Gains:
    """(K_p, K_i, K_d) of PRV-a and PRV-b as the station's autotuner returns them on the simulated rig."""
    def gains(side: str) -> tuple[float, float, float]:
        kp, ki, kd = autotune_sim(AutotuneSpec(side=side), seed=seed)["tuning"].gains
        return float(kp), float(ki), float(kd)

    return gains("a"), gains("b")


def measure(seed: int, gains: Gains | None) -> list[dict[str, Any]]:
    """SC-1 with the Cascade PID (``gains``; None: Eq 3.26): metrics and the toggle per chamber and |θ| band."""
    out = []
    for case in (c for c in main_cases() if c.scenario == "SC-1"):
        run = run_case(case, "pid", seed=seed, pid_gains=gains)
        res = run.result
        t, theta = res.column("t")[1:-1], res.column("theta")[1:-1]
        inside = (t >= run.window[0]) & (t <= run.window[1])
        band = np.digitize(np.abs(theta), BANDS_RAD[1:-1])
        row: dict[str, Any] = {"scenario": case.scenario, "target_nm": case.target, "direction": case.direction,
                               "metrics": run.metrics}
        for ch in ("p_a", "p_b"):
            amp = toggle_amplitude(res.column(ch))
            per_band = {f"{lo:g}-{hi:g}": (float(np.median(amp[inside & (band == k)]))
                                           if np.any(inside & (band == k)) else None)
                        for k, (lo, hi) in enumerate(itertools.pairwise(BANDS_RAD))}
            row[ch] = {"median_bar": float(np.median(amp[inside])), "by_abs_theta_rad": per_band}
        out.append(row)
    return out


def rmse_all_cases(seed: int, tuned: Gains) -> list[dict[str, Any]]:
    """RMSE [N·m] of the twelve main cases: Default, Fuzzy, and the Cascade PID with Eq 3.26's and ``tuned`` gains."""
    return [{"scenario": c.scenario, "target_nm": c.target, "direction": c.direction,
             "default": run_case(c, "default", seed=seed).metrics["rmse"],
             "fuzzy": run_case(c, "fuzzy", seed=seed).metrics["rmse"],
             "pid Eq 3.26": run_case(c, "pid", seed=seed).metrics["rmse"],
             "pid autotuned": run_case(c, "pid", seed=seed, pid_gains=tuned).metrics["rmse"]}
            for c in main_cases()]


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=0)
    seed = ap.parse_args().seed
    tuned = autotuned(seed)
    print(json.dumps({"autotuned_gains": {"a": tuned[0], "b": tuned[1]},
                      "Eq 3.26": measure(seed, None), "autotuned": measure(seed, tuned),
                      "rmse_all_cases": rmse_all_cases(seed, tuned)}, indent=1))
