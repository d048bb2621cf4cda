"""Shared dependencies: the station and the store live on ``app.state`` (set by the lifespan)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, HTTPException, Path, Request
from fastapi.exceptions import RequestValidationError

from app.api.jobs import Jobs
from app.engine.station import Station
from app.storage import Store


def get_station(request: Request) -> Station:
    """The app's single station."""
    station: Station = request.app.state.station
    return station


def get_store(request: Request) -> Store:
    """The app's run store."""
    store: Store = request.app.state.store
    return store


def get_jobs(request: Request) -> Jobs:
    """The app's background jobs (gap diagnoses)."""
    jobs: Jobs = request.app.state.jobs
    return jobs


StationDep = Annotated[Station, Depends(get_station)]
StoreDep = Annotated[Store, Depends(get_store)]
JobsDep = Annotated[Jobs, Depends(get_jobs)]
IdPath = Annotated[int, Path(ge=1, le=2**62, description="stored id")]
"""A stored row's id (bounded so no database sees an integer it cannot hold)."""


def completed_diagnosis(store: Store, run_id: int, comes: str) -> dict[str, Any]:
    """Stored run ``run_id``, which must be a complete gap diagnosis (404 or 409 saying why not).

    ``comes`` is what a running one's refusal promises, e.g. ``"report comes"``.
    """
    r = store.run(run_id)
    if r is None:
        raise HTTPException(404, f"run {run_id} does not exist")
    if r["kind"] != "diagnosis":
        raise HTTPException(404, f"run {run_id} is not a gap diagnosis (its kind: {r['kind']})")
    if r["status"] != "complete":
        why = (r["result"] or {}).get("error")
        raise HTTPException(409, f"diagnosis {run_id} is {r['status']}" + (f": {why}" if why else "")
                            + (f"; its {comes} when it is complete" if r["status"] == "running" else ""))
    return r


def _query_names(dependant: Any) -> frozenset[str]:
    """The query parameters a route declares, its dependencies' included."""
    names = {p.alias for p in dependant.query_params}
    for sub in dependant.dependencies:
        names |= _query_names(sub)
    return frozenset(names)


def known_query_only(request: Request) -> None:
    """Refuse a query parameter the route does not take (422 naming it and the ones it does).

    Left alone, ``?format=parquet`` on the export (which takes ``fmt``) would
    answer CSV and say nothing; a script's typo must not read as the default.
    """
    route = request.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if dependant is None or not request.url.path.startswith("/api/"):
        return  # a page's address may carry what a browser or a bookmark put there
    known = _query_names(dependant)
    unknown = [k for k in dict.fromkeys(request.query_params) if k not in known]
    if unknown:
        takes = ", ".join(sorted(known)) if known else "no query parameters"
        raise RequestValidationError([
            {"type": "extra_forbidden", "loc": ["query", k], "input": request.query_params[k],
             "msg": f"unknown query parameter {k!r}; this endpoint takes {takes}"} for k in unknown])
