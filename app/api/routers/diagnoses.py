"""Sim-to-real gap diagnoses (issue 6): start one, read it back as a stored run of kind ``diagnosis``.

A diagnosis runs in a worker thread, off the engine: it replays logs, it
does not drive the rig. Its source is either the diagnosis protocol run on
the simulated rig (optionally with effects switched on and parameter errors,
to see what the tool finds) or stored runs' logs. The report is the run's
``result`` (``GET /api/runs/{id}``); ``status`` is ``running`` until then.
"""

from __future__ import annotations

import json
import logging
import shutil
import threading
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Request
from pydantic import Field

from app.api.auth import ADMIN, AUTH_RESPONSES, READ
from app.api.deps import IdPath, JobsDep, StoreDep, completed_diagnosis
from app.api.diagnosis_report import DiagnosisTraces
from app.api.jobs import JobRefused
from app.api.models import Documented, RunInfo
from app.engine.params import EFFECT_NAMES, ParameterError
from app.engine.runlog import atomic_write_text
from app.storage import Store, strict_json

# running a diagnosis is an admin's; the protocol's table is documentation, read by any role (a therapist
# opening a stored report on the diagnosis page needs its effects' plain words)
router = APIRouter(prefix="/api/diagnoses", tags=["diagnoses"], responses=AUTH_RESPONSES)
EffectName = Literal[
    "inertia", "vane_leakage", "external_leakage", "heat_transfer", "tube_dynamics", "presliding_friction",
    "sensor_bias", "supply_droop", "valve_dynamics",
]
assert set(EffectName.__args__) == set(EFFECT_NAMES)  # type: ignore[attr-defined]


class ProtocolSource(Documented):
    """Run the diagnosis protocol on the simulated rig first.

    Attributes:
        effects: Effects switched on in the simulated rig (the diagnosed model lacks them).
        magnitude: 1 (smaller) or 2 (larger) of the suite's two magnitudes.
        param_error: Random error on the recalibratable nominal parameters (0.2 = ±20 %).
        errors: How the errors are drawn: ``grouped``, one per group the baseline
            recalibrates (all friction levels by one factor, both PRV capacities by
            one), or ``each``, one per parameter (every friction-table entry, each
            PRV capacity and dead volume), which the baseline can only approximate.
        seed: Seed of the parameter errors and the sensor noise.
        scale: Duration factor (1 ≈ 83 s of logs per repetition). Under 1 the logs pin
            the model's nominal values down less, and the recalibration may take values
            far from nominal (the report flags them); 1 or more for a diagnosis to act on.
    """

    effects: list[EffectName] = Field(default_factory=list, max_length=9)
    magnitude: Annotated[int, Field(ge=1, le=2)] = 2
    param_error: Annotated[float, Field(ge=0.0, le=0.5)] = 0.0
    errors: Literal["grouped", "each"] = "grouped"
    seed: Annotated[int, Field(ge=0, le=2**31)] = 0
    scale: Annotated[float, Field(ge=0.2, le=10.0)] = 1.0


Bounds = Annotated[dict[Annotated[str, Field(max_length=64)], tuple[float, float]], Field(max_length=16)]


class DiagnosisRequest(Documented):
    """What to diagnose: ``protocol`` (simulated) or ``run_ids`` (stored runs with logs).

    A diagnosis of ``run_ids`` is stored with the person and therapy session its runs all share.

    Attributes:
        protocol: Run the diagnosis protocol on the simulated rig, then diagnose its logs.
        run_ids: Stored runs whose logs are diagnosed (at least two: some are fitted on, the
            others held out).
        held_out: Names of the logs to score on (whole experiments withheld from every fit);
            default: the tool's own split.
        effects: The candidate effects to try (default: all nine); the baseline's
            recalibration is the same either way.
    """

    protocol: ProtocolSource | None = None
    run_ids: list[Annotated[int, Field(ge=1, le=2**62)]] | None = Field(None, min_length=2, max_length=200)
    held_out: list[Annotated[str, Field(max_length=128)]] | None = Field(None, max_length=200)
    effects: list[EffectName] | None = Field(None, min_length=1, max_length=9)
    bounds: Bounds | None = Field(
        None,
        description="The recalibration's range [low, high] per baseline parameter of the rotary rig, replacing the "
                    "wide default (e.g. {\"dead_volume_scale\": [0.9, 1.1]} for measured dead volumes); the report "
                    "lists every range used under baseline.bounds")


