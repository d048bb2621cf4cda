"""What holds the true model off the noise floor: the replay's own floor (issue 6, docs/diagnosis-record.md).

Replays held-out protocol logs of one withheld-effect case with the *true*
parameters (the suite's oracle) and the rig's sensor noise switched off, so
that what remains is the replay's, not the sensors'. Prints one JSON object:
the chamber pressures' RMS error [bar] per log for each pair of log sample
rate and replay step; at the station's rate, the same for the bare replay
(its regulators' own sawtooth everywhere, ``RotaryFamily(cycle_mean_s=0)``) and
for the replay averaged over a window everywhere, steps included (what the
family's prediction does only where the phase is lost); and the simulated
rig's own chamber pressure over a PRV-step hold (mean, SD [bar]) at
integration rates from 1 to 32 kHz, to show which step is converged. With
``--figure PNG`` it also draws rig, bare replay and prediction over
stretches where the PRV regulator cycles.

Run: ``python bench/replay_floor.py [--effect heat_transfer --magnitude 1 --seed 101] [--figure out.png]``
inside the project environment (a few seconds here).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter1d

from app.engine.diagnosis import protocol
from app.engine.diagnosis.protocol import run_protocol
from app.engine.diagnosis.rotary import RotaryFamily
from app.engine.diagnosis.suite import MAGNITUDES, perturbed, true_params

KINDS = ["prv_steps", "friction_sweep", "isotonic"]
PRESSURES = ("p_a", "p_b")


def rms(a: np.ndarray, b: np.ndarray) -> float:
    """RMS of ``a − b`` over the scored samples [bar]."""
    return float(np.sqrt(np.nanmean((a - b) ** 2)))


def main() -> dict[str, Any]:
    ap = argparse.ArgumentParser()
    ap.add_argument("--effect", default="heat_transfer", choices=sorted(MAGNITUDES))
    ap.add_argument("--magnitude", type=int, default=1, choices=(0, 1), help="0: the smaller, 1: the larger")
    ap.add_argument("--seed", type=int, default=101, help="the suite draw's seed")
    ap.add_argument("--figure", default="", help="also save a PNG of rig against replay there")
    a = ap.parse_args()
    noisy = perturbed(a.seed).with_effects(**{a.effect: MAGNITUDES[a.effect][a.magnitude]})
    rig = replace(noisy, sensors=replace(noisy.sensors, pressure_noise_bar=0.0, torque_noise_nm=0.0))
    x = true_params(rig, a.effect)
    rate0 = protocol.RATE_HZ
    out: dict[str, Any] = {"case": f"{a.effect}:{a.magnitude}:{a.seed}", "rms_bar": [], "bare_replay_bar": {},
                           "averaged_everywhere_bar": {}}
    shown: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
    bare_fam = RotaryFamily(cycle_mean_s=0.0)  # the replay's own sawtooth everywhere
    try:
        for rate in (rate0, 2000.0):
            protocol.RATE_HZ = rate
            held = [e for e in run_protocol(rig, seed=a.seed, kinds=KINDS) if e.meta["repetition"] == 2]
            for step_hz in (1000.0, 2000.0):
                fam = RotaryFamily(substep_hz=step_hz)
                row: dict[str, Any] = {"log_rate_hz": rate, "replay_step_hz": step_hz}
                for e in held:
                    prep = fam.prepare(e)
                    y, m = fam.predict(prep, x, (a.effect,)), fam.measured(prep)
                    row[e.name] = {c: rms(y[c], m[c]) for c in PRESSURES}
                    if rate == rate0 and step_hz == 1000.0:
                        bare = bare_fam.predict(bare_fam.prepare(e), x, (a.effect,))
                        out["bare_replay_bar"][e.name] = {c: rms(bare[c], m[c]) for c in PRESSURES}
                        out["averaged_everywhere_bar"][e.name] = {
                            f"{w:g} s": {c: rms(uniform_filter1d(bare[c], max(1, round(w * rate)), mode="nearest"),
                                                m[c]) for c in PRESSURES} for w in (0.05, 0.1, 0.2)}
                        shown.append((e.name, y["p_a"], bare["p_a"], m["p_a"]))
                out["rms_bar"].append(row)
        protocol.RATE_HZ = 2000.0
        out["hold_statistics_bar"] = {}
        for hz in (1000.0, 2000.0, 4000.0, 8000.0, 32000.0):
            (e,) = run_protocol(replace(rig, substep_hz=hz), seed=a.seed, kinds=["prv_steps"], repetitions=1)
            w = e.channels["p_a"][(e.t >= 2.0) & (e.t < 3.0)]
            out["hold_statistics_bar"][f"{hz:g} Hz"] = {"mean": float(w.mean()), "sd": float(w.std())}
    finally:
        protocol.RATE_HZ = rate0
    if a.figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axs = plt.subplots(2, 1, figsize=(10, 6), constrained_layout=True)
        for ax, (name, ya, ba, ma), (t0, t1) in zip(axs, [s for s in shown if not s[0].startswith("isotonic")],
                                                    ((2.0, 3.0), (3.5, 5.0)), strict=True):
            i = slice(round(t0 * rate0), round(t1 * rate0))
            t = np.arange(len(ma))[i] / rate0
            ax.plot(t, ma[i], "k", lw=1.2, label="rig, sensor noise off")
            ax.plot(t, ba[i], "r", lw=0.8, alpha=0.6, label="true model, bare replay")
            ax.plot(t, ya[i], "b", lw=1.4, label="true model, predicted (cycle mean where the phase is lost)")
            ax.set(title=f"{name}: chamber a", xlabel="time in log [s]", ylabel="p_a [bar abs]")
            ax.legend(loc="lower right")
        fig.savefig(a.figure, dpi=80)
    return out


if __name__ == "__main__":
    print(json.dumps(main()))
