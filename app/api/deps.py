"""Shared dependencies: the station and the store live on ``app.state`` (set by the lifespan)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path, Request

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
