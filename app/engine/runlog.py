"""Run logs: the fixed ``NAME.csv`` + ``NAME.json`` pair, appended as the run goes.

Durability: rows are buffered and handed to the operating system at least
once per ``write_every_s`` of wall time (default 0.2 s) and made durable with
``fsync`` at least once per ``flush_every_s`` (default 0.5 s). A ``kill -9``
of the process loses only what the operating system had not been handed (the
kernel keeps what was written), an operating-system crash what had not been
synced: both well inside the last second. With ``threaded=True`` (the paced
engine) two threads do this, one writing and one syncing: a disk busy with
something else (a CI machine installing packages beside the station) can
stall an ``fsync`` for most of a second, and neither the control loop nor the
hand-over of rows to the kernel may wait for it. The JSON metadata is written
atomically (temporary file + rename) at the start with ``"status":
"running"`` and rewritten at the end with ``"complete"`` (or
``"interrupted"``), so a reader never sees a half-written JSON.

A log left ``"running"`` by a killed process, or by an operating system that
went down before its last ``fsync``, can end in a partial line or in zeros
where unsynced pages were lost; :func:`repair_log` (run by the station on the
next start for each run the store finds still running) cuts it back to its
last whole row and marks it ``"interrupted"``, so every reader takes it.
"""

from __future__ import annotations

import json
import os
import re
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from app.engine.sim import LOG_COLUMNS

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so readers see either the old or the new file."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def new_log_name(directory: Path | str, prefix: str) -> str:
    """A name for a new log (or log folder) in ``directory``: ``PREFIX-YYYYMMDD-HHMMSS-mmm``.

    The local time to the millisecond; a name already taken there (the
    computer's clock set back, an NTP step) gets ``-2``, ``-3``, … after it,
    so a run is never refused for its name.
    """
    now = time.time()
    name = f"{prefix}-{time.strftime('%Y%m%d-%H%M%S', time.localtime(now))}-{int(now * 1e3) % 1000:03d}"
    d = Path(directory)
    taken = {p.name for p in d.glob(f"{name}*")} if d.is_dir() else set()
    candidate, n = name, 1
    while any(t == candidate or t.startswith(f"{candidate}.") for t in taken):
        n += 1
        candidate = f"{name}-{n}"
    return candidate