class BoundsCheck(Documented):
    """Recalibration ranges to check before a diagnosis is asked for (nothing runs).

    Attributes:
        bounds: As in :class:`DiagnosisRequest`.
    """

    bounds: Bounds


class BoundsChecked(Documented):
    """Ranges as a diagnosis would take them.

    Attributes:
        bounds: Parameter → [low, high] (a list: a tuple's response schema
            comes out as an OpenAPI 3.0 ``items`` array, which 3.1 refuses).
    """

    bounds: dict[str, list[float]]


class DiagnosisStarted(Documented):
    """A diagnosis accepted.

    Attributes:
        run_id: Stored id; ``GET /api/runs/{run_id}`` has the report once ``status`` is ``complete``.
        status: Always ``running`` here.
    """

    run_id: int
    status: Literal["running"] = "running"


class ProtocolExperiment(Documented):
    """One experiment of the diagnosis protocol.

    Attributes:
        name: Experiment kind (logs are named ``NAME-REP``, e.g. ``hold_closed-2``).
        description: What the station does in it.
        makes_visible: The candidate effects it shows.
    """

    name: str
    description: str
    makes_visible: list[EffectName]


class BaselineRange(Documented):
    """A baseline parameter the recalibration fits, with its default range (``bounds`` may narrow it).

    Attributes:
        name: Parameter name (a key of ``bounds``).
        meaning: What it scales.
        nominal: Where the recalibration starts (the simulator's nominal rig) [× nominal, or the gain].
        low: Default lower end.
        high: Default upper end.
    """

    name: str
    meaning: str
    nominal: float
    low: float
    high: float


class ProtocolTable(Documented):
    """The diagnosis protocol (issue 6 §6): every experiment is run twice; the second run of each is held out.

    Attributes:
        experiments: In the order the station runs them.
        preroll_s: Rest logged before each open-loop experiment's first step [s].
        candidates: The candidate effects the diagnosis tries (and a simulated rig can have switched on).
        candidate_meaning: What each candidate is on the rig, in plain words.
        baseline: The rotary rig's recalibrated parameters and their default ranges.
    """

    experiments: list[ProtocolExperiment]
    preroll_s: float
    candidates: list[EffectName]
    candidate_meaning: dict[EffectName, str]
    baseline: list[BaselineRange]


log = logging.getLogger(__name__)


@router.get("/protocol", response_model=ProtocolTable, dependencies=[READ],
            summary="The diagnosis protocol: each experiment and the effects it makes visible")
def protocol_table() -> ProtocolTable:
    """Which candidate effect each experiment of the protocol makes visible, what each effect means, and
    the baseline's recalibrated parameters with their default ranges (what `bounds` may narrow)."""
    from app.engine.diagnosis.protocol import DESCRIPTION, PREROLL_S, VISIBLE
    from app.engine.diagnosis.rotary import RotaryFamily
    from app.engine.params import EFFECT_MEANING, EFFECT_NAMES

    # validated against EffectName: an engine table naming an unknown effect fails here, not in the page
    return ProtocolTable.model_validate({
        "experiments": [{"name": k, "description": DESCRIPTION[k], "makes_visible": v} for k, v in VISIBLE.items()],
        "preroll_s": PREROLL_S, "candidates": list(EFFECT_NAMES), "candidate_meaning": EFFECT_MEANING,
        "baseline": [{"name": p.name, "meaning": m, "nominal": p.x0, "low": p.lo, "high": p.hi}
                     for p, m in RotaryFamily.default_ranges()]})


