"""Friction-curve fitting shared by the rotary and linear procedures.

The thesis's fit (Appendices 1–2): T_s (F_s) is the mean of the static tests;
the curve ``f(v) = f_c + (f_s − f_c)·exp(−(v/v_s)²) + B·v`` is fitted to the
dynamic (speed, friction) pairs *plus* the point (0, f_s), by bounded least
squares from the thesis's initial values (Tables 3.4–3.6). MATLAB's
``lsqcurvefit`` is replaced by :func:`scipy.optimize.least_squares` (trust
region reflective, which honours the bounds; MATLAB's Levenberg–Marquardt
silently ignored them before R2020b).

What the thesis lacked, added here:

* 95% confidence intervals for every parameter: Student-t for f_s (mean of
  the static tests) and *profile likelihood* for f_c, v_s and B. Profiles,
  unlike Jacobian (Wald) intervals, stay honest when a parameter sits on a
  bound or is barely identifiable — which v_s is whenever no dynamic test
  runs near the Stribeck speed (the reported interval then spans most of its
  bounds, instead of a falsely precise number);
* model selection between Stribeck and Coulomb + viscous by AICc on the same
  points, with a runs test on the residuals ordered by speed (systematic
  misfit shows as too few sign changes), beside the thesis's rule (Coulomb +
  viscous "when the fit sits on its bound").
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar, Generic, Literal, Protocol, TypeVar

import numpy as np
from numba import njit
from scipy import optimize, stats

Direction = Literal["positive", "negative"]
V_S_MIN = 1e-6  # v_s = 0 divides by zero; the bound is kept just off it


def stribeck(v: np.ndarray, fs: float, fc: float, vs: float, b: float, j: float = 2.0) -> np.ndarray:
    """Stribeck friction (Eq 3.12–3.13) in the thesis's signed convention.

    Args:
        v: Speed [rad/s or m/s] (same sign as the parameters' direction).
        fs: Static level [N·m or N].
        fc: Coulomb level.
        vs: Stribeck speed (signed like ``v``).
        b: Viscous coefficient (≥ 0).
        j: Shape exponent.
    """
    v = np.asarray(v, dtype=np.float64)
    return np.asarray(fc + (fs - fc) * np.exp(-np.abs(v / vs) ** j) + b * v)


@dataclass
class Interval:
    """A confidence interval.

    Attributes:
        lo: Lower end.
        hi: Upper end.
        method: ``"t"``, ``"profile"``.
        at_bound: Whether an end is the fit's bound (the data do not close it).
    """

    lo: float
    hi: float
    method: str
    at_bound: bool = False

    def contains(self, v: float) -> bool:
        """Whether ``v`` lies inside."""
        return self.lo <= v <= self.hi


@dataclass
class ModelChoice:
    """Stribeck vs Coulomb + viscous on the same data.

    Attributes:
        selected: ``"stribeck"`` or ``"coulomb_viscous"`` (AICc, Δ > 2 needed
            for the richer model).
        aicc_stribeck: AICc of the Stribeck fit.
        aicc_cv: AICc of the Coulomb + viscous fit.
        runs_p_stribeck: Runs-test p-value of the Stribeck residuals (speed order).
        runs_p_cv: Same for Coulomb + viscous.
        cv_fc: Coulomb level of the Coulomb + viscous fit.
        cv_b: Viscous coefficient of the Coulomb + viscous fit.
        thesis_rule: What the thesis GUI would print (Appendix 2's rule).
    """

    selected: str
    aicc_stribeck: float
    aicc_cv: float
    runs_p_stribeck: float
    runs_p_cv: float
    cv_fc: float
    cv_b: float
    thesis_rule: str


@dataclass
class FrictionFit:
    """One direction's identified friction.

    Attributes:
        direction: ``"positive"`` (CCW / extension) or ``"negative"``.
        fs: Static level (mean of the static tests).
        fs_sd: Standard deviation of the static tests.
        n_static: Valid static tests.
        fc: Coulomb level.
        vs: Stribeck speed.
        b: Viscous coefficient.
        n_dynamic: Valid dynamic tests.
        rmse: Fit residual RMS over the fitted points.
        ci: 95% intervals by parameter name.
        at_bound: Parameters that ended on a bound.
        speed_range: (min, max) |speed| of the dynamic tests.
        choice: Model selection, when computed.
    """

    direction: Direction
    fs: float
    fs_sd: float
    n_static: int
    fc: float
    vs: float
    b: float
    n_dynamic: int
    rmse: float
    ci: dict[str, Interval] = field(default_factory=dict)
    at_bound: list[str] = field(default_factory=list)
    speed_range: tuple[float, float] = (0.0, 0.0)
    choice: ModelChoice | None = None

    def as_dict(self) -> dict[str, Any]:
        """Plain nested view (JSON-ready)."""
        d = asdict(self)
        d["ci"] = {k: asdict(v) for k, v in self.ci.items()}
        return d

    def curve(self, v: np.ndarray) -> np.ndarray:
        """The fitted friction at speeds ``v``."""
        return stribeck(v, self.fs, self.fc, self.vs, self.b)


def _bounds(fs: float, sign: float, vs_max: float, b_max: float) -> tuple[np.ndarray, np.ndarray]:
    if sign > 0:
        return np.array([0.0, V_S_MIN, 0.0]), np.array([max(fs, 1e-9), vs_max, b_max])
    return np.array([min(fs, -1e-9), -vs_max, 0.0]), np.array([0.0, -V_S_MIN, b_max])


def _fit3(v: np.ndarray, f: np.ndarray, fs: float, x0: np.ndarray, lb: np.ndarray, ub: np.ndarray,
          fixed: dict[int, float] | None = None) -> tuple[np.ndarray, float]:
    """Least squares over the free entries of (fc, vs, b); returns (params, RSS)."""
    fixed = fixed or {}
    free = [i for i in range(3) if i not in fixed]

    def full(p: np.ndarray) -> np.ndarray:
        x = np.empty(3)
        x[free] = p
        for i, val in fixed.items():
            x[i] = val
        return x

    def res(p: np.ndarray) -> np.ndarray:
        fc, vs, b = full(p)
        return stribeck(v, fs, fc, vs, b) - f

    def jac(p: np.ndarray) -> np.ndarray:
        fc, vs, _b = full(p)
        r = (v / vs) ** 2
        e = np.exp(-r)
        cols = [1.0 - e, (fs - fc) * e * 2.0 * r / vs, v]
        return np.column_stack([cols[i] for i in free])

    x0f = np.clip(x0[free], lb[free] + 1e-12 * (ub[free] - lb[free]), ub[free] - 1e-12 * (ub[free] - lb[free]))
    sol = optimize.least_squares(res, x0f, jac=jac, bounds=(lb[free], ub[free]), method="trf",
                                 x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
    return full(sol.x), float(np.sum(sol.fun**2))


def _profile_interval(
    v: np.ndarray, f: np.ndarray, fs: float, best: np.ndarray, rss_min: float, lb: np.ndarray, ub: np.ndarray,
    idx: int, level: float = 0.95, n_grid: int = 33,
) -> Interval:
    """Profile-likelihood interval of parameter ``idx`` (F-test threshold)."""
    n, p = v.size, 3
    dof = max(n - p, 1)
    s2 = max(rss_min / dof, 1e-300)
    thr = float(stats.f.ppf(level, 1, dof))

    def excess(val: float, x0: np.ndarray) -> tuple[float, np.ndarray]:
        x, rss = _fit3(v, f, fs, x0, lb, ub, {idx: val})
        return (rss - rss_min) / s2 - thr, x

    ends: list[float] = []
    at_bound = False
    for end in (lb[idx], ub[idx]):
        grid = np.linspace(best[idx], end, n_grid)[1:]
        prev_val, prev_g = best[idx], -thr
        x0 = best.copy()
        found = None
        for val in grid:
            g, x0 = excess(float(val), x0)
            if g > 0:
                # refine the crossing between prev_val and val
                a, b_ = prev_val, float(val)
                ga = prev_g
                for _ in range(30):
                    m = 0.5 * (a + b_)
                    gm, _x = excess(m, x0)
                    if (gm > 0) == (ga > 0):
                        a, ga = m, gm
                    else:
                        b_ = m
                found = 0.5 * (a + b_)
                break
            prev_val, prev_g = float(val), g
        if found is None:
            found = float(end)
            at_bound = True
        ends.append(found)
    lo, hi = sorted(ends)
    return Interval(lo, hi, "profile", at_bound)


def runs_test_p(residuals: np.ndarray) -> float:
    """Wald–Wolfowitz runs test on residual signs: p of "too few runs" (misfit)."""
    s = np.sign(residuals[residuals != 0])
    n1, n2 = int(np.sum(s > 0)), int(np.sum(s < 0))
    if n1 == 0 or n2 == 0:
        return 0.0
    runs = 1 + int(np.sum(s[1:] != s[:-1]))
    n = n1 + n2
    mu = 2.0 * n1 * n2 / n + 1.0
    var = 2.0 * n1 * n2 * (2.0 * n1 * n2 - n) / (n * n * (n - 1.0)) if n > 1 else 0.0
    if var <= 0:
        return 1.0
    z = (runs - mu) / math.sqrt(var)
    return float(stats.norm.cdf(z))


def _aicc(rss: float, n: int, k: int) -> float:
    rss = max(rss, 1e-300)
    aic = n * math.log(rss / n) + 2 * k
    return aic + (2 * k * (k + 1)) / max(n - k - 1, 1)


def fit_friction(
    static: np.ndarray,
    speed: np.ndarray,
    force: np.ndarray,
    direction: Direction,
    x0: tuple[float, float, float],
    vs_max: float,
    b_max: float,
    with_ci: bool = True,
) -> FrictionFit:
    """The thesis's friction fit for one direction, with intervals and model choice.

    Args:
        static: Static test results (breakaway levels) [N·m or N], signed.
        speed: Dynamic tests' mean speeds [rad/s or m/s], signed.
        force: Dynamic tests' mean friction [N·m or N], signed.
        direction: ``"positive"`` or ``"negative"``.
        x0: Initial (f_c, v_s, B) (Tables 3.4–3.6 / Appendix values).
        vs_max: |v_s| upper bound (rotary 1 rad/s; linear 0.1 m/s).
        b_max: B upper bound (rotary 2; linear 100).
        with_ci: Whether to compute the profile intervals.
    """
    sign = 1.0 if direction == "positive" else -1.0
    st = np.asarray(static, dtype=np.float64)
    st = st[np.isfinite(st) & (sign * st > 0)]
    sp = np.asarray(speed, dtype=np.float64)
    fo = np.asarray(force, dtype=np.float64)
    ok = np.isfinite(sp) & np.isfinite(fo) & (sign * sp > 0)
    sp, fo = sp[ok], fo[ok]
    if st.size < 2:
        raise ValueError(f"{direction}: fewer than 2 valid static tests ({st.size}); cannot estimate the static level")
    if sp.size < 3:
        raise ValueError(f"{direction}: fewer than 3 valid dynamic tests ({sp.size}); cannot fit the curve")
    fs = float(st.mean())
    fs_sd = float(st.std(ddof=1))
    v = np.concatenate([[0.0], sp])
    f = np.concatenate([[fs], fo])
    lb, ub = _bounds(fs, sign, vs_max, b_max)
    best, rss = _fit3(v, f, fs, np.asarray(x0, dtype=np.float64), lb, ub)
    tol = 1e-6 * (ub - lb)
    names = ("fc", "vs", "b")
    at_bound = [names[i] for i in range(3) if best[i] - lb[i] <= tol[i] or ub[i] - best[i] <= tol[i]]
    ci: dict[str, Interval] = {}
    tq = float(stats.t.ppf(0.975, st.size - 1))
    half = tq * fs_sd / math.sqrt(st.size)
    ci["fs"] = Interval(fs - half, fs + half, "t")
    if with_ci:
        for i, nm in enumerate(names):
            ci[nm] = _profile_interval(v, f, fs, best, rss, lb, ub, i)
    # model selection on the same points
    n = v.size
    a_cv = np.column_stack([np.ones(n), v])
    cv_coef, *_ = np.linalg.lstsq(a_cv, f, rcond=None)
    r_cv = a_cv @ cv_coef - f
    r_st = stribeck(v, fs, best[0], best[1], best[2]) - f
    order = np.argsort(np.abs(v))
    aicc_st = _aicc(rss, n, 3)
    aicc_cv = _aicc(float(np.sum(r_cv**2)), n, 2)
    selected = "stribeck" if aicc_st < aicc_cv - 2.0 else "coulomb_viscous"
    on_vs_bound = abs(abs(best[1]) - vs_max) <= tol[1]
    thesis = "coulomb_viscous" if (on_vs_bound or f"{fs:.4g}" == f"{best[0]:.4g}") else "stribeck"
    choice = ModelChoice(selected, aicc_st, aicc_cv, runs_test_p(r_st[order]), runs_test_p(r_cv[order]),
                         float(cv_coef[0]), float(cv_coef[1]), thesis)
    return FrictionFit(direction, fs, fs_sd, int(st.size), float(best[0]), float(best[1]), float(best[2]),
                       int(sp.size), math.sqrt(rss / n), ci, at_bound,
                       (float(np.abs(sp).min()), float(np.abs(sp).max())), choice)


def breakaway_level(f: np.ndarray, pos: np.ndarray, rest_tol: float) -> float:
    """Force/torque at which a ramp broke the actuator away.

    The PRV raises the chamber pressure in steps (its regulator rests inside
    a deadband, then corrects with some overshoot), so breakaway happens
    part-way up one step. The thesis records the ramp's largest T_p (F_p),
    i.e. the top of that step plus its overshoot — biased upwards by up to a
    step (≈ 0.05 bar: 10–25% of F_s on the linear cylinders). Here the level
    is the midpoint of the two samples that bracket the first encoder count:
    the last one at rest (≤ the breakaway level) and the first one moved
    (≥ it, before the overshoot adds more).

    Args:
        f: Pneumatic force/torque samples of the ramp, sign-normalised to positive.
        pos: Position samples [rad or m].
        rest_tol: Position change that counts as motion [rad or m] (below one
            encoder count, so the first count counts).
    """
    f = np.asarray(f, dtype=np.float64)
    pos = np.asarray(pos, dtype=np.float64)
    if f.size == 0:
        return math.nan
    moved = np.nonzero(np.abs(pos - pos[0]) > rest_tol)[0]
    if moved.size == 0 or moved[0] < 1:
        return float(np.max(f))
    i = int(moved[0])
    return 0.5 * (float(f[i - 1]) + float(f[i]))


@njit(cache=True, error_model="numpy")
def onset_level(f: np.ndarray, x: np.ndarray, i: int, dt: float, fc: float, vs: float, b: float, m: float,
                fs_lo: float, fs_hi: float) -> float:
    """Breakaway level of one static test from the motion that followed it [N].

    The PRV raises the force in steps that can be half of a small cylinder's
    F_s, within one sample, and the first encoder count comes one or two
    samples after the breakaway: the samples bracketing that count do not
    bracket the crossing. After the crossing the piston obeys
    M·ẍ = F − F_f(ẋ), F_f the Stribeck curve with level F_s, so how far it
    got by each later sample says where in the step F_s lay. A grid over
    F_s × breakaway instant (inside the last three sample intervals before
    the count) is integrated with the force held per interval and the best
    match of the measured positions wins.

    Args:
        f: Pneumatic force at the samples, sign-normalised to positive [N].
        x: Position from rest at the samples, in the direction of motion [m].
        i: Index of the first sample that moved (≥ 1).
        dt: Sample period [s].
        fc: Coulomb level [N] (the dynamic fit's).
        vs: Stribeck speed [m/s] (the dynamic fit's).
        b: Viscous coefficient [N·s/m].
        m: Moving mass [kg].
        fs_lo: Lowest F_s considered [N].
        fs_hi: Highest F_s considered [N].

    Returns:
        The best-matching F_s [N] (NaN when nothing could be matched).
    """
    n_fs, n_frac, n_sub = 400, 8, 25
    best_sse = np.inf
    best = np.nan
    n = f.shape[0]
    for tb_k in range(max(1, i - 2), i + 1):
        for q in range(n_frac):
            t0 = (tb_k - 1 + 0.95 * q / (n_frac - 1)) * dt
            for g in range(n_fs):
                fs = fs_lo + (fs_hi - fs_lo) * g / (n_fs - 1)
                v = 0.0
                xx = 0.0
                sse = 0.0
                for k in range(tb_k, n):
                    t_start = max((k - 1) * dt, t0)
                    h = (k * dt - t_start) / n_sub
                    force = f[k]
                    for _ in range(n_sub):
                        if v <= 0.0 and force < fs:
                            a = 0.0  # static friction holds
                        else:
                            s = v / vs
                            a = (force - (fc + (fs - fc) * math.exp(-s * s) + b * v)) / m
                        v = max(v + a * h, 0.0)
                        xx += v * h
                    if k >= i - 1:
                        sse += (xx - x[k]) ** 2
                        if sse >= best_sse:
                            break  # the sum only grows: this candidate cannot win any more
                if sse < best_sse:
                    best_sse = sse
                    best = fs
    return best


def compile_onset_model() -> None:
    """Compile (or load from the cache) :func:`onset_level` now, not in the first fit."""
    onset_level(np.ones(3), np.zeros(3), 1, 0.005, 0.5, 0.05, 1.0, 1.0, 0.5, 1.0)


def curve_r2(data: Any, fits: tuple[tuple[str, FrictionFit], ...]) -> float:
    """R² of fitted curves on the dynamic tests of ``data`` (``data.arrays(direction)``).

    Args:
        data: Rotary or linear experiment data.
        fits: (direction name, its fit) pairs.
    """
    ys, ps = [], []
    for d, fit in fits:
        _, v, f = data.arrays(d)
        ok = np.isfinite(v) & np.isfinite(f)
        ys.append(f[ok])
        ps.append(fit.curve(v[ok]))
    y, p = np.concatenate(ys), np.concatenate(ps)
    return float(1.0 - np.sum((y - p) ** 2) / np.sum((y - y.mean()) ** 2))


class _Test(Protocol):
    direction: str


InputsT = TypeVar("InputsT")
StaticT = TypeVar("StaticT", bound=_Test)
DynamicT = TypeVar("DynamicT", bound=_Test)


@dataclass
class FrictionData(Generic[InputsT, StaticT, DynamicT]):
    """Everything a friction identification produced, test by test (rotary and linear).

    Subclasses name the fields their test records keep the static level, the
    dynamic speed and the dynamic friction in.

    Attributes:
        inputs: The GUI inputs.
        p_atm_bar: Atmospheric pressure used for the command scale [bar].
        seed: Seed of the random test positions and levels.
        static: Static tests in order.
        dynamic: Dynamic tests in order.
    """

    STATIC_FIELD: ClassVar[str]
    SPEED_FIELD: ClassVar[str]
    FRICTION_FIELD: ClassVar[str]

    inputs: InputsT
    p_atm_bar: float
    seed: int
    static: list[StaticT] = field(default_factory=list)
    dynamic: list[DynamicT] = field(default_factory=list)

    def arrays(self, direction: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(static levels, dynamic speeds, dynamic friction) of one direction."""
        st = [getattr(s, self.STATIC_FIELD) for s in self.static if s.direction == direction]
        dy = [d for d in self.dynamic if d.direction == direction]
        return (np.array(st, dtype=np.float64), np.array([getattr(d, self.SPEED_FIELD) for d in dy], dtype=np.float64),
                np.array([getattr(d, self.FRICTION_FIELD) for d in dy], dtype=np.float64))

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready view."""
        return {"inputs": asdict(self.inputs), "p_atm_bar": self.p_atm_bar,  # type: ignore[call-overload]
                "seed": self.seed, "static": [asdict(s) for s in self.static],  # type: ignore[call-overload]
                "dynamic": [asdict(d) for d in self.dynamic]}  # type: ignore[call-overload]


def friction_report(data: FrictionData[Any, Any, Any], result: Any) -> dict[str, Any]:
    """What a finished friction identification reports: the station's run result, which the dashboard draws.

    Args:
        data: The procedure's tests.
        result: Its fit (a ``RotaryFrictionResult`` or ``LinearFrictionResult``).

    Returns:
        ``parameters``: per direction, the thesis's symbols (the ``cwrr identify --json`` contract);
        ``fits``: each direction's :class:`FrictionFit` in full: the 95 % intervals (one that runs
        onto a bound of Tables 3.4/3.6 says these tests cannot pin that parameter down), the valid
        test counts, the fit's RMS, the speeds covered, and the Stribeck against the Coulomb +
        viscous fit (SPEC §6: show both); ``tests``: experiments run, static and dynamic;
        ``points``: (speed, friction) of every valid test, a static one at speed 0. A linear fit
        adds ``moving_mass_kg`` and ``static_method``.
    """

    def finite(*v: float) -> bool:
        return all(math.isfinite(x) for x in v)

    contract = result.contract()
    static = [[0.0, float(getattr(t, data.STATIC_FIELD))] for t in data.static if finite(getattr(t, data.STATIC_FIELD))]
    dynamic = [[float(getattr(t, data.SPEED_FIELD)), float(getattr(t, data.FRICTION_FIELD))] for t in data.dynamic
               if finite(getattr(t, data.SPEED_FIELD), getattr(t, data.FRICTION_FIELD))]
    out: dict[str, Any] = {"parameters": contract, "fits": {d: getattr(result, d).as_dict() for d in contract},
                           "tests": {"static": len(data.static), "dynamic": len(data.dynamic)},
                           "points": {"static": static, "dynamic": dynamic}}
    for extra in ("moving_mass_kg", "static_method"):
        if hasattr(result, extra):
            out[extra] = getattr(result, extra)
    return out
