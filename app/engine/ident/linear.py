"""Automated friction identification of a linear cylinder (thesis 3.2.4, Fig 3.20–3.27).

Sequencer (SPEC §6, Figures 3.22, 3.24, 3.25), at 200 Hz:

* **static** (per direction, N_s tests): random test position between 10% and
  90% of the stroke, reached by on–off moves; then the PRV ramps from 0 V at
  0.02 V/s into chamber a (extension; b open to atmosphere) or chamber b
  (retraction; a open to atmosphere) until the speed first reaches
  ±0.02 m/s; the largest pneumatic force (Eq 3.5–3.6) of the ramp is that
  test's F_s; PRV to 0 V.
* **dynamic** (per direction, N_d tests): z = 1.5 V (P_s = 2.5 bar abs), the
  opposite chamber open to atmosphere, u_a = 4.2 + 0.8·rand (Eq 3.18) or
  u_b = 5 + rand (Eq 3.19); the piston runs between 20% and 80% of the
  stroke; speed and force are averaged over the run's last third (the thesis
  crops "irregularities" without giving the rule; this mirrors the rotary
  rule of keeping the final 20% of the ROM), then the piston returns. Speed
  and acceleration come from a centred Savitzky–Golay derivative of the
  encoder position, and the estimator removes the runs' inertial force
  (see :meth:`LinearFrictionEstimator.fit`).

The thesis's linear rig has one PRV feeding both DCVs; the simulated rig's two
PRVs get the same command.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np
from scipy.signal import savgol_filter

from app.engine.constants import P_ATM_BAR
from app.engine.hardware.base import Command
from app.engine.ident.fitting import (
    Direction,
    FrictionData,
    FrictionFit,
    breakaway_level,
    curve_r2,
    fit_friction,
    onset_level,
)
from app.engine.ident.gui_rules import LinearInputs
from app.engine.ident.procedure import Procedure, Script

RAMP_RATE_V_S = 0.02  # SPEC §6
MOTION_THRESHOLD = 0.02  # m/s (consistent between 0.001 and 0.05, thesis 3.2.4)
Z_DYNAMIC = 1.5  # V → P_s = 2.5 bar abs
Z_MOVE = 0.3  # V: a gentle on–off move (≈ 0.5 m/s), so the piston stops well short of the end caps
REST_TOL_M = 5.0e-6  # half a count of the 0.01 mm linear encoder
STATIC_RAMP_MAX_V = 2.0  # a static ramp that reaches this without motion is abandoned [V]
STALL_S = 1.5
SG_WINDOW = 7  # Savitzky–Golay window [samples] for speed and acceleration of a dynamic run


@dataclass
class LinearStaticTest:
    """One static experiment: signed F_s [N] at the onset of motion (NaN if the
    piston never moved) and the thesis's statistic, the ramp's largest force.

    ``onset_*`` keep the samples around the first encoder count (force
    sign-normalised, position from rest in the direction of motion, the
    index of the first moved sample, the period) for the estimator's
    motion-based level ``fs_onset``."""

    direction: str
    k: int
    x_test: float
    fs: float
    fs_max: float
    z_breakaway: float
    t_start: float
    t_end: float
    onset_f: list[float] = field(default_factory=list)
    onset_x: list[float] = field(default_factory=list)
    onset_i: int = 0
    onset_dt: float = 0.0
    fs_onset: float = math.nan


@dataclass
class LinearDynamicTest:
    """One dynamic experiment: mean speed [m/s], force [N] and acceleration
    [m/s²] of the run's final third, with its samples (for the inertia fit)."""

    direction: str
    k: int
    u_drive: float
    v: float
    ff: float
    v_sd: float
    n_samples: int
    t_start: float
    t_end: float
    acc: float = math.nan
    v_samples: list[float] = field(default_factory=list)
    a_samples: list[float] = field(default_factory=list)
    f_samples: list[float] = field(default_factory=list)


@dataclass
class LinearFrictionData(FrictionData[LinearInputs, LinearStaticTest, LinearDynamicTest]):
    """Everything the linear experiments produced, test by test (``arrays``: F_s, v, F_f)."""

    STATIC_FIELD = "fs"
    SPEED_FIELD = "v"
    FRICTION_FIELD = "ff"


