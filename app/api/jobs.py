"""Background jobs of the server (gap diagnoses): started by a router, stopped by the lifespan.

A diagnosis takes minutes of CPU; one still running when the server stops
would outlive the store it reports to. Every job gets a stop event the
lifespan sets, then the lifespan waits for the job to record itself as
``cancelled`` before the store closes.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)


class JobRefused(RuntimeError):
    """A job that cannot start now (the API answers 409)."""


class Jobs:
    """Worker threads that can be asked to stop."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._threads: dict[str, threading.Thread] = {}
        self._stops: dict[str, threading.Event] = {}  # each job's own: one is stopped without the others
        self._said: dict[str, str] = {}  # what each running job last said it was doing
        self.stop = threading.Event()  # the server is stopping: set with every job's

    def start(self, name: str, target: Callable[[threading.Event], None], limit: int = 1) -> None:
        """Run ``target(stop)`` in a thread named ``name``.

        Args:
            name: Thread name (also the key of :meth:`join` and :meth:`cancel`).
            target: The work; it should return soon after its argument is set
                (by :meth:`cancel`, or :meth:`shutdown`, which also sets :attr:`stop`).
            limit: Most jobs running at once: a diagnosis takes both cores for
                minutes, and more of them would only slow each other and the
                engine down.

        Raises:
            JobRefused: The server is stopping, or ``limit`` jobs are running.
        """
        with self._lock:
            why = self._refusal(limit)
            if why:
                raise JobRefused(why)
            ev = threading.Event()
            t = threading.Thread(target=target, args=(ev,), name=name, daemon=True)
            self._threads[name], self._stops[name] = t, ev
            t.start()

    def _refusal(self, limit: int) -> str:
        if self.stop.is_set():
            return "the server is stopping; no new job starts"
        self._threads = {n: t for n, t in self._threads.items() if t.is_alive()}
        self._stops = {n: e for n, e in self._stops.items() if n in self._threads}
        self._said = {n: m for n, m in self._said.items() if n in self._threads}
        if len(self._threads) >= limit:
            return (f"{', '.join(self._threads)} is still running; start this one when it has finished "
                    "(poll its run)")
        return ""

    def refusal(self, limit: int = 1) -> str:
        """Why :meth:`start` would refuse now (``""``: it would not); lets a caller refuse
        before it stores anything."""
        with self._lock:
            return self._refusal(limit)

    def say(self, name: str, message: str) -> None:
        """Job ``name`` reports what it is doing now (read back by :meth:`progress`)."""
        with self._lock:
            self._said[name] = message

    def progress(self, name: str) -> str | None:
        """What job ``name`` last said it was doing; None once it has ended (or said nothing)."""
        with self._lock:
            t = self._threads.get(name)
            return self._said.get(name) if t is not None and t.is_alive() else None

    def running(self) -> list[str]:
        """Names of the jobs still running."""
        with self._lock:
            return [n for n, t in self._threads.items() if t.is_alive()]

    def cancel(self, name: str) -> bool:
        """Ask one job to stop; False when no job of that name is running."""
        with self._lock:
            t = self._threads.get(name)
            if t is None or not t.is_alive():
                return False
            self._stops[name].set()
            return True

    def join(self, name: str, timeout: float | None = None) -> bool:
        """Wait for one job; True when it has ended (or never existed)."""
        with self._lock:
            t = self._threads.get(name)
        if t is not None:
            t.join(timeout)
        return t is None or not t.is_alive()

    def shutdown(self, timeout: float = 30.0) -> None:
        """Ask every job to stop and wait up to ``timeout`` [s] for each."""
        self.stop.set()
        with self._lock:
            threads = list(self._threads.values())
            for ev in self._stops.values():
                ev.set()
        for t in threads:
            t.join(timeout)
            if t.is_alive():
                log.warning("job %s did not stop within %.0f s", t.name, timeout)
