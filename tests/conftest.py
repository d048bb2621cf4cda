"""Shared fixtures."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import settings

from app.engine.params import DCVParams, PlantParams

# The test command draws the same examples on every run, so CI passes or fails on the code, not
# on the draw; CWRR_HYPOTHESIS=explore draws new ones each run (a search for counterexamples).
settings.register_profile("ci", derandomize=True, database=None)
settings.register_profile("explore")
settings.load_profile(os.environ.get("CWRR_HYPOTHESIS", "ci"))

REFDATA = next((p for p in (Path(__file__).resolve().parents[2] / "shared" / "refdata", Path("/work/shared/refdata"))
                if p.is_dir()), Path("/work/shared/refdata"))
"""refdata/ next to the repository in a work tree; at its fixed path in a fresh clone elsewhere."""


@pytest.fixture(scope="session")
def params() -> PlantParams:
    """Default rotary rig (SPEC §1)."""
    return PlantParams()


@pytest.fixture(scope="session")
def sealed() -> PlantParams:
    """A rig whose DCVs close perfectly at 5 V (no underlap leakage)."""
    return PlantParams(dcv=DCVParams(underlap_fill_v=0.0, underlap_exh_v=0.0))


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def free_port() -> int:
    """A TCP port nobody listens on now."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def live_server(settings: Any) -> Iterator[str]:
    """The full app (lifespan included) served by uvicorn in a thread; yields its base URL."""
    import threading
    import time

    import uvicorn

    from app.api.main import create_app

    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=settings.port,
                                           log_level="warning"))
    th = threading.Thread(target=server.run, daemon=True)
    th.start()
    deadline = time.monotonic() + 60
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.05)
    assert server.started, "server did not start"
    try:
        yield f"http://127.0.0.1:{settings.port}"
    finally:
        server.should_exit = True
        th.join(30)


def viser_viewer(port: int, headers: dict[str, str] | None = None) -> Any:
    """A bare websocket to a viser server, as its page opens one (no 3-D view, no camera pose)."""
    import viser
    from websockets.sync.client import connect
    from websockets.typing import Subprotocol

    return connect(f"ws://127.0.0.1:{port}", additional_headers=headers or {}, open_timeout=10,
                   subprotocols=[Subprotocol(f"viser-v{viser.__version__}")])


@pytest.fixture()
def client(tmp_path: Path) -> Iterator[Any]:
    """The app with its lifespan running on the simulated plant, not yet connected, storing in ``tmp_path``."""
    from fastapi.testclient import TestClient

    from app.api.main import create_app
    from app.api.settings import Settings

    app = create_app(Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False))
    with TestClient(app) as c:
        yield c


def wait_engine(c: Any, cond: Any, timeout: float = 60.0) -> dict[str, Any]:
    """Poll ``GET /api/engine`` until ``cond(state)`` holds or ``timeout`` [s] passes; the last state."""
    import time

    deadline = time.monotonic() + timeout
    while True:
        st: dict[str, Any] = c.get("/api/engine").json()
        if cond(st) or time.monotonic() > deadline:
            return st
        time.sleep(0.1)
