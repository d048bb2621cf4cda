"""The engine loop: read → estimate → control → safety → write, on an injected clock.

With :class:`SimClock` the loop runs as fast as the CPU allows (the simulated
backend integrates exactly one period per tick); with :class:`WallClock` it is
paced in a background thread at the configured rate and reports period
jitter and overruns.
"""

from __future__ import annotations

import gc
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from app.engine.hardware.base import Command, HardwareInterface, Measurement


class Clock(Protocol):
    """Time source of the loop."""

    def now(self) -> float:
        """Current time [s]."""
        ...

    def sleep_until(self, t: float) -> None:
        """Return at time ``t`` [s] (immediately if past)."""
        ...


class SimClock:
    """Virtual time: ``sleep_until`` jumps, so loops run faster than real time."""

    def __init__(self, t0: float = 0.0) -> None:
        self._t = t0

    def now(self) -> float:
        """Current virtual time [s]."""
        return self._t

    def sleep_until(self, t: float) -> None:
        """Jump to ``t`` [s]."""
        self._t = max(self._t, t)


class WallClock:
    """Monotonic wall time; sleeps coarsely, then spins for the last 0.3 ms."""

    def __init__(self) -> None:
        self._t0 = time.perf_counter()

    def now(self) -> float:
        """Seconds since construction."""
        return time.perf_counter() - self._t0

    def sleep_until(self, t: float) -> None:
        """Sleep until ``t`` [s]."""
        while True:
            rem = t - self.now()
            if rem <= 0:
                return
            if rem > 0.0005:
                time.sleep(rem - 0.0003)


class Recorder(Protocol):
    """Receives every period's log row: t, z_a, z_b, u_a, u_b, p_a, p_b, p_s, theta, omega, torque
    (a :class:`~app.engine.runlog.RunLogWriter`, or a procedure keeping its own logs)."""

    def append(self, row: tuple[float, ...]) -> None:
        """Take one period's row (called inside the period: must not block)."""
        ...


class Controller(Protocol):
    """A controller stepped once per period with an explicit ``dt``."""

    def step(self, meas: Measurement, dt: float) -> Command:
        """Commands for this period."""
        ...


class Estimator(Protocol):
    """Turns raw measurements into the controller's view (filters, observers)."""

    def update(self, meas: Measurement, dt: float) -> Measurement:
        """Estimated measurement."""
        ...


class Safety(Protocol):
    """Filters commands between control and actuators."""

    def apply(self, cmd: Command, meas: Measurement) -> Command:
        """The command allowed to reach the actuators."""
        ...


class PassThroughSafety:
    """Minimal safety stage: NaN → safe values, inputs clipped to range."""

    def apply(self, cmd: Command, meas: Measurement) -> Command:
        """Clip the command."""
        return cmd.clipped()


@dataclass
class LoopStats:
    """Timing of the loop.

    Attributes:
        ticks: Control periods executed.
        overruns: Periods whose work finished after the next deadline.
        jitter_p50_ms: Median |actual − nominal start| [ms].
        jitter_p99_ms: 99th percentile [ms].
        jitter_max_ms: Largest [ms].
        rate_hz: Nominal loop rate [Hz].
        measured_rate_hz: Ticks per wall second over the recent window [Hz].
    """

    ticks: int = 0
    overruns: int = 0
    jitter_p50_ms: float = 0.0
    jitter_p99_ms: float = 0.0
    jitter_max_ms: float = 0.0
    rate_hz: float = 0.0
    measured_rate_hz: float = 0.0
    realtime: bool = False


RT_PRIORITY = 50
"""SCHED_FIFO priority of the paced engine thread (1–99; above every normal thread, below the kernel's own)."""

GIL_SWITCH_S = 0.0001
"""Interpreter switch interval while a paced engine runs [s] (CPython's default is 5 ms, a whole period).

A thread that wants the interpreter lock waits one interval before it may ask
the holder to drop it, and waits a whole interval again whenever the lock
passed between two other threads meanwhile. With the server's busy threads
(viser's publisher and event loop, uvicorn, the request workers) the woken
engine waited several intervals: a scheduler trace (``perf``) of late periods
showed it timing out every ≈ 0.53 ms at 0.5 ms. In alternating runs of the
10-browser load (``bench/load.py 10 --viser 2 --rps 50``), 0.1 ms against
0.5 ms lowered the watched p99 jitter from 0.96–1.60 to 0.53–0.64 ms at 200 Hz
and from 0.72–0.94 to 0.55–0.57 ms at 500 Hz; 0.05 and 0.02 ms did no better.
"""


