"""Automated experiment sequencers, stepped by the engine like any controller.

The thesis ran each identification as a Stateflow chart inside the Simulink
model (Figures 3.14, 3.15, 3.22, 3.24, 3.25). Here a procedure is a Python
generator — the flowchart reads top to bottom — wrapped as a
:class:`~app.engine.loop.Controller`: every control period the engine hands
it the measurement and applies the command it yields, through the same
safety stage and backend as a workout. The same object therefore runs
faster than real time on the simulator and paced on the rig.

Every procedure reports progress ("experiment k of N"), keeps each test's
result as soon as that test ends, and can be cancelled: the script is
abandoned, the rig is vented, and the data collected so far stays.
"""

from __future__ import annotations

import abc
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any

from app.engine.hardware.base import SAFE_COMMAND, Command, HardwareInterface, Measurement

Script = Generator[Command, None, None]


@dataclass
class Progress:
    """Where a procedure is.

    Attributes:
        phase: Current experiment block (e.g. ``"static CCW"``).
        k: Experiment number within the block (1-based; 0 before the first).
        n: Experiments in the block.
        done_tests: Experiments finished over the whole procedure.
        total_tests: Experiments in the whole procedure.
        state: ``"running"``, ``"finished"``, ``"cancelled"`` or ``"failed"``.
        message: Human-readable status.
    """

    phase: str = "idle"
    k: int = 0
    n: int = 0
    done_tests: int = 0
    total_tests: int = 0
    state: str = "running"
    message: str = ""

    @property
    def fraction(self) -> float:
        """Share of experiments done [0, 1]."""
        return self.done_tests / self.total_tests if self.total_tests else 0.0

    def as_dict(self) -> dict[str, Any]:
        """Plain view for the API."""
        return {"phase": self.phase, "k": self.k, "n": self.n, "done_tests": self.done_tests,
                "total_tests": self.total_tests, "state": self.state, "message": self.message,
                "fraction": self.fraction}


class Procedure(abc.ABC):
    """Base of every automated identification procedure.

    Subclasses implement :meth:`script`, a generator that yields one command
    per control period and reads :attr:`meas` (the latest measurement) after
    each ``yield``. Helpers :meth:`hold` and :meth:`until` cover the
    flowcharts' "wait" and "until condition" boxes.

    Args:
        vent_s: How long to vent after the script ends or is cancelled [s].
    """

    name: str = "procedure"

    def __init__(self, vent_s: float = 0.5) -> None:
        self.vent_s = vent_s
        self.progress = Progress()
        self.meas: Measurement = Measurement(0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0)
        self.dt = 0.002
        self._gen: Script | None = None
        self._cancel = False
        self._vent_until: float | None = None
        self.finished = False
        self.t_start: float | None = None
        self.t_end: float | None = None

    # ------------------------------------------------------------ engine side
    def step(self, meas: Measurement, dt: float) -> Command:
        """One control period (the engine's :class:`Controller` protocol)."""
        self.meas = meas
        self.dt = dt
        if self.t_start is None:
            self.t_start = meas.t
        if self.finished:
            return self.vent_command()
        if self._vent_until is not None:
            if meas.t >= self._vent_until:
                self.finished = True
                self.t_end = meas.t
            return self.vent_command()
        if self._cancel:
            self._abandon("cancelled", "Cancelled by the user; the rig is vented and the data so far is kept.")
            return self.vent_command()
        if self._gen is None:
            self._gen = self.script()
        try:
            return next(self._gen)
        except StopIteration:
            if self.progress.state == "running":
                self.progress.state = "finished"
                self.progress.message = "Experiments completed."
            self._vent_until = meas.t + self.vent_s
            return self.vent_command()
        except Exception as exc:  # a failed step must still leave the rig vented
            self._abandon("failed", f"{type(exc).__name__}: {exc}")
            return self.vent_command()

    def cancel(self) -> None:
        """Stop at the next period: vent the rig, keep the data so far."""
        self._cancel = True

    def _abandon(self, state: str, message: str) -> None:
        if self._gen is not None:
            self._gen.close()
        self.progress.state = state
        self.progress.message = message
        self._vent_until = self.meas.t + self.vent_s

    def vent_command(self) -> Command:
        """Both PRVs to atmosphere, DCVs open towards them (the safe state)."""
        return SAFE_COMMAND

    # ------------------------------------------------------------ script side
    @abc.abstractmethod
    def script(self) -> Script:
        """The flowchart: yield one :class:`Command` per period."""

    def hold(self, cmd: Command, seconds: float) -> Script:
        """Yield ``cmd`` for ``seconds`` [s]."""
        t_end = self.meas.t + seconds
        while self.meas.t < t_end - 0.5 * self.dt:
            yield cmd

    def until(
        self, cmd: Command | Callable[[], Command], done: Callable[[Measurement], bool], timeout: float
    ) -> Generator[Command, None, bool]:
        """Yield ``cmd`` (or ``cmd()``) until ``done(meas)``; False on timeout [s]."""
        t_end = self.meas.t + timeout
        while not done(self.meas):
            if self.meas.t >= t_end:
                return False
            yield cmd() if callable(cmd) else cmd
        return True

    def begin(self, phase: str, n: int) -> None:
        """Start an experiment block of ``n`` tests."""
        self.progress.phase = phase
        self.progress.n = n
        self.progress.k = 0

    def next_test(self) -> None:
        """Count the next experiment of the block."""
        self.progress.k += 1
        self.progress.message = f"{self.progress.phase}: experiment {self.progress.k} of {self.progress.n}"

    def test_done(self) -> None:
        """One experiment finished."""
        self.progress.done_tests += 1

    def block(self, phase: str, n: int, test: Callable[[], Script]) -> Script:
        """Run ``n`` experiments ``test()`` as one block, counting progress."""
        self.begin(phase, n)
        for _ in range(n):
            self.next_test()
            yield from test()
            self.test_done()


@dataclass
class RunSummary:
    """How a procedure run went.

    Attributes:
        sim_seconds: Rig (clock) time the procedure took [s].
        wall_seconds: Computer time [s].
        state: Final :attr:`Progress.state`.
    """

    sim_seconds: float
    wall_seconds: float
    state: str


def run_procedure(
    proc: Procedure,
    backend: HardwareInterface,
    clock: Any,
    rate_hz: float,
    max_seconds: float = 1.0e6,
    recorder: Any = None,
    on_progress: Callable[[Progress], None] | None = None,
) -> RunSummary:
    """Run ``proc`` to completion on ``backend`` through the engine loop.

    With a :class:`~app.engine.loop.SimClock` this runs as fast as the CPU
    allows; with a wall clock it is paced like the rig.

    Args:
        proc: The procedure.
        backend: The rig (simulated or real).
        clock: The engine clock.
        rate_hz: Control rate [Hz] (thesis: 500 rotary, 200 linear).
        max_seconds: Give up (cancel, vent) after this much rig time [s].
        recorder: Optional run log receiving every period.
        on_progress: Called about once per rig second with the progress.
    """
    from app.engine.loop import Engine

    engine = Engine(backend, proc, clock, rate_hz=rate_hz, recorder=recorder)
    backend.activate()
    w0 = time.perf_counter()
    t0 = clock.now()
    try:
        while not proc.finished:
            engine.run_for(1.0)
            if on_progress is not None:
                on_progress(proc.progress)
            if clock.now() - t0 > max_seconds and not proc._cancel:
                proc.cancel()
                proc.progress.message = f"Stopped after the {max_seconds:g} s time limit."
    finally:
        backend.deactivate()
    return RunSummary(clock.now() - t0, time.perf_counter() - w0, proc.progress.state)
