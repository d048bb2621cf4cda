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


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--heavy-files-first", action="store_true",
                     help="order the test files by how many tests marked slow each holds, most first "
                          "(./dev test, with --dist loadfile --no-loadscope-reorder)")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """``--heavy-files-first``: the files with the most slow tests go out first.

    ``./dev test`` hands whole files to its workers (``--dist loadfile``),
    one as each worker runs low, so a module-scoped fixture is built once (the
    DCV grid's takes ≈ 110 s; handed out test by test, two workers each built
    it). In collection order the last file out could be a long one and leave
    the other worker idle (44 s apart in one run); heavy files first, the
    short ones fill in at the end. xdist 3.8's per-test groups
    (``--dist loadgroup``) do not group under pytest 9.2 (pytest-xdist#1386).
    """
    if not config.getoption("heavy_files_first"):
        return
    weight: dict[str, int] = {}
    for item in items:
        path = item.nodeid.split("::")[0]
        weight[path] = weight.get(path, 0) + (item.get_closest_marker("slow") is not None)
    items.sort(key=lambda it: -weight[it.nodeid.split("::")[0]])  # stable: a file's tests stay in order


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


class ServedStation:
    """``cwrr serve`` in a process of its own, as the README's first command starts it.

    Unlike :func:`live_server` (the app in a thread of the test's process), its
    threads rank as the served station's do (``cwrr serve`` puts them above
    normal ones where the OS allows it), and nothing of the test's own
    process (a browser driver, the test itself) shares its interpreter lock.

    Args:
        data_dir: The station's data folder (``--data-dir``); its log goes there too.
        viser_port: The viser port (0: viser off).
        **env: Further settings as environment variables (``CWRR_...``).
    """

    ROOT = Path(__file__).resolve().parent.parent

    def __init__(self, data_dir: Path, viser_port: int = 0, **env: str) -> None:
        import subprocess
        import sys
        import time

        import httpx2 as httpx

        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        full = dict(os.environ, PYTHONPATH=str(self.ROOT))
        for k in ("CWRR_ADMIN_TOKEN", "CWRR_THERAPIST_TOKEN", "CWRR_DATA_DIR"):
            full.pop(k, None)
        full.update(env)
        data_dir.mkdir(parents=True, exist_ok=True)
        self.log = open(data_dir / f"server-{self.port}.log", "wb")
        self.proc = subprocess.Popen([sys.executable, "-m", "app", "serve", "--port", str(self.port),
                                      "--viser-port", str(viser_port), "--data-dir", str(data_dir)],
                                     cwd=self.ROOT, env=full,
                                     stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 180
        while True:
            assert self.proc.poll() is None, f"server exited with {self.proc.returncode}"
            try:
                if httpx.get(self.url + "/api/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "server did not come up"
            time.sleep(0.2)

    def api(self, method: str, path: str, **kw: Any) -> Any:
        """One request; asserts success and returns the JSON answer."""
        import httpx2 as httpx

        r = httpx.request(method, self.url + path, timeout=30, **kw)
        assert r.status_code < 300, (path, r.status_code, r.text)
        return r.json()

    def stop(self, sig: int | None = None) -> None:
        """End the server (SIGTERM unless ``sig`` says otherwise) and close its log."""
        import signal
        import subprocess

        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM if sig is None else sig)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.log.close()


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
