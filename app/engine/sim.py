"""The simulated rig: state outside the model, a zero-order-hold stepper, and
a compiled closed-loop batch runner for faster-than-real-time workouts."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit

from app.engine.constants import BAR
from app.engine.control import pipeline as cpl
from app.engine.control.config import ControllerConfig
from app.engine.human import HumanProgram
from app.engine.params import ParameterError, PlantParams
from app.engine.physics import plant as pl
from app.engine.physics import sensors as sn
from app.engine.physics.jit import NO_REFCOUNT

LOG_COLUMNS: tuple[str, ...] = ("t", "z_a", "z_b", "u_a", "u_b", "p_a", "p_b", "p_s", "theta", "omega", "torque")
"""The run-log column set (issue 6's fixed format)."""
TRUTH_COLUMNS: tuple[str, ...] = ("ti_true", "tf_true", "theta_true", "omega_true", "pa_true", "pb_true", "mode")


class Simulator:
    """A simulated rig advanced in control periods with commands held between.

    Args:
        params: Plant parameters.
        seed: Seed of the sensor-noise generator.
        program: What the user intends (rotary rig); default: rests at neutral.
        x0: Initial state; default: at rest at neutral, both chambers at
            atmosphere.
    """

    def __init__(
        self,
        params: PlantParams | None = None,
        seed: int = 0,
        program: HumanProgram | None = None,
        x0: np.ndarray | None = None,
    ) -> None:
        self.params = params or PlantParams()
        self.kernel = pl.build_kernel(self.params)
        self.rng = np.random.default_rng(seed)
        self.program = program or HumanProgram.rest()
        self.x = pl.initial_state(self.params) if x0 is None else np.array(x0, dtype=np.float64)
        if self.x.shape != (pl.NX,):
            raise ParameterError(f"x0 must have {pl.NX} entries")
        self.t = 0.0
        self.cmd = np.array([0.0, 0.0, 5.0, 5.0, 0.0, 0.0])
        self.out = np.zeros(pl.NO)
        self._sensor_state = np.zeros(sn.NS)
        self._sc: Any = None
        self._sc_params: PlantParams | None = None
        self._noise = np.empty((0, 4))
        self._noise_i = 0
        self._meas = np.empty(sn.NM)
        # the compiled step's scratch (it is compiled without reference counting, so cannot allocate it)
        self._work = np.empty(pl.NWORK)
        self._jac = np.empty((pl.NN, pl.NN))
        self._am_fn: Any = None
        self._am_key: tuple[Any, Any, Any, Any] = (None, None, None, None)

    @property
    def substep(self) -> float:
        """Plant integration step [s]."""
        return float(self.kernel.h)

    def set_program(self, program: HumanProgram) -> None:
        """Replace what the user intends from now on."""
        self.program = program

    def set_command(self, z_a: float, z_b: float, u_a: float, u_b: float) -> None:
        """Hold these valve commands [V] from now on."""
        self.cmd[0:4] = (z_a, z_b, u_a, u_b)

    def set_disturbance(self, dp_a_bar: float = 0.0, dp_b_bar: float = 0.0) -> None:
        """Pressure disturbance at the PRV exits [bar] (SC-4: dp_b = −0.4)."""
        self.cmd[4] = dp_a_bar * BAR
        self.cmd[5] = dp_b_bar * BAR

    def advance(self, duration: float) -> None:
        """Advance ``duration`` seconds (rounded to whole substeps)."""
        n = int(round(duration / self.kernel.h))
        if n > 0:
            self.t = pl.advance(self.t, self.x, self.cmd, self.kernel, n, self.program.t, self.program.pos, self.out)

    def advance_to(self, t: float) -> None:
        """Advance to time ``t`` [s] (no-op if already past it)."""
        self.advance(t - self.t)

    def _sensor_const(self) -> Any:
        if self._sc is None or self._sc_params is not self.params:
            self._sc, self._sc_params = sn.build_sensor_const(self.params), self.params
        return self._sc

    def measure(self, dt: float) -> np.ndarray:
        """Sample the sensors (measurement vector, see :mod:`sensors`).

        Args:
            dt: Time since the previous sample [s] (the speed estimate's step).
        """
        sc = self._sensor_const()
        pa, pb = pl.chamber_pressures(self.x, self.kernel)
        ti = self.true_interaction()
        m = np.empty(sn.NM)
        ps = pl.supply_sensor_pressure(self.x, self.kernel, sc.ps_at_prv_a)
        sn.measure(pa, pb, ps, self.x[pl.I_POS], ti, sc, self.rng.standard_normal(4),
                   self._sensor_state, dt, m)
        return m

    def advance_and_measure(self, t: float, dt: float) -> np.ndarray:
        """Advance to ``t`` [s], then sample the sensors — one compiled call.

        Same result as :meth:`advance_to` then :meth:`measure` (the noise comes
        from the same generator, drawn in blocks); this is the per-period path
        of the simulated backend, where call overhead dominates.

        Args:
            t: Time to advance to [s].
            dt: The sampling period [s]. The plant moves in whole steps, so the
                time that passed since the previous sample is n·h; the speed
                estimate divides by that when it differs from ``dt`` by half a
                step or more (a late tick), and by ``dt`` itself otherwise (the
                same number, without n·h's rounding).
        """
        sc = self._sensor_const()
        if self._noise_i >= self._noise.shape[0]:
            self._noise = self.rng.standard_normal((1024, 4))
            self._noise_i = 0
        h = self.kernel.h
        n = max(0, int(round((t - self.t) / h)))
        if n > 0 and abs(n * h - dt) >= 0.5 * h:
            dt = n * h
        args = (float(self.t), self.x, self.cmd, self.kernel, n, self.program.t, self.program.pos, self.out, sc,
                self._noise[self._noise_i], self._sensor_state, float(dt), self._meas, self._work, self._jac)
        fn = self._am_fn
        key = self._am_key
        if fn is None or key[0] is not self.kernel or key[1] is not sc or key[2] is not self.program \
                or key[3] is not self.x:
            fn = self._am_fn = _compiled_entry(_advance_measure, args)
            self._am_key = (self.kernel, sc, self.program, self.x)
        self.t = fn(*args)
        self._noise_i += 1
        return self._meas

    def true_interaction(self) -> float:
        """User torque at the current state [N·m]."""
        k = self.kernel
        return float(pl.human_torque(self.t, self.x[pl.I_POS], self.x[pl.I_VEL], self.program.t,
                                     self.program.pos, k.hum_k, k.hum_d, k.hum_lim))

    def truth(self) -> dict[str, float]:
        """True (noise-free) values of the main quantities, SI except bar."""
        pa, pb = pl.chamber_pressures(self.x, self.kernel)
        return {
            "t": self.t, "theta": float(self.x[pl.I_POS]), "omega": float(self.x[pl.I_VEL]),
            "p_a_bar": pa / BAR, "p_b_bar": pb / BAR, "p_s_bar": float(self.x[pl.I_PS]) / BAR,
            "ti": self.true_interaction(), "tf": float(self.out[pl.O_TF]),
        }


def _compiled_entry(dispatcher: Any, args: tuple[Any, ...]) -> Any:
    """The machine-code entry of ``dispatcher`` for these argument types.

    A call through numba's dispatcher types every argument again (the 66-field
    kernel tuple among them): ≈ 6 µs of the ≈ 8 µs a period's call costs
    before any physics. The entry found once for the types of ``args`` is
    reused while the kernel, the sensor constants, the program and the state
    are the same objects. The entry does not check types (an int64 array would
    be read as float64), so every argument whose type could change is either
    one of those or a float64 array the simulator made itself.
    """
    sig = tuple(dispatcher.typeof_pyval(a) for a in args)
    if sig not in dispatcher.overloads:
        dispatcher.compile(sig)
    return dispatcher.overloads[sig].entry_point


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def _advance_measure(
    t: float, x: np.ndarray, cmd: np.ndarray, k: Any, n: int, prog_t: np.ndarray, prog_pos: np.ndarray,
    out: np.ndarray, sc: Any, noise: np.ndarray, st: np.ndarray, dt: float, meas: np.ndarray, work: np.ndarray,
    jac: np.ndarray,
) -> float:
    for i in range(n):
        pl.step(t + i * k.h, x, cmd, k, prog_t, prog_pos, out, work, jac)
    t += n * k.h
    pa, pb = pl.chamber_pressures(x, k)
    ti = pl.human_torque(t, x[pl.I_POS], x[pl.I_VEL], prog_t, prog_pos, k.hum_k, k.hum_d, k.hum_lim)
    sn.measure(pa, pb, pl.supply_sensor_pressure(x, k, sc.ps_at_prv_a), x[pl.I_POS], ti, sc, noise, st, dt, meas)
    return t


@njit(cache=True, error_model="numpy")
def _closed_loop(
    x: np.ndarray, k: Any, sc: Any, cp: np.ndarray, fr_est: np.ndarray, fz: np.ndarray, prog_t: np.ndarray,
    prog_pos: np.ndarray, n_ticks: int, n_sub: int, dt: float, noise: np.ndarray, dist: np.ndarray,
    log: np.ndarray, truth: np.ndarray,
) -> None:
    st_s = np.zeros(sn.NS)
    st_c = np.zeros(cpl.NSTATE)
    meas = np.empty(sn.NM)
    cmd4 = np.zeros(4)
    cmd = np.zeros(pl.NU)
    out = np.zeros(pl.NO)
    work = np.empty(pl.NWORK)
    jac = np.empty((pl.NN, pl.NN))
    t = 0.0
    for i in range(n_ticks):
        pa, pb = pl.chamber_pressures(x, k)
        ti = pl.human_torque(t, x[pl.I_POS], x[pl.I_VEL], prog_t, prog_pos, k.hum_k, k.hum_d, k.hum_lim)
        sn.measure(pa, pb, x[pl.I_PS], x[pl.I_POS], ti, sc, noise[i], st_s, dt, meas)
        cpl.control_step(meas, st_c, cp, fr_est, fz, dt, cmd4)
        cmd[0] = cmd4[0]
        cmd[1] = cmd4[1]
        cmd[2] = cmd4[2]
        cmd[3] = cmd4[3]
        cmd[4] = dist[i, 0]
        cmd[5] = dist[i, 1]
        log[i, 0] = t
        log[i, 1] = cmd[0]
        log[i, 2] = cmd[1]
        log[i, 3] = cmd[2]
        log[i, 4] = cmd[3]
        log[i, 5] = meas[sn.M_PA]
        log[i, 6] = meas[sn.M_PB]
        log[i, 7] = meas[sn.M_PS]
        log[i, 8] = meas[sn.M_POS]
        log[i, 9] = meas[sn.M_VEL]
        log[i, 10] = meas[sn.M_TQ]
        truth[i, 0] = ti
        truth[i, 1] = out[pl.O_TF]
        truth[i, 2] = x[pl.I_POS]
        truth[i, 3] = x[pl.I_VEL]
        truth[i, 4] = pa / BAR
        truth[i, 5] = pb / BAR
        truth[i, 6] = st_c[cpl.S_MODE]
        for j in range(n_sub):
            pl.step(t + j * k.h, x, cmd, k, prog_t, prog_pos, out, work, jac)
        t += n_sub * k.h


@dataclass
class WorkoutResult:
    """A simulated run: the log in the fixed column set plus the truth.

    Attributes:
        log: (n, 11) array, columns :data:`LOG_COLUMNS` (bar, V, rad, N·m).
        truth: (n, 7) array, columns :data:`TRUTH_COLUMNS`.
        meta: Run metadata (issue 6's JSON fields and more).
    """

    log: np.ndarray
    truth: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def column(self, name: str) -> np.ndarray:
        """One column of the log or the truth by name."""
        if name in LOG_COLUMNS:
            return np.asarray(self.log[:, LOG_COLUMNS.index(name)])
        return np.asarray(self.truth[:, TRUTH_COLUMNS.index(name)])


def run_workout(
    params: PlantParams | None = None,
    program: HumanProgram | None = None,
    duration: float = 60.0,
    rate_hz: float = 200.0,
    control: ControllerConfig | None = None,
    seed: int = 0,
    disturbance_bar: np.ndarray | None = None,
    pw_bar: float = 3.0,
) -> WorkoutResult:
    """Simulate a closed-loop workout faster than real time (compiled loop).

    The rig starts at rest at neutral with both chambers at ``pw_bar`` (the
    station pressurises before the user engages).

    Args:
        params: Plant parameters.
        program: What the user intends; default: a 60 s FP isotonic workout.
        duration: Simulated time [s].
        rate_hz: Control rate [Hz]; the substep rate must be a multiple.
        control: Controller; default: Default controller, 1.2 N·m, ``pw_bar``.
        seed: Sensor-noise seed.
        disturbance_bar: (n_ticks, 2) PRV-exit pressure disturbances [bar].
        pw_bar: Working pressure P_w [bar abs].
    """
    params = params or PlantParams()
    k = pl.build_kernel(params)
    n_sub_f = (1.0 / rate_hz) / k.h
    n_sub = int(round(n_sub_f))
    if n_sub < 1 or abs(n_sub - n_sub_f) > 1e-6:
        raise ParameterError(f"rate_hz = {rate_hz} must divide the plant substep rate {params.substep_hz} Hz")
    dt = n_sub * k.h
    n = int(round(duration / dt))
    if program is None:
        from app.engine.human import isotonic

        program = isotonic(+1, repetitions=8)
    control = control or ControllerConfig(controller="default", pw_bar=pw_bar, p_atm_bar=params.p_atm / BAR)
    pw_bar = control.pw_bar
    cp, fr_est, fz = control.pack()
    x = pl.initial_state(params, 0.0, pw_bar, pw_bar)
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((n, 4))
    dist = np.zeros((n, 2)) if disturbance_bar is None else np.asarray(disturbance_bar, dtype=np.float64) * BAR
    log = np.empty((n, len(LOG_COLUMNS)))
    truth = np.empty((n, len(TRUTH_COLUMNS)))
    sc = sn.build_sensor_const(params)
    _closed_loop(x, k, sc, cp, fr_est, fz, program.t, program.pos, n, n_sub, dt, noise, dist, log, truth)
    meta = {
        "rig": params.rig, "sample_rate_hz": rate_hz, "p_atm_bar": params.p_atm / BAR,
        "working_pressure_bar": pw_bar, "experiment": "workout", "human": True, "seed": seed,
        "effects": params.effects.active(), "controller": control.controller, "target_nm": control.target_nm,
        "pdra": control.pdra, "tdra": control.tdra,
    }
    return WorkoutResult(log, truth, meta)
