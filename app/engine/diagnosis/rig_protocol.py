"""The diagnosis protocol run by the engine on the connected rig (issue 6 §6).

:func:`~app.engine.diagnosis.protocol.run_protocol` runs the protocol on a
simulator of its own. On a station the same experiments
(:func:`~app.engine.diagnosis.protocol.schedules` and the isotonic workout) go through the engine
loop instead — read → control → safety → write on whatever backend is
connected — as a :class:`~app.engine.ident.procedure.Procedure`, so they run
paced on the rig and faster than real time on a simulated clock. Each
experiment becomes one log in the station's format, written as
``KIND-REP.csv`` + ``.json``, with the commands the backend applied.

Per experiment: the PRVs bring both chambers to its start pressure through
the DCVs (:data:`PRESSURISE_S`, longer while a simulated user brings the
handle back to neutral, and :data:`RELAX_S` for it to relax where the
handle stopped), then the log opens with :data:`~app.engine.diagnosis.protocol.PREROLL_S`
at rest (PRVs holding that pressure, DCVs shut at 5 V) and the schedule's
commands follow. The isotonic experiment is closed-loop, as in
:func:`~app.engine.diagnosis.protocol.run_protocol`: its log opens at the
start pressure and the Default controller (1.2 N·m) runs while the user
pushes. The experiments that need the user (a sweep of the handle, the
rocking, the push) say so in the progress message; on the simulated rig
the simulated user does it.

The loop never touches the disk: it hands each period's row to a queue,
and a writer thread opens, appends to (``fsync`` at least every 0.5 s) and
closes the logs.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from app.engine.constants import BAR, P_ATM
from app.engine.control.config import ControllerConfig
from app.engine.control.interaction import InteractionController
from app.engine.diagnosis.protocol import (
    DESCRIPTION,
    ISOTONIC_PW_BAR,
    ISOTONIC_S,
    PREROLL_S,
    VISIBLE,
    Schedule,
    isotonic_program,
    schedules,
)
from app.engine.hardware.base import SAFE_COMMAND, Command
from app.engine.human import HumanProgram
from app.engine.ident.procedure import Procedure, Script
from app.engine.runlog import RunLogWriter
from app.engine.safety import release_command

KINDS: tuple[str, ...] = tuple(VISIBLE)
"""The protocol's experiments, in the order they run."""

PRESSURISE_S = 1.5
"""Both chambers at the experiment's start pressure before its log opens [s] (as a workout starts)."""

RELAX_S = 0.3
"""A simulated user's time to relax where the handle stopped, before the log opens [s]."""

_PROMPT = {
    "friction_sweep": "please move the handle back and forth, slowly, then faster, then fast",
    "sine_sweep": "please rock the handle to and fro, faster and faster",
    "isotonic": "please turn the handle against the robot, in one direction and back, as in a workout",
}


class _LogWriter:
    """The protocol's logs, written by a thread of their own (the control loop only enqueues)."""

    def __init__(self, on_log: Callable[[Path, dict[str, Any]], None] | None = None) -> None:
        self._q: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self.on_log = on_log
        self.done: list[Path] = []
        self.error = ""
        self._thread = threading.Thread(target=self._run, name="cwrr-protocol-logs", daemon=True)
        self._thread.start()

    def open(self, directory: Path, name: str, meta: dict[str, Any]) -> None:
        self._q.put(("open", (directory, name, meta)))

    def append(self, row: tuple[float, ...]) -> None:
        self._q.put(("row", row))

    def close(self, status: str) -> None:
        self._q.put(("close", status))

    def finish(self, timeout: float = 30.0) -> None:
        """Write what is queued and stop the thread."""
        self._q.put(("stop", None))
        self._thread.join(timeout)

    def _run(self) -> None:
        w: RunLogWriter | None = None
        while True:
            what, arg = self._q.get()
            try:
                if what == "open":
                    if w is not None:
                        w.close("incomplete")
                    w = RunLogWriter(*arg)
                elif what == "row" and w is not None:
                    w.append(arg)
                elif what in ("close", "stop") and w is not None:
                    w.close(arg if what == "close" else "incomplete")
                    if w.error:
                        raise OSError(w.error)
                    if arg == "complete":
                        self.done.append(w.csv_path)
                        if self.on_log is not None:
                            self.on_log(w.csv_path, w.meta)
                    w = None
                if what == "stop":
                    return
            except Exception as exc:  # a full disk, a store gone: stop logging, say so, let the rig be
                self.error = f"{type(exc).__name__}: {exc}"
                w = None


