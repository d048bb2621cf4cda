"""The embedded run store (SQLite, standard library).

Holds runs (workouts and identifications: spec, status, metrics, identified
parameters, the path of the run's time-series log), parameter sets and
sessions. The time series themselves live in each run's fsynced CSV log
(:class:`~app.engine.runlog.RunLogWriter`), appended while the run goes;
the store points at it. SQLite runs in WAL mode so the API reads while the
station writes.

Only ``sqlite:///PATH`` URLs are implemented; see README for PostgreSQL.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL,
    status TEXT NOT NULL,
    started REAL NOT NULL,
    ended REAL,
    spec TEXT NOT NULL,
    metrics TEXT,
    result TEXT,
    log_csv TEXT NOT NULL,
    person TEXT NOT NULL DEFAULT '',
    notes TEXT NOT NULL DEFAULT ''
);
CREATE TABLE IF NOT EXISTS param_sets (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL,
    name TEXT NOT NULL,
    payload TEXT NOT NULL,
    created REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS sessions (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    person TEXT NOT NULL,
    notes TEXT NOT NULL DEFAULT '',
    created REAL NOT NULL
);
"""


def sqlite_path(url: str) -> Path:
    """The file of a ``sqlite:///PATH`` URL.

    Raises:
        ValueError: For any other scheme, naming what is supported.
    """
    prefix = "sqlite:///"
    if not url.startswith(prefix):
        scheme = url.split(":", 1)[0] if ":" in url else url
        raise ValueError(f"database_url scheme {scheme!r} is not supported; use sqlite:///PATH")
    return Path(url[len(prefix):])


class Store:
    """Runs, parameter sets and sessions in one SQLite file (thread-safe).

    Args:
        url: ``sqlite:///PATH`` (the folder is created).
    """

    def __init__(self, url: str) -> None:
        path = sqlite_path(url)
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
        self._db.row_factory = sqlite3.Row
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.executescript(SCHEMA)
            # a run still "running" at start-up was cut short by a crash or kill;
            # its log holds everything up to the last flush
            self._db.execute("UPDATE runs SET status='interrupted' WHERE status='running'")

    def close(self) -> None:
        """Close the connection."""
        with self._lock:
            self._db.close()

    # ------------------------------------------------------------------ runs

    def run_started(self, kind: str, spec: dict[str, Any], log_csv: str) -> int:
        """Record a new run; returns its id."""
        with self._lock:
            cur = self._db.execute(
                "INSERT INTO runs(kind, status, started, spec, log_csv, person, notes) VALUES (?,?,?,?,?,?,?)",
                (kind, "running", time.time(), json.dumps(spec), log_csv, str(spec.get("person", "")),
                 str(spec.get("notes", ""))))
            return int(cur.lastrowid or 0)

    def run_finished(self, run_id: int, status: str, metrics: dict[str, Any] | None,
                     result: dict[str, Any] | None) -> None:
        """Record how a run ended."""
        with self._lock:
            self._db.execute("UPDATE runs SET status=?, ended=?, metrics=?, result=? WHERE id=?",
                             (status, time.time(), json.dumps(metrics) if metrics is not None else None,
                              json.dumps(result, default=float) if result is not None else None, run_id))

    def runs(self, limit: int = 100, offset: int = 0, kind: str | None = None) -> list[dict[str, Any]]:
        """Newest first."""
        q = "SELECT * FROM runs" + (" WHERE kind=?" if kind else "") + " ORDER BY id DESC LIMIT ? OFFSET ?"
        args: tuple[Any, ...] = ((kind,) if kind else ()) + (limit, offset)
        with self._lock:
            return [self._run(r) for r in self._db.execute(q, args).fetchall()]

    def run(self, run_id: int) -> dict[str, Any] | None:
        """One run, or None."""
        with self._lock:
            r = self._db.execute("SELECT * FROM runs WHERE id=?", (run_id,)).fetchone()
        return self._run(r) if r is not None else None

    @staticmethod
    def _run(r: sqlite3.Row) -> dict[str, Any]:
        d = dict(r)
        for k in ("spec", "metrics", "result"):
            d[k] = json.loads(d[k]) if d[k] else None
        return d

    # ------------------------------------------------------------ param sets

    def save_params(self, kind: str, name: str, payload: dict[str, Any]) -> int:
        """Store a validated parameter set; returns its id."""
        with self._lock:
            cur = self._db.execute("INSERT INTO param_sets(kind, name, payload, created) VALUES (?,?,?,?)",
                                   (kind, name, json.dumps(payload), time.time()))
            return int(cur.lastrowid or 0)

    def param_set(self, set_id: int) -> dict[str, Any] | None:
        """One stored parameter set, or None."""
        with self._lock:
            r = self._db.execute("SELECT * FROM param_sets WHERE id=?", (set_id,)).fetchone()
        return dict(r, payload=json.loads(r["payload"])) if r is not None else None

    def param_sets(self, kind: str | None = None) -> list[dict[str, Any]]:
        """Stored parameter sets, newest first."""
        q = "SELECT * FROM param_sets" + (" WHERE kind=?" if kind else "") + " ORDER BY id DESC"
        with self._lock:
            rows = self._db.execute(q, (kind,) if kind else ()).fetchall()
        return [dict(r, payload=json.loads(r["payload"])) for r in rows]

    # --------------------------------------------------------------- sessions

    def add_session(self, person: str, notes: str = "") -> int:
        """Open a session for a pseudonymous person id."""
        with self._lock:
            cur = self._db.execute("INSERT INTO sessions(person, notes, created) VALUES (?,?,?)",
                                   (person, notes, time.time()))
            return int(cur.lastrowid or 0)

    def sessions(self) -> list[dict[str, Any]]:
        """All sessions, newest first."""
        with self._lock:
            return [dict(r) for r in self._db.execute("SELECT * FROM sessions ORDER BY id DESC").fetchall()]
