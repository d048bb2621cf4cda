"""Automated friction identification of the vane cylinder (thesis 3.2.4, Fig 3.13–3.19).

The sequencer follows SPEC §6 and the flowcharts of Figures 3.14–3.15:

* **static** (per direction, N_s tests): go to a random test position
  (Eq 3.15) between 20% and 80% of the ROM, vent both chambers
  (z_a = z_b = 0), set both to P_w, then ramp the driving chamber's PRV by
  0.01 V every 0.05 s with the counter chamber held at P_w, until the speed
  passes ±0.2 rad/s; the largest pneumatic torque (Eq 3.4) of the ramp is
  that test's T_s; vent.
* **dynamic** (per direction, N_d tests): counter chamber at P_w, start at
  θ_min (CCW) / θ_max (CW), set the driving PRV to the random level of
  Eq 3.16 / 3.17 and let the vane run across; keep only the steady section
  (> 60% ROM for CCW, < 40% ROM for CW) and average speed and torque there;
  stop by setting the driving chamber back to P_w, vent, return.

Two interpretation choices (the thesis is ambiguous; SPEC §1/§3 pin P_w as
absolute and the PRV map as P = z + P_atm):

* the command for "P_w" is z_w = P_w − P_atm (gauge volts), so the counter
  chamber really sits at the P_w the friction table is labelled with; the
  random levels of Eq 3.16–3.17 are offsets on that same gauge scale;
* the breakaway torque is the midpoint of the two samples bracketing the
  first encoder count (:func:`~app.engine.ident.fitting.breakaway_level`): the thesis's "max
  T_p" sits on top of the PRV's last pressure step and is biased upwards;
  it is kept beside it (``ts_max``).

Valve routing throughout: DCV-a fully open supply→a (u_a = 0 V), DCV-b fully
open supply→b (u_b = 10 V), so each PRV sets its chamber's pressure (the
interaction-control routing of 3.2.4).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from app.engine.constants import P_ATM_BAR
from app.engine.hardware.base import Command
from app.engine.ident.fitting import FrictionData, FrictionFit, breakaway_level, curve_r2, fit_friction
from app.engine.ident.gui_rules import RotaryInputs
from app.engine.ident.procedure import Procedure, Script

U_A_OPEN = 0.0  # DCV-a: supply → chamber a fully open
U_B_OPEN = 10.0  # DCV-b: supply → chamber b fully open
RAMP_STEP_V = 0.01  # SPEC §6
RAMP_PERIOD_S = 0.05
MOTION_THRESHOLD = 0.2  # rad/s
MOVE_DRIVE_V = 0.9  # pressure difference used to reposition the vane [bar]
REST_TOL_RAD = 0.0008  # half a count of the 4096-count encoder (1.53 mrad)
STATIC_RAMP_MAX_V = 4.0  # a static ramp that gains this much without motion is abandoned [V]
STALL_S = 1.0  # a dynamic run with no motion for this long is abandoned [s]


@dataclass
class StaticTest:
    """One static experiment.

    Attributes:
        direction: ``"ccw"`` or ``"cw"``.
        k: Test number (1-based) within its direction.
        theta_test: Position the test ran at [rad].
        ts: Breakaway torque [N·m] (signed; NaN if the vane never moved),
            from :func:`~app.engine.ident.fitting.breakaway_level`.
        ts_max: The thesis's statistic: largest 10 ms mean of T_p in the ramp.
        z_breakaway: Driving PRV command at detection [V].
        t_start: Start of the ramp on the engine clock [s].
        t_end: Detection time [s].
    """

    direction: str
    k: int
    theta_test: float
    ts: float
    ts_max: float
    z_breakaway: float
    t_start: float
    t_end: float


@dataclass
class DynamicTest:
    """One dynamic experiment.

    Attributes:
        direction: ``"ccw"`` or ``"cw"``.
        k: Test number (1-based) within its direction.
        z_drive: Driving PRV command (Eq 3.16/3.17) [V].
        omega: Mean speed over the steady section [rad/s] (NaN if none).
        tf: Mean friction (= pneumatic) torque over it [N·m].
        omega_sd: Speed SD over the steady section [rad/s].
        n_samples: Samples in the steady section.
        t_start: Release time [s].
        t_end: End of the run [s].
    """

    direction: str
    k: int
    z_drive: float
    omega: float
    tf: float
    omega_sd: float
    n_samples: int
    t_start: float
    t_end: float
    p_a: float = math.nan
    p_b: float = math.nan


@dataclass
class RotaryFrictionData(FrictionData[RotaryInputs, StaticTest, DynamicTest]):
    """Everything the rotary experiments produced, test by test (``arrays``: T_s, ω, T_f)."""

    STATIC_FIELD = "ts"
    SPEED_FIELD = "omega"
    FRICTION_FIELD = "tf"


class RotaryFrictionProcedure(Procedure):
    """The rotary static + dynamic experiment sequencer (Figures 3.14–3.15).

    Args:
        inputs: Validated GUI inputs.
        seed: Seed of ``rand()`` (test positions, Eq 3.15–3.17 levels).
        p_atm_bar: Atmospheric pressure [bar abs] (PRV command offset).
        settle_s: Dwell after each pressure change [s].
        run_timeout_s: Longest a dynamic run or a move may take [s].
    """

    name = "rotary_friction"

    def __init__(self, inputs: RotaryInputs, seed: int = 0, p_atm_bar: float = P_ATM_BAR, settle_s: float = 0.3,
                 run_timeout_s: float = 8.0) -> None:
        super().__init__(vent_s=0.5)
        self.inputs = inputs
        self.rng = np.random.default_rng(seed)
        self.p_atm_bar = p_atm_bar
        self.settle_s = settle_s
        self.run_timeout_s = run_timeout_s
        self.data = RotaryFrictionData(inputs, p_atm_bar, seed)
        rom = math.radians(inputs.rom_deg)
        self.rom = rom
        self.theta_stop_min = -0.5 * rom  # ROM symmetric about neutral
        self.theta_min = self.theta_stop_min + 0.2 * rom
        self.theta_max = self.theta_stop_min + 0.8 * rom
        self.z_w = max(inputs.pw_bar - p_atm_bar, 0.0)
        self.progress.total_tests = 2 * (inputs.ns + inputs.nd)

    def pct_rom(self, theta: float) -> float:
        """Angle as a fraction of the ROM from the CW end stop [-]."""
        return (theta - self.theta_stop_min) / self.rom

    def torque(self) -> float:
        """Pneumatic torque from the measured pressures (Eq 3.4) [N·m]."""
        return (self.meas.p_a - self.meas.p_b) * self.inputs.torque_per_bar

    def cmd(self, z_a: float, z_b: float) -> Command:
        """PRV commands with the identification routing."""
        return Command(z_a, z_b, U_A_OPEN, U_B_OPEN)

    # ---------------------------------------------------------------- helpers
    def move_to(self, target: float) -> Script:
        """Rotate towards ``target`` [rad] until it is crossed, then vent (Fig 3.14's on–off move)."""
        sgn = 1.0 if target > self.meas.theta else -1.0
        z_hi = self.z_w + MOVE_DRIVE_V
        drive = self.cmd(z_hi, self.z_w) if sgn > 0 else self.cmd(self.z_w, z_hi)
        yield from self.hold(self.cmd(self.z_w, self.z_w), self.settle_s)
        yield from self.until(drive, lambda m: sgn * (m.theta - target) >= 0.0, self.run_timeout_s)
        yield from self.hold(self.cmd(0.0, 0.0), self.settle_s)

    # ---------------------------------------------------------------- flowcharts
    def script(self) -> Script:
        """Static CCW, static CW, dynamic CCW, dynamic CW (the thesis's order)."""
        for d in ("ccw", "cw"):
            yield from self.block(f"static {d.upper()}", self.inputs.ns, partial(self.static_test, d))
        for d in ("ccw", "cw"):
            yield from self.block(f"dynamic {d.upper()}", self.inputs.nd, partial(self.dynamic_test, d))

    def static_test(self, direction: str) -> Script:
        """One static experiment (Figure 3.14 a/b)."""
        theta_t = self.theta_min + float(self.rng.random()) * (self.theta_max - self.theta_min)  # Eq 3.15
        yield from self.move_to(theta_t)
        yield from self.hold(self.cmd(self.z_w, self.z_w), self.settle_s)
        sgn = 1.0 if direction == "ccw" else -1.0
        z = self.z_w
        z_limit = min(self.z_w + STATIC_RAMP_MAX_V, 10.0)
        avg: deque[float] = deque(maxlen=5)
        best = -math.inf
        xs: list[float] = []
        fs: list[float] = []
        t0 = self.meas.t
        next_step = t0 + RAMP_PERIOD_S
        moved = False
        while z <= z_limit:
            if self.meas.t >= next_step - 0.5 * self.dt:
                z += RAMP_STEP_V
                next_step += RAMP_PERIOD_S
            yield self.cmd(z, self.z_w) if sgn > 0 else self.cmd(self.z_w, z)
            tq = sgn * self.torque()
            xs.append(self.meas.theta)
            fs.append(tq)
            avg.append(tq)
            best = max(best, sum(avg) / len(avg))
            if sgn * self.meas.omega >= MOTION_THRESHOLD:
                moved = True
                break
        level = breakaway_level(np.asarray(fs), np.asarray(xs), REST_TOL_RAD) if moved else math.nan
        self.data.static.append(StaticTest(direction, self.progress.k, theta_t, sgn * level,
                                           sgn * best if moved else math.nan, z, t0, self.meas.t))
        yield from self.hold(self.cmd(0.0, 0.0), self.settle_s)

    def dynamic_test(self, direction: str) -> Script:
        """One dynamic experiment (Figure 3.15 a/b)."""
        ccw = direction == "ccw"
        start, stop = (self.theta_min, self.theta_max) if ccw else (self.theta_max, self.theta_min)
        # return to the start position (from whichever side we are on)
        yield from self.move_to(start)
        yield from self.hold(self.cmd(self.z_w, self.z_w), self.settle_s)
        spread = 0.75 if ccw else 0.9  # Eq 3.16 / 3.17
        z_drive = self.z_w + 0.48 + spread * float(self.rng.random())
        sgn = 1.0 if ccw else -1.0
        drive = self.cmd(z_drive, self.z_w) if ccw else self.cmd(self.z_w, z_drive)
        w_sum = w_sq = tq_sum = pa_sum = pb_sum = 0.0
        n = 0
        t0 = self.meas.t
        t_end = t0 + self.run_timeout_s
        t_stall = t0 + STALL_S
        while sgn * (self.meas.theta - stop) < 0.0 and self.meas.t < t_end:
            yield drive
            if sgn * self.meas.omega > MOTION_THRESHOLD:
                t_stall = self.meas.t + STALL_S
            elif self.meas.t > t_stall:
                break  # the level stays below breakaway: the vane never leaves (test kept as NaN)
            pct = self.pct_rom(self.meas.theta)
            steady = pct > 0.6 if ccw else pct < 0.4
            if steady and sgn * (self.meas.theta - stop) < 0.0:
                w = self.meas.omega
                w_sum += w
                w_sq += w * w
                tq_sum += self.torque()
                pa_sum += self.meas.p_a
                pb_sum += self.meas.p_b
                n += 1
        if n >= 2:
            mean_w = w_sum / n
            sd = math.sqrt(max(w_sq / n - mean_w * mean_w, 0.0))
            rec = DynamicTest(direction, self.progress.k, z_drive, mean_w, tq_sum / n, sd, n, t0, self.meas.t,
                              pa_sum / n, pb_sum / n)
        else:
            rec = DynamicTest(direction, self.progress.k, z_drive, math.nan, math.nan, math.nan, n, t0, self.meas.t)
        self.data.dynamic.append(rec)
        # stop: driving chamber back to P_w, then vent both
        yield from self.hold(self.cmd(self.z_w, self.z_w), self.settle_s)
        yield from self.hold(self.cmd(0.0, 0.0), self.settle_s)


@dataclass
class RotaryFrictionResult:
    """Identified rotary friction at one working pressure.

    Attributes:
        pw_bar: Working pressure [bar abs].
        ccw: CCW fit (positive values).
        cw: CW fit (thesis signs: T_s, T_c, ω_s negative; B positive).
    """

    pw_bar: float
    ccw: FrictionFit
    cw: FrictionFit

    def contract(self) -> dict[str, dict[str, float]]:
        """The ``cwrr identify rotary --json`` contract."""

        def one(f: FrictionFit) -> dict[str, float]:
            return {"Ts": f.fs, "Tc": f.fc, "ws": f.vs, "B": f.b, "Ts_sd": f.fs_sd}

        return {"ccw": one(self.ccw), "cw": one(self.cw)}


class RotaryFrictionEstimator:
    """Fit Table 3.4's model to rotary experiment data (scikit-learn style).

    Attributes:
        params_: The result after :meth:`fit`.
    """

    def __init__(self, with_ci: bool = True) -> None:
        self.with_ci = with_ci
        self.params_: RotaryFrictionResult | None = None

    def fit(self, data: RotaryFrictionData) -> RotaryFrictionEstimator:
        """Estimate T_s (mean, SD) and fit T_c, ω_s, B per direction (Appendix 1)."""
        st, w, tf = data.arrays("ccw")
        ccw = fit_friction(st, w, tf, "positive", (1.0, 1.0, 2.0), 1.0, 2.0, self.with_ci)
        st, w, tf = data.arrays("cw")
        cw = fit_friction(st, w, tf, "negative", (-1.0, -1.0, 2.0), 1.0, 2.0, self.with_ci)
        self.params_ = RotaryFrictionResult(data.inputs.pw_bar, ccw, cw)
        return self

    def score(self, data: RotaryFrictionData) -> float:
        """R² of the fitted curves on ``data``'s dynamic tests (both directions)."""
        if self.params_ is None:
            raise RuntimeError("fit first")
        return curve_r2(data, (("ccw", self.params_.ccw), ("cw", self.params_.cw)))

class OpenLoopValidation(RotaryFrictionProcedure):
    """Open-loop, load-free friction validation (thesis 4.2.1, Figures 4.13–4.15).

    Both chambers at P_w, one raised to a random level (the dynamic tests'
    Eq 3.16–3.17 levels, PRVs under their own built-in controller); at the
    steady speed the driving chamber's pressure is predicted from the
    friction model, P^t = P_counter + T_f(ω)/(A_v·r), and compared with the
    measured one. Run with a different seed from the identification, these
    tests are held out from the fit.

    Args:
        inputs: GUI inputs (only geometry, ROM and P_w are used).
        n_tests: Runs per direction.
        seed: Seed of the random levels.
        p_atm_bar: Atmospheric pressure [bar abs].
    """

    name = "open_loop_validation"

    def __init__(self, inputs: RotaryInputs, n_tests: int = 10, seed: int = 100, p_atm_bar: float = P_ATM_BAR) -> None:
        super().__init__(inputs, seed=seed, p_atm_bar=p_atm_bar)
        self.n_tests = n_tests
        self.progress.total_tests = 2 * n_tests

    def script(self) -> Script:
        """CCW then CW runs."""
        for d in ("ccw", "cw"):
            yield from self.block(f"validation {d.upper()}", self.n_tests, partial(self.dynamic_test, d))

    def report(self, table: Any) -> dict[str, Any]:
        """Predicted vs measured driving-chamber pressure per run, with % error.

        Args:
            table: :class:`~app.engine.params.RotaryFriction` under test.
        """
        from app.engine.ident.fitting import stribeck

        ccw, cw = table.at(self.inputs.pw_bar)
        rows: list[dict[str, Any]] = []
        for d in self.data.dynamic:
            if not math.isfinite(d.omega):
                continue
            side = ccw if d.direction == "ccw" else cw
            tf = float(stribeck(np.array([d.omega]), side.fs, side.fc, side.vs, side.b)[0])
            if d.direction == "ccw":
                meas, pred = d.p_a, d.p_b + tf / self.inputs.torque_per_bar
            else:
                meas, pred = d.p_b, d.p_a - tf / self.inputs.torque_per_bar
            rows.append({"direction": d.direction, "omega": d.omega, "p_measured_bar": meas,
                         "p_predicted_bar": pred, "error_pct": 100.0 * (pred - meas) / meas})
        errs = np.abs(np.array([float(r["error_pct"]) for r in rows]))
        return {"pw_bar": self.inputs.pw_bar, "runs": rows,
                "max_abs_error_pct": float(errs.max()) if errs.size else math.nan,
                "mean_abs_error_pct": float(errs.mean()) if errs.size else math.nan}


THESIS_TABLE_4_4 = {0.75: {"mae": 0.043, "rmse": 0.006}, 1.5: {"mae": 0.143, "rmse": 0.081}}
"""Table 4.4 (P_w = 5.4 bar, CCW) [N·m]. As printed, RMSE < MAE, which no error
signal allows (RMSE ≥ MAE always); we compare against both numbers as given."""


def closed_loop_validation(target_nm: float, pw_bar: float = 5.4, friction: Any = None, seed: int = 0,
                           params: Any = None, gains: Any = None) -> dict[str, Any]:
    """Closed-loop, loaded friction validation (thesis 4.2.1, Figures 4.17–4.19, Table 4.4).

    The user rotates CCW at a low steady speed, stalls and returns (the
    isotonic program); the cascade PID loops (Table 4.3 gains) track the
    chamber pressures of Eq 4.4 built from the friction table under test; the
    measured interaction torque is compared with the target while the handle
    moves CCW (ω ≥ the identification's 0.2 rad/s threshold).

    Args:
        target_nm: Desired interaction torque [T_i]^t [N·m].
        pw_bar: Working pressure [bar abs] (thesis: 5.4).
        friction: :class:`~app.engine.params.RotaryFriction` used by the
            controller (e.g. an identified sweep's table); default Table 4.2.
        seed: Sensor-noise seed.
        params: Plant (default: the nominal rig, whose truth is Table 4.2).
        gains: Cascade PID gains (default Table 4.3).

    Returns:
        MAE and RMSE [N·m] with the thesis's values, and the traces.
    """
    from app.engine.control.config import TABLE_4_3_GAINS, ControllerConfig
    from app.engine.human import isotonic
    from app.engine.metrics import mae, rmse
    from app.engine.params import PlantParams, RotaryFriction
    from app.engine.sim import LOG_COLUMNS, run_workout

    cfg = ControllerConfig(controller="pid", target_nm=target_nm, pw_bar=pw_bar,
                           friction=friction or RotaryFriction(), pid_gains=gains or TABLE_4_3_GAINS)
    program = isotonic(+1, repetitions=1)
    duration = float(program.t[-1])
    # 4.2.1 ran at 500 Hz
    res = run_workout(params or PlantParams(), program, duration, rate_hz=500.0, control=cfg, seed=seed)
    t = res.log[:, LOG_COLUMNS.index("t")]
    ti = res.log[:, LOG_COLUMNS.index("torque")]
    om = res.log[:, LOG_COLUMNS.index("omega")]
    moving = om >= MOTION_THRESHOLD
    if moving.sum() < 10:
        raise RuntimeError("the handle never moved CCW: nothing to validate")
    e = target_nm - ti[moving]
    tm = t[moving]
    out = {"pw_bar": pw_bar, "target_nm": target_nm, "mae_nm": mae(tm, e), "rmse_nm": rmse(tm, e),
           "mean_torque_nm": float(ti[moving].mean()), "n_samples": int(moving.sum()),
           "thesis": THESIS_TABLE_4_4.get(target_nm), "t": t, "torque": ti, "moving": moving}
    return out
