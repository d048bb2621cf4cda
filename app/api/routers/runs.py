"""Stored runs: list, detail, time series, export (CSV, Parquet, MATLAB .mat), and run logs imported from elsewhere."""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import FileResponse, Response
from pydantic import Field, ValidationError

from app.api.auth import ADMIN, AUTH_RESPONSES, READ, THERAPIST
from app.api.compare import CONTROLLERS, compared_runs, radar_scale
from app.api.deps import IdPath, JobsDep, StoreDep, completed_diagnosis
from app.api.diagnosis_report import DiagnosisReport
from app.api.models import ComparedRun, Comparison, Documented, NotesIn, PersonFilter, RunInfo, Series
from app.engine.params import ParameterError
from app.engine.station import RunKind
from app.storage import StoreUnavailable

router = APIRouter(prefix="/api/runs", tags=["runs"], dependencies=[READ], responses=AUTH_RESPONSES)
# its own path: under /api/runs a PATCH of it had reached PATCH /api/runs/{run_id} (422, not 405)
exercises_router = APIRouter(prefix="/api/exercises", tags=["runs"], dependencies=[READ], responses=AUTH_RESPONSES)
NOT_FOUND: dict[int | str, dict[str, Any]] = {404: {"description": "No such run, or it has no time series"}}


def _get(store: StoreDep, run_id: int) -> dict[str, Any]:
    r = store.run(run_id)
    if r is None:
        raise HTTPException(404, f"run {run_id} does not exist")
    return r


def _log_path(r: dict[str, Any]) -> Path:
    path = Path(r["log_csv"]) if r["log_csv"] else None
    if path is None or not path.is_file():
        raise HTTPException(404, f"run {r['id']} has no time series")
    return path


def _load(r: dict[str, Any]) -> tuple[list[str], np.ndarray]:
    with open(_log_path(r), encoding="utf-8") as fh:
        cols = fh.readline().strip().split(",")
        body = fh.read()
    # a run still being written may end in a partial line (one cut after its last comma has every
    # comma a row has): only lines the writer ended are rows
    lines = [ln for ln in body[: body.rfind("\n") + 1].splitlines() if ln.count(",") == len(cols) - 1]
    data = np.loadtxt(lines, delimiter=",", ndmin=2) if lines else np.zeros((0, len(cols)))
    return cols, data


@router.get("", response_model=list[RunInfo], summary="Runs, newest first")
def list_runs(store: StoreDep, limit: Annotated[int, Query(ge=1, le=1000, description="At most this many runs")] = 100,
              offset: Annotated[int, Query(ge=0, le=10**9, description="Skip this many of the newest first")] = 0,
              kind: Annotated[RunKind | None, Query(description="Only runs of this kind (a misspelt kind is "
                                                                "refused, not answered with an empty list)")] = None,
              session_id: Annotated[int | None, Query(ge=1, le=2**62, description="Only this therapy session's runs")]
              = None,
              person: PersonFilter = None,
              with_result: Annotated[bool, Query(description=(
                  "false: each run's result is left out (null; GET /api/runs/{id} has it). A gap "
                  "diagnosis's report alone is tens of kilobytes; the dashboard's history needs none"))] = True,
              ) -> list[RunInfo]:
    """Every kind of run: exercises, identifications, tunings, protocol experiments, diagnoses and imported
    logs, each with its status (`running`, `complete`, `stopped`, `fault`, `finished`, `cancelled`, `failed`,
    `interrupted` when the server died under it), metrics and result. The filters combine."""
    return [RunInfo.from_row(r) for r in store.runs(limit, offset, kind, session_id, person, with_result)]


# the six metrics' columns in the exercises table, with their units in plain ASCII (a spreadsheet opening
# a UTF-8 file without a byte-order mark garbles "N·m"; with one, a script's first column name does)
EXERCISE_METRIC_COLUMNS: dict[str, str] = {"mae": "mae_Nm", "iae": "iae_Nms", "itae": "itae_Nms2",
                                           "evar": "evar_N2m2", "rmse": "rmse_Nm", "maxae": "maxae_Nm"}
EXERCISE_COLUMNS: tuple[str, ...] = (
    "run", "started_utc", "person", "session", "scenario", "controller", "target_Nm", "status",
    *EXERCISE_METRIC_COLUMNS.values(), "angle_min_deg", "angle_max_deg", "warnings", "notes")