class RunLogWriter:
    """Appends one run's rows to ``DIR/NAME.csv`` and keeps ``DIR/NAME.json``.

    Args:
        directory: Folder of the log pair (created if missing).
        name: Log name (letters, digits, ``_.-``).
        meta: Metadata; must hold the fixed keys ``rig``,
            ``sample_rate_hz``, ``p_atm_bar``, ``working_pressure_bar``,
            ``experiment``, ``human``.
        flush_every_s: Longest wall time between durable flushes (``fsync``) [s].
        threaded: Write and ``fsync`` from background threads (``append`` never touches the disk).
        write_every_s: With ``threaded``, longest wall time between hand-overs of rows to the
            operating system [s] (what a killed process can lose).
    """

    REQUIRED_META = ("rig", "sample_rate_hz", "p_atm_bar", "working_pressure_bar", "experiment", "human")

    def __init__(self, directory: Path | str, name: str, meta: dict[str, Any], flush_every_s: float = 0.5,
                 threaded: bool = False, write_every_s: float = 0.2) -> None:
        if not _NAME.match(name):
            raise ValueError(f"log name {name!r} must be 1–128 characters of letters, digits, '_', '.', '-'")
        missing = [k for k in self.REQUIRED_META if k not in meta]
        if missing:
            raise ValueError(f"log metadata lacks {', '.join(missing)}")
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.name = name
        self.csv_path = self.dir / f"{name}.csv"
        self.json_path = self.dir / f"{name}.json"
        self.meta = dict(meta, status="running", started_unix=time.time(), columns=list(LOG_COLUMNS))
        self.flush_every_s = flush_every_s
        self.write_every_s = min(write_every_s, flush_every_s)
        try:
            # "x": the check and the creation are one step, so no other writer's log is overwritten
            self._fh = open(self.csv_path, "x", encoding="utf-8", newline="")
        except FileExistsError:
            raise FileExistsError(f"log {self.csv_path} already exists") from None
        self._fh.write(",".join(LOG_COLUMNS) + "\n")
        self._buf: list[str] = []
        self._buf_lock = threading.Lock()  # appends vs. the writer taking the buffer
        self._io_lock = threading.Lock()  # one writer of the file at a time
        self._last_flush = time.monotonic()
        self.rows = 0
        self.error = ""  # the first failure to write or sync the log (a full disk), "" while none
        self._sync()
        atomic_write_text(self.json_path, json.dumps(self.meta, indent=1))
        self._done = threading.Event()
        self._threads: list[threading.Thread] = []
        if threaded:
            self._threads = [threading.Thread(target=self._write_loop, name=f"cwrr-log-{name}", daemon=True),
                             threading.Thread(target=self._sync_loop, name=f"cwrr-sync-{name}", daemon=True)]
            for th in self._threads:
                th.start()

    def _failed(self, exc: OSError) -> None:
        # the first failure is the cause (a full or failing disk); the writer keeps retrying, since
        # the io buffer keeps what it could not write and space may come back
        if not self.error:
            self.error = f"{exc.strerror or exc} ({self.csv_path})"

    def _write_loop(self) -> None:
        while not self._done.wait(self.write_every_s):
            try:
                self._write()
            except OSError as exc:  # a dead writer thread had left the run going on unrecorded
                self._failed(exc)

    def _sync_loop(self) -> None:
        # apart from the writer: an fsync that waits on a busy disk holds up neither the next
        # hand-over of rows to the kernel nor the loop; it syncs what was written until it began
        while not self._done.wait(self.flush_every_s):
            with self._io_lock:
                if self._fh.closed:
                    return
                fd = self._fh.fileno()
            try:
                os.fsync(fd)  # close() joins this thread (for up to 10 s) before it closes fd
            except OSError as exc:
                if self._fh.closed:
                    return  # closed after all, by a close() that stopped waiting for this sync
                self._failed(exc)
                continue
            self._last_flush = time.monotonic()

    @staticmethod
    def _line(row: Iterable[float]) -> str:
        # t to the microsecond at any age of the station's clock (six significant digits would
        # merge 200 Hz samples once it passes 1000 s); the channels to six significant digits
        it = iter(row)
        return ",".join([f"{next(it):.6f}", *(f"{v:.6g}" for v in it)])

    def append(self, row: Iterable[float]) -> None:
        """Add one row in :data:`LOG_COLUMNS` order."""
        line = self._line(row)
        with self._buf_lock:
            self._buf.append(line)
            self.rows += 1
        if not self._threads and time.monotonic() - self._last_flush >= self.flush_every_s:
            self.flush()

    def append_many(self, rows: Any) -> None:
        """Add many rows (an (n, 11) array) at once, then flush."""
        lines = [self._line(r) for r in rows]
        with self._buf_lock:
            self._buf.extend(lines)
            self.rows += len(lines)
        self.flush()

    def flush(self) -> None:
        """Write the buffered rows durably."""
        with self._io_lock:
            if self._write_locked():
                self._sync()

    def _write(self) -> None:
        """Hand the buffered rows to the operating system (the writer thread's step)."""
        with self._io_lock:
            self._write_locked()

    def _write_locked(self) -> bool:
        """:meth:`_write` with ``_io_lock`` held; False once the file is closed."""
        with self._buf_lock:
            lines, self._buf = self._buf, []
        if self._fh.closed:
            return False
        if lines:
            self._fh.write("\n".join(lines) + "\n")
            self._fh.flush()
        return True

    def _sync(self) -> None:
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._last_flush = time.monotonic()

    def close(self, status: str = "complete", **extra: Any) -> None:
        """Flush, close and mark the run ``status`` in the metadata.

        Never raises for a failing disk: the station must end the run whatever
        the disk does (a full disk had made STOP raise and left the run going).
        What failed is in :attr:`error`.
        """
        if self._fh.closed:
            return
        self._done.set()
        for th in self._threads:
            th.join(10.0)
        try:
            self.flush()
        except OSError as exc:
            self._failed(exc)
        with self._io_lock:
            try:
                self._fh.close()  # flushes again, and closes the file even when that fails
            except OSError as exc:
                self._failed(exc)
        self.meta.update(extra, status=status, rows=self.rows, ended_unix=time.time())
        if self.error:
            self.meta["write_error"] = self.error
        try:
            atomic_write_text(self.json_path, json.dumps(self.meta, indent=1))
        except OSError as exc:
            self._failed(exc)

    def __enter__(self) -> RunLogWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close("complete" if exc_type is None else "interrupted")


REPAIR_TAIL_BYTES = 4 << 20
"""How much of a log's end :func:`repair_log` searches for a cut row or lost pages [bytes] (a 1 kHz log
writes 80 kB a second; an operating system loses at most the last half second of them)."""


def repair_log(csv_path: Path | str) -> int | None:
    """Cut a log whose writer died back to its last whole row; mark it ``"interrupted"``.

    The rows after the first NUL byte (a page the operating system had not
    synced reads back as zeros) and a last line without its newline are
    dropped: a row is written with its newline in one piece, so a line that
    has it is whole. The JSON, if it still says ``"running"``, is rewritten
    atomically with ``"status": "interrupted"``, the rows kept and
    ``recovered_unix``. Only for a log nobody writes any more.

    Args:
        csv_path: The log's CSV.

    Returns:
        The whole rows kept, or None when the CSV does not exist.
    """
    path = Path(csv_path)
    if not path.is_file():
        return None
    with open(path, "rb+") as fh:
        size = fh.seek(0, os.SEEK_END)
        # only the tail can be unsynced (a second of rows at most), so the scan for lost pages and
        # the cut look at the last REPAIR_TAIL_BYTES; the rows are counted in chunks
        start = max(0, size - REPAIR_TAIL_BYTES)
        fh.seek(start)
        tail = fh.read()
        nul = tail.find(b"\0")
        end = start + tail.rfind(b"\n", 0, nul if nul >= 0 else len(tail)) + 1
        if end < size:
            fh.truncate(end)
            fh.flush()
            os.fsync(fh.fileno())
        fh.seek(0)
        newlines, left = 0, end
        while left > 0:
            chunk = fh.read(min(left, 1 << 20))
            newlines += chunk.count(b"\n")
            left -= len(chunk)
    rows = max(newlines - 1, 0)  # less the header
    meta_path = path.with_suffix(".json")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return rows  # no sidecar to mark (written atomically: there or not)
    if isinstance(meta, dict) and meta.get("status") == "running":
        meta.update(status="interrupted", rows=rows, recovered_unix=time.time())
        atomic_write_text(meta_path, json.dumps(meta, indent=1))
    return rows
