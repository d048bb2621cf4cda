"""Closed-loop frequency-response PID autotuner for the PRV pressure loops (thesis 3.6.2).

The thesis used Simulink's closed-loop "PID Autotuner" block on each PRV loop
(target bandwidth 2 rad/s, phase margin 60°, initial gains
[K_p, K_i, K_d] = [0.25, 1.5, 0.0005], N = 100, 95 s). That block's
optimiser is not published, so this is our own, stated design:

1. **Evaluation** (the experiment, :class:`PIDAutotuneProcedure`): the PRV-j
   loop runs with the initial gains around P_w while a sum of sines at
   ω_c·[1/10, 1/3, 1, 3, 10] (the thesis's test frequencies) is added to the
   controller's output. The plant input z and output P_j are recorded.
2. **Estimation** (:func:`estimate_frf`): G(jω_k) = Y(ω_k)/Z(ω_k) by Fourier
   projection over whole periods of the slowest sine. With the perturbation
   injected at the plant input this ratio is the plant's response even in
   closed loop.
3. **Optimisation** (:func:`tune_pid`): the loop L = C·G must cross 0 dB at
   ω_c with phase −180° + PM. With G(jω_c) known this fixes the controller's
   complex value C(jω_c); a PIDF C(s) = K_p + K_i/s + K_d·s/(1 + s/N) has
   three non-negative gains, so we solve the two equations in the least-squares
   sense with gains ≥ 0, preferring the smallest derivative gain. When the
   plant lags less than 30° at ω_c the required C has a negative real part:
   no K_p ≥ 0 can give exactly 60°, the optimum sits on K_p = 0 and the margin
   comes out larger — the thesis's "every time zero K_p" (3.6.2).
4. **Testing** (:func:`step_test`): pressure steps with the initial, tuned and
   the thesis's gains on the same rig.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from app.engine.constants import P_ATM_BAR
from app.engine.control import pipeline as cpl
from app.engine.control.blocks import PRVController
from app.engine.control.config import ControllerConfig
from app.engine.hardware.base import Command
from app.engine.ident.procedure import Procedure, Script
from app.engine.params import ParameterError, check_working_pressure

CORNER_FACTORS = (0.1, 1.0 / 3.0, 1.0, 3.0, 10.0)  # thesis 3.6.2, × ω_c
INITIAL_GAINS = (0.25, 1.5, 0.0005)  # thesis 3.6.2: K_p, K_i [1/s], K_d [s]
THESIS_TUNED = {"a": (0.0, 2.034, 0.0098), "b": (0.0, 2.042, 0.0107)}  # autotuner output, before manual K_p
THESIS_FINAL = {"a": (0.45, 2.034, 0.0098), "b": (0.55, 2.042, 0.0107)}  # Eq 3.26 gains (K_p set by hand)


@dataclass(frozen=True)
class AutotuneSpec:
    """What to tune for.

    Attributes:
        side: ``"a"`` (PRV-a) or ``"b"`` (PRV-b).
        bandwidth_rad_s: Target crossover ω_c [rad/s] (thesis: 2).
        phase_margin_deg: Target phase margin [deg] (thesis: 60).
        pw_bar: Operating pressure P_w [bar abs].
        amplitude_bar: Amplitude of each injected sine [bar]; the five sum to
            at most 5× this, kept below the vane's break-away torque.
        periods: Whole periods of the slowest sine to analyse (after one
            period of settling).
        n_filter: Derivative filter coefficient N [1/s] (thesis: 100).
        initial: Gains the loop runs with during the experiment.
        p_atm_bar: The lab's atmosphere [bar abs] (PRV command offset, Eq 3.7).
    """

    side: str = "a"
    bandwidth_rad_s: float = 2.0
    phase_margin_deg: float = 60.0
    pw_bar: float = 3.0
    amplitude_bar: float = 0.05
    periods: int = 2
    n_filter: float = 100.0
    initial: tuple[float, float, float] = INITIAL_GAINS
    p_atm_bar: float = P_ATM_BAR

    def __post_init__(self) -> None:
        if self.side not in ("a", "b"):
            raise ParameterError(f"side = {self.side!r} must be 'a' or 'b'")
        check_working_pressure(self.pw_bar)
        if not 0.05 <= self.bandwidth_rad_s <= 50.0:
            raise ParameterError(f"bandwidth_rad_s = {self.bandwidth_rad_s}: must lie in 0.05–50 rad/s")
        if not 10.0 <= self.phase_margin_deg <= 90.0:
            raise ParameterError(f"phase_margin_deg = {self.phase_margin_deg}: must lie in 10–90°")
        if not 0.005 <= self.amplitude_bar <= 0.5:
            raise ParameterError(f"amplitude_bar = {self.amplitude_bar}: must lie in 0.005–0.5 bar")
        if not 1 <= self.periods <= 20:
            raise ParameterError(f"periods = {self.periods}: must lie in 1–20")
        if any(g < 0 or not math.isfinite(g) for g in self.initial):
            raise ParameterError("initial gains must be finite and ≥ 0")

    @property
    def frequencies(self) -> np.ndarray:
        """Test frequencies [rad/s]."""
        return self.bandwidth_rad_s * np.asarray(CORNER_FACTORS)

    @property
    def duration_s(self) -> float:
        """Experiment length: one settling period plus the analysed ones [s]."""
        return (self.periods + 1) * 2.0 * math.pi / float(self.frequencies.min())


@dataclass
class FrequencyResponse:
    """Estimated plant frequency response.

    Attributes:
        w: Frequencies [rad/s].
        g: Complex response G(jω) of P_j [bar] to z_j [bar] at each ω.
        coherence: Share of the output's power at each ω explained by the
            linear response (1 = noise-free) [-].
    """

    w: np.ndarray
    g: np.ndarray
    coherence: np.ndarray

    def at(self, w: float) -> complex:
        """G(jω) by interpolation of gain (log) and phase over log ω."""
        lw = np.log(self.w)
        mag = np.exp(np.interp(math.log(w), lw, np.log(np.abs(self.g))))
        ph = np.interp(math.log(w), lw, np.unwrap(np.angle(self.g)))
        return complex(mag * np.exp(1j * ph))

    def as_dict(self) -> dict[str, Any]:
        """JSON view (gain in dB, phase in degrees)."""
        return {"w_rad_s": self.w.tolist(), "gain_db": (20 * np.log10(np.abs(self.g))).tolist(),
                "phase_deg": np.degrees(np.unwrap(np.angle(self.g))).tolist(), "coherence": self.coherence.tolist()}


def estimate_frf(t: np.ndarray, z: np.ndarray, y: np.ndarray, w: np.ndarray) -> FrequencyResponse:
    """G(jω) = Y(ω)/Z(ω) from a joint least-squares fit of every test sine.

    Fitting all sines (and an offset) together leaves no leakage between
    them, whatever the record length — the test frequencies' ratios (such as
    1/3 ÷ 1/10) are not integers, so no window holds whole periods of all.

    Args:
        t: Sample times [s], spanning at least one period of the slowest ω.
        z: Plant input samples [bar].
        y: Plant output samples [bar].
        w: Frequencies to estimate [rad/s].
    """
    # N samples cover N·dt of signal, one sample period more than t[-1] − t[0]; a record
    # cut at a sample boundary may miss a fraction of a sample, which the joint fit tolerates
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    span = float(t[-1] - t[0]) + dt
    if span < 2.0 * math.pi / float(np.min(w)) - dt:
        raise ParameterError(f"the record ({span:.1f} s) is shorter than one period at {np.min(w):g} rad/s")
    tc = t - t[0]
    basis = np.column_stack([np.ones_like(tc)] + [f(wk * tc) for wk in w for f in (np.cos, np.sin)])
    cz, *_ = np.linalg.lstsq(basis, z, rcond=None)
    cy, *_ = np.linalg.lstsq(basis, y, rcond=None)
    # a·cos + b·sin = Re((a − jb)·e^{jωt})
    zk = cz[1::2] - 1j * cz[2::2]
    yk = cy[1::2] - 1j * cy[2::2]
    resid = y - basis @ cy
    # coherence per ω: the sine's power against the residual noise power in one frequency bin
    noise = float(np.var(resid)) * 4.0 / t.size
    coh = np.abs(yk) ** 2 / (np.abs(yk) ** 2 + noise)
    return FrequencyResponse(np.asarray(w, dtype=float), yk / zk, coh)


def pidf(w: float | np.ndarray, kp: float, ki: float, kd: float, n: float) -> Any:
    """C(jω) of K_p + K_i/s + K_d·s/(1 + s/N)."""
    s = 1j * np.asarray(w, dtype=float)
    return kp + ki / s + kd * s / (1.0 + s / n)


@dataclass
class PIDTuning:
    """Tuned gains and what they achieve on the estimated response.

    Attributes:
        kp: K_p [-] (bar of command per bar of error).
        ki: K_i [1/s].
        kd: K_d [s].
        n_filter: N [1/s].
        crossover_rad_s: Achieved 0 dB crossover of L = C·G [rad/s].
        phase_margin_deg: Achieved phase margin [deg].
        exact: Whether both targets are met (else a gain sits on its bound).
        note: Why not, in words.
    """

    kp: float
    ki: float
    kd: float
    n_filter: float
    crossover_rad_s: float
    phase_margin_deg: float
    exact: bool
    note: str = ""

    @property
    def gains(self) -> tuple[float, float, float]:
        """(K_p, K_i, K_d)."""
        return self.kp, self.ki, self.kd


def loop_margins(frf: FrequencyResponse, kp: float, ki: float, kd: float, n: float) -> tuple[float, float]:
    """(crossover [rad/s], phase margin [deg]) of C·G on a fine log grid over the estimated band."""
    grid = np.exp(np.linspace(math.log(frf.w.min()), math.log(frf.w.max()), 2000))
    lg = np.array([frf.at(float(x)) for x in grid]) * pidf(grid, kp, ki, kd, n)
    mag = np.abs(lg)
    idx = np.nonzero((mag[:-1] >= 1.0) & (mag[1:] < 1.0))[0]
    if idx.size == 0:
        return math.nan, math.nan
    i = int(idx[0])
    f = (0.0 - math.log(mag[i])) / (math.log(mag[i + 1]) - math.log(mag[i]))
    wc = float(math.exp(math.log(grid[i]) + f * (math.log(grid[i + 1]) - math.log(grid[i]))))
    lc = frf.at(wc) * complex(pidf(wc, kp, ki, kd, n))
    return wc, 180.0 + math.degrees(math.atan2(lc.imag, lc.real))


def loop_response(frf: FrequencyResponse, kp: float, ki: float, kd: float, n: float,
                  points: int = 80) -> dict[str, list[float]]:
    """The open loop C·G over the estimated band, as a Bode chart draws it.

    Args:
        frf: Estimated plant response.
        kp: K_p [-].
        ki: K_i [1/s].
        kd: K_d [s].
        n: Derivative filter coefficient [1/s].
        points: Log-spaced frequencies between the lowest and the highest test frequency.

    Returns:
        ``w_rad_s`` [rad/s], ``gain_db`` [dB] (−inf where C is zero) and ``phase_deg`` [deg,
        unwrapped]: what :func:`loop_margins` reads its crossover and margin from.
    """
    grid = np.exp(np.linspace(math.log(frf.w.min()), math.log(frf.w.max()), points))
    lg = np.array([frf.at(float(x)) for x in grid]) * pidf(grid, kp, ki, kd, n)
    with np.errstate(divide="ignore"):
        gain = 20.0 * np.log10(np.abs(lg))
    phase = np.degrees(np.unwrap(np.angle(lg)))
    return {"w_rad_s": grid.tolist(), "gain_db": gain.tolist(), "phase_deg": phase.tolist()}


def tune_pid(frf: FrequencyResponse, wc: float = 2.0, pm_deg: float = 60.0, n: float = 100.0,
             kd_weight: float = 1e-3) -> PIDTuning:
    """PIDF gains ≥ 0 that put L's crossover at ``wc`` with phase margin ``pm_deg`` (module doc, step 3).

    Args:
        frf: Estimated plant response (must bracket ``wc``).
        wc: Target crossover [rad/s].
        pm_deg: Target phase margin [deg].
        n: Derivative filter coefficient [1/s].
        kd_weight: Weight of the preference for a small K_d (relative).
    """
    if not frf.w.min() <= wc <= frf.w.max():
        raise ParameterError(f"target bandwidth {wc} rad/s lies outside the measured {frf.w.min():.3g}–"
                             f"{frf.w.max():.3g} rad/s")
    g = frf.at(wc)
    target = math.radians(-180.0 + pm_deg)
    c_mag = 1.0 / abs(g)

    def res(x: np.ndarray) -> np.ndarray:
        kp, ki, kd = x[0] * c_mag, x[1] * c_mag * wc, x[2] * c_mag / wc  # scaled: all three O(1)
        lc = g * complex(pidf(wc, kp, ki, kd, n))
        # the crossover is held (weight 100), the phase comes as close as gains ≥ 0 allow
        return np.array([100.0 * math.log(max(abs(lc), 1e-12)), math.atan2(lc.imag, lc.real) - target,
                         kd_weight * x[2]])

    best = None
    for x0 in ([1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.5], [1.0, 0.0, 0.5]):
        sol = least_squares(res, x0, bounds=([0.0, 0.0, 0.0], [np.inf, np.inf, np.inf]))
        if best is None or sol.cost < best.cost:
            best = sol
    assert best is not None
    kp, ki, kd = (float(best.x[0] * c_mag), float(best.x[1] * c_mag * wc), float(best.x[2] * c_mag / wc))
    w_x, pm = loop_margins(frf, kp, ki, kd, n)
    exact = abs(w_x - wc) < 0.05 * wc and abs(pm - pm_deg) < 2.0
    note = ""
    if not exact and kp < 1e-9 and (np.exp(1j * target) / g).real < 0:
        note = (f"G(jω_c) lags only {-math.degrees(math.atan2(g.imag, g.real)):.1f}°: {pm_deg:g}° needs "
                f"K_p < 0, so K_p sits on 0 and the margin is {pm:.1f}° (the thesis also got K_p = 0)")
    if kp < 1e-9:
        # bench/pid_chatter.py: with both loops tuned so, SC-4 at 0.6 N·m drove the torque to −0.69 N·m
        # within 25 ms of the disturbance and the intention detector to supination (RMSE 1.14 N·m)
        note += ("; " if note else "") + (
            "without K_p nothing answers a pressure disturbance in its first ticks: on the simulated rig, "
            "SC-4 at 0.6 N·m with both loops tuned to K_p = 0 switched the intention detector to supination. "
            "The thesis set K_p by hand afterwards (Eq 3.26); try these gains in SC-4 before exercising with them")
    return PIDTuning(kp, ki, kd, n, w_x, pm, exact, note)


# --------------------------------------------------------------------------- experiment


class PIDAutotuneProcedure(Procedure):
    """Evaluation stage: the PRV-j loop with the initial gains plus the test sines.

    Both chambers are held at P_w (the other side by its PRV directly), so the
    small pressure swings leave the vane at rest against its static friction.
    """

    name = "pid_autotune"

    def __init__(self, spec: AutotuneSpec) -> None:
        super().__init__(vent_s=0.5)
        self.spec = spec
        self.progress.total_tests = 1
        self.side = 0 if spec.side == "a" else 1
        cfg = ControllerConfig(controller="pid", pw_bar=spec.pw_bar, pid_gains=(spec.initial, spec.initial),
                               p_atm_bar=spec.p_atm_bar)
        self.controller = PRVController(spec.side, "pid", cfg)
        self.controller.cp[cpl.P_N] = spec.n_filter
        self.p_atm = float(self.controller.cp[cpl.P_PATM])
        self.t: list[float] = []
        self.z: list[float] = []
        self.y: list[float] = []
        rng = np.random.default_rng(0)
        self.phases = rng.uniform(0, 2 * math.pi, len(CORNER_FACTORS))  # fixed: keeps the peak sum low

    def perturbation(self, t: float) -> float:
        """Sum of the test sines [bar]."""
        w = self.spec.frequencies
        return float(self.spec.amplitude_bar * np.sum(np.sin(w * t + self.phases)))

    def command(self, z_abs: float) -> Command:
        """PRV-j at ``z_abs`` [bar abs], the other PRV at P_w, both DCVs routing to their chambers."""
        zj = max(z_abs - self.p_atm, 0.0)
        zo = self.spec.pw_bar - self.p_atm
        return Command(zj, zo, 0.0, 10.0) if self.side == 0 else Command(zo, zj, 0.0, 10.0)

    def loop(self, ref: float, seconds: float, perturb: bool, record: bool) -> Script:
        """Run the PRV-j loop at reference ``ref`` [bar abs] for ``seconds``, optionally with the sines."""
        t0 = self.meas.t
        while self.meas.t - t0 < seconds - 0.5 * self.dt:
            m = self.meas
            pj = m.p_a if self.side == 0 else m.p_b
            z = self.controller.step(ref, pj, self.dt) + (self.perturbation(m.t - t0) if perturb else 0.0)
            if record:
                self.t.append(m.t - t0)
                self.z.append(z)
                self.y.append(pj)
            yield self.command(z)

    def script(self) -> Script:
        """Pressurise, settle in closed loop, then the sines for the experiment length."""
        self.begin("frequency-response experiment", 1)
        self.next_test()
        yield from self.hold(self.command(self.spec.pw_bar), 2.0)
        yield from self.loop(self.spec.pw_bar, 2.0, False, False)
        yield from self.loop(self.spec.pw_bar, self.spec.duration_s, True, True)
        self.test_done()

    def frf(self) -> FrequencyResponse:
        """Estimation stage on the record after its first (settling) period of the slowest sine."""
        t = np.asarray(self.t)
        keep = t >= 2.0 * math.pi / float(self.spec.frequencies.min())
        return estimate_frf(t[keep], np.asarray(self.z)[keep], np.asarray(self.y)[keep], self.spec.frequencies)


# --------------------------------------------------------------------------- testing


@dataclass
class StepMetrics:
    """Pressure-step response of one gain set (the testing stage).

    Attributes:
        label: Which gains.
        gains: (K_p, K_i, K_d).
        rise_s: 10–90 % rise time [s].
        settle_s: 2 % settling time [s].
        overshoot_pct: Overshoot [%].
        iae: Integral of |error| over the step [bar·s].
        t: Samples [s].
        p: Measured pressure [bar abs].
    """

    label: str
    gains: tuple[float, float, float]
    rise_s: float
    settle_s: float
    overshoot_pct: float
    iae: float
    t: list[float] = field(default_factory=list)
    p: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """JSON view without the trace."""
        d = asdict(self)
        d.pop("t")
        d.pop("p")
        return d


class StepTestProcedure(PIDAutotuneProcedure):
    """A P_w → P_w + step pressure step of PRV-j with given gains (no sines)."""

    name = "pid_step_test"

    def __init__(self, spec: AutotuneSpec, gains: tuple[float, float, float], step_bar: float = 0.5,
                 hold_s: float = 6.0) -> None:
        super().__init__(replace(spec, initial=gains))
        self.step_bar = step_bar
        self.hold_s = hold_s

    def script(self) -> Script:
        """Settle at P_w in closed loop, step the reference, hold."""
        self.begin("step test", 1)
        self.next_test()
        yield from self.hold(self.command(self.spec.pw_bar), 2.0)
        yield from self.loop(self.spec.pw_bar, 3.0, False, False)
        yield from self.loop(self.spec.pw_bar + self.step_bar, self.hold_s, False, True)
        self.test_done()

    def metrics(self, label: str) -> StepMetrics:
        """Rise, settling, overshoot and IAE of the recorded step."""
        t = np.asarray(self.t)
        p = np.asarray(self.y)
        p0 = self.spec.pw_bar
        frac = (p - p0) / self.step_bar
        # sensor noise: judge crossings on a light moving average
        k = max(1, int(0.02 / self.dt))
        fs = np.convolve(frac, np.ones(k) / k, mode="same")
        r10 = t[np.argmax(fs >= 0.1)] if (fs >= 0.1).any() else math.nan
        r90 = t[np.argmax(fs >= 0.9)] if (fs >= 0.9).any() else math.nan
        outside = np.nonzero(np.abs(fs[k:-k] - 1.0) > 0.02)[0]
        settle = float(t[k + outside[-1]]) if outside.size else 0.0
        return StepMetrics(label, tuple(self.spec.initial), float(r90 - r10), settle,  # type: ignore[arg-type]
                           float(max(0.0, (fs[k:-k].max() - 1.0) * 100.0)),
                           float(np.sum(np.abs(self.step_bar - (p - p0))) * self.dt), t.tolist(), p.tolist())


def step_test(spec: AutotuneSpec, gains: dict[str, tuple[float, float, float]], rate_hz: float = 200.0,
              seed: int = 0) -> list[StepMetrics]:
    """Testing stage on the simulated rig for each named gain set."""
    from app.engine.ident.runner import simulate
    from app.engine.params import PlantParams

    out = []
    for label, g in gains.items():
        proc = StepTestProcedure(spec, g)
        simulate(proc, PlantParams(), rate_hz, seed=seed)
        out.append(proc.metrics(label))
    return out


def autotune_sim(spec: AutotuneSpec | None = None, rate_hz: float = 200.0, seed: int = 0) -> dict[str, Any]:
    """Evaluation, estimation, optimisation and testing on the simulated rig.

    Returns:
        ``{"spec", "frf", "tuning", "thesis_margins", "steps", "rig_seconds"}``.
    """
    from app.engine.ident.runner import simulate
    from app.engine.params import PlantParams

    spec = spec or AutotuneSpec()
    proc = PIDAutotuneProcedure(spec)
    run = simulate(proc, PlantParams(), rate_hz, seed=seed)
    if run.summary.state != "finished":
        raise RuntimeError(f"autotune experiment {run.summary.state}: {proc.progress.message}")
    frf = proc.frf()
    tuning = tune_pid(frf, spec.bandwidth_rad_s, spec.phase_margin_deg, spec.n_filter)
    thesis_auto = THESIS_TUNED[spec.side]
    thesis_final = THESIS_FINAL[spec.side]
    steps = step_test(spec, {"initial": spec.initial, "tuned": tuning.gains, "thesis autotuner": thesis_auto,
                             "thesis Eq 3.26": thesis_final}, rate_hz, seed)
    margins = {label: loop_margins(frf, *g, spec.n_filter)
               for label, g in (("thesis autotuner", thesis_auto), ("thesis Eq 3.26", thesis_final))}
    return {"spec": asdict(spec), "frf": frf, "tuning": tuning, "thesis_margins": margins, "steps": steps,
            "rig_seconds": run.summary.sim_seconds}
