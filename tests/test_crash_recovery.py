"""Issue 7 items 4–5: ``kill -9`` of the server mid-run loses at most the last second of the log;
clients that vanish mid-run change nothing.

A real ``cwrr serve`` process on the simulated plant, paced at 200 Hz, is
killed with SIGKILL three seconds into a workout; a second server started on
the same data folder must list the run as interrupted and serve its log.
"""

from __future__ import annotations

import itertools
import json
import signal
import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx2 as httpx
import pytest

from app.engine.diagnosis.logs import read_log
from tests.conftest import ServedStation as Server

pytestmark = [pytest.mark.slow, pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL")]


@pytest.fixture()
def servers(tmp_path: Path) -> Iterator[list[Server]]:
    started: list[Server] = []
    yield started
    for s in started:
        s.stop()


def test_kill_9_mid_run_loses_at_most_the_last_second_and_the_run_is_listed_as_interrupted(
        tmp_path: Path, servers: list[Server]) -> None:
    first = Server(tmp_path)
    servers.append(first)
    assert first.api("GET", "/api/engine")["state"] == "idle"
    run_id = first.api("POST", "/api/engine/start", json={"scenario": "SC-1", "person": "p-kill"})["run_id"]
    time.sleep(3.0)
    assert first.api("GET", "/api/engine")["state"] == "running"
    t_kill = time.time()
    first.proc.send_signal(signal.SIGKILL)
    first.proc.wait(10)
    assert first.proc.returncode == -signal.SIGKILL

    second = Server(tmp_path)  # same data folder, same SQLite store
    servers.append(second)
    run = second.api("GET", f"/api/runs/{run_id}")
    assert run["status"] == "interrupted" and run["person"] == "p-kill" and run["has_series"]
    series = second.api("GET", f"/api/runs/{run_id}/series")
    rows = series["rows"]
    t = [r[series["columns"].index("t")] for r in rows]
    assert len(rows) > 200  # 1 s at 200 Hz at least
    backwards = [(i, rows[i], rows[i + 1]) for i, (a, b) in enumerate(itertools.pairwise(t)) if not b > a]
    assert not backwards, (len(rows), backwards[:3])  # the rows themselves, should it ever happen again
    # the log's clock (the rig's, counted from connect) runs with the wall clock (paced), and its
    # first row comes after the run was stored as started: what the log spans short of the time
    # from that start to the kill is what was lost, or more
    lost_s = (t_kill - run["started"]) - (t[-1] - t[0])
    assert lost_s <= 1.0, f"{lost_s:.2f} s of the log lost"
    # the metadata is whole JSON (written atomically) and the CSV exports
    meta_files = list(tmp_path.rglob("*.json"))
    assert meta_files and all(isinstance(json.loads(p.read_text()), dict) for p in meta_files)
    # the log pair itself says so too, and cut back to whole rows it reads as any log does (the
    # gap diagnosis, `cwrr diagnose`): its JSON had said "running" for good
    (log_csv,) = (tmp_path / "runs").glob("run-*.csv")
    meta = json.loads(log_csv.with_suffix(".json").read_text())
    assert meta["status"] == "interrupted" and meta["rows"] == len(rows), (meta["status"], meta.get("rows"))
    assert len(read_log(log_csv).t) == len(rows)
    csv = httpx.get(f"{second.url}/api/runs/{run_id}/export?fmt=csv", timeout=30)
    assert csv.status_code == 200 and csv.text.count("\n") >= len(rows)
    # and the station is usable again: a new run starts on the restarted server
    assert second.api("GET", "/api/engine")["state"] == "idle"
    new_id = second.api("POST", "/api/engine/start", json={"scenario": "SC-1"})["run_id"]
    assert new_id != run_id
    second.api("POST", "/api/engine/stop")


def _hang_up(port: int, request: bytes, reset: bool) -> None:
    """Send ``request`` and vanish: a normal close, or a TCP reset (SO_LINGER 0) as a pulled cable gives."""
    import struct

    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    if reset:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    s.sendall(request)
    s.close()


def test_clients_vanishing_mid_run_leave_the_run_and_its_log_intact(tmp_path: Path, servers: list[Server]) -> None:
    srv = Server(tmp_path)
    servers.append(srv)
    run_id = srv.api("POST", "/api/engine/start", json={"scenario": "SC-1"})["run_id"]
    for i in range(6):
        reset = bool(i % 2)
        # half a request: the body never arrives, so nothing may be created
        _hang_up(srv.port, b"POST /api/sessions HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                           b"Content-Length: 200\r\n\r\n{\"person\": \"half", reset)
        # a big answer nobody stays to read (the dashboard's live poll, tab closed mid-transfer)
        _hang_up(srv.port, b"GET /api/live?since=-1&max_rows=15000 HTTP/1.1\r\nHost: x\r\n\r\n", reset)
        time.sleep(0.2)
    st = srv.api("GET", "/api/engine")
    assert st["state"] == "running" and st["safety"]["fault"] is None
    assert srv.api("GET", "/api/sessions") == []
    srv.api("POST", "/api/engine/stop")
    overruns = srv.api("GET", "/api/health")["overruns"]
    run = srv.api("GET", f"/api/runs/{run_id}")
    assert run["status"] == "stopped", run["status"]
    series = srv.api("GET", f"/api/runs/{run_id}/series")
    t = [r[series["columns"].index("t")] for r in series["rows"]]
    steps = [b - a for a, b in itertools.pairwise(t)]
    # every period the loop ran is logged, none twice; a period is missing only where the loop
    # itself skipped it (an overrun it counted), never a row lost to a vanished client. Counted
    # over the run's span, not from single steps: t is when each period started, so under CI
    # load a period started 4.5 ms late looks like a 9.5 ms gap and a 0.5 ms step after it (seen
    # once in CI: five 10 ms steps and a 0.5 ms one, one overrun counted); ±1 for the jitter of
    # the first and last period
    missing = round((t[-1] - t[0]) * 200) + 1 - len(t)
    assert len(t) > 200 and min(steps) > 0.0 and missing <= overruns + 1, (missing, overruns, min(steps), max(steps))
