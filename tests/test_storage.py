"""The run store on both dialects: SQLite always, PostgreSQL where a server is available.

``./dev test`` (and CI) starts a local PostgreSQL and sets ``CWRR_TEST_DATABASE_URL``;
elsewhere the PostgreSQL case is skipped with the reason.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.storage import Store

PG_URL = os.environ.get("CWRR_TEST_DATABASE_URL", "")


@pytest.fixture(params=["sqlite", "postgresql"])
def url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path}/store.sqlite3"
        return
    if not PG_URL:
        pytest.skip("no PostgreSQL server (CWRR_TEST_DATABASE_URL unset; ./dev test starts one where it can)")
    import uuid

    import psycopg

    # a schema of its own for each test: parallel workers share the server, not the tables
    schema = f"t_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(PG_URL, autocommit=True) as db:
        db.execute(f"CREATE SCHEMA {schema}")
    sep = "&" if "?" in PG_URL else "?"
    try:
        yield f"{PG_URL}{sep}options=-csearch_path%3D{schema}"
    finally:
        with psycopg.connect(PG_URL, autocommit=True) as db:
            db.execute(f"DROP SCHEMA {schema} CASCADE")


def test_runs_sessions_and_parameter_sets_round_trip(url: str) -> None:
    s = Store(url)
    sid = s.add_session("P-007", "left arm")
    rid = s.run_started("workout", {"scenario": "SC-2", "person": "P-007", "session_id": sid}, "/x.csv")
    other = s.run_started("rotary_friction", {"procedure": "rotary"}, "")
    s.run_finished(rid, "complete", {"mae": 0.13, "rmse": 0.2}, {"window_s": [1.5, 7.0]})
    got = s.run(rid)
    assert got is not None
    assert got["status"] == "complete" and got["metrics"] == {"mae": 0.13, "rmse": 0.2}
    assert got["result"] == {"window_s": [1.5, 7.0]} and got["session_id"] == sid and got["person"] == "P-007"
    # Unix times keep sub-second precision (PostgreSQL's REAL would round them to minutes)
    assert abs(got["ended"] - got["started"]) < 5.0 and got["ended"] != round(got["ended"], -2)
    assert [r["id"] for r in s.runs()] == [other, rid]
    assert [r["id"] for r in s.runs(kind="workout")] == [rid]
    assert [r["id"] for r in s.runs(session_id=sid)] == [rid]
    brief = s.runs(kind="workout", with_result=False)[0]  # the list without each run's result, the rest as stored
    assert brief["result"] is None and {**brief, "result": got["result"]} == s.run(rid)
    assert s.run(10**9) is None
    ps = s.save_params("gains", "trial", {"kp_a": 0.7})
    assert s.param_set(ps) is not None and s.param_set(ps)["payload"] == {"kp_a": 0.7}  # type: ignore[index]
    assert [p["id"] for p in s.param_sets("gains")] == [ps] and s.param_sets("rotary") == []
    assert s.session(sid)["person"] == "P-007" and [x["id"] for x in s.sessions("P-007")] == [sid]  # type: ignore[index]
    later = s.add_session("P-008")
    assert [x["id"] for x in s.sessions()] == [later, sid] and [x["id"] for x in s.sessions(limit=1, offset=1)] == [sid]
    again = s.run_started("workout", {"session_id": sid}, "")
    assert s.session_run_ids([sid, later]) == {sid: [again, rid], later: []} and s.session_run_ids([]) == {}
    many = [s.add_session("P-009") for _ in range(600)]  # more than one query's parameters
    s.run_started("workout", {"session_id": many[-1]}, "")
    got_many = s.session_run_ids([*many, sid])
    assert len(got_many) == 601 and got_many[sid] == [again, rid] and len(got_many[many[-1]]) == 1
    assert s.session(sid)["notes_edited"] is None  # type: ignore[index]
    assert s.set_session_notes(sid, "left arm; tired after SC-2") and not s.set_session_notes(10**9, "x")
    assert s.run(rid)["notes_edited"] is None  # type: ignore[index]
    assert s.set_run_notes(rid, "said it pulled") and not s.set_run_notes(10**9, "")
    assert s.run(rid)["notes"] == "said it pulled" and s.run(rid)["notes_edited"] > 0  # type: ignore[index]
    row = s.session(sid)
    assert row is not None and row["notes"] == "left arm; tired after SC-2" and row["notes_edited"] >= row["created"]
    assert row["notes_at_open"] == "left arm" and s.set_session_notes(sid, "left arm; tired")
    assert s.session(sid)["notes_at_open"] == "left arm"  # type: ignore[index]  # the first, not the last edit
    s.close()


def test_a_run_left_running_by_a_crash_is_interrupted_on_reopen(url: str) -> None:
    s = Store(url)
    rid = s.run_started("workout", {"scenario": "SC-1"}, "")
    done = s.run_started("workout", {"scenario": "SC-1"}, "/logs/done.csv")
    s.run_finished(done, "complete", None, None)
    s.close()  # no run_finished: the process died
    again = Store(url)
    assert again.run(rid)["status"] == "interrupted"  # type: ignore[index]
    assert again.run(done)["status"] == "complete"  # type: ignore[index]
    assert again.interrupted_at_open == [(rid, "")]  # what the station repairs the logs of
    assert Store(url).interrupted_at_open == []  # once


def test_a_station_starting_calls_only_its_own_runs_interrupted(url: str) -> None:
    """One database, two rigs: the second station's start had marked the first one's live run
    interrupted (until it ended) and handed it to its own log repair."""
    rig1 = Store(url, station="1f0c lab-pc:/data/rig1")
    live = rig1.run_started("workout", {"scenario": "SC-1"}, "/data/rig1/runs/a.csv")
    rig2 = Store(url, station="77ab lab-pc:/data/rig2")
    near = Store(url, station="1f0cd lab-pc:/data/rig1b")  # an id that begins like rig 1's is another station
    assert rig2.interrupted_at_open == near.interrupted_at_open == []
    assert rig2.run(live)["status"] == "running"  # type: ignore[index]
    assert rig2.run(live)["station"] == "1f0c lab-pc:/data/rig1"  # type: ignore[index]
    rig1.close()  # rig 1's station dies; its next start, in a container recreated on the same volume
    # (another host name, the same id), calls its run interrupted
    again = Store(url, station="1f0c 3b9e4a7c0d12:/data")
    assert again.interrupted_at_open == [(live, "/data/rig1/runs/a.csv")]
    near.close()
    rig2.close()
    again.close()


def _log_cut_short(tmp_path: Path, rows: int) -> Path:
    """A run log whose writer died: ``rows`` whole rows, then half a row, its JSON still "running"."""
    from app.engine.runlog import RunLogWriter

    w = RunLogWriter(tmp_path, "cut", {"rig": "rotary", "sample_rate_hz": 200.0, "p_atm_bar": 1.013,
                                       "working_pressure_bar": 3.0, "experiment": "isotonic", "human": True})
    for i in range(rows):
        w.append([i / 200, 2.0, 2.0, 5.0, 5.0, 2.0, 2.0, 6.0, 0.01 * i, 0.0, 0.1])
    w.flush()
    w._fh.write("1.000000,2,2,5,5,2.0")  # the process is killed here, in the middle of a row
    w._fh.flush()
    return w.csv_path


def test_a_log_cut_short_is_repaired_to_its_whole_rows_and_marked_interrupted(tmp_path: Path) -> None:
    import json

    from app.engine.diagnosis.logs import LogFormatError, read_log
    from app.engine.runlog import repair_log

    csv = _log_cut_short(tmp_path, 150)
    with pytest.raises(LogFormatError, match=r"a row is not 11 numbers .* still says \"running\".*repair"):
        read_log(csv)
    assert json.loads(csv.with_suffix(".json").read_text())["status"] == "running"
    assert repair_log(csv) == 150
    meta = json.loads(csv.with_suffix(".json").read_text())
    assert meta["status"] == "interrupted" and meta["rows"] == 150 and meta["recovered_unix"] > 0
    exp = read_log(csv)
    assert len(exp.t) == 150 and exp.channels["theta"][-1] == pytest.approx(1.49)
    assert repair_log(csv) == 150 and csv.read_bytes().endswith(b"\n")  # a second repair changes nothing
    # an operating system that went down before its fsync: the unsynced pages read back as zeros
    # (whole rows after them included), and a log complete before them keeps its status
    with open(csv, "ab") as fh:
        fh.write(b"\0" * 700 + b"1.5,2,2,5,5,2,2,6,0,0,0.1\n")
    meta["status"] = "complete"
    csv.with_suffix(".json").write_text(json.dumps(meta))
    assert repair_log(csv) == 150 and len(read_log(csv).t) == 150
    assert json.loads(csv.with_suffix(".json").read_text())["status"] == "complete"
    assert repair_log(tmp_path / "none.csv") is None


def test_a_log_name_taken_already_gets_a_suffix_and_a_taken_log_is_never_overwritten(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from app.engine import runlog

    # the clock set back a second: the next run's name is the last one's; it had been refused (409)
    monkeypatch.setattr(runlog.time, "time", lambda: 1_800_000_000.25)
    first = runlog.new_log_name(tmp_path, "run")
    assert first.startswith("run-") and first.endswith("-250")
    w = _log_cut_short(tmp_path, 3)
    w.rename(tmp_path / f"{first}.csv")
    assert runlog.new_log_name(tmp_path, "run") == f"{first}-2"
    (tmp_path / f"{first}-2").mkdir()  # a protocol's folder takes a name too
    assert runlog.new_log_name(tmp_path, "run") == f"{first}-3"
    assert runlog.new_log_name(tmp_path, "rotary_friction") != f"{first}-3"
    assert runlog.new_log_name(tmp_path / "none", "run") == first
    before = (tmp_path / f"{first}.csv").read_bytes()
    with pytest.raises(FileExistsError, match="already exists"):
        runlog.RunLogWriter(tmp_path, first, {"rig": "rotary", "sample_rate_hz": 200.0, "p_atm_bar": 1.013,
                                              "working_pressure_bar": 3.0, "experiment": "x", "human": False})
    assert (tmp_path / f"{first}.csv").read_bytes() == before


def test_one_station_per_data_folder_and_a_killed_one_leaves_no_lock(tmp_path: Path) -> None:
    import subprocess
    import sys

    from app.storage import DataDirInUse, claim_data_dir, release_data_dir

    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from app.storage import claim_data_dir; "
                               "claim_data_dir(sys.argv[1]); print('held', flush=True); time.sleep(60)",
                               str(tmp_path)], stdout=subprocess.PIPE, text=True, cwd=Path(__file__).parents[1])
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(DataDirInUse, match=rf"in use by another station \(pid {holder.pid}\).*CWRR_DATA_DIR"):
            claim_data_dir(tmp_path)
    finally:
        holder.kill()
        holder.wait(10)
    claim_data_dir(tmp_path)  # the kernel dropped the dead holder's lock
    claim_data_dir(tmp_path / ".")  # claims in one process nest
    release_data_dir(tmp_path)
    release_data_dir(tmp_path)
    release_data_dir(tmp_path)  # one release too many does nothing
    assert (tmp_path / ".station.lock").read_text().strip().isdigit()
    (tmp_path / "a-file").write_text("")
    with pytest.raises(ValueError, match=r"data folder .*a-file/data cannot be written .*CWRR_DATA_DIR"):
        claim_data_dir(tmp_path / "a-file" / "data")


def test_an_unreachable_postgresql_is_refused_without_leaking_the_password() -> None:
    with pytest.raises(ValueError, match="cannot reach the database") as err:
        Store("postgresql://lab:s3cret@127.0.0.1:1/cwrr")
    assert "s3cret" not in str(err.value) and "lab:***@127.0.0.1:1" in str(err.value)


def test_a_store_made_before_sessions_gains_the_columns(tmp_path: Path) -> None:
    import sqlite3

    path = tmp_path / "old.sqlite3"
    db = sqlite3.connect(path)
    db.execute("CREATE TABLE runs (id INTEGER PRIMARY KEY AUTOINCREMENT, kind TEXT NOT NULL, status TEXT NOT NULL, "
               "started REAL NOT NULL, ended REAL, spec TEXT NOT NULL, metrics TEXT, result TEXT, "
               "log_csv TEXT NOT NULL, person TEXT NOT NULL DEFAULT '', notes TEXT NOT NULL DEFAULT '')")
    db.execute("INSERT INTO runs(kind,status,started,spec,log_csv) VALUES ('workout','complete',1.0,'{}','')")
    db.execute("CREATE TABLE sessions (id INTEGER PRIMARY KEY AUTOINCREMENT, person TEXT NOT NULL, "
               "notes TEXT NOT NULL DEFAULT '', created REAL NOT NULL)")
    db.execute("INSERT INTO sessions(person, notes, created) VALUES ('P-001', 'left', 1.0)")
    db.commit()
    db.close()
    s = Store(f"sqlite:///{path}")
    assert s.run(1)["session_id"] is None  # type: ignore[index]
    assert s.session(1)["notes_edited"] is None and s.set_session_notes(1, "left; edited")  # type: ignore[index]
    assert s.session(1)["notes_at_open"] == "left"  # type: ignore[index]
    assert s.run(1)["notes_edited"] is None and s.set_run_notes(1, "edited")  # type: ignore[index]


def test_stores_opened_at_once_on_one_database_all_come_up(url: str) -> None:
    """Two stations (or a station and a script) starting together: making the schema is serialised
    (PostgreSQL's CREATE TABLE IF NOT EXISTS alone races with itself)."""
    import threading

    errors: list[BaseException] = []
    stores: list[Store] = []
    gate = threading.Barrier(6)

    def open_one() -> None:
        try:
            gate.wait(10)
            stores.append(Store(url))
        except BaseException as exc:  # collected for the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=open_one) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not errors, errors
    rid = stores[0].run_started("workout", {}, "")
    assert all(s.run(rid) is not None for s in stores)
    for s in stores:
        s.close()


def test_the_radar_compares_a_run_with_like_runs_only(url: str) -> None:
    """The viser radar sets a workout beside the latest complete run of each other controller for the
    same person, scenario and target: another person's arm, another target, or a run stopped half way
    (scored over what it reached) would make the controllers differ for reasons of their own."""
    from app.api.compare import latest_per_controller

    store = Store(url)  # on PostgreSQL too where a server runs: the person filter is SQL

    def run(controller: str, person: str, mae: float, status: str = "complete", scenario: str = "SC-1",
            target: float = 1.2) -> int:
        rid = store.run_started("workout", {"scenario": scenario, "controller": controller, "target_nm": target,
                                            "person": person}, "")
        store.run_finished(rid, status, {"mae": mae}, None)
        return rid

    run("pid", "P-1", 0.20)
    run("default", "P-1", 0.30)
    run("fuzzy", "P-2", 0.11)  # another person
    run("default", "P-1", 0.31, status="stopped")  # later, but cut short
    run("default", "P-1", 0.32, target=0.6)  # another target
    run("pid", "P-1", 0.21, scenario="SC-2")  # another scenario
    ref = run("fuzzy", "P-1", 0.10, status="stopped")  # the run shown is shown whatever its ending
    got = latest_per_controller(store, ref)
    assert got == {"fuzzy": {"mae": 0.10}, "default": {"mae": 0.30}, "pid": {"mae": 0.20}}
    # a metric a run could not give is stored as null: such a run has no polygon (the chart had raised)
    store.run_finished(run("default", "P-1", 0.29), "complete", {"mae": 0.29, "evar": None}, None)
    assert latest_per_controller(store, ref) == got
    blank = run("pid", "P-1", 0.5)
    store.run_finished(blank, "stopped", {"mae": None}, None)
    assert latest_per_controller(store, blank) == {}
    assert latest_per_controller(store, run("pid", "", 0.5)) == {"pid": {"mae": 0.5}}  # nobody named: no one else
    assert latest_per_controller(store, 999) == {}


def test_strict_json_writes_what_a_fit_could_not_give_as_null() -> None:
    import json

    import numpy as np

    from app.storage import strict_json

    text = strict_json({"sd": {"a": float("nan"), "b": np.float64(np.inf)}, "v": [1.5, -np.inf]}, indent=1)
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"sd": {"a": None, "b": None}, "v": [1.5, None]}
    assert text.startswith("{\n ")  # indented as asked
    # what JSON has no type for goes through ``default``, and what that gives is cleaned too
    from decimal import Decimal

    assert strict_json({"x": Decimal("NaN"), "y": Decimal("0.5")}, default=float) == '{"x": null, "y": 0.5}'
    with pytest.raises(TypeError):
        strict_json({"x": Decimal("0.5")})


