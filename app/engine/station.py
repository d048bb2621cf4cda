"""The station: one backend, one paced engine thread, and the state machine the server drives.

States (issue 5)::

    disconnected ──connect──▶ idle ──start──▶ running ───┐
          ▲                   │ ▲ ──estimate─▶ identifying ┤ stop / finished
          └────disconnect─────┘ └──────── stopping ◀──────┘
    any ──engine error, safety fault, e-stop──▶ fault (latched; ``clear`` → disconnected)

While connected the engine thread always runs: idle periods send the
backend's safe command; a run or an identification swaps its own
controller in behind a :class:`Supervisor`, so the loop (read → estimate →
control → safety → write) never changes shape. Finishing work — closing the
log, scoring, storing — happens off the engine thread.

Runs are logged with :class:`~app.engine.runlog.RunLogWriter` (fsync at
least every 0.5 s of wall time) and reported to an optional
:class:`RunSink` (the server's SQLite store).
"""

from __future__ import annotations

import bisect
import enum
import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, Literal, Protocol, get_args

import numpy as np

from app.engine import paramsets
from app.engine.constants import BAR, P_ATM
from app.engine.control.config import ControllerConfig, ControllerName
from app.engine.control.interaction import InteractionController
from app.engine.hardware.base import RIG_KINDS, SAFE_COMMAND, Command, HardwareInterface, Measurement
from app.engine.hardware.config import HardwareConfig, save_config
from app.engine.hardware.factory import make_factory
from app.engine.loop import REFREEZE_S, Controller, Engine, Recorder, WallClock, refreeze_heap, settle_heap
from app.engine.metrics import angle_range_deg, toggle_report
from app.engine.params import LinearCylinder, ParameterError, PlantParams, SensorParams, check_range
from app.engine.runlog import RunLogWriter, new_log_name
from app.engine.safety import RELEASE_S, SafetyLimits, SafetySupervisor, release_command
from app.engine.scenarios import SCENARIOS, Case, ScenarioSettings, case_controller, case_program, score_case

CONTROL_RATE_HZ = 200.0  # thesis 3.3
ROTARY_IDENT_RATE_HZ = 500.0  # thesis 4.2.1
DEFAULT_PW_BAR = 3.0  # P_w of the thesis's HIL tests [bar abs] (SPEC §1)
MIN_PARTIAL_WINDOW_S = 1.0  # a stopped run is scored only over at least this much of its window
logger = logging.getLogger(__name__)

PRESSURISE_S = 1.5  # both chambers brought to P_w before the user engages (as run_workout starts)
RELAX_AFTER_RUN_S = 0.5  # the simulated user, back at neutral after a run, relaxes this long after the move
RELEASE_TAU_S = 0.05  # the release starts from the chambers' pressures averaged over about this long [s]


class State(enum.StrEnum):
    """Engine states."""

    DISCONNECTED = "disconnected"
    IDLE = "idle"
    RUNNING = "running"
    IDENTIFYING = "identifying"
    STOPPING = "stopping"
    FAULT = "fault"


ALLOWED: dict[str, tuple[State, ...]] = {
    "connect": (State.DISCONNECTED,),
    "disconnect": (State.IDLE,),
    "start": (State.IDLE,),
    "estimate": (State.IDLE,),
    "stop": (State.RUNNING, State.IDENTIFYING),
    "clear": (State.FAULT,),
    "calibrate": (State.IDLE,),
}
"""Which states each action is legal in."""

_WHY: dict[State, str] = {
    State.DISCONNECTED: "the rig is not connected; connect first",
    State.IDLE: "nothing is running",
    State.RUNNING: "a run is in progress; stop it first",
    State.IDENTIFYING: "an identification is in progress; stop it first",
    State.STOPPING: "the station is stopping; wait a moment",
    State.FAULT: "a fault is latched; clear it first",
}


_WHY_ACTION: dict[tuple[str, State | None], str] = {
    ("connect", State.IDLE): "the rig is connected already; disconnect first to connect another",
    ("disconnect", State.DISCONNECTED): "the rig is not connected; there is nothing to disconnect",
    ("stop", State.DISCONNECTED): "nothing is running",
    ("clear", None): "no fault is latched; there is nothing to clear",  # in every state but a fault
}
"""Where the state's own reason (:data:`_WHY`) would not answer the action (``None``: in any state):
connecting while idle is refused because a rig is connected, not because nothing runs."""


class TransitionError(RuntimeError):
    """An action that is illegal in the current state (the API answers 409).

    Attributes:
        action: The refused action.
        state: The state it was refused in.
    """

    def __init__(self, action: str, state: State, why: str | None = None) -> None:
        self.action = action
        self.state = state
        super().__init__(f"cannot {action} while {state.value}: "
                         f"{why or _WHY_ACTION.get((action, state)) or _WHY_ACTION.get((action, None)) or _WHY[state]}")


LINEAR_IDENT_RATE_HZ = 200.0
"""Linear friction identification rate [Hz] (thesis 4.2.2)."""


@dataclass(frozen=True)
class Rig:
    """Which rig the station drives.

    Attributes:
        kind: ``"rotary"`` (the CWRR forearm axis: workouts, rotary
            identification, PID tuning), ``"linear"`` (the linear test
            cylinder of thesis 3.2.4: linear friction identification) or
            ``"cpr"`` (the constant-volume set-up of Figure 3.10: the linear
            cylinder held extended, chamber b open, PS-0 at DCV-a's supply
            port: the directional valve's CPR map and flow model).
        cylinder: The thesis's cylinder on the linear rig (``"C1"``, ``"C2"``, ``"C3"``;
            the simulator's catalogue — a real rig ignores it).
    """

    kind: str = "rotary"
    cylinder: str = "C3"

    def __post_init__(self) -> None:
        if self.kind not in RIG_KINDS:
            raise ParameterError(f"rig: {self.kind!r} must be one of {', '.join(RIG_KINDS)}")
        if self.cylinder not in ("C1", "C2", "C3"):
            raise ParameterError(f"cylinder: {self.cylinder!r} must be C1, C2 or C3 "
                                 "(the cylinders of thesis Tables 4.5–4.6)")

    @property
    def stroke(self) -> float | None:
        """The cylinder's stroke in the catalogue [m] on the linear set-ups (None on the forearm robot):
        the piston runs from 0 (retracted) to it."""
        if self.kind == "rotary":
            return None
        return LinearCylinder.catalogue(self.cylinder).stroke  # type: ignore[arg-type]  # checked above


RunKind = Literal["workout", "rotary_friction", "linear_friction", "dcv_flow", "pid_tuning", "diagnosis_protocol",
                  "protocol", "diagnosis", "imported"]
"""What a stored run is: an exercise, an identification or tuning, the diagnosis protocol (its own run and
one per experiment's log), a diagnosis, or a log imported from elsewhere. Typed, so that a new kind is
added here, where the API's run filter and the dashboard's history labels look for it."""
RUN_KINDS: tuple[str, ...] = get_args(RunKind)


class RunSink(Protocol):
    """Where finished (and started) runs are reported; the server's store implements it."""

    def run_started(self, kind: RunKind, spec: dict[str, Any], log_csv: str) -> int:
        """Record a new run; returns its id."""
        ...

    def run_finished(self, run_id: int, status: str, metrics: dict[str, Any] | None,
                     result: dict[str, Any] | None) -> None:
        """Record how a run ended."""
        ...