def set_scheduling(policy: str, priority: int = 0) -> str:
    """Set the calling thread's scheduling policy (threads it starts later inherit it).

    Args:
        policy: ``"SCHED_FIFO"``, ``"SCHED_RR"`` or ``"SCHED_OTHER"``.
        priority: Static priority (1–99 for the real-time policies, 0 otherwise).

    Returns:
        ``""`` on success, else why not.
    """
    import os

    if not hasattr(os, "sched_setscheduler"):
        return f"no {policy} on this OS"
    try:
        os.sched_setscheduler(0, getattr(os, policy), os.sched_param(priority))  # 0: the calling thread
    except (PermissionError, OSError) as exc:
        return f"{policy} refused ({exc.strerror or exc}); needs root or CAP_SYS_NICE"
    return ""


def make_realtime(priority: int = RT_PRIORITY) -> str:
    """Give the calling thread SCHED_FIFO priority, if the OS allows it.

    A browser, a compiler or a fuzzer on the same machine then cannot push the
    control period back: the kernel runs this thread the moment its sleep ends.
    Needs Linux and root or CAP_SYS_NICE (``docker run --cap-add SYS_NICE``);
    elsewhere the loop runs at normal priority and says so.

    Returns:
        ``""`` on success, else why not.
    """
    return set_scheduling("SCHED_FIFO", priority)


SERVER_RT_PRIORITY = 10
"""SCHED_RR priority of every other server thread when real-time is on (below the loop's)."""


def make_server_realtime(priority: int = SERVER_RT_PRIORITY) -> str:
    """Put the calling thread, and every thread it starts later, in SCHED_RR at ``priority``.

    The loop thread holds SCHED_FIFO, but it needs the interpreter lock; if a
    normal-priority server thread holding the lock is pushed off the CPU by a
    browser or a build, the loop waits for it (priority inversion — measured:
    stalls of 0.3–0.5 s with ten Chromium pages on a 2-core machine). Server
    threads that only ever block on I/O lose nothing by ranking above
    ordinary programs. Call it before the server starts its threads.

    Returns:
        ``""`` on success, else why not.
    """
    return set_scheduling("SCHED_RR", priority)


def settle_heap() -> int:
    """Collect every generation, then exempt what survives from later collections (:func:`gc.freeze`).

    Call it before a paced loop starts, never while one runs. A collection of
    the oldest generation runs on whichever thread allocates, holding the
    interpreter lock throughout, and scans every object the process holds:
    a served station holds ≈ 280 000 after start-up (FastAPI, viser, numba,
    SciPy), and one such collection took 290–400 ms here — the 258 ms stall
    and the watchdog fault of a watched run under CI. Frozen objects are not
    scanned again, so a later full collection only visits what was allocated
    since. What was frozen and dies later (a previous connection's backend)
    is returned to the collector by the next call, which unfreezes first.

    Returns:
        How many objects are frozen.
    """
    gc.unfreeze()
    refreeze_heap()
    return gc.get_freeze_count()


def refreeze_heap() -> float:
    """Collect what was allocated since the last freeze, then freeze the survivors too.

    The station's watcher calls it every :data:`REFREEZE_S` while connected,
    beside the running loop: it scans only the unfrozen objects (a few
    seconds' survivors, a millisecond or two), where the collector's own
    full collection would wait until tens of thousands had piled up (a 22 ms
    one latched the overrun fault, five late periods at 200 Hz, in a watched
    run under CI). A frozen object freed by reference counting is freed as
    usual; one that dies inside a reference cycle waits for the next
    :func:`settle_heap` (the next connect).

    Returns:
        How long it took [ms].
    """
    t0 = time.perf_counter()
    gc.collect()
    gc.freeze()
    return (time.perf_counter() - t0) * 1e3


REFREEZE_S = 2.0
"""Period of :func:`refreeze_heap` while a station is connected [s]."""