class LinearFrictionProcedure(Procedure):
    """The linear static + dynamic sequencer (Figures 3.22, 3.24, 3.25).

    Args:
        inputs: Validated GUI inputs.
        seed: Seed of ``rand``.
        p_atm_bar: Atmospheric pressure [bar abs] (force balance Eq 3.5–3.6).
        settle_s: Dwell after each valve change [s].
    """

    name = "linear_friction"

    def __init__(self, inputs: LinearInputs, seed: int = 0, p_atm_bar: float = P_ATM_BAR,
                 settle_s: float = 0.3) -> None:
        super().__init__(vent_s=0.5)
        self.inputs = inputs
        self.rng = np.random.default_rng(seed)
        self.p_atm_bar = p_atm_bar
        self.settle_s = settle_s
        self.data = LinearFrictionData(inputs, p_atm_bar, seed)
        self.L = inputs.stroke_mm * 1e-3
        self.a_a = inputs.area_a
        self.a_rod = inputs.area_rod
        self.progress.total_tests = 2 * (inputs.ns + inputs.nd)

    def force(self) -> float:
        """Pneumatic force from the measured pressures (Eq 3.5–3.6) [N]."""
        m = self.meas
        a_b = self.a_a - self.a_rod
        return 1e5 * (m.p_a * self.a_a - m.p_b * a_b - self.p_atm_bar * self.a_rod)

    @staticmethod
    def extend(z: float, u_a: float = 0.0) -> Command:
        """Fill a through DCV-a (``u_a`` < 5 V), b to atmosphere."""
        return Command(z, z, u_a, 0.0)

    @staticmethod
    def retract(z: float, u_b: float = 10.0) -> Command:
        """Fill b through DCV-b (``u_b`` > 5 V), a to atmosphere."""
        return Command(z, z, 10.0, u_b)

    VENT = Command(0.0, 0.0, 10.0, 0.0)  # both chambers open to atmosphere

    def move_to(self, target: float) -> Script:
        """On–off move until ``target`` [m] is crossed, then both chambers vent."""
        sgn = 1.0 if target > self.meas.theta else -1.0
        drive = self.extend(Z_MOVE) if sgn > 0 else self.retract(Z_MOVE)
        yield from self.until(drive, lambda m: sgn * (m.theta - target) >= 0.0, 10.0)
        yield from self.hold(self.VENT, self.settle_s)

    def script(self) -> Script:
        """Static extension, static retraction, dynamic extension, dynamic retraction."""
        for d in ("extension", "retraction"):
            yield from self.block(f"static {d}", self.inputs.ns, partial(self.static_test, d))
        for d in ("extension", "retraction"):
            yield from self.block(f"dynamic {d}", self.inputs.nd, partial(self.dynamic_test, d))
        yield from self.move_to(0.1 * self.L)  # home (thesis: x = 0.1 L)

    def static_test(self, direction: str) -> Script:
        """One static experiment (Figure 3.22)."""
        x_t = (0.1 + 0.8 * float(self.rng.random())) * self.L
        yield from self.move_to(x_t)
        ext = direction == "extension"
        sgn = 1.0 if ext else -1.0
        z = 0.0
        avg: deque[float] = deque(maxlen=5)
        best = -math.inf
        xs: list[float] = []
        fs: list[float] = []
        t0 = self.meas.t
        moved = False
        while z <= STATIC_RAMP_MAX_V:
            z = RAMP_RATE_V_S * (self.meas.t - t0)
            yield self.extend(z) if ext else self.retract(z)
            f = sgn * self.force()
            xs.append(self.meas.theta)
            fs.append(f)
            avg.append(f)
            best = max(best, sum(avg) / len(avg))
            if sgn * self.meas.omega >= MOTION_THRESHOLD:
                moved = True
                break
        level = breakaway_level(np.asarray(fs), np.asarray(xs), REST_TOL_M) if moved else math.nan
        rec = LinearStaticTest(direction, self.progress.k, x_t, sgn * level, sgn * best if moved else math.nan, z,
                               t0, self.meas.t)
        first = np.nonzero(np.abs(np.asarray(xs) - xs[0]) > REST_TOL_M)[0] if moved else np.zeros(0, dtype=int)
        if first.size and first[0] >= 1:
            j0 = max(0, int(first[0]) - 4)
            rec.onset_f = fs[j0:]
            rec.onset_x = [sgn * (v - xs[0]) for v in xs[j0:]]
            rec.onset_i = int(first[0]) - j0
            rec.onset_dt = self.dt
        self.data.static.append(rec)
        yield from self.hold(self.VENT, self.settle_s)

    def dynamic_test(self, direction: str) -> Script:
        """One dynamic experiment (Figures 3.24–3.25)."""
        ext = direction == "extension"
        start, stop = (0.2 * self.L, 0.8 * self.L) if ext else (0.8 * self.L, 0.2 * self.L)
        yield from self.move_to(start)
        if ext:
            u = 4.2 + 0.8 * float(self.rng.random())  # Eq 3.18
            drive = self.extend(Z_DYNAMIC, u)
        else:
            u = 5.0 + float(self.rng.random())  # Eq 3.19
            drive = self.retract(Z_DYNAMIC, u)
        sgn = 1.0 if ext else -1.0
        t0 = self.meas.t
        xs: list[float] = []
        fs: list[float] = []
        t_stall = t0 + STALL_S
        while sgn * (self.meas.theta - stop) < 0.0 and self.meas.t < t0 + 30.0:
            yield drive
            xs.append(self.meas.theta)
            fs.append(self.force())
            if sgn * self.meas.omega > MOTION_THRESHOLD:
                t_stall = self.meas.t + STALL_S
            elif self.meas.t > t_stall:
                break
        rec = LinearDynamicTest(direction, self.progress.k, u, math.nan, math.nan, math.nan, 0, t0, self.meas.t)
        if len(xs) >= SG_WINDOW and sgn * (self.meas.theta - stop) >= 0.0:
            x = np.asarray(xs)
            # centred (zero-lag) speed and acceleration from the encoder: at these
            # speeds the causal speed filter lags by ~a·τ, and the run is short
            v = savgol_filter(x, SG_WINDOW, 2, deriv=1, delta=self.dt, mode="interp")
            a = savgol_filter(x, SG_WINDOW, 2, deriv=2, delta=self.dt, mode="interp")
            frac = (x - start) / (stop - start)
            keep = (frac >= 2.0 / 3.0) & (frac < 1.0)
            n = int(keep.sum())
            if n >= 2:
                f = np.asarray(fs)[keep]
                rec = LinearDynamicTest(direction, self.progress.k, u, float(v[keep].mean()), float(f.mean()),
                                        float(v[keep].std()), n, t0, self.meas.t, float(a[keep].mean()),
                                        v[keep].tolist(), a[keep].tolist(), f.tolist())
        self.data.dynamic.append(rec)
        yield from self.hold(self.VENT, self.settle_s)


