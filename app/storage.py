"""The run store: SQLite by default (standard library), PostgreSQL by URL.

Holds runs (workouts and identifications: spec, status, metrics, identified
parameters, the path of the run's time-series log), parameter sets and
therapy sessions. The time series themselves live in each run's fsynced CSV
log (:class:`~app.engine.runlog.RunLogWriter`), appended while the run goes;
the store points at it. Every write is one auto-committed statement, so a
crash leaves either the whole row or none of it.

URLs: ``sqlite:///PATH`` (WAL mode, so the API reads while the station writes)
or ``postgresql://user:pass@host:port/db`` (needs ``psycopg``, installed with
the project). The two dialects differ only in placeholders and column types.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import shutil
import sqlite3
import tempfile
import threading
import time
from collections.abc import Callable
from contextlib import closing
from pathlib import Path
from typing import Any


def strict_json(obj: Any, indent: int | None = None, default: Callable[[Any], Any] | None = None) -> str:
    """``obj`` as strict JSON: NaN and ±inf (an SD a fit could not give, say) become null.

    Python's own ``json.dumps`` writes them as the bare tokens ``NaN`` and
    ``Infinity``, which JavaScript's ``JSON.parse``, ``jq`` and most other
    readers refuse (the API's and the browsers' among them). ``default`` converts what JSON has no type for (as
    ``json.dumps``'s does), and its result is cleaned the same way.
    """

    def clean(o: Any) -> Any:
        if isinstance(o, float):
            return o if math.isfinite(o) else None
        if isinstance(o, dict):
            return {k: clean(v) for k, v in o.items()}
        if isinstance(o, list | tuple):
            return [clean(v) for v in o]
        if hasattr(o, "tolist"):  # numpy scalars and arrays
            return clean(o.tolist())
        if default is not None and not isinstance(o, str | int | bool | type(None)):
            return clean(default(o))
        return o

    return json.dumps(clean(obj), allow_nan=False, indent=indent)


_TABLES = """
CREATE TABLE IF NOT EXISTS runs (
    id {pk},
    kind TEXT NOT NULL,
    status TEXT NOT NULL,
    started {real} NOT NULL,
    ended {real},
    spec TEXT NOT NULL,
    metrics TEXT,
    result TEXT,
    log_csv TEXT NOT NULL,
    person TEXT NOT NULL DEFAULT '',
    notes TEXT NOT NULL DEFAULT '',
    session_id {int},
    notes_edited {real},
    station TEXT NOT NULL DEFAULT ''
);
CREATE TABLE IF NOT EXISTS param_sets (
    id {pk},
    kind TEXT NOT NULL,
    name TEXT NOT NULL,
    payload TEXT NOT NULL,
    created {real} NOT NULL
);
CREATE TABLE IF NOT EXISTS sessions (
    id {pk},
    person TEXT NOT NULL,
    notes TEXT NOT NULL DEFAULT '',
    created {real} NOT NULL,
    notes_edited {real},
    notes_at_open TEXT
);
"""
# PostgreSQL's REAL is 4 bytes: Unix times would lose whole seconds
_SQLITE = {"pk": "INTEGER PRIMARY KEY AUTOINCREMENT", "real": "REAL", "int": "INTEGER"}
_POSTGRES = {"pk": "BIGSERIAL PRIMARY KEY", "real": "DOUBLE PRECISION", "int": "BIGINT"}
_ADDED = (("runs", "session_id", "{int}"),  # sessions linked to runs
          ("runs", "notes_edited", "{real}"), ("sessions", "notes_edited", "{real}"),  # notes edited afterwards
          ("sessions", "notes_at_open", "TEXT"),
          ("runs", "station", "TEXT NOT NULL DEFAULT ''"))  # which station's run: one database, several rigs
"""Columns added since the first schema: (table, column, type): a store made before gains them on open."""


CONNECT_TIMEOUT_S = 10
"""How long a PostgreSQL server may take to answer a connection [s]: an address nobody answers had
held the station's start for the operating system's TCP timeout (minutes)."""


def database_dialect(url: str) -> str:
    """``"sqlite"`` or ``"postgresql"``: which store a database URL names.

    Raises:
        ValueError: For any other scheme, naming what is supported (the URL itself is not
            echoed: it may carry a password).
    """
    if url.startswith(("postgresql://", "postgres://")):
        return "postgresql"
    if url.startswith("sqlite:///"):
        return "sqlite"
    scheme = url.split(":", 1)[0] if ":" in url else "(none)"
    raise ValueError(f"database_url: scheme {scheme!r} is not supported; use sqlite:///PATH or "
                     "postgresql://USER:PASSWORD@HOST/DB")


def check_database(url: str) -> None:
    """Whether the store at ``url`` can be reached, without opening it as a store (which would mark
    this station's running runs interrupted before the server's own store could repair their logs).

    Raises:
        ValueError: Naming what is wrong (the password left out).
    """
    if database_dialect(url) == "sqlite":
        return  # its folder is the data folder's check
    import psycopg

    try:
        psycopg.connect(url, connect_timeout=CONNECT_TIMEOUT_S).close()
    except psycopg.Error as exc:
        raise ValueError(f"cannot reach the database at {redact_url(url)}: {str(exc).strip()}") from None


def sqlite_path(url: str) -> Path:
    """The file of a ``sqlite:///PATH`` URL.

    Raises:
        ValueError: For any other scheme, naming what is supported.
    """
    if database_dialect(url) != "sqlite":
        raise ValueError(f"database_url: {redact_url(url)} is not a sqlite:///PATH URL")
    return Path(url[len("sqlite:///"):])


def redact_url(url: str) -> str:
    """The URL without its password (for messages)."""
    head, at, tail = url.rpartition("@")
    if not at:
        return url
    scheme, _, cred = head.partition("://")
    return f"{scheme}://{cred.split(':', 1)[0]}:***@{tail}"


def _unavailable() -> tuple[type[Exception], ...]:
    try:
        import psycopg
    except ImportError:  # pragma: no cover - psycopg is a project dependency
        return (sqlite3.OperationalError,)
    return (sqlite3.OperationalError, psycopg.OperationalError)


_UNAVAILABLE = _unavailable()
"""What a store that cannot be used now raises: a full disk, a locked file, a database gone."""


class StoreUnavailable(RuntimeError):
    """The store cannot take or give a statement now (a full disk, a locked or unreachable database)."""


class DataDirInUse(RuntimeError):
    """Another process holds the data folder (its station is running)."""


_CLAIMS: dict[Path, list[Any]] = {}  # resolved folder → [open lock file, claims in this process]
_CLAIMS_LOCK = threading.Lock()


def claim_data_dir(path: str | Path) -> None:
    """Hold the data folder ``path`` for this process, or raise :class:`DataDirInUse`.

    One station per folder: two would each mark the other's running runs
    interrupted and repair (cut back) logs still being written, and on a
    rig's configuration both would drive it. The claim is an exclusive
    ``flock`` on ``PATH/.station.lock``, which the kernel drops when the
    process ends however it ends, so a killed station leaves no stale lock.
    Claims in one process nest (the command line holds the folder from
    before compiling; the server's lifespan claims it again).

    Args:
        path: The station's data folder (created if missing).

    Raises:
        DataDirInUse: Another process holds it; the message names its pid.
        ValueError: The folder cannot be made or written.
    """
    folder = Path(path).resolve()
    with _CLAIMS_LOCK:
        if folder in _CLAIMS:
            _CLAIMS[folder][1] += 1
            return
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fh = open(folder / ".station.lock", "a+", encoding="utf-8")  # held open: the lock lives with it
        except OSError as exc:
            raise ValueError(f"data folder {folder} cannot be written ({exc.strerror or exc}); "
                             f"give the station one it may write (CWRR_DATA_DIR or --data-dir)") from None
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "unknown"
            fh.close()
            raise DataDirInUse(f"data folder {folder} is in use by another station (pid {holder}); stop it, "
                               f"or give this one its own folder (CWRR_DATA_DIR or --data-dir)") from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"{os.getpid()}\n")
        fh.flush()
        _CLAIMS[folder] = [fh, 1]


def release_data_dir(path: str | Path) -> None:
    """Give back one :func:`claim_data_dir` of ``path``; the last one unlocks the folder."""
    folder = Path(path).resolve()
    with _CLAIMS_LOCK:
        claim = _CLAIMS.get(folder)
        if claim is None:
            return
        claim[1] -= 1
        if claim[1] <= 0:
            del _CLAIMS[folder]
            claim[0].close()  # closing the file drops the flock


class Store:
    """Runs, parameter sets and sessions (thread-safe: one connection behind a lock).

    Args:
        url: ``sqlite:///PATH`` (the folder is created) or ``postgresql://…``.
        station: Which station writes through this store: its lasting id,
            then (after a space) whatever helps a reader, e.g. the host and
            data folder. A lab may keep several rigs' runs in one PostgreSQL
            database, and a station starting may only call its own runs
            interrupted, not those another station is running; its own are
            those whose station starts with the same id (the host name of a
            container recreated on the same volume changes, the id does not).

    Attributes:
        interrupted_at_open: ``(run id, log CSV path)`` of each run of this
            station (or of none named) found still running when the store
            opened (cut short by a crash or kill), now marked ``interrupted``.
    """

    def __init__(self, url: str, station: str = "") -> None:
        self._lock = threading.Lock()
        self._url = url
        self.station = station
        self.dialect = database_dialect(url)
        if self.dialect == "postgresql":
            try:
                import psycopg
            except ImportError as exc:  # pragma: no cover - psycopg is a project dependency
                raise ValueError("database_url is PostgreSQL but psycopg is not installed") from exc
            try:
                self._db: Any = psycopg.connect(url, autocommit=True, connect_timeout=CONNECT_TIMEOUT_S)
            except psycopg.OperationalError as exc:
                raise ValueError(f"cannot reach the database at {redact_url(url)}: {str(exc).strip()}") from None
            ddl = _TABLES.format(**_POSTGRES)
            with self._lock:
                # two stations (or a station and a test) starting at once on one database: PostgreSQL's
                # CREATE TABLE IF NOT EXISTS is not safe against a concurrent one (a unique violation on
                # pg_type), so the schema is made under a session advisory lock
                self._db.execute("SELECT pg_advisory_lock(hashtext('cwrr-store-schema'))")
                try:
                    for stmt in filter(str.strip, ddl.split(";")):
                        self._db.execute(stmt)
                    for table, col, kind in _ADDED:
                        self._db.execute(f"ALTER TABLE {table} ADD COLUMN IF NOT EXISTS {col} "
                                         + kind.format(**_POSTGRES))
                finally:
                    self._db.execute("SELECT pg_advisory_unlock(hashtext('cwrr-store-schema'))")
        else:
            path = sqlite_path(url)
            path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
            # the same race on SQLite: in a loaded CI run, one of six stores opened together failed
            # with "database is locked" while switching to WAL or making the schema, so (as with
            # PostgreSQL's advisory lock above) the schema is made under a file lock
            with self._lock, open(path.with_name(path.name + ".schema-lock"), "a") as gate:
                fcntl.flock(gate, fcntl.LOCK_EX)  # released when the file closes
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.executescript(_TABLES.format(**_SQLITE))
                have = {t: {r[1] for r in self._db.execute(f"PRAGMA table_info({t})").fetchall()}
                        for t in {t for t, _, _ in _ADDED}}
                for table, col, kind in _ADDED:  # SQLite has no ADD COLUMN IF NOT EXISTS
                    if col not in have[table]:
                        self._db.execute(f"ALTER TABLE {table} ADD COLUMN {col} " + kind.format(**_SQLITE))
        # a run still "running" at start-up was cut short by a crash or kill;
        # its log holds everything up to the last flush (the station repairs the logs of these:
        # app.engine.runlog.repair_log)
        key = station.split(" ", 1)[0]
        self.interrupted_at_open: list[tuple[int, str]] = [
            (int(r["id"]), self._log_now(str(r["log_csv"] or ""), str(r["station"] or ""))) for r in
            self._exec("UPDATE runs SET status='interrupted' WHERE status='running' "
                       "AND (station = '' OR station = ? OR station LIKE ?) RETURNING id, log_csv, station",
                       (key, f"{key} %"))]

    def close(self) -> None:
        """Close the connection."""
        with self._lock:
            self._db.close()

    def _exec(self, sql: str, args: tuple[Any, ...] = ()) -> list[dict[str, Any]]:
        """Run one statement; rows as dicts (``?`` placeholders in both dialects)."""
        if self.dialect == "postgresql":
            sql = sql.replace("?", "%s")
        with self._lock:
            for attempt in (1, 2):
                try:
                    cur = self._db.execute(sql, args)
                    if cur.description is None:
                        return []
                    names = [d[0] for d in cur.description]
                    return [dict(zip(names, row, strict=True)) for row in cur.fetchall()]
                except _UNAVAILABLE as exc:  # the API answers 503 with this, not a bare 500
                    if attempt == 1 and self._reconnected():
                        continue
                    raise StoreUnavailable(f"the run store cannot be used now: {str(exc).strip()}") from exc
        raise AssertionError("unreachable")  # pragma: no cover

    def _reconnected(self) -> bool:
        """A new PostgreSQL connection in place of one the server dropped (restarted, say); False if none.

        The station had kept a dead connection until it was restarted itself: every store call
        failed after a database restart.
        """
        if self.dialect != "postgresql" or not (self._db.closed or self._db.broken):
            return False
        import psycopg

        try:
            db = psycopg.connect(self._url, autocommit=True, connect_timeout=CONNECT_TIMEOUT_S)
        except psycopg.OperationalError:
            return False
        self._db.close()
        self._db = db
        return True

    def _insert(self, sql: str, args: tuple[Any, ...]) -> int:
        return int(self._exec(sql + " RETURNING id", args)[0]["id"])

    # ------------------------------------------------------------------ runs

    def run_started(self, kind: str, spec: dict[str, Any], log_csv: str) -> int:
        """Record a new run; returns its id."""
        sid = spec.get("session_id")
        return self._insert(
            "INSERT INTO runs(kind, status, started, spec, log_csv, person, notes, session_id, station) "
            "VALUES (?,?,?,?,?,?,?,?,?)",
            (kind, "running", time.time(), strict_json(spec), log_csv, str(spec.get("person", "")),
             str(spec.get("notes", "")), int(sid) if sid is not None else None, self.station))

    def run_finished(self, run_id: int, status: str, metrics: dict[str, Any] | None,
                     result: dict[str, Any] | None) -> None:
        """Record how a run ended."""
        self._exec("UPDATE runs SET status=?, ended=?, metrics=?, result=? WHERE id=?",
                   (status, time.time(), strict_json(metrics) if metrics is not None else None,
                    strict_json(result) if result is not None else None, run_id))

    def runs(self, limit: int = 100, offset: int = 0, kind: str | None = None,
             session_id: int | None = None, person: str | None = None,
             with_result: bool = True) -> list[dict[str, Any]]:
        """Newest first, optionally of one kind, one session or one person (each given filter applies).

        ``with_result=False`` leaves each run's ``result`` out (None), unread: a gap diagnosis's
        report alone is tens of kilobytes, and a list of runs rarely needs them.
        """
        where: list[str] = []
        args: list[Any] = []
        if kind:
            where.append("kind=?")
            args.append(kind)
        if session_id is not None:
            where.append("session_id=?")
            args.append(session_id)
        if person is not None:
            where.append("person=?")
            args.append(person)
        cols = "*" if with_result else "id, kind, status, started, ended, spec, metrics, NULL AS result, log_csv, " \
            "person, notes, session_id, notes_edited, station"
        q = f"SELECT {cols} FROM runs" + (" WHERE " + " AND ".join(where) if where else "") + \
            " ORDER BY id DESC LIMIT ? OFFSET ?"
        return [self._run(r) for r in self._exec(q, (*args, limit, offset))]

    def set_run_notes(self, run_id: int, notes: str) -> bool:
        """Replace a run's notes (an observation made after it); False if there is no such run.

        When they were last changed is kept beside them (``notes_edited``).
        """
        return bool(self._exec("UPDATE runs SET notes=?, notes_edited=? WHERE id=? RETURNING id",
                               (notes, time.time(), run_id)))

    def run(self, run_id: int) -> dict[str, Any] | None:
        """One run, or None."""
        rows = self._exec("SELECT * FROM runs WHERE id=?", (run_id,))
        return self._run(rows[0]) if rows else None

    def _run(self, d: dict[str, Any]) -> dict[str, Any]:
        for k in ("spec", "metrics", "result"):
            d[k] = json.loads(d[k]) if d[k] else None
        d["log_csv"] = self._log_now(d.get("log_csv") or "", d.get("station") or "")
        return d

    def _log_now(self, log_csv: str, station: str) -> str:
        """Where a run's log is now.

        A run keeps its log's path as written, under its station's data folder then. A folder moved
        (a new disk, a backup restored on another machine, a volume mounted elsewhere) keeps its
        station id (``.station-id`` moves with it), so a log of this station's that is not where it
        was written is looked for at the same place under the folder's new path. Without this, every
        run of a moved folder had lost its series, exports and diagnosis though its logs were there.
        Another station's runs (a shared PostgreSQL database) keep their paths.
        """
        if not log_csv or not self.station or os.path.exists(log_csv):
            return log_csv
        sid, _, then = station.partition(" ")
        mine, _, now = self.station.partition(" ")
        old, new = then.partition(":")[2], now.partition(":")[2]  # "host:folder"; a host name has no colon
        if sid != mine or not old or not new or old == new:
            return log_csv
        try:
            moved = Path(new) / Path(log_csv).relative_to(old)
        except ValueError:
            return log_csv
        return str(moved) if moved.exists() else log_csv

    # ------------------------------------------------------------ param sets

    def save_params(self, kind: str, name: str, payload: dict[str, Any]) -> int:
        """Store a validated parameter set; returns its id."""
        return self._insert("INSERT INTO param_sets(kind, name, payload, created) VALUES (?,?,?,?)",
                            (kind, name, json.dumps(payload), time.time()))

    def param_set(self, set_id: int) -> dict[str, Any] | None:
        """One stored parameter set, or None."""
        rows = self._exec("SELECT * FROM param_sets WHERE id=?", (set_id,))
        return dict(rows[0], payload=json.loads(rows[0]["payload"])) if rows else None

    def param_sets(self, kind: str | None = None) -> list[dict[str, Any]]:
        """Stored parameter sets, newest first."""
        q = "SELECT * FROM param_sets" + (" WHERE kind=?" if kind else "") + " ORDER BY id DESC"
        return [dict(r, payload=json.loads(r["payload"])) for r in self._exec(q, (kind,) if kind else ())]

    # --------------------------------------------------------------- sessions

    def add_session(self, person: str, notes: str = "") -> int:
        """Open a session for a pseudonymous person id."""
        return self._insert("INSERT INTO sessions(person, notes, created) VALUES (?,?,?)",
                            (person, notes, time.time()))

    def set_session_notes(self, session_id: int, notes: str) -> bool:
        """Replace a session's notes (written after the exercises, as often as not); False if there is no such session.

        When they were last changed is kept beside them (``notes_edited``), and
        the notes the session opened with are kept once (``notes_at_open``), so
        the record shows what was written when.
        """
        rows = self._exec("UPDATE sessions SET notes_at_open=COALESCE(notes_at_open, notes), notes=?, notes_edited=? "
                          "WHERE id=? RETURNING id", (notes, time.time(), session_id))
        return bool(rows)

    def session(self, session_id: int) -> dict[str, Any] | None:
        """One session, or None."""
        rows = self._exec("SELECT * FROM sessions WHERE id=?", (session_id,))
        return rows[0] if rows else None

    def sessions(self, person: str | None = None, limit: int = 100, offset: int = 0) -> list[dict[str, Any]]:
        """Sessions, newest first (optionally one person's)."""
        q = "SELECT * FROM sessions" + (" WHERE person=?" if person else "") + " ORDER BY id DESC LIMIT ? OFFSET ?"
        return self._exec(q, ((person,) if person else ()) + (limit, offset))

    def session_run_ids(self, session_ids: list[int]) -> dict[int, list[int]]:
        """Each session's run ids, newest first, in one query: listing sessions had read every run's
        whole row (a diagnosis's report among them) to give its id."""
        if not session_ids:
            return {}
        out: dict[int, list[int]] = {int(i): [] for i in session_ids}
        ids = list(out)
        for k in range(0, len(ids), 500):  # an SQLite before 3.32 takes at most 999 parameters
            part = ids[k:k + 500]
            marks = ",".join("?" * len(part))
            for r in self._exec(f"SELECT id, session_id FROM runs WHERE session_id IN ({marks}) ORDER BY id DESC",
                                tuple(part)):
                out[int(r["session_id"])].append(int(r["id"]))
        return out


SKIPPED_IN_BACKUP = (".station.lock",)
"""Files of a data folder a backup leaves out: the running station's lock (the database's own files are
written as one consistent snapshot instead, and its schema lock and write-ahead files are left out)."""


def backup_data_dir(data_dir: str | Path, out: str | Path, db_url: str) -> dict[str, Any]:
    """Copy a station's data folder to ``out``, consistently, while its station may be running.

    The SQLite store is copied with SQLite's online backup (one consistent snapshot, however busy the
    station is; a plain copy of a database in write-ahead mode can miss the last writes or be torn),
    then every other file: run logs, imported logs, diagnosis logs, ``.station-id``. A run the snapshot
    holds as running is one a restored station will call interrupted and cut back to its last whole
    sample, as after a kill. The copy is made beside ``out`` and renamed into place at the end, so a
    failed backup leaves no folder that looks like one. Restore by starting a station on the copy
    (``--data-dir``): its runs' logs are found there (:meth:`Store._log_now`).

    Args:
        data_dir: The station's data folder.
        out: The backup's folder: it must not exist yet, nor lie inside the data folder.
        db_url: The station's database URL: a PostgreSQL database is not copied (that is ``pg_dump``'s
            work); only the folder's files are.

    Returns:
        ``out``, the ``database`` copied (its file in the backup, or what to do instead), the ``runs``
        it holds, and the ``files`` and ``bytes`` copied besides it.

    Raises:
        ValueError: ``data_dir`` is not a folder, ``out`` exists or lies inside it.
    """
    src, dst = Path(data_dir).resolve(), Path(out).resolve()
    if not src.is_dir():
        raise ValueError(f"data folder {src} does not exist")
    if dst.exists():
        raise ValueError(f"{dst} exists: a backup goes to a new folder")
    if dst.is_relative_to(src):
        raise ValueError(f"{dst} lies inside the data folder {src}: each backup would hold the last")
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.partial-", dir=dst.parent))
    try:
        db_files: set[Path] = set()
        runs: int | None = None
        if database_dialect(db_url) == "sqlite":
            db = sqlite_path(db_url).resolve()
            db_files = {db.with_name(db.name + sfx) for sfx in ("", "-wal", "-shm", "-journal", ".schema-lock")}
            inside = db.is_relative_to(src)
            copy = tmp / (db.relative_to(src) if inside else Path(db.name))
            copy.parent.mkdir(parents=True, exist_ok=True)
            with closing(sqlite3.connect(str(db), timeout=30)) as live, closing(sqlite3.connect(str(copy))) as snap:
                live.backup(snap)
                runs = int(snap.execute("SELECT COUNT(*) FROM runs").fetchone()[0])
            database = str(dst / copy.relative_to(tmp)) + ("" if inside else f" (from {db}, outside the folder)")
        else:
            database = f"not copied: {redact_url(db_url)} is PostgreSQL; back it up with pg_dump"
        files = size = 0
        for path in sorted(src.rglob("*")):
            if path.is_dir() or path in db_files or path.name in SKIPPED_IN_BACKUP:
                continue
            target = tmp / path.relative_to(src)
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                shutil.copy2(path, target)
            except FileNotFoundError:  # removed while the backup ran (a failed upload's temporary folder)
                continue
            files += 1
            size += target.stat().st_size
        tmp.rename(dst)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {"out": str(dst), "database": database, "runs": runs, "files": files, "bytes": size}