def exercises_csv(runs: list[dict[str, Any]]) -> str:
    """Stored exercises as one table, one row each in the order given (:data:`EXERCISE_COLUMNS`).

    A metric the run could not give, or a range it did not record, is an empty cell; angles are
    positive towards pronation.
    """
    import csv
    from datetime import UTC, datetime

    def cell(v: Any) -> Any:
        return "" if v is None else v

    def text(v: str) -> str:
        # typed text (notes, a person's id) that a spreadsheet would run as a formula is kept as text
        # (OWASP's CSV injection: "=HYPERLINK(…)" in a note became a live link in the clinical record)
        return "'" + v if v[:1] in ("=", "+", "-", "@", "\t", "\r") else v

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(EXERCISE_COLUMNS)
    for r in runs:
        spec, metrics, result = r["spec"] or {}, r["metrics"] or {}, r["result"] or {}
        lo, hi = result.get("angle_range_deg") or (None, None)
        w.writerow([r["id"], datetime.fromtimestamp(r["started"], UTC).isoformat(timespec="seconds"),
                    text(r["person"] or ""), cell(r["session_id"]), cell(spec.get("scenario")),
                    cell(spec.get("controller")), cell(spec.get("target_nm")), r["status"],
                    *(cell(metrics.get(k)) for k in EXERCISE_METRIC_COLUMNS), cell(lo), cell(hi),
                    text(" ".join(result.get("warnings") or ())), text(r["notes"] or "")])
    return buf.getvalue()


@exercises_router.get("", responses={200: {"content": {"text/csv": {}}, "description": "The table, as CSV"}},
                      response_class=Response,
                      summary="Stored exercises as one CSV table, oldest first (e.g. one person's)")
