"""`cwrr backup`: a station's data folder copied consistently, also while the station runs, and restorable."""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.api.main import create_app
from app.api.settings import Settings
from app.cli import main as cli_main
from app.engine.sim import LOG_COLUMNS, run_workout

META = {"rig": "rotary", "sample_rate_hz": 200.0, "p_atm_bar": 1.01325, "working_pressure_bar": 3.0,
        "experiment": "workout", "human": True}


def _app(folder: Path) -> Any:
    return create_app(Settings(data_dir=str(folder), viser_port=0, auto_connect=False))


def _csv(seconds: float) -> str:
    data = run_workout(duration=seconds).log
    return ",".join(LOG_COLUMNS) + "\n" + "\n".join(",".join(f"{v:.9g}" for v in row) for row in data) + "\n"


def test_a_backup_taken_while_the_station_runs_restores_every_run(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    live, out = tmp_path / "data", tmp_path / "backups" / "2026-12-08"
    with TestClient(_app(live)) as c:
        ids = [c.post("/api/runs", json={"name": f"rig-{k}", "meta": META, "csv": _csv(1.0 + k)}).json()["id"]
               for k in range(2)]
        series = {i: c.get(f"/api/runs/{i}/series").json()["rows"] for i in ids}
        store = c.app.state.store  # type: ignore[attr-defined]
        cut = store.run_started("workout", {"person": "P-007"}, "")  # an exercise going on as the backup runs
        # the station keeps writing while the backup copies: its snapshot is whole all the same
        stop, going = threading.Event(), threading.Event()

        def write() -> None:
            for k in range(10**6):
                rid = store.run_started("workout", {}, "")
                store.run_finished(rid, "complete", {"mae": 0.1}, {})
                if k == 20:
                    going.set()
                if stop.is_set():
                    return

        writer = threading.Thread(target=write)
        writer.start()
        try:
            assert going.wait(30)
            assert cli_main(["backup", str(out), "--data-dir", str(live)]) == 0
        finally:
            stop.set()
            writer.join()
    said = capsys.readouterr().out
    assert said.startswith(f"cwrr backup: {out}: the database {out}/cwrr.sqlite3 (")
    assert "runs), and 5 files" in said  # .station-id, two logs and their JSON
    assert sorted(p.name for p in out.iterdir()) == [".station-id", "cwrr.sqlite3", "imported"]  # no lock
    with sqlite3.connect(out / "cwrr.sqlite3") as db:
        assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
    assert (out / ".station-id").read_text() == (live / ".station-id").read_text()
    # a station started on the copy has every run, with its series; the one cut short is interrupted
    with TestClient(_app(out)) as c:
        for i in ids:
            run = c.get(f"/api/runs/{i}").json()
            assert run["has_series"] and c.get(f"/api/runs/{i}/series").json()["rows"] == series[i]
        assert c.get(f"/api/runs/{cut}").json()["status"] == "interrupted"


def test_a_backup_is_refused_where_it_would_overwrite_or_nest_and_writes_nothing(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    live = tmp_path / "data"
    with TestClient(_app(live)):
        pass
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "keep.txt").write_text("mine")
    for out, why in ((taken, f"{taken} exists: a backup goes to a new folder"),
                     (live / "backup", f"{live / 'backup'} lies inside the data folder {live}"),):
        assert cli_main(["backup", str(out), "--data-dir", str(live)]) == 2
        assert why in capsys.readouterr().err
    assert cli_main(["backup", str(tmp_path / "b"), "--data-dir", str(tmp_path / "nowhere")]) == 2
    assert f"data folder {tmp_path / 'nowhere'} does not exist" in capsys.readouterr().err
    assert (taken / "keep.txt").read_text() == "mine" and not (live / "backup").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "taken"]  # no partial copy left behind