class ProtocolProcedure(Procedure):
    """The diagnosis protocol's experiments on the connected rig.

    Also the engine's run recorder: :meth:`append` takes each period's row
    (time, applied commands, measurements) into the current experiment's log.

    Args:
        outdir: Folder for the logs (created).
        repetitions: Runs of every experiment, 1–3 (the last is the one held out).
        scale: Duration factor, 0.2–10 (1 ≈ 83 s of logs per repetition).
        kinds: Experiments to run (default all of :data:`KINDS`).
        rate_hz: The loop's rate [Hz] (the logs' sample rate).
        p_atm_bar: Atmospheric pressure [bar abs] (the PRVs' zero).
        backend: The backend's name (kept in each log's metadata).
        set_program: The simulated user's program setter (None on a real rig).
        on_log: Called with each log's CSV path and metadata as soon as its experiment ran to
            its end (in the writer thread: the station stores it as a run then,
            so a crash later loses none of the finished experiments).
        meta: More metadata for every log (the station's person and session id).

    Raises:
        ValueError: A bad argument, named (nothing is created).
    """

    name = "diagnosis_protocol"
    fit_on_abort = True  # a fault later on leaves the finished experiments' logs good

    def __init__(self, outdir: Path | str, repetitions: int = 2, scale: float = 1.0,
                 kinds: Sequence[str] | None = None, rate_hz: float = 200.0, p_atm_bar: float = P_ATM / BAR,
                 backend: str = "sim", set_program: Callable[[HumanProgram], None] | None = None,
                 on_log: Callable[[Path, dict[str, Any]], None] | None = None,
                 meta: dict[str, Any] | None = None) -> None:
        super().__init__(vent_s=0.5)
        kinds = list(kinds) if kinds else list(KINDS)
        unknown = [k for k in kinds if k not in KINDS]
        if unknown:
            raise ValueError(f"kinds: no protocol experiment {', '.join(unknown)}; known: {', '.join(KINDS)}")
        if not 1 <= repetitions <= 3:
            raise ValueError(f"repetitions = {repetitions} must be 1–3")
        if not 0.2 <= scale <= 10.0:
            raise ValueError(f"scale = {scale} must be in 0.2–10")
        self.outdir = Path(outdir)
        self.repetitions = repetitions
        self.scale = scale
        self.kinds = kinds
        self.rate_hz = rate_hz
        self.p_atm_bar = p_atm_bar
        self.backend = backend
        self.set_program = set_program
        self.on_log = on_log
        self.meta = dict(meta or {})
        self._logs: _LogWriter | None = None
        self._logging = False
        self._release: tuple[float, tuple[float, float]] | None = None

    def vent_command(self) -> Command:
        """A controlled stop (:data:`~app.engine.safety.RELEASE_S`) when the protocol ends or is stopped.

        A person may hold the handle through the sweeps and push through the isotonic workout; dropped
        at once, the chambers empty at their own rates and the torque on the arm reverses. From the
        chambers' pressures at the first vented period.
        """
        if self._release is None:
            m = self.meas
            self._release = (m.t, (m.p_a, m.p_b))
            if self.set_program is not None and self.progress.state != "finished":
                # stopped mid-experiment: the simulated user leaves that experiment's program (a sweep
                # had run on to its end) and, once the chambers have vented, brings the handle back
                self.set_program(HumanProgram.move(m.theta, 0.0, m.t, wait_s=1.0))
        return release_command(self.meas.t, *self._release, self.p_atm_bar)

    # ------------------------------------------------------------ the engine's recorder
    @property
    def log_error(self) -> str:
        """Why the experiments' logs cannot be written ("" while they can): the station stops on it."""
        return self._logs.error if self._logs is not None else ""

    def append(self, row: tuple[float, ...]) -> None:
        """One period's row, into the log of the experiment under way (none between experiments)."""
        if self._logging and self._logs is not None:
            self._logs.append(row)

    def finish_logs(self) -> list[Path]:
        """Wait for the writer; the logs of the experiments that ran to their end (CSV paths)."""
        logs = self._logs
        if logs is None:
            return []
        logs.finish()
        if logs.error:
            raise OSError(f"the protocol's logs could not be written: {logs.error}")
        return list(logs.done)

    # ------------------------------------------------------------ the script
    def script(self) -> Script:
        logs = self._logs = _LogWriter(self.on_log)
        plan: list[tuple[int, str, Schedule | None]] = []
        for rep in range(self.repetitions):
            sch = {s.name: s for s in schedules(rep, self.scale)}
            plan += [(rep, k, sch.get(k)) for k in KINDS if k in self.kinds]
        self.begin("diagnosis protocol", len(plan))
        self.progress.total_tests = len(plan)
        for rep, kind, s in plan:
            self.next_test()
            # a person still pressing on a handle that static friction holds opens the log preloaded
            # (the simulated user relaxes the same way: RELAX_S)
            what = _PROMPT.get(kind, "please bring the handle to neutral, then relax your arm and hold it still")
            self.progress.message = (f"experiment {self.progress.k} of {self.progress.n}: {kind}, repetition "
                                     f"{rep + 1} — {DESCRIPTION[kind]}; {what}")
            pw = s.pw_bar if s is not None else ISOTONIC_PW_BAR
            z = pw - self.p_atm_bar  # PRV static map P = z + P_atm (SPEC §3)
            pressurise = PRESSURISE_S
            if self.set_program is not None:  # the simulated user brings the handle back to neutral
                theta = self.meas.theta
                self.set_program(HumanProgram.move(theta, 0.0, self.meas.t))
                pressurise = max(PRESSURISE_S, HumanProgram.move_time(theta, 0.0) + 0.5)
            filling = Command(z, z, SAFE_COMMAND.u_a, SAFE_COMMAND.u_b)  # PRVs at z, DCVs open to the chambers
            yield from self.hold(filling, pressurise)
            rest_at = 0.0
            if self.set_program is not None:
                # The arm's pull stops short of neutral where static friction holds the handle
                # (≈ 0.06 rad at 20 N·m/rad); a user asked to hold still then relaxes there
                # instead of pressing on, and the experiment runs about that angle. Pressing on,
                # every log but the first had opened with 1.0–1.3 N·m on a stuck handle.
                rest_at = self.meas.theta
                self.set_program(HumanProgram(np.array([self.meas.t, self.meas.t + RELAX_S]),
                                              np.array([0.0, rest_at])))
                yield from self.hold(filling, RELAX_S)
            name = f"{kind}-{rep + 1}"
            meta = {**self.meta, "rig": "rotary", "sample_rate_hz": self.rate_hz, "p_atm_bar": self.p_atm_bar,
                    "working_pressure_bar": pw, "experiment": kind, "human": s.human if s is not None else True,
                    "repetition": rep + 1, "scale": self.scale, "backend": self.backend, "source": "station"}
            logs.open(self.outdir, name, meta)
            self._logging = True
            t0 = self.meas.t
            prog = s.program if s is not None else isotonic_program(rep)
            if self.set_program is not None:  # programs run on rig time, from the log's start
                self.set_program(HumanProgram(prog.t + t0, prog.pos + rest_at))
            try:
                if s is None:  # the isotonic workout: the Default controller while the user pushes
                    ctl = InteractionController(ControllerConfig(controller="default", pw_bar=pw,
                                                                 p_atm_bar=self.p_atm_bar))
                    while self.meas.t - t0 < ISOTONIC_S * self.scale - 0.5 * self.dt:
                        yield ctl.step(self.meas, self.dt)
                else:
                    rest = Command(z, z, 5.0, 5.0)
                    while (tt := self.meas.t - t0) < PREROLL_S + s.duration - 0.5 * self.dt:
                        yield rest if tt < PREROLL_S - 1e-9 else Command(*s.commands(tt - PREROLL_S))
            except GeneratorExit:  # cancelled or faulted mid-experiment: keep what was logged
                self._logging = False
                logs.close("incomplete")
                raise
            self._logging = False
            logs.close("complete")
            self.test_done()
        if self.set_program is not None:
            self.set_program(HumanProgram.move(self.meas.theta, 0.0, self.meas.t))
