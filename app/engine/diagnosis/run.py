"""Diagnosis of a directory of logs: choose the reader and the family, split, run the core."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from app.engine.diagnosis.core import diagnose
from app.engine.diagnosis.families import ChamberFamily, DriveFamily, split_time
from app.engine.diagnosis.logs import Experiment, LogFormatError, read_chamber_leak, read_emps, read_logdir

PROTOCOL: dict[str, list[str]] = {
    "inertia": ["slow sine (free handle)", "isotonic workout with reversals"],
    "vane_leakage": ["hold with the DCVs closed at unequal chamber pressures"],
    "external_leakage": ["hold with the DCVs closed at equal chamber pressures", "closed-chamber decay"],
    "heat_transfer": ["PRV steps per chamber (vane locked)", "hold right after a fast fill"],
    "tube_dynamics": ["PRV steps per chamber (vane locked)", "DCV steps at constant supply"],
    "presliding_friction": ["friction sweeps through zero speed", "slow sine (free handle)"],
    "sensor_bias": ["vented rest (all channels at known values)"],
    "supply_droop": ["simultaneous fills of both chambers (supply flow)", "DCV steps at constant supply"],
    "valve_dynamics": ["PRV steps per chamber (vane locked)", "DCV steps at constant supply"],
}
"""Diagnosis protocol: the experiments that make each effect visible (used to name the
experiment that separates two confusable effects)."""


def _detect(d: Path) -> str:
    if any(d.glob("*.mat")):
        return "emps"
    csvs = sorted(d.glob("*.csv"))
    if csvs and not any(d.glob("*.json")):
        first = csvs[0].read_text(encoding="utf-8", errors="replace").split("\n", 1)[0]
        if first.count(";") == 2:
            return "chamber_leak"
    return "station"


def _split(exps: list[Experiment], held_out: list[str] | None) -> tuple[list[Experiment], list[Experiment]]:
    if held_out:
        unknown = [h for h in held_out if h not in {e.name for e in exps}]
        if unknown:
            raise LogFormatError(f"--held-out: no experiment named {', '.join(unknown)}; have "
                                 f"{', '.join(e.name for e in exps)}")
        held = [e for e in exps if e.name in held_out]
        calib = [e for e in exps if e.name not in held_out]
        if not calib:
            raise LogFormatError("--held-out: every experiment is held out; none is left to fit on")
        return calib, held
    if len(exps) == 1:
        a, b = split_time(exps[0])
        return [a], [b]
    n_held = max(1, math.ceil(len(exps) / 3))
    return exps[:-n_held], exps[-n_held:]


def diagnose_dir(logdir: str | Path, adapter: str = "auto", held_out: list[str] | None = None) -> dict[str, Any]:
    """The report for the logs in ``logdir``.

    Args:
        logdir: Directory of logs.
        adapter: ``station`` (the fixed NAME.csv + NAME.json format),
            ``chamber_leak`` or ``emps`` (refdata adapters), or ``auto``.
        held_out: Experiment names withheld from fitting.

    Returns:
        The report (one per chamber under ``"reports"`` for ``chamber_leak``,
        each chamber being a different physical object).
    """
    d = Path(logdir)
    if not d.is_dir():
        raise LogFormatError(f"{d}: not a directory")
    kind = _detect(d) if adapter == "auto" else adapter
    if kind == "emps":
        exps = [read_emps(p) for p in sorted(d.glob("*.mat"))]
        calib, held = _split(exps, held_out)
        return diagnose(DriveFamily(), calib, held, protocol=PROTOCOL) | {"adapter": "emps"}
    if kind == "chamber_leak":
        reports = {}
        for p in sorted(d.glob("*.csv")):
            a, b = split_time(read_chamber_leak(p))
            reports[p.stem] = diagnose(ChamberFamily(), [a], [b], protocol=PROTOCOL)
        return {"adapter": "chamber_leak", "reports": reports}
    exps = read_logdir(d)  # refuses malformed logs with the problem named
    raise LogFormatError(f"{d}: {len(exps)} station logs read and checked, but the replay family for CWRR "
                         "logs (simulator driven by the logged commands and motion) is not built yet; "
                         "only the chamber_leak and emps adapters can be diagnosed")
