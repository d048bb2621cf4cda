"""Application factory: lifespan owns the engine; routers stay thin."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Annotated

from fastapi import Depends, FastAPI, Request
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel

from app.api.settings import Settings
from app.engine.service import Station

STATIC = Path(__file__).resolve().parent.parent / "static"


class Health(BaseModel):
    """Engine health.

    Attributes:
        state: Engine state.
        backend: Backend name.
        rate_hz: Nominal loop rate [Hz].
        measured_rate_hz: Achieved rate [Hz].
        ticks: Periods executed.
        overruns: Periods that missed their deadline.
        jitter_p50_ms: Median start jitter [ms].
        jitter_p99_ms: 99th-percentile start jitter [ms].
        jitter_max_ms: Largest start jitter [ms].
    """

    state: str
    backend: str
    rate_hz: float
    measured_rate_hz: float
    ticks: int
    overruns: int
    jitter_p50_ms: float
    jitter_p99_ms: float
    jitter_max_ms: float


def get_station(request: Request) -> Station:
    """The app's engine (a dependency, so tests can override it)."""
    station: Station = request.app.state.station
    return station


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app; the engine starts and stops with the lifespan."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        station = Station(rate_hz=settings.rate_hz)
        app.state.station = station
        if settings.start_engine:
            station.start()
        try:
            yield
        finally:
            station.stop()

    app = FastAPI(title="CWRR Lab Station", version="0.1.0", lifespan=lifespan)

    @app.get("/api/health", response_model=Health, summary="Engine state, loop rate, jitter and overruns")
    def health(station: Annotated[Station, Depends(get_station)]) -> Health:
        return Health(**station.health())

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC / "index.html")

    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app