def exercises_table(store: StoreDep, person: PersonFilter = None,
                    session_id: Annotated[int | None, Query(ge=1, le=2**62, description="Only this therapy session's")]
                    = None,
                    limit: Annotated[int, Query(ge=1, le=10000, description="The newest this many")] = 1000,
                    ) -> Response:
    """One row per exercise (a person's progress for their clinical record, or a study's runs for a
    script): when, scenario, controller and target, how it ended, its six metrics, the range of motion it
    reached and what the station noticed, with the notes. Oldest first; the filters combine."""
    rows = store.runs(limit, 0, "workout", session_id, person, True)[::-1]
    name = f"exercises-{person}.csv" if person else "exercises.csv"
    return Response(exercises_csv(rows), media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="{name}"'})


@router.get("/{run_id}", response_model=RunInfo, responses=NOT_FOUND, summary="One run with metrics and results")
def run_detail(run_id: IdPath, store: StoreDep, jobs: JobsDep) -> RunInfo:
    """`result` is the run's own: an exercise's scored window (counted from `result.program_start_s` on the
    log's clock), each chamber's period-2 toggle over it (`pressure_toggle_bar`) and, past 0.02 bar, a
    plain-words `warnings` entry (the pressure loop chatters), the range of motion it reached
    (`angle_range_deg`: the lowest and highest measured angle over its program [deg, positive pronation]),
    an identification's parameters with their intervals and test points, a tuning's gains and loops, a
    diagnosis's report. `has_series`: whether a log is stored for `…/series` and `…/export`. `progress`: while a
    gap diagnosis runs, what it is doing now."""
    r = _get(store, run_id)
    said = jobs.progress(f"diagnosis-{run_id}") if r["kind"] == "diagnosis" and r["status"] == "running" else None
    return RunInfo.from_row(r, said)


@router.get("/{run_id}/comparison", response_model=Comparison,
            responses={404: {"description": "No such run"},
                       409: {"description": "The run is not an exercise, or has no metrics to compare"}},
            summary="An exercise beside each other controller's latest like run (the radar chart's data)")
def comparison(run_id: IdPath, store: StoreDep) -> Comparison:
    """The thesis's radar charts set the three controllers side by side on one scenario and target. This
    sets an exercise beside the latest complete run of each other controller for the same person,
    scenario and target (another person's arm or a run cut short would differ for reasons of its own),
    with each metric's largest value among them (the radar's rim) and its lowest's controller."""
    r = _get(store, run_id)
    if r["kind"] != "workout":
        raise HTTPException(409, f"run {run_id} is not an exercise (kind {r['kind']!r}): only exercises are "
                                 "compared")
    runs = compared_runs(store, r)
    if not runs:
        why = "it is still running" if r["status"] == "running" else \
            f"it ended ({r['status']}) before any of its metrics could be scored"
        raise HTTPException(409, f"exercise {run_id} has no metrics to compare: {why}")
    scale = radar_scale(runs)
    spec = r["spec"] or {}
    have = {c["controller"] for c in runs}
    return Comparison(run_id=run_id, scenario=spec.get("scenario"), target_nm=spec.get("target_nm"),
                      person=r["person"] or "", runs=[ComparedRun(**c) for c in runs], scale=scale,
                      best={m: min(runs, key=lambda c: c["metrics"][m])["controller"] for m in scale},
                      missing=[c for c in CONTROLLERS if c not in have])


@router.get("/{run_id}/report", response_model=DiagnosisReport, response_model_exclude_unset=True,  # as stored
            responses={404: {"description": "No such run, or it is not a gap diagnosis"},
                       409: {"description": "The diagnosis is still running, failed or was cancelled, or its "
                                            "stored report predates the schema"}},
            summary="A gap diagnosis's report, typed (the run's result, with a schema)")
def diagnosis_report(run_id: IdPath, store: StoreDep) -> DiagnosisReport:
    """The same report as the run's `result`, validated against `DiagnosisReport` so that a client can be
    generated from the schema: baseline, ranking, verdict, where the gap lies, how far it shrinks."""
    r = completed_diagnosis(store, run_id, "report comes")
    try:
        return DiagnosisReport.model_validate(r["result"] | {"run_id": run_id})
    except ValidationError as exc:  # a report stored by an older engine, without a field the schema needs
        first = exc.errors()[0]
        raise HTTPException(409, f"diagnosis {run_id}'s stored report does not fit the schema "
                                 f"({'.'.join(map(str, first['loc']))}: {first['msg']}); GET /api/runs/{run_id} "
                                 "has it as stored") from None


@router.patch("/{run_id}", response_model=RunInfo, dependencies=[THERAPIST],
              responses={404: {"description": "No such run"}}, summary="Replace a run's notes")
def edit_notes(run_id: IdPath, body: NotesIn, store: StoreDep) -> RunInfo:
    """What was observed after the run; `notes_edited` records when, and the notes it started with stay
    in its `spec`."""
    if not store.set_run_notes(run_id, body.notes):
        raise HTTPException(404, f"run {run_id} does not exist")
    return RunInfo.from_row(_get(store, run_id))


@router.get("/{run_id}/series", response_model=Series, responses=NOT_FOUND,
            summary="Time series, every n-th sample")
def series(run_id: IdPath, store: StoreDep,
           every: int = Query(1, ge=1, le=10000, description="Every n-th sample (1: all)"),
           max_rows: Annotated[int | None, Query(ge=2, le=10**7, description=(
               "At most this many rows: ``every`` is raised as far as needed (a plot of a run of "
               "any length asks for what it can draw)"))] = None) -> Series:
    """The run's log as rows of the fixed columns (`t` on the engine's clock, the units as in the log
    format), a running run's as far as written; `meta` is the log's JSON header."""
    r = _get(store, run_id)
    cols, data = _load(r)
    if max_rows is not None:
        every = max(every, -(-len(data) // max_rows))
    return Series(columns=cols, rows=data[::every].tolist(), every=every, rows_total=len(data), meta=_meta(r))


def _meta(r: dict[str, Any]) -> dict[str, Any]:
    """The log's JSON header beside its CSV (a plot needs its ``p_atm_bar`` to draw the PRV commands)."""
    try:
        meta = json.loads(_log_path(r).with_suffix(".json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}  # the series itself is still worth having without it
    return meta if isinstance(meta, dict) else {}


UNITS = "t s; z_a,z_b,u_a,u_b V; p_a,p_b,p_s bar abs; theta rad; omega rad/s; torque N·m"
"""The log columns' units, said in every export."""


def _matlab_name(k: str) -> str:
    """``k`` as a MATLAB name (a letter first, then letters, digits and ``_``, at most 63): savemat skips
    a variable or field it would refuse, with only a warning."""
    name = re.sub(r"\W", "_", k, flags=re.ASCII)
    return (name if name[:1].isalpha() else f"x{name}")[:63]


def _numbers(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _for_matlab(v: Any) -> Any:
    """A JSON value as ``scipy.io.savemat`` writes it: objects become structs (their keys
    :func:`_matlab_name`), null an empty matrix (savemat refuses None)."""
    if v is None:
        return np.empty((0, 0))
    if isinstance(v, dict):
        return {_matlab_name(str(k)): _for_matlab(x) for k, x in v.items()}
    if isinstance(v, list):
        if v and all(_numbers(x) for x in v):
            return np.asarray(v, dtype=float)
        # rows of numbers, all as long (an identification's test points): a matrix, one row each
        if v and all(isinstance(x, list) and x and _numbers(x[0]) for x in v) \
                and all(len(x) == len(v[0]) and all(_numbers(y) for y in x) for x in v):
            return np.asarray(v, dtype=float)
        cells = np.empty(len(v), dtype=object)
        cells[:] = [_for_matlab(x) for x in v]
        return cells
    return v


FILES: dict[int | str, dict[str, Any]] = {
    **NOT_FOUND, 200: {"description": "The log as a file, in the format asked for",
                       "content": {"text/csv": {}, "application/x-matlab-data": {},
                                   "application/vnd.apache.parquet": {}}}}


def _parquet(r: dict[str, Any]) -> bytes:
    """The series as one Parquet table; spec, metrics and result ride along as schema metadata."""
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    cols, data = _load(r)
    meta = {"run_id": str(r["id"]), "kind": r["kind"], "status": r["status"],
            "spec": json.dumps(r["spec"] or {}), "metrics": json.dumps(r["metrics"] or {}),
            "result": json.dumps(r["result"] or {}), "log": json.dumps(_meta(r)), "units": UNITS}
    table = pa.table({c: data[:, i] for i, c in enumerate(cols)}).replace_schema_metadata(meta)
    buf = pa.BufferOutputStream()
    pq.write_table(table, buf, compression="zstd")
    return bytes(buf.getvalue().to_pybytes())


@router.get("/{run_id}/export", responses=FILES, response_class=Response,
            summary="Download the time series as CSV, Parquet or MATLAB .mat")
def export(run_id: IdPath, store: StoreDep, fmt: Annotated[Literal["csv", "parquet", "mat"], Query(
        description="csv (the log format), parquet (spec, metrics, result and the log's JSON header in its "
                    "metadata) or mat (MATLAB: one variable per column, metric_<name> per metric, the log's JSON "
                    "header as the struct meta, the run's result (identified parameters, scored window, ...) as "
                    "the struct result, run_id and units)")] = "csv"
        ) -> Response:
    """The whole log as a file named `run-<id>.<ext>`; 404 when the run has no log."""
    r = _get(store, run_id)
    if fmt == "csv":
        return FileResponse(_log_path(r), media_type="text/csv", filename=f"run-{run_id}.csv")
    if fmt == "parquet":
        return Response(_parquet(r), media_type="application/vnd.apache.parquet",
                        headers={"Content-Disposition": f'attachment; filename="run-{run_id}.parquet"'})
    from scipy.io import savemat

    cols, data = _load(r)
    buf = io.BytesIO()
    mdict: dict[str, Any] = {c: data[:, i] for i, c in enumerate(cols)}
    mdict["columns"] = np.array(cols, dtype=object)
    for k, v in (r["metrics"] or {}).items():
        mdict[_matlab_name(f"metric_{k}")] = _for_matlab(v)
    # what a MATLAB user needs beside the columns: the sample rate, the atmosphere, the scenario, the target
    mdict["meta"] = _for_matlab(_meta(r))
    if r["result"]:  # what the run found: an identification's parameters, an exercise's scored window
        mdict["result"] = _for_matlab(r["result"])
    mdict["run_id"] = int(r["id"])
    mdict["units"] = UNITS
    savemat(buf, mdict, do_compression=True)
    return Response(buf.getvalue(), media_type="application/x-matlab-data",
                    headers={"Content-Disposition": f'attachment; filename="run-{run_id}.mat"'})


class LogImport(Documented):
    """A run log recorded elsewhere (another station, the rig's own DAQ, a script), in the station's format.

    Attributes:
        name: The log's name (its file stem; a diagnosis names held-out logs by it).
        meta: The log's JSON metadata: at least ``rig``, ``sample_rate_hz``, ``p_atm_bar``,
            ``working_pressure_bar``, ``experiment``, ``human``.
        csv: The CSV text; the header exactly ``t,z_a,z_b,u_a,u_b,p_a,p_b,p_s,theta,omega,torque``
            (s, V, bar abs, rad, rad/s, N·m).
        notes: Free text stored with the run.
    """

    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")]
    meta: dict[str, Any]
    csv: Annotated[str, Field(min_length=1)]
    notes: Annotated[str, Field(max_length=2000)] = ""


def _parse_log(req: LogImport) -> np.ndarray:
    """The checked (n, 11) array of an uploaded log, or a ParameterError naming the problem."""
    from app.engine.diagnosis.logs import LogFormatError, check_frame, header_columns

    lines = req.csv.splitlines()
    try:
        header = header_columns(req.name, lines[0])
    except LogFormatError as exc:
        raise ParameterError(f"csv: {exc}") from None
    rows = [ln for ln in lines[1:] if ln.strip()]
    try:
        data = np.loadtxt(rows, delimiter=",", ndmin=2) if rows else np.zeros((0, len(header)))
    except ValueError as exc:
        raise ParameterError(f"csv: a row is not {len(header)} numbers ({exc})") from None
    if data.size and data.shape[1] != len(header):
        raise ParameterError(f"csv: rows have {data.shape[1]} values, the header {len(header)}")
    try:
        check_frame(req.name, header, data, req.meta)
    except LogFormatError as exc:
        field = "meta" if str(exc).startswith(f"{req.name}.json") else "csv"
        raise ParameterError(f"{field}: {exc}") from None
    return data


@router.post("", response_model=RunInfo, status_code=201, dependencies=[ADMIN],
             responses={413: {"description": "Larger than CWRR_MAX_UPLOAD_BYTES"}},
             summary="Store a run log recorded elsewhere (checked first), e.g. to diagnose it")
def import_log(req: LogImport, store: StoreDep, request: Request) -> RunInfo:
    """The log is checked as ``cwrr diagnose`` checks a log directory (columns, units, NaN, time);
    a refused log leaves nothing behind. Accepted, it is a run of kind ``imported`` whose series and
    exports work like a recorded run's and whose id a diagnosis accepts in ``run_ids``."""
    data = _parse_log(req)
    root = Path(request.app.state.station.data_dir) / "imported"
    # written in a temporary folder and renamed into place before the run is stored: a run never
    # points at a half-written log
    tmp: Path | None = None
    try:
        from app.engine.sim import LOG_COLUMNS

        root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".upload-", dir=root))
        np.savetxt(tmp / f"{req.name}.csv", data, delimiter=",", header=",".join(LOG_COLUMNS), comments="",
                   fmt="%.9g")
        (tmp / f"{req.name}.json").write_text(json.dumps(req.meta, indent=1), encoding="utf-8")
        for f in tmp.iterdir():
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
        final = root / tmp.name.removeprefix(".upload-")
        tmp.rename(final)
    except BaseException as exc:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError):  # a full disk: 503 saying so, and nothing left behind (it was a bare 500)
            raise StoreUnavailable(f"the log cannot be stored in the data folder: {exc.strerror or exc}") from exc
        raise
    spec = {"name": req.name, "meta": req.meta, "notes": req.notes, "rows": int(data.shape[0])}
    try:
        run_id = store.run_started("imported", spec, str(final / f"{req.name}.csv"))
    except StoreUnavailable:
        shutil.rmtree(final, ignore_errors=True)  # no run points at it
        raise
    duration = float(data[-1, 0] - data[0, 0])
    store.run_finished(run_id, "complete", None, {"rows": int(data.shape[0]), "duration_s": duration,
                                                  "rig": req.meta["rig"], "experiment": req.meta["experiment"]})
    return RunInfo.from_row(_get(store, run_id))
