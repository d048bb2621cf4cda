"""Diagnosis of a directory of logs: choose the reader and the family, split, run the core."""

from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import Any

from app.engine.diagnosis.core import diagnose
from app.engine.diagnosis.families import ChamberFamily, DriveFamily, split_time
from app.engine.diagnosis.logs import Experiment, LogFormatError, read_chamber_leak, read_emps, read_logdir
from app.engine.diagnosis.protocol import effect_experiments
from app.engine.diagnosis.rotary import RotaryFamily

PROTOCOL: dict[str, list[str]] = effect_experiments() | {
    # outside the rotary protocol: the refdata adapters' own experiments
    "external_leakage": [*effect_experiments()["external_leakage"], "closed-chamber decay"],
}
"""Diagnosis protocol: effect → the experiments that make it visible (the table of
:data:`~app.engine.diagnosis.protocol.VISIBLE`; used to name the experiment that
separates two confusable effects)."""


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


def diagnose_dir(logdir: str | Path, adapter: str = "auto", held_out: list[str] | None = None,
                 stop: threading.Event | None = None) -> dict[str, Any]:
    """The report for the logs in ``logdir``.

    Args:
        logdir: Directory of logs.
        adapter: ``station`` (the fixed NAME.csv + NAME.json format),
            ``chamber_leak`` or ``emps`` (refdata adapters), or ``auto``.
        held_out: Experiment names withheld from fitting.
        stop: Once set, the diagnosis ends with
            :class:`~app.engine.diagnosis.core.Cancelled`.

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
        return diagnose(DriveFamily(), calib, held, protocol=PROTOCOL, stop=stop) | {"adapter": "emps"}
    if kind == "chamber_leak":
        reports = {}
        for p in sorted(d.glob("*.csv")):
            a, b = split_time(read_chamber_leak(p))
            reports[p.stem] = diagnose(ChamberFamily(), [a], [b], protocol=PROTOCOL, stop=stop)
        return {"adapter": "chamber_leak", "reports": reports}
    exps = read_logdir(d)  # refuses malformed logs with the problem named
    linear = [e.name for e in exps if e.meta["rig"] != "rotary"]
    if linear:
        raise LogFormatError(f"{d}: {', '.join(linear)} come from the linear rig; the replay family covers "
                             "the rotary rig (diagnose linear-rig logs in a directory of their own once it does)")
    calib, held = _split_station(exps, held_out)
    return diagnose(RotaryFamily(), calib, held, protocol=PROTOCOL, stop=stop) | {"adapter": "station"}


def _split_station(exps: list[Experiment], held_out: list[str] | None) -> tuple[list[Experiment], list[Experiment]]:
    """Hold out whole experiments: the last repetition of every kind that was run more than once.

    A protocol run (:func:`~app.engine.diagnosis.protocol.run_protocol`) repeats
    every experiment, so each kind is both fitted and scored; logs of kinds
    run once are only fitted on. Without repetitions, the generic split.
    """
    if held_out:
        return _split(exps, held_out)
    kinds: dict[str, list[Experiment]] = {}
    for e in exps:
        kinds.setdefault(str(e.meta["experiment"]), []).append(e)
    held = [v[-1] for v in kinds.values() if len(v) > 1]
    if not held:
        return _split(exps, None)
    return [e for e in exps if e not in held], held