@dataclass(frozen=True)
class RunSpec:
    """A scenario run as the therapist picks it.

    Attributes:
        scenario: ``"SC-1"`` … ``"SC-4"`` (thesis 4.4–4.7).
        controller: ``"default"``, ``"pid"`` or ``"fuzzy"``.
        target_nm: Signed target torque [N·m] (positive: pronation, CCW).
        pw_bar: Working pressure [bar abs].
        person: Pseudonymous id of the person exercising.
        notes: Free text.
        workout: Workout shape overrides (:data:`~app.engine.paramsets.WORKOUT_FIELDS`).
        gains: Cascade PID gains (:data:`~app.engine.paramsets.GAIN_FIELDS`); None keeps Eq 3.26's.
        fuzzy: Fuzzy scheduler overrides (``e_range`` [bar], ``de_range`` [bar/s], ``defuzz``).
        session_id: The therapy session the run belongs to.
    """

    scenario: str = "SC-1"
    controller: ControllerName = "fuzzy"
    target_nm: float = 1.2
    pw_bar: float = 3.0
    person: str = ""
    notes: str = ""
    workout: dict[str, float] | None = None
    gains: dict[str, float] | None = None
    fuzzy: dict[str, Any] | None = None
    session_id: int | None = None

    def __post_init__(self) -> None:
        if self.scenario not in SCENARIOS:
            raise ParameterError(f"scenario: {self.scenario!r} must be one of {', '.join(SCENARIOS)}")
        if not (0.1 <= abs(self.target_nm) <= 3.0) or not math.isfinite(self.target_nm):
            raise ParameterError(f"target_nm: {self.target_nm} N·m must be within ±0.1–3 N·m")
        if self.scenario in ("SC-3", "SC-4") and self.target_nm < 0:
            raise ParameterError(f"target_nm: {self.scenario} is defined for pronation only (thesis 4.6–4.7), "
                                 "so the target must be positive")
        if not (1.5 <= self.pw_bar <= 6.0):
            raise ParameterError(f"pw_bar: {self.pw_bar} bar must be within 1.5–6 bar abs")
        for kind, values in (("workout", self.workout), ("gains", self.gains), ("fuzzy", self.fuzzy)):
            if values is not None:
                paramsets.validate(kind, values, partial=True)

    @property
    def settings(self) -> ScenarioSettings:
        """The workout shape at this run's working pressure."""
        return ScenarioSettings(pw_bar=self.pw_bar, **(self.workout or {}))

    def controller_config(self) -> ControllerConfig:
        """The controller this run uses."""
        gains = paramsets.build("gains", self.gains) if self.gains is not None else None
        fuzzy = paramsets.build("fuzzy", self.fuzzy) if self.fuzzy is not None else None
        return case_controller(self.case, self.controller, self.settings, gains, fuzzy)

    @property
    def case(self) -> Case:
        """The scenario case (PDRA/TDRA as the scenario defines them)."""
        on = self.scenario != "SC-1"
        return Case(self.scenario, self.target_nm, on, on)


LIVE_COLUMNS: tuple[str, ...] = ("t", "torque", "target", "p_a", "p_b", "p_ref_a", "p_ref_b", "omega", "theta")
"""Columns of the live ring buffer (s, N·m, N·m, bar, bar, bar, bar, rad/s, rad)."""