@dataclass
class LinearFrictionResult:
    """Identified linear friction (Tables 4.5–4.6 form).

    Attributes:
        extension: Extension fit (positive values).
        retraction: Retraction fit (F_s, F_c, v_s negative; B positive).
        moving_mass_kg: Fitted moving mass used for the inertia correction [kg]
            (0 when the correction is off).
        static_method: How F_s was read per direction: ``"onset"`` (from the
            motion after breakaway) or ``"bracket"`` (the samples around the
            first encoder count).
    """

    extension: FrictionFit
    retraction: FrictionFit
    moving_mass_kg: float = 0.0
    static_method: tuple[str, str] = ("bracket", "bracket")

    def contract(self) -> dict[str, dict[str, Any]]:
        """The ``cwrr identify linear --json`` contract."""

        def one(f: FrictionFit) -> dict[str, Any]:
            model = f.choice.selected if f.choice else "stribeck"
            return {"Fs": f.fs, "Fc": f.fc, "vs": f.vs, "B": f.b, "model": model}

        return {"extension": one(self.extension), "retraction": one(self.retraction)}


class LinearFrictionEstimator:
    """Fit Tables 3.5–3.6's model to linear experiment data (Appendix 2).

    Attributes:
        params_: The result after :meth:`fit`.
    """

    def __init__(self, with_ci: bool = True, inertia_correction: bool = True) -> None:
        self.with_ci = with_ci
        self.inertia_correction = inertia_correction
        self.params_: LinearFrictionResult | None = None
        self.mass_ = 0.0

    def fit(self, data: LinearFrictionData) -> LinearFrictionEstimator:
        """F_s as the static mean; F_c, v_s, B by bounded least squares (Table 3.5 start, 3.6 bounds).

        With ``inertia_correction`` each run's mean force is first corrected
        by M̂·a, M̂ the moving mass fitted over every run's samples
        (F = F_c,dir + B·v + M·a, both directions at once): on short strokes
        the runs never reach a truly constant speed, and the thesis's
        averaging would otherwise fold M·a into the friction.
        """
        self.mass_ = self._fit_mass(data) if self.inertia_correction else 0.0
        out = []
        methods = []
        for d, sign in (("extension", 1.0), ("retraction", -1.0)):
            st, v, f = data.arrays(d)
            if self.mass_:
                acc = np.array([t.acc for t in data.dynamic if t.direction == d], dtype=np.float64)
                f = f - self.mass_ * acc
            x0 = (5.0 * sign, 0.1 * sign, 100.0)
            direction: Direction = "positive" if sign > 0 else "negative"
            fit = fit_friction(st, v, f, direction, x0, 0.1, 100.0, self.with_ci)
            method = "bracket"
            onset = self._onset_levels(data, d, fit)
            if onset is not None:
                fit = fit_friction(sign * onset, v, f, direction, x0, 0.1, 100.0, self.with_ci)
                method = "onset"
            out.append(fit)
            methods.append(method)
        self.params_ = LinearFrictionResult(out[0], out[1], self.mass_, (methods[0], methods[1]))
        return self

    def _onset_levels(self, data: LinearFrictionData, direction: str, fit: FrictionFit) -> np.ndarray | None:
        """Each static test's level from the motion after breakaway (:func:`onset_level`), or None.

        It needs the low-speed friction: only when the dynamic runs reached the
        Stribeck region (the slowest within 2·v_s) and the moving mass is known.
        Otherwise the bracket levels stand (on a valve too fast for slow runs
        v_s is not identified, and a wrong v_s biases the motion model).
        """
        if not self.mass_ or not math.isfinite(fit.vs) or fit.speed_range[0] > 2.0 * abs(fit.vs):
            return None
        tests = [t for t in data.static if t.direction == direction and t.onset_f]
        if len(tests) < 2:
            return None
        fc, vs, b = abs(fit.fc), abs(fit.vs), fit.b
        out = []
        for t in tests:
            f = np.asarray(t.onset_f, dtype=np.float64)
            x = np.asarray(t.onset_x, dtype=np.float64)
            hi = float(f[: t.onset_i + 1].max())  # it broke away by the first count: F_s is below the force seen
            t.fs_onset = math.copysign(onset_level(f, x, t.onset_i, t.onset_dt, fc, vs, b, self.mass_, fc, hi),
                                       t.fs)
            out.append(abs(t.fs_onset))
        return np.asarray(out)

    @staticmethod
    def _fit_mass(data: LinearFrictionData) -> float:
        rows, y = [], []
        for t in data.dynamic:
            if not t.v_samples:
                continue
            e = 1.0 if t.direction == "extension" else 0.0
            for v, a, f in zip(t.v_samples, t.a_samples, t.f_samples, strict=True):
                rows.append((e, 1.0 - e, v, a))
                y.append(f)
        if len(y) < 8:
            return 0.0
        coef, *_ = np.linalg.lstsq(np.asarray(rows), np.asarray(y), rcond=None)
        return max(float(coef[3]), 0.0)

    def score(self, data: LinearFrictionData) -> float:
        """R² of the fitted curves on the dynamic tests (both directions)."""
        if self.params_ is None:
            raise RuntimeError("fit first")
        return curve_r2(data, (("extension", self.params_.extension), ("retraction", self.params_.retraction)))
