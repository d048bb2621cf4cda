"""Exercises compared like with like: a run beside each other controller's latest complete run.

What the thesis's radar charts (Fig 4.26 on) set side by side: the three
controllers on one scenario and target. The viser radar and the dashboard's
comparison (``GET /api/runs/{id}/comparison``) both take their runs from here.
"""

from __future__ import annotations

import math
from typing import Any, get_args

from app.engine.control.config import ControllerName
from app.engine.metrics import METRICS

CONTROLLERS: tuple[str, ...] = get_args(ControllerName)
"""The controllers an exercise can run with, in the order a comparison lists them."""
LOOKED_AT = 200
"""How many of the person's newest exercises are searched for runs to compare with."""


def drawable(metrics: Any) -> bool:
    """Metrics a radar can draw: a metric a run could not give is stored as null, which has no radius."""
    return bool(metrics) and all(isinstance(v, int | float) and math.isfinite(v) for v in metrics.values())


def compared_runs(store: Any, ref: dict[str, Any]) -> list[dict[str, Any]]:
    """An exercise and the latest run of each other controller to compare it with, the exercise first.

    Only like with like: the same person (their arms, not the controllers, would differ otherwise),
    scenario and target, and runs that went to their end (a stopped run is scored over the part it
    reached). The run itself is shown whatever its ending, as a result panel beside the radar shows it.

    Args:
        store: The run store.
        ref: The exercise to compare, as the store holds it (``Store.run``).

    Returns:
        One entry per controller: ``controller``, ``run_id``, ``status``, ``started`` [Unix s] and
        ``metrics``; empty when the run is not an exercise or has no metrics a radar can draw.
    """
    if ref["kind"] != "workout" or not drawable(ref.get("metrics")):
        return []
    spec = ref["spec"] or {}
    sc, tg = spec.get("scenario"), spec.get("target_nm")

    def entry(r: dict[str, Any]) -> dict[str, Any]:
        return {"controller": str((r["spec"] or {}).get("controller")), "run_id": r["id"], "status": r["status"],
                "started": r["started"], "metrics": r["metrics"]}

    out = [entry(ref)]
    seen = {out[0]["controller"]}
    for r in store.runs(LOOKED_AT, 0, "workout", person=ref.get("person") or ""):
        s = r["spec"] or {}
        if r["status"] == "complete" and drawable(r.get("metrics")) and s.get("scenario") == sc \
                and s.get("target_nm") == tg and s.get("controller") not in seen:
            seen.add(s["controller"])
            out.append(entry(r))
    return out


def latest_per_controller(store: Any, run_id: int) -> dict[str, dict[str, float]]:
    """:func:`compared_runs` of run ``run_id`` as controller → metrics (what a radar chart draws); empty
    when there is no such run or it has no metrics."""
    ref = store.run(run_id)
    return {} if ref is None else {r["controller"]: r["metrics"] for r in compared_runs(store, ref)}


def radar_scale(runs: list[dict[str, Any]]) -> dict[str, float]:
    """Each metric's largest value among ``runs``: the radar's rim, as the thesis's charts scale them (a
    metric zero for every run: 1, so its axis still has a length). Metrics some run lacks are left out."""
    return {m: max(float(r["metrics"][m]) for r in runs) or 1.0
            for m in METRICS if runs and all(m in r["metrics"] for r in runs)}
