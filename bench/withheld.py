"""The withheld-effect suite (issue 6): nine effects × two magnitudes, plus effect-free rigs.

Each case simulates the diagnosis protocol on a rig with one effect the
diagnosed model lacks (nominal parameters off by up to ±20 %, sensor noise),
diagnoses it and records where the true effect ranked. Prints one JSON
object: the rank-1 rate, the true effects' held-out gap closure, the
false-positive rate on effect-free rigs, and every case.

Run: ``python bench/withheld.py [--seeds N] [--nulls N] [--seed0 S] [--null-seed0 S]`` inside the project
environment (≈ 20 s per case on two cores).

``--errors each`` gives every nominal parameter an error of its own
(:func:`~app.engine.diagnosis.suite.perturbed_each`) instead of one per
group; the oracle GC is then the group averages' (approximate).

``--structural`` runs instead the rigs that differ from the diagnosed model
in form (:data:`~app.engine.diagnosis.suite.STRUCTURAL`), each effect-free
(seeds 300, 301, …) and each with one withheld effect
(:data:`~app.engine.diagnosis.suite.STRUCTURAL_PAIRS`, seeds 310, 311, …).

``--once coverage`` runs the protocol once per case (no repetition to hold
out) and splits it as ``cwrr diagnose`` splits such logs
(:func:`~app.engine.diagnosis.run.split_by_coverage`); ``--once last_third``
by the rule that split them before (docs/diagnosis-record.md, "Logs run once").

``--per-direction`` runs the rigs whose static and Coulomb friction is off
per direction on top of the grouped errors
(:func:`~app.engine.diagnosis.suite.friction_per_direction`;
:data:`PER_DIRECTION`): two effect-free ones and two with sensor offsets as
well; each row also carries the fitted offsets, what they were weighed
against (``weighed``) and how far the verdict's model closes the gap
(docs/diagnosis-record.md, "A sensor offset or friction per direction"; saved in
``docs/figures/withheld_per_direction.json``).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from app.engine.diagnosis.suite import ERRORS, MAGNITUDES, STRUCTURAL, STRUCTURAL_PAIRS, run_case, summarise

PER_DIRECTION: tuple[tuple[str | None, int, int, float], ...] = (
    (None, 0, 0, 0.15), (None, 0, 1, 0.15), ("sensor_bias", 0, 100, 0.15), ("sensor_bias", 1, 101, -0.15))
"""(withheld effect, magnitude, seed, friction asymmetry) of ``--per-direction``'s rigs."""

WEIGHED_KEYS = ("explanation", "instead_of", "gap_closure", "params", "effect_gap_closure", "gc_difference_ci90",
                "confusable", "better", "dropped", "also", "effect_beside_it", "beside_effect")


def weighed(result: dict[str, Any]) -> dict[str, Any]:
    """What a case's sensor-offset fit was, what it was weighed against, and how far the verdict's model closes."""
    rep = result["report"]
    bias = next((r for r in rep["ranking"] if r["effect"] == "sensor_bias"), None)
    hf = rep["how_far"]
    span = hf["e_before"] - hf["e_floor"]
    return {"sensor_bias": None if bias is None else {k: bias[k] for k in ("gap_closure", "significant", "params")},
            "weighed": [{k: a.get(k) for k in WEIGHED_KEYS} for a in rep["alternatives"]],
            "how_far": {"model": hf["model"], "gap_closure": (hf["e_before"] - hf["e_after"]) / span if span > 0
                        else 0.0}}


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=1, help="parameter-error/noise draws per effect and magnitude")
    ap.add_argument("--nulls", type=int, default=4, help="effect-free rigs")
    ap.add_argument("--effects", nargs="*", default=list(MAGNITUDES))
    ap.add_argument("--seed0", type=int, default=100,
                    help="first draw's seed (docs/diagnosis-record.md's tables: 100, 101)")
    ap.add_argument("--null-seed0", type=int, default=200, help="first effect-free rig's seed")
    ap.add_argument("--structural", action="store_true", help="the form-mismatched rigs instead (see above)")
    ap.add_argument("--per-direction", action="store_true",
                    help="the rigs with friction off per direction instead (see above)")
    ap.add_argument("--errors", choices=list(ERRORS), default="grouped",
                    help="nominal parameters off by group (what the baseline recalibrates) or each by its own error")
    ap.add_argument("--once", choices=["coverage", "last_third"],
                    help="the protocol run once, split as cwrr diagnose splits such logs (coverage) or by the rule "
                         "that split before (last_third)")
    a = ap.parse_args()
    results = []
    if a.per_direction:
        results = [run_case(eff, mag, seed=seed, friction_asymmetry=asym) for eff, mag, seed, asym in PER_DIRECTION]
        out = summarise(results)
        for row, r in zip(out["rows"], results, strict=True):
            row |= weighed(r)
        print(json.dumps(out, indent=1))
        raise SystemExit(0)
    if a.structural:
        for k, name in enumerate(STRUCTURAL):
            results.append(run_case(None, seed=300 + k, structural=name))
            eff, mag = STRUCTURAL_PAIRS[name]
            results.append(run_case(eff, mag, seed=310 + k, structural=name))
    else:
        for seed in range(a.seeds):
            for eff in a.effects:
                for mag in (0, 1):
                    results.append(run_case(eff, mag, seed=a.seed0 + seed, errors=a.errors, once=a.once))
        for seed in range(a.nulls):
            results.append(run_case(None, seed=a.null_seed0 + seed, errors=a.errors, once=a.once))
    print(json.dumps(summarise(results), indent=1))