def _checked_bounds(bounds: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
    from app.engine.diagnosis.rotary import RotaryFamily

    try:
        return RotaryFamily.checked_bounds(bounds)
    except ValueError as exc:
        raise ParameterError(f"bounds: {exc}") from None


@router.post("/bounds", response_model=BoundsChecked, dependencies=[ADMIN],
             summary="Check recalibration ranges with the rules a diagnosis applies (nothing runs); 422 says why")
def check_bounds(req: BoundsCheck) -> BoundsChecked:
    """The ranges as a diagnosis would take them, or the same 422 `POST /api/diagnoses` would give."""
    # the page asks before the protocol runs on the rig: a range refused only when the diagnosis is
    # posted would come after minutes of experiments
    return BoundsChecked(bounds={k: list(v) for k, v in _checked_bounds(req.bounds).items()})


def _work(store: Store, run_id: int, req: DiagnosisRequest, logdir: Path, sources: list[Path],
          stop: threading.Event, server_stopping: threading.Event,
          progress: Callable[[str], None] | None = None) -> None:
    from app.engine.diagnosis.core import Cancelled
    from app.engine.diagnosis.protocol import run_protocol
    from app.engine.diagnosis.run import diagnose_dir
    from app.engine.diagnosis.suite import simulated_rig

    try:
        if req.protocol is not None:
            p = req.protocol
            rig = simulated_rig(p.seed, p.param_error, p.errors, dict.fromkeys(p.effects, p.magnitude))
            run_protocol(rig, seed=p.seed, scale=p.scale, outdir=logdir, stop=stop, progress=progress)
        else:
            logdir.mkdir(parents=True, exist_ok=True)
            for src in sources:
                for suffix in (".csv", ".json"):
                    shutil.copyfile(src.with_suffix(suffix), logdir / (src.stem + suffix))
        report = diagnose_dir(logdir, adapter="station", held_out=req.held_out, stop=stop, bounds=req.bounds,
                              traces=True, candidates=req.effects, progress=progress)
        # ≈ 10⁵ numbers: beside the logs, not in the run's result, which every listing of runs carries;
        # a disk that cannot take them costs the pictures, not the diagnosis (its traces then answer 404)
        try:
            atomic_write_text(traces_path(logdir), strict_json(report.pop("traces")))
        except OSError:
            log.exception("diagnosis %d: its traces could not be kept", run_id)
        v = report["verdict"]
        hf = report["how_far"]
        # metrics are numbers (the runs table's contract); the verdict's names are in the report
        store.run_finished(run_id, "complete", {"effects_found": float(len(v["effects"])), "e_before": hf["e_before"],
                                                "e_after": hf["e_after"], "e_floor": hf["e_floor"],
                                                "unexplained_share": hf["unexplained_share"]}, report)
    except Cancelled as exc:
        why = "the server stopped" if server_stopping.is_set() else "stopped on request"
        store.run_finished(run_id, "cancelled", None, {"error": f"{exc} ({why})"})
    except Exception as exc:  # the job's failure is its stored result, not a lost thread
        try:
            store.run_finished(run_id, "failed", None, {"error": str(exc), "trace": traceback.format_exc(limit=3)})
        except Exception:  # the store itself is gone: the log is all that is left
            log.exception("diagnosis %d failed and could not be recorded", run_id)


def logdir_of(data_dir: Path, run_id: int) -> Path:
    """Where diagnosis ``run_id`` keeps its logs (and its traces)."""
    return data_dir / "diagnoses" / f"diagnosis-{run_id}"


def traces_path(logdir: Path) -> Path:
    """The file a diagnosis's traces are kept in, beside its logs."""
    return logdir / "traces.json"


def _common_who(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The person and therapy session all of a diagnosis's input runs share (a field they differ on is left out).

    A diagnosis of one person's protocol runs is then listed with that person and session, like its inputs.
    """
    out: dict[str, Any] = {}
    for key in ("person", "session_id"):
        values = {r.get(key) for r in runs}
        if len(values) == 1 and (v := values.pop()) not in (None, ""):
            out[key] = v
    return out


@router.post("", response_model=DiagnosisStarted, status_code=202, dependencies=[ADMIN],
             responses={409: {"description": "A diagnosis is already running, or the server is stopping"}},
             summary="Start a gap diagnosis (protocol on the simulator, or stored runs); poll GET /api/runs/{id}")
def start(req: DiagnosisRequest, store: StoreDep, jobs: JobsDep, request: Request) -> DiagnosisStarted:
    """Either runs the protocol on the simulated rig with chosen effects switched on (`protocol`), or takes
    stored runs' logs (`run_ids`: the protocol's runs on the rig, or logs uploaded with `POST /api/runs`).
    The diagnosis runs in the background as a run of kind `diagnosis`; its report is the run's result
    (`GET /api/runs/{id}/report`). One at a time."""
    if (req.protocol is None) == (req.run_ids is None):
        raise ParameterError("body = request: give exactly one of protocol or run_ids")
    sources: list[Path] = []
    inputs: list[dict[str, Any]] = []
    for rid in req.run_ids or []:
        r = store.run(rid)
        if r is None:
            raise ParameterError(f"run_ids = {rid}: run {rid} does not exist")
        path = Path(r["log_csv"]) if r["log_csv"] else None
        if path is None or not path.is_file() or not path.with_suffix(".json").is_file():
            raise ParameterError(f"run_ids = {rid}: run {rid} has no log to replay")
        sources.append(path)
        inputs.append(r)
    if len({s.stem for s in sources}) != len(sources):
        raise ParameterError("run_ids: two runs share a log name")
    if req.held_out:
        from app.engine.diagnosis.protocol import VISIBLE

        names = {s.stem for s in sources} or {f"{k}-{r}" for k in VISIBLE for r in (1, 2)}
        unknown = [h for h in req.held_out if h not in names]
        if unknown:
            raise ParameterError(f"held_out = {unknown[0]!r}: no log of that name; have {', '.join(sorted(names))}")
        if set(req.held_out) >= names:
            raise ParameterError("held_out: every log is held out; none is left to fit on")
    if req.bounds:
        _checked_bounds(req.bounds)
    busy = jobs.refusal()
    if busy:
        raise HTTPException(409, busy)
    data_dir = Path(request.app.state.station.data_dir)
    spec: dict[str, Any] = req.model_dump() | _common_who(inputs)
    run_id = store.run_started("diagnosis", spec, "")
    logdir = logdir_of(data_dir, run_id)
    try:
        name = f"diagnosis-{run_id}"
        jobs.start(name, lambda stop: _work(store, run_id, req, logdir, sources, stop, jobs.stop,
                                            lambda msg: jobs.say(name, msg)))
    except JobRefused as exc:  # lost a race with another request: the stored run says why
        store.run_finished(run_id, "cancelled", None, {"error": str(exc)})
        raise HTTPException(409, str(exc)) from exc
    return DiagnosisStarted(run_id=run_id)


@router.get("/{run_id}/traces", response_model=DiagnosisTraces, dependencies=[READ],
            responses={404: {"description": "No such run, not a gap diagnosis, or one kept without traces"},
                       409: {"description": "The diagnosis is still running, failed or was cancelled"}},
            summary="Where in time the gap lies: each held-out log measured beside the predictions")
def traces(run_id: IdPath, store: StoreDep, request: Request) -> DiagnosisTraces:
    """Each held-out log's channels over time: the measurement, the recalibrated baseline's prediction and
    the prediction of the model the verdict ends with, as at most 300 block means per series. The report
    (`GET /api/runs/{id}/report`) says how large the residuals are per channel, regime and log; these say
    when they arise. Kept beside the diagnosis's logs; a diagnosis stored before the station kept them
    answers 404."""
    completed_diagnosis(store, run_id, "traces come")
    path = traces_path(logdir_of(Path(request.app.state.station.data_dir), run_id))
    if not path.is_file():
        raise HTTPException(404, f"diagnosis {run_id} has no traces (it was stored before the station kept them)")
    return DiagnosisTraces.model_validate(json.loads(path.read_text(encoding="utf-8")) | {"run_id": run_id})


STOP_WAIT_S = 20.0
"""How long a stop request waits for the diagnosis to record itself cancelled [s]: it checks between
replays, each a few seconds on a 2-core station."""


@router.post("/{run_id}/stop", response_model=RunInfo, dependencies=[ADMIN],
             responses={404: {"description": "No such run, or it is not a gap diagnosis"},
                        409: {"description": "The diagnosis is not running (in this server)"}},
             summary="Stop a running gap diagnosis; answers the run once it is recorded cancelled")
def stop_diagnosis(run_id: IdPath, store: StoreDep, jobs: JobsDep) -> RunInfo:
    """The diagnosis stops at its next step; nothing it found so far is kept as a report."""
    r = store.run(run_id)
    if r is None:
        raise HTTPException(404, f"run {run_id} does not exist")
    if r["kind"] != "diagnosis":
        raise HTTPException(404, f"run {run_id} is not a gap diagnosis (its kind: {r['kind']})")
    name = f"diagnosis-{run_id}"
    if r["status"] != "running" or not jobs.cancel(name):
        raise HTTPException(409, f"diagnosis {run_id} is {r['status']}"
                                 + ("" if r["status"] != "running" else " in the store, but no job of this server "
                                    "runs it")
                                 + "; there is nothing to stop")
    jobs.join(name, STOP_WAIT_S)
    return RunInfo.from_row(store.run(run_id) or r)