class LiveBuffer:
    """Thread-safe ring buffer of recent samples for dashboards and plots.

    The engine thread appends one row per period; readers copy slices.

    Args:
        seconds: History kept [s].
        rate_hz: Rows per second.
    """

    def __init__(self, seconds: float = 30.0, rate_hz: float = CONTROL_RATE_HZ) -> None:
        self.n = int(seconds * rate_hz)
        self._a = np.zeros((self.n, len(LIVE_COLUMNS)))
        self._i = 0  # rows written in total
        self._lock = threading.Lock()

    def append(self, row: tuple[float, ...]) -> None:
        """Add one row in :data:`LIVE_COLUMNS` order."""
        with self._lock:
            self._a[self._i % self.n] = row
            self._i += 1

    def since(self, t: float, max_rows: int = 2000) -> np.ndarray:
        """Rows newer than ``t`` [s], oldest first, at most ``max_rows`` (the newest)."""
        with self._lock:
            # copy only the newest max_rows: readers poll often, the ring holds 30 s
            k = min(self._i, self.n, max(int(max_rows), 0))
            idx = (np.arange(self._i - k, self._i)) % self.n
            rows = self._a[idx]  # fancy indexing copies
        return rows[rows[:, 0] > t]

    def window(self, seconds: float, max_points: int) -> tuple[int, np.ndarray]:
        """The last ``seconds`` [s] of rows, thinned to at most ``max_points`` + 1, oldest first.

        Thinning keeps every k-th row counted from the first row ever written,
        not from the window's start, so successive windows share their samples
        and a live chart of a noisy signal does not shimmer as it scrolls; the
        newest row is always included. Only the kept rows are copied under the
        lock (the engine appends under it).

        Returns:
            ``(written, rows)``: rows written in total so far (unchanged means no
            new sample) and the thinned rows.
        """
        with self._lock:
            end = self._i
            lo = max(0, end - self.n)
            if end == 0:
                return 0, np.zeros((0, len(LIVE_COLUMNS)))
            t_from = self._a[(end - 1) % self.n, 0] - seconds
            # first row inside the window (times rise since the last clear; the newest is inside)
            lo = bisect.bisect_left(range(lo, end), t_from, key=lambda i: self._a[i % self.n, 0]) + lo
            step = max(1, -(-(end - lo) // max(int(max_points), 1)))
            idx = np.arange(lo + (-lo) % step, end, step)
            if idx.size == 0 or idx[-1] != end - 1:
                idx = np.append(idx, end - 1)
            rows = self._a[idx % self.n]
        return end, rows

    def latest(self) -> np.ndarray | None:
        """The newest row, or None before the first."""
        with self._lock:
            return self._a[(self._i - 1) % self.n].copy() if self._i else None

    def clear(self) -> None:
        """Forget everything (a new connection starts a new time axis)."""
        with self._lock:
            self._i = 0


class Supervisor:
    """The engine's only controller: delegates to the current job, else the safe command."""

    def __init__(self, safe: Command) -> None:
        self.safe = safe
        self.job: Controller | None = None

    def step(self, meas: Measurement, dt: float) -> Command:
        """Commands for this period."""
        job = self.job
        return job.step(meas, dt) if job is not None else self.safe


@dataclass
class RunJob:
    """A scenario run in progress: pressurise, then the interaction controller until the rotation ends.

    Attributes:
        spec: What was asked for.
        controller: The interaction controller.
        t_end: End of the rotation from the program start [s].
        t_d: Disturbance time from the program start [s] or None.
        on_program_start: Called once, with the rig time [s], at the end of
            pressurising (starts the simulated user).
        on_disturbance: Called once at the disturbance time (SC-4's PRV-b drop).
        pressurise_s: Time at P_w before the program starts [s] (longer when the
            user first brings the handle back to neutral).
        on_release: Called once, with the rig time [s], when the controlled stop
            begins (tells the simulated user the exercise is over).
    """

    spec: RunSpec
    controller: InteractionController
    t_end: float
    t_d: float | None
    on_program_start: Callable[[float], None]
    on_disturbance: Callable[[], None]
    pressurise_s: float = PRESSURISE_S
    on_release: Callable[[float], None] | None = None
    t0: float | None = None
    t_prog: float | None = None
    disturbed: bool = False
    done: bool = False
    # tr, torque, mode, p_a, p_b, theta: one row per period of the program
    rows: list[tuple[float, float, float, float, float, float]] = field(default_factory=list)
    ending: str = "complete"
    t_release: float | None = None
    release_from: tuple[float, float] = (0.0, 0.0)  # the chambers' pressures it starts from [bar abs]
    p_mean: tuple[float, float] | None = None  # the chambers' recent pressures [bar abs] (RELEASE_TAU_S)

    def request_stop(self) -> None:
        """End the run early (STOP): the next period starts the release (:data:`RELEASE_S`). A run whose
        program is over and whose release has begun stays complete."""
        if self.t_release is None:
            self.ending = "stopped"

    def step(self, meas: Measurement, dt: float) -> Command:
        """One period of the run."""
        if self.t0 is None:
            self.t0 = meas.t
        if self.done:
            return SAFE_COMMAND
        if self.p_mean is None:
            self.p_mean = (meas.p_a, meas.p_b)
        elif self.t_release is None:
            k = min(dt / RELEASE_TAU_S, 1.0)
            self.p_mean = (self.p_mean[0] + k * (meas.p_a - self.p_mean[0]),
                           self.p_mean[1] + k * (meas.p_b - self.p_mean[1]))
        if self.t_release is None and self.ending == "stopped":
            self._begin_release(meas)
        if self.t_release is not None:
            return self._release(meas.t)
        if self.t_prog is None:
            if meas.t - self.t0 < self.pressurise_s:
                z = self.spec.pw_bar - self.controller.config.p_atm_bar  # PRV static map P = z + P_atm (SPEC §3)
                return Command(z, z, SAFE_COMMAND.u_a, SAFE_COMMAND.u_b)
            self.t_prog = meas.t
            self.on_program_start(meas.t)
        tr = meas.t - self.t_prog
        if self.t_d is not None and not self.disturbed and tr >= self.t_d:
            self.disturbed = True
            self.on_disturbance()
        cmd = self.controller.step(meas, dt)
        self.rows.append((tr, meas.torque, float(self.controller.mode), meas.p_a, meas.p_b, meas.theta))
        if tr >= self.t_end + 0.5:
            self._begin_release(meas)
        return cmd

    def _begin_release(self, meas: Measurement) -> None:
        self.t_release = meas.t
        if self.on_release is not None:
            try:
                self.on_release(meas.t)
            except Exception:  # the simulated user's cue runs in the loop: it must not fault the rig
                logger.exception("the release's callback failed")
        if meas.t == self.t0:  # stopped before its first period gave a command: nothing to lower
            self.done = True
        else:
            # averaged, not one sample: a small chamber under the thesis's gains can toggle 1.4 bar
            # from one period to the next (SC-4's hold), and one sample set the release 0.7 bar high
            assert self.p_mean is not None  # step keeps it from the first period on
            self.release_from = self.p_mean

    def _release(self, t: float) -> Command:
        assert self.t_release is not None
        cmd = release_command(t, self.t_release, self.release_from, self.controller.config.p_atm_bar)
        if self.done or cmd == SAFE_COMMAND:
            self.done = True
            return SAFE_COMMAND
        return cmd

    @property
    def fraction(self) -> float:
        """Share of the run done [0, 1]."""
        if self.t_prog is None or not self.rows:
            return 0.0
        return min(1.0, self.rows[-1][0] / (self.t_end + 0.5))


class Station:
    """Owns the backend and the engine thread; every action is a state transition.

    Args:
        backend_factory: Builds the backend for a connection, given the
            engine's clock, period [s] and :class:`Rig` (simulator by default).
        data_dir: Where run logs are written.
        sink: Optional run store.
        rate_hz: Control rate [Hz].
        realtime: Run the paced loop at SCHED_FIFO priority where the OS allows it.
        limits: Safety limits beyond each rig's defaults (``SafetyLimits``
            field → value, e.g. ``{"p_max_bar": 5.0}``).
        stall_s: The engine watchdog's stall time [s].
        hardware: The hardware configuration (backend, channels, scaling);
            its backend replaces ``backend_factory`` unless it is ``sim``.
        hardware_path: Where ``hardware`` came from; calibrations are saved there.

    Attributes:
        p_atm_bar: The lab's atmosphere [bar abs] (``hardware.p_atm_bar``; sea
            level without a configuration): the PRVs regulate above it (Eq 3.7),
            the controllers and procedures command with it, the simulated rig
            lives in it, and every log records it.
    """

    def __init__(
        self,
        backend_factory: Callable[[WallClock, float, Rig], HardwareInterface] | None = None,
        data_dir: Path | str = "data",
        sink: RunSink | None = None,
        rate_hz: float = CONTROL_RATE_HZ,
        realtime: bool = False,
        limits: dict[str, Any] | None = None,
        stall_s: float = 1.0,
        hardware: HardwareConfig | None = None,
        hardware_path: Path | str | None = None,
    ) -> None:
        self.hardware = hardware
        self.hardware_path = Path(hardware_path) if hardware_path is not None else None
        self.p_atm_bar = hardware.p_atm_bar if hardware is not None else P_ATM / BAR
        if hardware is not None:
            backend_factory = backend_factory or make_factory(hardware)
            limits = {**hardware.limits, **(limits or {})}
        self.realtime = realtime
        self.limit_overrides = dict(limits or {})
        SafetyLimits.for_rig("rotary", **self.limit_overrides)  # refuse bad limits at construction
        self.stall_s = stall_s
        self.safety = SafetySupervisor(SafetyLimits.for_rig("rotary", **self.limit_overrides), 1.0 / rate_hz,
                                       p_atm_bar=self.p_atm_bar)
        self.backend_factory = backend_factory or partial(_sim_backend, p_atm_bar=self.p_atm_bar)
        self.data_dir = Path(data_dir)
        self.sink = sink
        self.rate_hz = rate_hz
        self.live = LiveBuffer(rate_hz=ROTARY_IDENT_RATE_HZ)
        self.clock = WallClock()
        self.backend: HardwareInterface | None = None
        self.rig = Rig()
        self.engine: Engine | None = None
        self.supervisor: Supervisor | None = None
        self._state = State.DISCONNECTED
        self._lock = threading.RLock()
        self._job: RunJob | None = None
        self._proc: Any = None
        self._proc_kind = ""
        self._proc_fit: Callable[[Any], dict[str, Any]] = dict
        self._log: RunLogWriter | None = None
        self._proc_log: RunLogWriter | None = None  # an identification's own log (not the protocol's)
        self._run_id: int | None = None
        self.last_run: dict[str, Any] | None = None
        self.fault_message = ""
        self._watch: threading.Thread | None = None
        self._watch_stop = threading.Event()
        self.heap_frozen = 0  # objects exempted from collection at the last connect (see settle_heap)
        self.heap_refreeze_ms = 0.0  # how long the watcher's last refreeze took [ms] (see refreeze_heap)

    # ------------------------------------------------------------------ state

    @property
    def state(self) -> State:
        """Current state (an engine error or a safety fault latches :attr:`State.FAULT`)."""
        with self._lock:
            if self._state != State.FAULT:
                f = self.safety.fault
                if f is not None:
                    self.fault_message = f.message
                    self._state = State.FAULT
                elif self.engine is not None and self.engine.error is not None:
                    self.fault_message = f"{type(self.engine.error).__name__}: {self.engine.error}"
                    self._state = State.FAULT
            return self._state

    def allowed(self) -> list[str]:
        """Actions legal now."""
        st = self.state
        scaled = isinstance(getattr(self.backend, "config", None), HardwareConfig)
        return [a for a, ok in ALLOWED.items()
                if st in ok and (a != "calibrate" or scaled) and self._backend_refuses(a) is None]

    def _backend_refuses(self, action: str) -> str | None:
        """Why the connected backend cannot do ``action`` whatever the state (``None`` if it can)."""
        if action == "estimate" and self.backend is not None and not self.backend.responds_to_commands:
            # a procedure measures how the rig answers its commands; a recording answers none of them
            return (f"the {self.backend.name} backend plays a recorded log and does not respond to commands; "
                    "identification and the diagnosis protocol need the rig or the simulator (disconnect and "
                    "connect another backend)")
        return None

    def _require(self, action: str) -> None:
        st = self.state
        if st not in ALLOWED[action]:
            raise TransitionError(action, st)

    def require(self, action: str, rig: str | None = None) -> None:
        """Raise :class:`TransitionError` unless ``action`` is legal now (on ``rig``, if given).

        Lets a caller refuse before it does costly preparation; the action
        itself checks again under the lock.
        """
        with self._lock:
            self._require(action)
            if rig is not None and self.rig.kind != rig:
                raise TransitionError(action, self.state, f"this needs the {rig} rig; the {self.rig.kind} rig is "
                                      f"connected (disconnect and connect rig={rig})")
            why = self._backend_refuses(action)
            if why is not None:
                raise TransitionError(action, self.state, why)

    # ---------------------------------------------------------------- actions

    def connect(self, rig: Rig | None = None) -> None:
        """disconnected → idle: build and activate the backend, start the paced loop.

        Args:
            rig: Which rig (the rotary CWRR axis by default).
        """
        with self._lock:
            self._require("connect")
            rig = rig or Rig()
            self.clock = WallClock()
            backend = self.backend_factory(self.clock, 1.0 / self.rate_hz, rig)
            self.rig = rig
            self.supervisor = Supervisor(backend.safe_command())
            self.safety = SafetySupervisor(SafetyLimits.for_rig(rig.kind, **self.limit_overrides),
                                           1.0 / self.rate_hz, plant_responds=backend.responds_to_commands,
                                           p_atm_bar=self.p_atm_bar)
            # The first read/step compiles the numba kernels (seconds on a fresh
            # install); doing it here keeps that stall out of the loop's jitter.
            backend.activate()  # a real backend cannot be read before its link is open
            warm = InteractionController()
            warm.step(backend.read(), 1.0 / self.rate_hz)
            if rig.kind == "linear":
                # the linear friction fit's onset model is compiled code too; it runs beside the loop
                from app.engine.ident.fitting import compile_onset_model

                compile_onset_model()
            self.backend = backend
            self.live.clear()
            # before the loop runs: the collector's one long pause happens here, not in a period
            self.heap_frozen = settle_heap()
            self._start_engine(self.rate_hz)
            self._state = State.IDLE
            self._watch_stop.clear()
            self._watch = threading.Thread(target=self._watcher, name="cwrr-watch", daemon=True)
            self._watch.start()

    def disconnect(self) -> None:
        """idle → disconnected: stop the loop, leave the rig safe."""
        with self._lock:
            self._require("disconnect")
            self._shutdown()
            self._state = State.DISCONNECTED

    def start(self, spec: RunSpec) -> int | None:
        """idle → running: a scenario run; returns the stored run id (None without a store)."""
        with self._lock:
            self._require("start")
            if self.rig.kind != "rotary":
                raise TransitionError("start", self.state, f"workouts run on the rotary rig; the {self.rig.kind} "
                                      "rig is connected (disconnect and connect rig=rotary)")
            assert self.backend is not None and self.supervisor is not None
            settings = spec.settings
            case = spec.case
            prog, t_end, t_d = case_program(case, settings)
            ctl = InteractionController(replace(spec.controller_config(), p_atm_bar=self.p_atm_bar))
            backend = self.backend
            set_program = getattr(backend, "set_program", None)
            set_dist = getattr(backend, "set_disturbance", None)

            # a run started while the simulated user is away from neutral: they bring the
            # handle back during pressurising (which waits for them), then the program starts
            pressurise_s = PRESSURISE_S
            last = self.live.latest()
            if set_program is not None and last is not None:
                from app.engine.human import HumanProgram

                theta = float(last[LIVE_COLUMNS.index("theta")])
                start_pos = float(prog.pos[0])
                if abs(theta - start_pos) > 0.01:
                    set_program(HumanProgram.move(theta, start_pos, float(last[0])))
                    pressurise_s = max(PRESSURISE_S, HumanProgram.move_time(theta, start_pos) + 0.5)

            def program_start(t_rig: float) -> None:
                if set_program is not None:  # the simulated user; a real person needs no cue here
                    from app.engine.human import HumanProgram

                    set_program(HumanProgram(prog.t + t_rig, prog.pos))  # programs run on rig time

            def disturb() -> None:
                if spec.scenario == "SC-4" and set_dist is not None:
                    set_dist(0.0, settings.dp_b_bar)

            job = RunJob(spec, ctl, t_end, t_d, program_start, disturb, pressurise_s=pressurise_s,
                         on_release=lambda _t: self._user_comes_back())
            name = new_log_name(self.data_dir / "runs", "run")
            meta = {"rig": "rotary", "sample_rate_hz": self.rate_hz, "p_atm_bar": self.p_atm_bar,
                    "working_pressure_bar": spec.pw_bar, "experiment": "workout", "human": True,
                    "backend": backend.name, **asdict(spec)}
            run_log, run_id = self._begin_record("start", "workout", asdict(spec),
                                                 lambda: RunLogWriter(self.data_dir / "runs", name, meta,
                                                                      threaded=True))
            assert run_log is not None
            self._log, self._run_id = run_log, run_id
            self._job = job
            assert self.engine is not None
            self.engine.recorder = self._log
            self.supervisor.job = job
            self._state = State.RUNNING
            return self._run_id

    def estimate(self, procedure: Any, kind: RunKind, fit: Callable[[Any], dict[str, Any]],
                 rig: str = "rotary", spec: dict[str, Any] | None = None,
                 rate_hz: float | None = None, recorder: Recorder | None = None) -> int | None:
        """idle → identifying: run an identification procedure at its rate.

        Args:
            procedure: A :class:`~app.engine.ident.procedure.Procedure`.
            kind: Result kind (e.g. ``"rotary_friction"``).
            fit: Turns the finished procedure into a JSON-able result.
            rig: The rig the procedure needs (one of :data:`RIG_KINDS`).
            spec: What was asked for (stored with the run).
            rate_hz: Loop rate [Hz]; default 500 on the rotary rig (thesis
                4.2.1), 200 on the others (4.2.2).
            recorder: Receives every period's log row while the procedure
                runs (the diagnosis protocol's logs). Without one, the
                procedure's periods are logged as one run log (the fixed
                format, exported like a workout's).
        """
        with self._lock:
            self.require("estimate", rig)
            assert self.backend is not None and self.supervisor is not None
            set_program = getattr(self.backend, "set_program", None)
            if set_program is not None:
                from app.engine.human import HumanProgram

                set_program(HumanProgram.absent())  # nobody holds the handle during identification
            rate = rate_hz or (ROTARY_IDENT_RATE_HZ if rig == "rotary" else LINEAR_IDENT_RATE_HZ)
            # recorded first: a run that cannot be recorded changes nothing (the loop keeps running)
            proc_log, run_id = self._begin_record(
                "estimate", kind, {"procedure": procedure.name, **(spec or {})},
                None if recorder is not None else lambda: self._procedure_log(kind, rig, rate, spec or {}))
            self._stop_engine()
            self._proc, self._proc_kind, self._proc_fit = procedure, kind, fit
            self._proc_log, self._run_id = proc_log, run_id
            self.supervisor.job = procedure
            self._start_engine(rate)
            assert self.engine is not None
            self.engine.recorder = recorder if recorder is not None else self._proc_log
            self._state = State.IDENTIFYING
            return self._run_id

    def _begin_record(self, action: str, kind: RunKind, spec: dict[str, Any],
                      make_log: Callable[[], RunLogWriter] | None) -> tuple[RunLogWriter | None, int | None]:
        """Open the run's log and its row in the store, or raise :class:`TransitionError` saying why not.

        A full disk or a store gone had let the log's exception through (a 500), left a log open
        with its threads running when the store then failed, and, for an identification, the
        engine stopped with the station still idle.
        """
        run_log = None
        try:
            run_log = make_log() if make_log is not None else None
            run_id = self.sink.run_started(kind, spec, str(run_log.csv_path) if run_log is not None else "") \
                if self.sink else None
        except Exception as exc:  # sqlite3's errors are not OSErrors: any failure to record is one
            if run_log is not None:  # a log of nothing, under a run nobody will see: not kept
                run_log.close("failed")
                run_log.csv_path.unlink(missing_ok=True)
                run_log.json_path.unlink(missing_ok=True)
            raise TransitionError(action, self.state, f"the run cannot be recorded ({exc}); free space in the "
                                  "data folder, or check the run store") from exc
        return run_log, run_id

    def _procedure_log(self, kind: str, rig: str, rate_hz: float, spec: dict[str, Any]) -> RunLogWriter:
        """The run log of an identification: every period the procedure drives, in the fixed format.

        The thesis's GUIs kept each experiment's data; a researcher refits it, plots it, or hands a
        rotary friction sweep to the gap diagnosis as a calibration log. A procedure that names no
        working pressure (the linear friction sweep, the valve map over supplies) is logged at the
        thesis's 3 bar abs, and the metadata says it is that default.
        """
        pw = spec.get("pw_bar")
        if pw is None and spec.get("ps_bar"):
            pw = max(spec["ps_bar"])  # the valve map's highest supply
        meta: dict[str, Any] = {
            "rig": "rotary" if rig == "rotary" else "linear", "setup": rig, "sample_rate_hz": rate_hz,
            "p_atm_bar": self.p_atm_bar, "working_pressure_bar": float(pw if pw is not None else DEFAULT_PW_BAR),
            "experiment": kind, "human": False, "backend": self.backend.name if self.backend else "",
            **({"working_pressure_note": "the thesis's default: the procedure sets its own pressures"}
               if pw is None else {}),
            **({"cylinder": self.rig.cylinder} if rig != "rotary" else {})}
        runs = self.data_dir / "runs"
        return RunLogWriter(runs, new_log_name(runs, kind), meta, threaded=True)

    def run_protocol(self, repetitions: int = 2, scale: float = 1.0, kinds: list[str] | None = None,
                     person: str = "", notes: str = "", session_id: int | None = None) -> int | None:
        """idle → identifying: the diagnosis protocol's experiments on the connected rotary rig.

        Each experiment's log is stored as a run of kind ``protocol`` as soon
        as it ran to its end (so a stop, a fault or a crash later keeps it);
        the protocol's own run lists them (``result.run_ids``: what a
        diagnosis takes). See :mod:`app.engine.diagnosis.rig_protocol`.
        ``person`` (pseudonymous id) and ``session_id`` are kept with the
        protocol's run, each experiment's run and each log's metadata;
        ``notes`` with the protocol's run.

        Raises:
            ValueError: A bad argument, named (nothing moves).
            TransitionError: Not idle, or not the rotary rig.
        """
        from app.engine.diagnosis.rig_protocol import ProtocolProcedure

        with self._lock:
            self.require("estimate", "rotary")
            assert self.backend is not None
            outdir = self.data_dir / "runs" / new_log_name(self.data_dir / "runs", "protocol")
            sink = self.sink
            logs: list[dict[str, Any]] = []
            who: dict[str, Any] = {"person": person, "session_id": session_id}

            def store_log(csv: Path, meta: dict[str, Any]) -> None:  # as each experiment ends: a crash later keeps it
                rid = sink.run_started("protocol", {"experiment": meta["experiment"],
                                                    "repetition": meta["repetition"], "log": csv.stem, **who},
                                       str(csv)) if sink else None
                if sink is not None and rid is not None:
                    sink.run_finished(rid, "complete", None, {"log": csv.stem})
                logs.append({"name": csv.stem, "run_id": rid})

            proc = ProtocolProcedure(outdir, repetitions, scale, kinds, rate_hz=self.rate_hz, p_atm_bar=self.p_atm_bar,
                                     backend=self.backend.name, set_program=getattr(self.backend, "set_program", None),
                                     on_log=store_log, meta=who)
            spec = {"repetitions": repetitions, "scale": scale, "kinds": proc.kinds, **who, "notes": notes}

            def store_logs(p: ProtocolProcedure) -> dict[str, Any]:
                p.finish_logs()  # the writer has stored every finished experiment's log by now
                return {"log_dir": str(outdir), "logs": list(logs),
                        "run_ids": [g["run_id"] for g in logs if g["run_id"] is not None]}

            return self.estimate(proc, "diagnosis_protocol", store_logs, rig="rotary", spec=spec,
                                 rate_hz=self.rate_hz, recorder=proc)

    def stop(self) -> None:
        """running/identifying → stopping → idle: end the work early, keeping what was recorded."""
        with self._lock:
            self._require("stop")
            if self._state == State.IDENTIFYING:
                self._proc.cancel()  # the procedure vents and keeps its data; the watcher finishes it
                self._state = State.STOPPING
                return
            job = self._job
            assert job is not None
            job.request_stop()
            self._state = State.STOPPING
        # the engine lowers the pressures (RELEASE_S) and the watcher then ends the run; waited for here
        # so that STOP answers with the run ended, as before the release. A loop that no longer steps
        # the job (it ended, or hangs) has the run ended here instead
        deadline = time.monotonic() + RELEASE_S + 1.0
        while time.monotonic() < deadline:
            with self._lock:
                if self._job is not job:
                    return
            time.sleep(0.01)
        with self._lock:
            if self._job is job:
                self._finish_run("stopped")

    def clear(self) -> None:
        """fault → disconnected: acknowledge the fault, drop the backend (the explicit reset)."""
        with self._lock:
            self._require("clear")
            self._shutdown()
            self.fault_message = ""
            self.safety.reset()
            self._state = State.DISCONNECTED

    def estop(self, source: str = "API") -> None:
        """Emergency stop, from any state: latch a fault; the next period writes the safe state.

        Legal everywhere (never a :class:`TransitionError`): pressing it twice,
        or while disconnected, still leaves a latched fault to clear.
        """
        fault = self.safety.trip("estop", f"emergency stop ({source})", self._engine_now)
        with self._lock:
            if self._state != State.FAULT:
                self.fault_message = fault.message  # the first fault latched, maybe an earlier one
                self._state = State.FAULT

    def calibrate(self, what: str, seconds: float = 1.0, p_atm_bar: float | None = None) -> dict[str, Any]:
        """Zero a sensor from ``seconds`` of idle samples and save the configuration with today's date.

        The station must be idle (chambers venting, nobody holding the handle
        for the torque zero, the handle at neutral for the encoder zero).

        Args:
            what: ``torque_zero``, ``pressure_offsets`` (chambers a and b at
                atmosphere) or ``encoder_zero``.
            seconds: Averaging time [s].
            p_atm_bar: The atmosphere the vented chambers read [bar abs]
                (default: the station's, :attr:`p_atm_bar`; a barometer's
                reading of the day is closer).

        Returns:
            What changed: ``{"what", "date", "samples", "before", "after"}``.

        Raises:
            TransitionError: Not idle, or the backend has no sensor scaling (the simulator).
            ParameterError: The samples say the rig is not in the state the zero needs.
        """
        if what not in ("torque_zero", "pressure_offsets", "encoder_zero"):
            raise ParameterError(f"what = {what!r} must be torque_zero, pressure_offsets or encoder_zero")
        check_range("seconds", seconds, 0.2, 30.0, unit="s")
        p_atm_bar = self.p_atm_bar if p_atm_bar is None else p_atm_bar
        check_range("p_atm_bar", p_atm_bar, 0.7, 1.1, unit="bar abs")
        with self._lock:
            self._require("calibrate")
            cfg = getattr(self.backend, "config", None)
            if not isinstance(cfg, HardwareConfig):
                raise TransitionError("calibrate", self.state, f"the {self.backend.name if self.backend else ''} "
                                      "backend has no sensor scaling to calibrate (modbus and quanser do)")
            last = self.live.latest()
            t_from = float(last[0]) if last is not None else -1.0
        time.sleep(seconds)  # the loop keeps sampling meanwhile; the live buffer holds the samples
        rows = self.live.since(t_from, 100_000)
        with self._lock:
            if self.state != State.IDLE or getattr(self.backend, "config", None) is not cfg:
                raise TransitionError("calibrate", self.state, "the station changed state while calibrating")
            assert isinstance(cfg, HardwareConfig)
            if len(rows) < 10:
                raise ParameterError(f"seconds = {seconds}: only {len(rows)} samples arrived; is the loop running?")
            col = {c: rows[:, i] for i, c in enumerate(LIVE_COLUMNS)}
            if what == "torque_zero":
                m, sd = float(np.mean(col["torque"])), float(np.std(col["torque"]))
                if abs(m) > 1.0 or sd > 0.2:
                    raise ParameterError(f"what = torque_zero: the torque reads {m:.2f} ± {sd:.2f} N·m; let go of "
                                         "the handle (nobody may hold it while the sensor is zeroed)")
                tq = cfg.inputs.torque
                new = cfg.calibrated(what, inputs=cfg.inputs.model_copy(
                    update={"torque": tq.model_copy(update={"offset": tq.offset - m})}))
                before, after = {"torque_offset_nm": tq.offset}, {"torque_offset_nm": tq.offset - m}
            elif what == "pressure_offsets":
                ma, mb = float(np.mean(col["p_a"])), float(np.mean(col["p_b"]))
                if max(abs(ma - p_atm_bar), abs(mb - p_atm_bar)) > 0.3:
                    raise ParameterError(f"what = pressure_offsets: the chambers read {ma:.2f} and {mb:.2f} bar abs, "
                                         f"not the atmosphere ({p_atm_bar:.2f}); wait until they have vented")
                pa, pb = cfg.inputs.p_a, cfg.inputs.p_b
                new = cfg.calibrated(what, inputs=cfg.inputs.model_copy(update={
                    "p_a": pa.model_copy(update={"offset": pa.offset - (ma - p_atm_bar)}),
                    "p_b": pb.model_copy(update={"offset": pb.offset - (mb - p_atm_bar)})}))
                before = {"p_a_offset_bar": pa.offset, "p_b_offset_bar": pb.offset}
                after = {"p_a_offset_bar": new.inputs.p_a.offset, "p_b_offset_bar": new.inputs.p_b.offset}
            else:
                m, w = float(np.mean(col["theta"])), float(np.max(np.abs(col["omega"])))
                if w > 0.05:
                    raise ParameterError(f"what = encoder_zero: the handle moves ({w:.2f} rad/s); hold it still "
                                         "at neutral")
                enc = cfg.encoder
                # the reading becomes zero: the neutral angle, or the linear piston's position now
                shift = enc.position_to_counts(m, self.rig.kind) - enc.zero_counts
                new = cfg.calibrated(what, encoder=enc.model_copy(update={"zero_counts": enc.zero_counts + shift}))
                before, after = {"zero_counts": enc.zero_counts}, {"zero_counts": enc.zero_counts + shift}
            if self.hardware_path is not None:
                try:
                    save_config(new, self.hardware_path)  # atomic: the old file or the new, never half
                except OSError as exc:  # saved first: a calibration not saved is not applied either
                    raise TransitionError("calibrate", self.state, f"the calibration cannot be saved to "
                                          f"{self.hardware_path} ({exc.strerror or exc}); nothing changed") from exc
            self.backend.config = new  # type: ignore[union-attr]
            self.hardware = new
            date = getattr(new.calibration, what)
        return {"what": what, "date": date, "samples": len(rows), "before": before, "after": after,
                "saved_to": str(self.hardware_path) if self.hardware_path else None}

    def close(self) -> None:
        """Stop everything (server shutdown)."""
        with self._lock:
            if self._job is not None:
                self._finish_run("interrupted")
            if self._proc is not None:
                self._proc.cancel()
            self._shutdown()
            if self._proc_log is not None:  # the loop has stopped: its last rows are in, the log says why it ends
                self._proc_log.close("interrupted")
                self._proc_log = None
            self._state = State.DISCONNECTED

    # --------------------------------------------------------------- reports

    def status(self) -> dict[str, Any]:
        """State, allowed actions and progress of the current work."""
        st = self.state
        cfg = getattr(self.backend, "config", None)
        out: dict[str, Any] = {"state": st.value, "allowed": self.allowed(), "run_id": self._run_id,
                               "backend": self.backend.name if self.backend else None,
                               "calibration": (cfg.calibration.model_dump() if isinstance(cfg, HardwareConfig)
                                               else None),
                               "rig": self._rig_status() if self.backend else None,
                               "fault": self.fault_message, "progress": None, "last_run": self.last_run,
                               "safety": self.safety.status(), "p_atm_bar": self.p_atm_bar}
        if self._job is not None:
            out["progress"] = {"kind": "workout", "fraction": self._job.fraction,
                               "phase": ("releasing" if self._job.t_release is not None
                                         else "pressurising" if self._job.t_prog is None else "exercising")}
        elif self._proc is not None:
            out["progress"] = {"kind": self._proc_kind, **self._proc.progress.as_dict()}
        return out

    def _rig_status(self) -> dict[str, Any]:
        """The connected rig, with the cylinder's catalogue stroke [mm] on the linear set-ups."""
        stroke = self.rig.stroke
        return asdict(self.rig) | {"stroke_mm": None if stroke is None else round(stroke * 1e3, 6)}

    def health(self) -> dict[str, Any]:
        """Loop health for ``/api/health``."""
        st = self.engine.stats() if self.engine is not None else None
        base: dict[str, Any] = asdict(st) if st is not None else {"ticks": 0, "overruns": 0, "jitter_p50_ms": 0.0,
                                                  "jitter_p99_ms": 0.0, "jitter_max_ms": 0.0,
                                                  "rate_hz": self.rate_hz, "measured_rate_hz": 0.0,
                                                  "realtime": False}
        base["realtime_note"] = self.engine.realtime_note if self.engine is not None else "engine not running"
        base |= {"switch_interval_ms": round(sys.getswitchinterval() * 1e3, 6), "heap_frozen": self.heap_frozen,
                 "heap_refreeze_ms": self.heap_refreeze_ms}
        return {"state": self.state.value, "backend": self.backend.name if self.backend else "none", **base}

    # -------------------------------------------------------------- internals

    def _on_tick(self, meas: Measurement, cmd: Command) -> None:
        job = self._job
        if job is not None and job.t_prog is not None:
            i = job.controller.internals()
            self.live.append((meas.t, meas.torque, job.spec.target_nm, meas.p_a, meas.p_b, i["p_ref_a"],
                              i["p_ref_b"], meas.omega, meas.theta))
        else:
            self.live.append((meas.t, meas.torque, math.nan, meas.p_a, meas.p_b, math.nan, math.nan,
                              meas.omega, meas.theta))

    def _start_engine(self, rate_hz: float) -> None:
        assert self.backend is not None and self.supervisor is not None
        if hasattr(self.backend, "period"):
            self.backend.period = 1.0 / rate_hz
        self.safety.period = 1.0 / rate_hz
        self.engine = Engine(self.backend, self.supervisor, self.clock, rate_hz, safety=self.safety,
                             on_tick=self._on_tick, realtime=self.realtime, stall_s=self.stall_s)
        self.engine.start()

    def _stop_engine(self) -> None:
        if self.engine is not None:
            self.engine.stop()

    def _shutdown(self) -> None:
        self._watch_stop.set()
        self._stop_engine()
        if self.backend is not None:
            self.backend.deactivate()
        self.engine = None
        self.backend = None
        self._job = None
        self._proc = None

    def _watcher(self) -> None:
        """Finishes work that ended by itself (off the engine thread)."""
        fault_seen: float | None = None
        frozen_at = time.monotonic()
        while not self._watch_stop.wait(0.05):
            if time.monotonic() - frozen_at >= REFREEZE_S:
                self.heap_refreeze_ms = refreeze_heap()
                frozen_at = time.monotonic()
            try:
                fault_seen = self._watch_once(fault_seen)
            except Exception as exc:  # an unforeseen error must not end the thread that ends runs
                logger.exception("station watcher")
                why = f"ending the work under way failed ({type(exc).__name__}: {exc})"
                self.safety.trip("engine_error", why, self._engine_now)
                with self._lock:
                    self._drop_work(why)

    def _drop_work(self, why: str) -> None:
        """Take the work under way off the station after ending it failed (the fault is latched)."""
        for run_log in (self._log, self._proc_log):
            if run_log is not None:
                run_log.close("fault")  # never raises for the disk
        if self._job is not None or self._proc is not None:
            self._store_end("fault", None, {"error": why})
            self.last_run = {"run_id": self._run_id, "status": "fault", "metrics": None}
        if self.supervisor is not None:
            self.supervisor.job = None
        if self.engine is not None:
            self.engine.recorder = None
        if self._proc is not None:
            self._proc.cancel()
        self._job, self._log, self._proc_log, self._proc = None, None, None, None

    def _watch_once(self, fault_seen: float | None) -> float | None:
        """One look of the watcher; returns when it first saw the latched fault (None: no fault)."""
        with self._lock:
            if self.state == State.FAULT:
                fault_seen = fault_seen or time.monotonic()
                # the record ends with the safe state in it: wait for a period after the fault
                # (at most 0.5 s: a dead loop will not log one)
                if self._job is not None and (self._safe_period_logged()
                                              or time.monotonic() - fault_seen > 0.5):
                    self._finish_run("fault")
                if self._proc is not None:
                    self._abort_procedure("fault")
                return fault_seen
            why = self._log_failure()
            if why:  # a full or failing disk: the run went on unrecorded, and STOP raised
                self.safety.trip("log_failed", why, self._engine_now)
                return None
            if self._job is not None and self._job.done:
                self._finish_run(self._job.ending)
            elif self._proc is not None and self._proc.finished:
                self._finish_procedure()
            return None

    def _engine_now(self) -> float:
        """The engine's last completed period's time [s] (NaN before one): a fault tripped from another
        thread reads it once the fault is in force (SafetySupervisor.trip)."""
        engine = self.engine
        last = engine.last_measurement if engine is not None else None
        return last.t if last is not None else math.nan

    def _log_failure(self) -> str:
        """Why the work under way cannot be recorded ("" while it can)."""
        for what, err in (("run", self._log.error if self._log is not None else ""),
                          ("run", self._proc_log.error if self._proc_log is not None else ""),
                          ("protocol", getattr(self._proc, "log_error", "") if self._proc is not None else "")):
            if err:
                return (f"the {what}'s log cannot be written ({err}): stopped so that nothing goes unrecorded; "
                        "free space in the data folder, clear and start again")
        return ""

    def _safe_period_logged(self) -> bool:
        """Whether the log holds a period that began after the fault was latched (so wrote the safe state).

        The fault's time is the measurement it was found in (or, for an
        e-stop, the last one before the press); the period under way then may
        still finish with its own command, so the one after it is awaited.
        """
        f, eng = self.safety.fault, self.engine
        if f is None or eng is None or eng.last_measurement is None or not math.isfinite(f.t):
            return True
        return eng.last_measurement.t > f.t + 1.5 * eng.period

    def _user_comes_back(self) -> None:
        """The simulated user, told the exercise is over, eases off their push over :data:`RELEASE_S`
        where the handle is (as the controlled stop eases the robot's), waits for the chambers to vent,
        then lowers the arm back to neutral (snapping back would yank it) and relaxes. A real person
        needs no cue.

        Letting go of a 1.4 N·m push within one period had thrown the handle at 1.3 rad/s against the
        robot's torque. Static friction stops the vented vane short of neutral (≈ 0.06 rad); pressing
        on there, the arm's pull had shown 1.2 N·m on the idle station until the next run.
        """
        set_program = getattr(self.backend, "set_program", None)
        if set_program is None:
            return
        from app.engine.human import HumanProgram

        last = self.live.latest()
        if last is None:
            set_program(HumanProgram.rest())
            return
        t0, theta = float(last[0]), float(last[LIVE_COLUMNS.index("theta")])
        human = getattr(getattr(self.backend, "params", None), "human", None)
        push = 0.0
        if human is not None and human.stiffness > 0.0:
            # the arm's push as the sensor reads it, held at first: the angle the arm then aims at
            recent = self.live.since(t0 - 0.02, 100)
            torque = float(np.mean(recent[:, LIVE_COLUMNS.index("torque")])) if len(recent) else 0.0
            push = float(np.clip(torque, -human.torque_limit, human.torque_limit)) / human.stiffness
        back = HumanProgram.move(theta, 0.0, t0, wait_s=max(1.0, RELEASE_S))
        eased = HumanProgram(np.r_[t0, t0 + RELEASE_S, back.t[1:]], np.r_[theta + push, theta, back.pos[1:]])
        set_program(eased.let_go(float(eased.t[-1]) + RELAX_AFTER_RUN_S))

    def _finish_run(self, status: str) -> None:
        job, log = self._job, self._log
        assert job is not None and self.supervisor is not None
        self.supervisor.job = None
        if self.engine is not None:
            self.engine.recorder = None
        set_dist = getattr(self.backend, "set_disturbance", None)
        if set_dist is not None:
            set_dist(0.0, 0.0)
        if job.t_release is None:  # ended without the controlled stop (a fault, the server stopping)
            self._user_comes_back()
        metrics: dict[str, Any] | None = None
        result: dict[str, Any] = {"window_s": None}
        if len(job.rows) > 10:
            a = np.asarray(job.rows)
            # an overrun followed by a catch-up tick can sample the plant twice at
            # one rig time; the metrics need strictly increasing times
            a = a[np.r_[True, np.diff(a[:, 0]) > 0]]
            result["angle_range_deg"] = angle_range_deg(a[:, 5])
            try:
                m, window, t_on = score_case(job.spec.case, a[:, 0], a[:, 1], a[:, 2], job.t_end, job.t_d,
                                             job.spec.settings)
                w_end = min(window[1], float(a[-1, 0]))
                # the window and the engagement count from the program's start (after pressurising);
                # program_start_s puts them on the run log's clock, where a plot of the run needs them
                result |= {"window_s": [window[0], w_end], "t_engage_s": t_on if math.isfinite(t_on) else None,
                           "partial": w_end < window[1], "program_start_s": job.t_prog}
                if w_end - window[0] >= MIN_PARTIAL_WINDOW_S:
                    metrics = m  # a stopped run is scored over the part of the window it reached
                    result |= toggle_report(a[:, 0], a[:, 3], a[:, 4], (window[0], w_end))
                else:
                    result["note"] = (f"stopped {max(w_end - window[0], 0.0):.2f} s into the evaluation window; "
                                      f"metrics need at least {MIN_PARTIAL_WINDOW_S:g} s")
            except ValueError as exc:  # too short a window (stopped early)
                result |= {"window_s": None, "note": str(exc)}
            except Exception as exc:  # a scoring bug must not keep the run from ending (STOP, the watcher)
                logger.exception("run %s: scoring failed", self._run_id)
                result |= {"window_s": None, "note": f"scoring failed ({type(exc).__name__}: {exc})"}
        if status == "fault":
            result["fault"] = self._fault_detail()
        if log is not None:
            log.close(status, metrics=metrics)
        self._store_end(status, metrics, result)
        self.last_run = {"run_id": self._run_id, "status": status, "metrics": metrics}
        if result.get("angle_range_deg") is not None:
            self.last_run["angle_range_deg"] = result["angle_range_deg"]
        if result.get("warnings"):  # shown with the metrics wherever they are (the dashboard, viser)
            self.last_run["warnings"] = list(result["warnings"])
        self._job, self._log = None, None
        if self._state != State.FAULT:
            self._state = State.IDLE

    def _store_end(self, status: str, metrics: dict[str, Any] | None, result: dict[str, Any]) -> None:
        """Record how the run ended; a store that cannot take it (a full disk) does not keep the station
        from ending the run: the run stays "running" there, and the next start calls it interrupted."""
        if self.sink is None or self._run_id is None:
            return
        try:
            self.sink.run_finished(self._run_id, status, metrics, result)
        except Exception as exc:
            logger.error("run %s ended %s but the store could not record it: %s", self._run_id, status, exc)

    def _fault_detail(self) -> dict[str, Any]:
        f = self.safety.fault
        return f.as_dict() if f is not None else {"code": "engine_error", "message": self.fault_message}

    def _abort_procedure(self, status: str) -> None:
        """A fault ended the identification: store what it had, leave the engine writing safe outputs."""
        proc = self._proc
        proc.cancel()
        result: dict[str, Any] = {"progress": proc.progress.as_dict(), "fault": self._fault_detail()}
        if getattr(proc, "fit_on_abort", False):  # what ran to its end is still good (the protocol's logs)
            self._detach_recorder(proc)  # before the fit waits for its logs
            try:
                result |= self._proc_fit(proc)
            except Exception as exc:
                result["error"] = f"{type(exc).__name__}: {exc}"
        self._record_procedure(status, result)

    def _record_procedure(self, status: str, result: dict[str, Any]) -> None:
        """Store how the procedure ended and take it off the loop."""
        if self._proc_log is not None:  # closed first: a run read as ended has its whole log
            self._detach_recorder(self._proc_log)
            self._proc_log.close(status)
            self._proc_log = None
        self._store_end(status, None, result)
        self.last_run = {"run_id": self._run_id, "status": status, "result": result}
        assert self.supervisor is not None
        self.supervisor.job = None
        self._detach_recorder(self._proc)
        self._proc = None

    def _detach_recorder(self, recorder: Any) -> None:
        """Stop the loop handing its rows to ``recorder`` (if it still does)."""
        if self.engine is not None and self.engine.recorder is recorder:
            self.engine.recorder = None

    def _finish_procedure(self) -> None:
        proc = self._proc
        status = proc.progress.state
        result: dict[str, Any] | None = None
        try:
            result = self._proc_fit(proc)
        except ValueError as exc:
            # stopped before the fit had enough: that is what the operator chose, not an error (the
            # dashboard had shown "cancelled (ValueError: …)"); a finished procedure that cannot be fitted is one
            result = ({"note": f"stopped before there was enough to fit ({exc})"} if status == "cancelled"
                      else {"error": f"{type(exc).__name__}: {exc}"})
        except Exception as exc:  # a bug in a fit: keep the status, say what it was
            result = {"error": f"{type(exc).__name__}: {exc}"}
        self._record_procedure(status, {"progress": proc.progress.as_dict(), **(result or {})})
        self._stop_engine()
        self._start_engine(self.rate_hz)
        self._state = State.IDLE


def _sim_backend(clock: WallClock, period: float, rig: Rig, p_atm_bar: float = P_ATM / BAR) -> HardwareInterface:
    from app.engine.hardware.sim import SimulatedRig
    from app.engine.human import HumanProgram

    if rig.kind == "rotary":
        params = PlantParams()
    elif rig.kind == "linear":
        params = PlantParams.linear_rig(rig.cylinder)  # type: ignore[arg-type]
    else:  # Figure 3.10: PS-0 moved to the DCV's supply port
        params = PlantParams.linear_rig(rig.cylinder, sensors=SensorParams(supply_tap="prv_a"))  # type: ignore[arg-type]
    params = replace(params, p_atm=p_atm_bar * BAR)
    sim = SimulatedRig(clock, params, period=period)
    sim.set_program(HumanProgram.rest() if rig.kind == "rotary" else HumanProgram.absent())
    return sim