def test_a_station_keeps_its_id_in_its_folder_whatever_its_host_is_called(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A container recreated on the same volume gets a new host name; it is the same station and must
    call its own killed runs interrupted (its runs had been matched on host and folder)."""
    import socket

    from app.api.main import station_name

    first = station_name(tmp_path)
    sid = (tmp_path / ".station-id").read_text().strip()
    assert first.split(" ")[0] == sid and len(sid) == 32 and f"{socket.gethostname()}:{tmp_path.resolve()}" in first
    monkeypatch.setattr(socket, "gethostname", lambda: "3b9e4a7c0d12")
    again = station_name(tmp_path)
    assert again.split(" ")[0] == sid and "3b9e4a7c0d12" in again
    assert station_name(tmp_path / "other").split(" ")[0] != sid  # another folder, another station


def test_a_long_log_is_repaired_from_its_tail_and_its_rows_counted_whole(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The repair reads only the end of a log (an unsynced second at most); a log longer than that
    window keeps every row before it, and the rows are still counted from the start."""
    import json

    from app.engine import runlog
    from app.engine.diagnosis.logs import read_log

    monkeypatch.setattr(runlog, "REPAIR_TAIL_BYTES", 700)  # a few rows: the window starts mid-row
    csv = _log_cut_short(tmp_path, 400)
    assert csv.stat().st_size > 10 * 700
    with open(csv, "ab") as fh:
        fh.write(b"\0" * 300)  # lost pages after the cut row
    assert runlog.repair_log(csv) == 400
    assert len(read_log(csv).t) == 400 and json.loads(csv.with_suffix(".json").read_text())["rows"] == 400


def test_a_store_whose_database_dropped_its_connection_reconnects(url: str) -> None:
    """A PostgreSQL restarted under a running station: the store had kept its dead connection, and every
    call failed until the station itself was restarted."""
    if not url.startswith("postgresql"):
        pytest.skip("a SQLite store has no connection to lose")
    import psycopg

    s = Store(url)
    sid = s.add_session("P-pg", "")
    with pytest.raises(psycopg.OperationalError):  # the server ends this connection, as a restart would
        s._db.execute("SELECT pg_terminate_backend(pg_backend_pid())")
    assert s._db.closed or s._db.broken
    assert s.session(sid)["person"] == "P-pg"  # type: ignore[index]  # on a new connection
    assert s.run_started("workout", {"scenario": "SC-1"}, "") > 0
    s.close()


def test_a_run_a_kill_left_running_is_repaired_where_its_moved_folder_now_is(tmp_path: Path) -> None:
    """The crash repair looks for the log where the folder is now (the station's id moved with it)."""
    from app.api.main import repair_interrupted_logs, station_name

    first = tmp_path / "a"
    store = Store(f"sqlite:///{first}/cwrr.sqlite3", station=station_name(first))
    log = first / "runs" / "run-1.csv"
    log.parent.mkdir()
    log.write_text("t,z_a,z_b,u_a,u_b,p_a,p_b,p_s,theta,omega,torque\n0,1,1,0,10,1,1,8,0,0,0\n0.005,1,1,0,10,1")
    rid = store.run_started("workout", {}, str(log))
    store._db.close()  # killed: no close, no end of the run
    moved = tmp_path / "b"
    first.rename(moved)
    store = Store(f"sqlite:///{moved}/cwrr.sqlite3", station=station_name(moved))
    try:
        assert store.interrupted_at_open == [(rid, str(moved / "runs" / "run-1.csv"))]
        assert repair_interrupted_logs(store, moved) == [rid]  # the half-written last row cut back
        assert (moved / "runs" / "run-1.csv").read_text().splitlines()[-1] == "0,1,1,0,10,1,1,8,0,0,0"
        assert store.run(rid)["log_csv"] == str(moved / "runs" / "run-1.csv")  # type: ignore[index]
    finally:
        store.close()
