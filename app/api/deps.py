"""Shared dependencies: the station and the store live on ``app.state`` (set by the lifespan)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

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


StationDep = Annotated[Station, Depends(get_station)]
StoreDep = Annotated[Store, Depends(get_store)]
