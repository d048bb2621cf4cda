"""Working-pressure sweep of the rotary identification → the controllers' friction table.

Thesis 4.2.1 ran the procedure at P_w = 1…6 bar and tabulated the results
(Table 4.2), from which the friction surfaces of Figure 4.12 and the
estimator's 1-D lookups (3.3.2) are built. :func:`sweep_rotary_sim` does the
same on the simulator; :meth:`FrictionSweep.to_table` turns any sweep (from
the simulator or from rig runs) into a :class:`~app.engine.params.RotaryFriction`
that :class:`~app.engine.control.config.ControllerConfig` takes as its
``friction`` — so a lab can re-identify its own cylinder and control with it.

On the simulator the pressures run in parallel worker processes (one per
core); the rig, of course, runs them one after another.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.engine.ident.rotary import RotaryFrictionResult
from app.engine.params import ParameterError, PlantParams, RotaryFriction

TABLE_FIELDS: tuple[str, ...] = ("pw_bar", "ts_ccw", "tc_ccw", "ws_ccw", "b_ccw", "ts_cw", "tc_cw", "ws_cw", "b_cw")
"""The :class:`RotaryFriction` columns a friction table file holds."""


@dataclass
class SweepPoint:
    """One working pressure of a sweep.

    Attributes:
        result: The fitted parameters.
        sim_seconds: Rig time of the experiments [s].
        wall_seconds: Computer time [s].
    """

    result: RotaryFrictionResult
    sim_seconds: float
    wall_seconds: float


@dataclass
class FrictionSweep:
    """Identified friction against working pressure.

    Attributes:
        points: One entry per pressure, increasing.
    """

    points: list[SweepPoint]

    @property
    def pw_bar(self) -> list[float]:
        """The pressures [bar abs]."""
        return [p.result.pw_bar for p in self.points]

    def to_table(self) -> RotaryFriction:
        """Table 4.2's form, ready for the controllers' estimator."""
        if len(self.points) < 1:
            raise ParameterError("a sweep needs at least one working pressure")
        r = [p.result for p in self.points]
        return RotaryFriction(
            pw_bar=tuple(x.pw_bar for x in r),
            ts_ccw=tuple(x.ccw.fs for x in r), tc_ccw=tuple(x.ccw.fc for x in r),
            ws_ccw=tuple(x.ccw.vs for x in r), b_ccw=tuple(x.ccw.b for x in r),
            ts_cw=tuple(x.cw.fs for x in r), tc_cw=tuple(x.cw.fc for x in r),
            ws_cw=tuple(x.cw.vs for x in r), b_cw=tuple(x.cw.b for x in r),
        )

    def as_dict(self) -> dict[str, Any]:
        """JSON view: the table plus every fit's details."""
        t = self.to_table()
        return {
            "table": {k: list(getattr(t, k)) for k in TABLE_FIELDS},
            "fits": [{"pw_bar": p.result.pw_bar, "ccw": p.result.ccw.as_dict(), "cw": p.result.cw.as_dict(),
                      "sim_seconds": p.sim_seconds, "wall_seconds": p.wall_seconds} for p in self.points],
        }


def save_table(table: RotaryFriction, path: str | Path) -> None:
    """Write a friction table as JSON (atomically)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    data: dict[str, Any] = {k: list(getattr(table, k)) for k in TABLE_FIELDS}
    data["shape_j"] = table.shape_j
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def load_table(path: str | Path) -> RotaryFriction:
    """Read a friction table written by :func:`save_table` (validated)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ParameterError(f"friction table {path}: {exc}") from exc
    if not isinstance(data, dict):
        raise ParameterError(f"friction table {path}: expected a JSON object")
    kw: dict[str, Any] = {}
    for k in TABLE_FIELDS:
        if k not in data:
            raise ParameterError(f"friction table {path}: missing {k!r}")
        kw[k] = tuple(float(v) for v in data[k])
    if "shape_j" in data:
        kw["shape_j"] = float(data["shape_j"])
    return RotaryFriction(**kw)


def _one(args: tuple[float, int, int, int, PlantParams | None]) -> SweepPoint:
    from app.engine.ident.runner import identify_rotary_sim

    pw, ns, nd, seed, params = args
    res, run = identify_rotary_sim(pw, ns, nd, seed=seed, params=params)
    return SweepPoint(res, run.summary.sim_seconds, run.summary.wall_seconds)


def sweep_rotary_sim(
    pressures: list[float], ns: int, nd: int, seed: int = 0, params: PlantParams | None = None,
    workers: int | None = None,
) -> FrictionSweep:
    """Identify at each working pressure on the simulator (Table 4.2 / Fig 4.12).

    Args:
        pressures: Working pressures [bar abs].
        ns: Static tests per direction.
        nd: Dynamic tests per direction.
        seed: Base seed (pressure i uses ``seed + i``).
        params: Plant (truth); default the SPEC rig with Table 4.2 friction.
        workers: Worker processes (default: one per core, at most one per pressure).
    """
    jobs = [(float(pw), ns, nd, seed + i, params) for i, pw in enumerate(sorted(pressures))]
    n = workers or min(len(jobs), os.cpu_count() or 1)
    if n <= 1:
        pts = [_one(j) for j in jobs]
    else:
        # spawn, not fork: the caller may be the threaded server
        with ProcessPoolExecutor(max_workers=n, mp_context=mp.get_context("spawn")) as ex:
            pts = list(ex.map(_one, jobs))
    return FrictionSweep(pts)
