"""Stored runs: list, detail, time series, export (CSV, MATLAB .mat)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any, Literal

import numpy as np
from fastapi import APIRouter, HTTPException, Query
from fastapi.responses import FileResponse, Response

from app.api.auth import AUTH_RESPONSES, READ
from app.api.deps import IdPath, StoreDep
from app.api.models import RunInfo, Series

router = APIRouter(prefix="/api/runs", tags=["runs"], dependencies=[READ], responses=AUTH_RESPONSES)
NOT_FOUND: dict[int | str, dict[str, Any]] = {404: {"description": "No such run, or it has no time series"}}


def _info(r: dict[str, Any]) -> RunInfo:
    return RunInfo(**{k: r[k] for k in ("id", "kind", "status", "started", "ended", "metrics", "result", "person",
                                        "notes", "session_id")}, spec=r["spec"] or {},
                   has_series=bool(r["log_csv"]) and Path(r["log_csv"]).is_file())


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
        # a run still being written may end in a partial line; keep the complete ones
        lines = [ln for ln in fh.read().splitlines() if ln.count(",") == len(cols) - 1]
    data = np.loadtxt(lines, delimiter=",", ndmin=2) if lines else np.zeros((0, len(cols)))
    return cols, data


@router.get("", response_model=list[RunInfo], summary="Runs, newest first")
def list_runs(store: StoreDep, limit: int = Query(100, ge=1, le=1000), offset: int = Query(0, ge=0, le=10**9),
              kind: str | None = Query(None, max_length=40),
              session_id: int | None = Query(None, ge=1, le=2**62)) -> list[RunInfo]:
    return [_info(r) for r in store.runs(limit, offset, kind, session_id)]


@router.get("/{run_id}", response_model=RunInfo, responses=NOT_FOUND, summary="One run with metrics and results")
def run_detail(run_id: IdPath, store: StoreDep) -> RunInfo:
    return _info(_get(store, run_id))


@router.get("/{run_id}/series", response_model=Series, responses=NOT_FOUND,
            summary="Time series, every n-th sample")
def series(run_id: IdPath, store: StoreDep, every: int = Query(1, ge=1, le=10000)) -> Series:
    cols, data = _load(_get(store, run_id))
    return Series(columns=cols, rows=data[::every].tolist(), every=every)


FILES: dict[int | str, dict[str, Any]] = {
    **NOT_FOUND, 200: {"content": {"text/csv": {}, "application/x-matlab-data": {},
                                   "application/vnd.apache.parquet": {}}}}


def _parquet(r: dict[str, Any]) -> bytes:
    """The series as one Parquet table; spec and metrics ride along as schema metadata."""
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    cols, data = _load(r)
    meta = {"run_id": str(r["id"]), "kind": r["kind"], "status": r["status"],
            "spec": json.dumps(r["spec"] or {}), "metrics": json.dumps(r["metrics"] or {}),
            "units": "t s; z_a,z_b,u_a,u_b V; p_a,p_b,p_s bar abs; theta rad; omega rad/s; torque N·m"}
    table = pa.table({c: data[:, i] for i, c in enumerate(cols)}).replace_schema_metadata(meta)
    buf = pa.BufferOutputStream()
    pq.write_table(table, buf, compression="zstd")
    return bytes(buf.getvalue().to_pybytes())


@router.get("/{run_id}/export", responses=FILES,
            summary="Download the time series as CSV, Parquet or MATLAB .mat")
def export(run_id: IdPath, store: StoreDep, fmt: Literal["csv", "parquet", "mat"] = "csv") -> Response:
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
        mdict[f"metric_{k}"] = v
    savemat(buf, mdict, do_compression=True)
    return Response(buf.getvalue(), media_type="application/x-matlab-data",
                    headers={"Content-Disposition": f'attachment; filename="run-{run_id}.mat"'})