class Engine:
    """Runs one backend with one controller at a fixed rate.

    Args:
        backend: The rig.
        controller: Called once per period.
        clock: Time source (inject :class:`SimClock` for tests).
        rate_hz: Control rate [Hz] (thesis: 200 Hz control, 500 Hz identification).
        safety: Command filter before the actuators.
        estimator: Optional estimator between read and control.
        recorder: Optional run log receiving every period's row.
        on_tick: Optional observer called with (measurement, applied command);
            must be quick (it runs inside the period).
        realtime: Ask for SCHED_FIFO priority for the paced thread (see
            :func:`make_realtime`); :attr:`realtime_note` says why not when refused.
        stall_s: Watchdog of the paced thread: when no period has completed
            for this long [s], a second thread writes the backend's safe
            command itself and latches a ``stall`` fault in ``safety`` (if it
            has ``trip``). It cannot help when another thread holds the
            interpreter lock throughout; on the real rig the DAQ's own
            watchdog covers that and a dead process. The default, 1 s, is
            four times the longest pause seen on a 2-core machine busy with
            a browser and a test run (258 ms tripped a 0.25 s watchdog there):
            a held command is safe for that long, a spurious trip ends a
            therapy session.
    """

    def __init__(
        self,
        backend: HardwareInterface,
        controller: Controller,
        clock: Clock,
        rate_hz: float = 200.0,
        safety: Safety | None = None,
        estimator: Estimator | None = None,
        recorder: Recorder | None = None,
        on_tick: Callable[[Measurement, Command], None] | None = None,
        realtime: bool = False,
        stall_s: float = 1.0,
    ) -> None:
        if not (1.0 <= rate_hz <= 10000.0):
            raise ValueError(f"rate_hz = {rate_hz} is outside its allowed range [1, 10000] Hz")
        self.backend = backend
        self.controller = controller
        self.clock = clock
        self.rate_hz = rate_hz
        self.period = 1.0 / rate_hz
        self.safety = safety or PassThroughSafety()
        self.estimator = estimator
        self.recorder = recorder
        self.on_tick = on_tick
        self.ticks = 0
        self.overruns = 0
        self._jitter: deque[float] = deque(maxlen=4096)
        self._wall: deque[float] = deque(maxlen=512)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._next = 0.0
        self.last_measurement: Measurement | None = None
        self.last_command: Command | None = None
        self.error: BaseException | None = None
        self.want_realtime = realtime
        self.realtime = False
        self.realtime_note = "not requested"
        if not 0.0 < stall_s <= 60.0:
            raise ValueError(f"stall_s = {stall_s} is outside its allowed range (0, 60] s")
        self.stall_s = stall_s
        self.stalls = 0
        self._watchdog: threading.Thread | None = None
        self._last_done = time.monotonic()

    def tick(self) -> Command:
        """One period: read → estimate → control → safety → write → log."""
        meas = self.backend.read()
        est = self.estimator.update(meas, self.period) if self.estimator else meas
        cmd = self.controller.step(est, self.period)
        cmd = self.safety.apply(cmd, meas)
        applied = self.backend.write(cmd)
        if self.recorder is not None:
            self.recorder.append((meas.t, applied.z_a, applied.z_b, applied.u_a, applied.u_b,
                                  meas.p_a, meas.p_b, meas.p_s, meas.theta, meas.omega, meas.torque))
        self.last_measurement = meas
        self.last_command = applied
        if self.on_tick is not None:
            self.on_tick(meas, applied)
        self.ticks += 1
        self._last_done = time.monotonic()
        return applied

    def reset_window(self) -> None:
        """Start the jitter and rate window afresh (benchmarks measure one phase at a time)."""
        self._jitter.clear()
        self._wall.clear()

    def run_for(self, duration: float) -> None:
        """Run synchronously for ``duration`` seconds of clock time.

        An exception from the backend or a stage leaves the rig as the paced
        thread would (fault latched in ``safety``, safe command written,
        :attr:`error` set) and is then raised.
        """
        n = int(round(duration * self.rate_hz))
        t = self.clock.now()
        try:
            if getattr(self.backend, "paced_by_hardware", False):
                prev = math.nan
                for _ in range(n):
                    prev = self._hardware_tick(prev)
                return
            for i in range(n):
                self.clock.sleep_until(t + i * self.period)
                self._timed_tick(t + i * self.period)
        except BaseException as exc:
            self._fail(exc)
            raise
        self.clock.sleep_until(t + n * self.period)

    def _fail(self, exc: BaseException) -> None:
        self.error = exc
        trip = getattr(self.safety, "trip", None)
        if trip is not None:
            link = isinstance(exc, (OSError, TimeoutError, ConnectionError))
            t = self.last_measurement.t if self.last_measurement is not None else math.nan
            trip("link_lost" if link else "engine_error", f"{type(exc).__name__}: {exc}", t)
        self._write_safe(self._fault_command())

    def _write_safe(self, cmd: Command) -> None:
        """Write a safe command, tolerating a backend that cannot take it.

        The link may be what failed or stalled; the DAQ's (or coupler's) own
        watchdog then holds the safe outputs.
        """
        try:
            self.backend.write(cmd)
        except Exception:
            pass

    def _fault_command(self) -> Command:
        """The safety stage's fault state if it has one, else the backend's safe command."""
        cmd = getattr(self.safety, "fault_command", None)
        return cmd if isinstance(cmd, Command) else self.backend.safe_command()

    def _timed_tick(self, deadline: float) -> None:
        start = self.clock.now()
        self._jitter.append(abs(start - deadline))
        self.tick()
        end = self.clock.now()
        self._wall.append(end)
        if end > deadline + self.period:
            self.overruns += 1

    def _hardware_tick(self, prev_sample: float) -> float:
        """One period on a backend whose :meth:`read` waits for the device's clock.

        The period is the device's, so jitter is how far the interval between
        two samples' arrivals strays from it, and an overrun is a period whose
        work outlasted the period (the next sample was already waiting).

        Returns:
            The arrival time of this period's sample [s].
        """
        self.tick()
        end = self.clock.now()
        meas = self.last_measurement
        t_sample = meas.t if meas is not None else end
        if math.isfinite(prev_sample):
            self._jitter.append(abs(t_sample - prev_sample - self.period))
        self._wall.append(end)
        if end - t_sample > self.period:
            self.overruns += 1
        return t_sample

    def start(self) -> None:
        """Run paced in a background thread until :meth:`stop`."""
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError("engine already running")
        self._stop.clear()
        self._last_done = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="cwrr-engine", daemon=True)
        self._thread.start()
        self._watchdog = threading.Thread(target=self._watch, name="cwrr-watchdog", daemon=True)
        self._watchdog.start()

    def _watch(self) -> None:
        """Safe outputs when the paced thread stops completing periods (see ``stall_s``)."""
        tripped = False
        while not self._stop.wait(min(self.period, self.stall_s / 4)):
            late = time.monotonic() - self._last_done
            if late < self.stall_s:
                tripped = False
                continue
            if tripped or self._thread is None or not self._thread.is_alive():
                continue
            tripped = True
            self.stalls += 1
            trip = getattr(self.safety, "trip", None)
            if trip is not None:
                trip("stall", f"the control loop completed no period for {late * 1e3:.0f} ms "
                     f"(watchdog: {self.stall_s * 1e3:.0f} ms)")
            self._write_safe(self._fault_command())

    def _run(self) -> None:
        if self.want_realtime:
            import sys

            # how long a woken engine waits before it may ask the GIL's holder to drop it (GIL_SWITCH_S)
            sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH_S))
            self.realtime_note = make_realtime()
            self.realtime = not self.realtime_note
        nxt = self.clock.now()
        try:
            if getattr(self.backend, "paced_by_hardware", False):
                prev = math.nan
                while not self._stop.is_set():
                    prev = self._hardware_tick(prev)
                return
            while not self._stop.is_set():
                self.clock.sleep_until(nxt)
                self._timed_tick(nxt)
                nxt += self.period
                lag = self.clock.now() - nxt
                if lag > self.period:
                    # skip missed periods rather than bursting to catch up
                    nxt += (int(lag / self.period)) * self.period
        except BaseException as exc:
            self._fail(exc)

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the background thread and put the rig in its safe state."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        if self._watchdog is not None:
            self._watchdog.join(timeout)
            self._watchdog = None
        self._write_safe(self.backend.safe_command())

    @property
    def running(self) -> bool:
        """Whether the background thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def stats(self) -> LoopStats:
        """Current timing statistics."""
        j = np.asarray(self._jitter) * 1e3
        w = list(self._wall)
        rate = (len(w) - 1) / (w[-1] - w[0]) if len(w) > 1 and w[-1] > w[0] else 0.0
        return LoopStats(
            ticks=self.ticks, overruns=self.overruns,
            jitter_p50_ms=float(np.percentile(j, 50)) if j.size else 0.0,
            jitter_p99_ms=float(np.percentile(j, 99)) if j.size else 0.0,
            jitter_max_ms=float(j.max()) if j.size else 0.0,
            rate_hz=self.rate_hz, measured_rate_hz=rate, realtime=self.realtime,
        )
