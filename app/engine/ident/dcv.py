"""Directional-valve identification: CPR maps and the new flow model (thesis 3.2.3, 4.1).

Set-up (Figure 3.10): port 2 of the DCV feeds chamber a of a fully extended
linear cylinder — a constant volume V — through PRV-a, which sets the supply
pressure P_s = z + P_atm. Chamber b stays open to atmosphere so the piston
rests on its end cap.

CPR mapping (3.2.3 steps 1–5, at each P_s of the grid):

* **filling**, u = 0 … 5.9 V in 0.1 V steps: vent the chamber (u = 10 V),
  apply u, wait for Ṗ_a ≈ 0; a(u, P_s) = P_a / P_s;
* **exhausting**, u = 4 … 10 V: fill the chamber to P_s (u = 0 V), apply u,
  wait for Ṗ_a ≈ 0; a(u, P_s) = P_atm / P_a.

"Ṗ_a ≈ 0" is made precise by how much P_a still has to move, not by its
slope alone (:func:`remaining_change`): a slow approach — a signal near 5 V,
where only the null-zone leakage flows, has time constants of tens of
seconds — can creep at a slope that looks flat while tenths of a bar are
still to come. The test ends once the projected further change (of an
exponential or an algebraic approach, whichever is larger) is below
:data:`SETTLED_REMAINING_BAR`, or once no motion is resolved above the
sensor noise; :data:`MAX_TEST_S` caps it.

Flow-model fit (4.1.2): every test's transient gives measured mass flows
ṁ_m = Ṗ_a·V / (n·R·T) (Eq 4.1; n = 1 isothermal, 1.4 adiabatic), Ṗ_a from a
centred moving-average filter. At P_s = 5 bar each signal of the unstable
band gets ε(u) and g(u) = α1(u)·u + α2(u)·u² by least squares on
ṁ = sgn(d)·|d|^ε·g / (c_p·T·k(P_s)), d = P_u·a − P_d (Eq 3.10–3.11). The
tests at the other supply pressures then give k(P_s) (normalised to
k(5 bar) = 1) and its polynomial (Eq 4.2: cubic filling; Eq 4.3: quartic
exhausting).

Unit convention (SPEC §3 asks for one): pressures in Pa, c_p in J/(kg·K),
T in K, ṁ in kg/s, u in V, so g is in kg/s·(J/kg)·Pa^−ε and α1 = g/u, α2 = 0.
α1 and α2 cannot be separated at one signal: ∂ṁ/∂α2 = u·∂ṁ/∂α1, so the
Jacobian of the thesis's three-parameter fit is rank 2 and any α1/α2 split
with the same g fits equally — which is why Table 4.1's pairs look erratic.
We report g and store α1 = g/u, α2 = 0, the simulator's convention.

The literature models of Section 2.3 are fitted to the same flow data for
the comparison of 4.1.3: standard (Eq 2.2–2.4: a = 1, b = 0.528, ε = 0.5, one
effective area per signal), improved (Eq 2.5: a = 1, b and ε per signal) and
Bobrow–McDonell (Eq 2.6: a = 1, four constants per direction).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from functools import partial
from typing import Any, Literal

import numpy as np
from numba import njit
from scipy.ndimage import uniform_filter1d
from scipy.optimize import brentq, least_squares

from app.engine.constants import BAR, CP_AIR, GAMMA_AIR, P_ATM_BAR, R_AIR
from app.engine.hardware.base import Command
from app.engine.ident.gui_rules import MSG_PW, MSG_REASONABLE
from app.engine.ident.procedure import Procedure, Script
from app.engine.params import ParameterError
from app.engine.physics.flow import interp2_clip

Mode = Literal["filling", "exhausting"]
ModelName = Literal["new", "standard", "improved", "bobrow"]
MODELS: tuple[ModelName, ...] = ("new", "standard", "improved", "bobrow")

SETTLED_REMAINING_BAR = 0.01  # ≈ 3× the sensor's noise; a moves by ≤ 0.005 at P_s ≥ 2 bar
MIN_WINDOW_S = 0.5  # shortest of the three windows remaining_change compares
NOISE_K = 4.0  # a difference of two window means counts as motion beyond NOISE_K of its noise SD
MIN_TEST_S = 2.0
MAX_TEST_S = 300.0
CHECK_EVERY_S = 0.25
MAF_WINDOW_S = 0.05  # shortest moving-average window of the pressure derivative (Eq 4.1)
MAF_FRACTION = 0.02  # ... which grows to this share of a slow test's length (see measured_flow)
MIN_SWING_BAR = 0.05  # a test whose pressure moves less than this shows no flow to fit (Table 4.1's "-")
FIT_PS_BAR = 5.0  # Table 4.1's supply pressure
Z_EXTEND = 1.0  # V: pushes the piston onto its end cap before the tests
PS_TAP_TOL_BAR = 0.5  # PS-0 further than this from the set supply pressure is not at the DCV port

# Section 2.3 constants (k = γ of air): Eq 2.3 and 2.4
B_STANDARD = 0.528
C1_STD = math.sqrt(GAMMA_AIR / R_AIR * (2.0 / (GAMMA_AIR + 1.0)) ** ((GAMMA_AIR + 1.0) / (GAMMA_AIR - 1.0)))
C2_STD = math.sqrt(2.0 * GAMMA_AIR / (R_AIR * (GAMMA_AIR - 1.0)))


def _grid(lo: float, hi: float, step: float) -> tuple[float, ...]:
    n = int(round((hi - lo) / step))
    return tuple(round(lo + i * step, 6) for i in range(n + 1))


@dataclass(frozen=True)
class DCVInputs:
    """What the CPR/flow identification needs to know (validated).

    Attributes:
        chamber_volume_cm3: Volume of the fully extended chamber a, dead volume
            included [cm³].
        ps_bar: Supply pressures to map [bar abs] (thesis: 2–7, ΔP_s = 1).
        u_fill: Filling signals [V] (thesis: 0 ≤ u < 6, Δu = 0.1).
        u_exh: Exhausting signals [V] (thesis: 4–10, Δu = 0.1).
        band_fill: Unstable band fitted for filling [V] (thesis: 4.5–5.7).
        band_exh: Unstable band fitted for exhausting [V] (thesis: 4.5–5.9;
            Table 4.1 starts at 4.7).
        temperature_k: Air temperature T [K].
        polytropic_n: n of Eq 4.1 (1 isothermal … 1.4 adiabatic) [-].
    """

    chamber_volume_cm3: float = 245.3
    ps_bar: tuple[float, ...] = (2.0, 3.0, 4.0, 5.0, 6.0, 7.0)
    u_fill: tuple[float, ...] = _grid(0.0, 5.9, 0.1)
    u_exh: tuple[float, ...] = _grid(4.0, 10.0, 0.1)
    band_fill: tuple[float, float] = (4.5, 5.7)
    band_exh: tuple[float, float] = (4.5, 5.9)
    temperature_k: float = 293.15
    polytropic_n: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.chamber_volume_cm3) and self.chamber_volume_cm3 > 0):
            raise ParameterError(f"chamber_volume_cm3: {MSG_REASONABLE}")
        if not self.ps_bar:
            raise ParameterError("ps_bar: give at least one supply pressure")
        for p in self.ps_bar:
            if not (math.isfinite(p) and 1.0 <= p <= 8.0):
                raise ParameterError(f"ps_bar = {p}: {MSG_PW}")
        if not self.u_fill and not self.u_exh:
            raise ParameterError("u_fill: give filling or exhausting signals (or both)")
        for name in ("u_fill", "u_exh"):
            us = getattr(self, name)
            if any(not (math.isfinite(u) and 0.0 <= u <= 10.0) for u in us):
                raise ParameterError(f"{name}: DCV signals must lie in 0–10 V")
        for name in ("band_fill", "band_exh"):
            lo, hi = getattr(self, name)
            if not 0.0 <= lo < hi <= 10.0:
                raise ParameterError(f"{name} = ({lo}, {hi}): need 0 ≤ low < high ≤ 10 V")
        if not (math.isfinite(self.temperature_k) and 200.0 <= self.temperature_k <= 400.0):
            raise ParameterError(f"temperature_k = {self.temperature_k}: must lie in 200–400 K")
        if not 1.0 <= self.polytropic_n <= GAMMA_AIR + 1e-9:
            raise ParameterError(f"polytropic_n = {self.polytropic_n}: must lie in 1–{GAMMA_AIR:.2f}")

    @property
    def volume_m3(self) -> float:
        """V [m³]."""
        return self.chamber_volume_cm3 * 1e-6

    @property
    def n_tests(self) -> int:
        """Tests in a full CPR map."""
        return len(self.ps_bar) * (len(self.u_fill) + len(self.u_exh))


def check_fittable(inputs: DCVInputs, fit_ps_bar: float = FIT_PS_BAR) -> None:
    """Refuse, before any air moves, a grid the flow-model fit cannot use.

    The flow model is fitted at one supply pressure (Table 4.1: 5 bar) on the
    signals of each mode's unstable band, at least two of them.

    Raises:
        ParameterError: Naming the field to change.
    """
    if not any(abs(p - fit_ps_bar) < 1e-6 for p in inputs.ps_bar):
        raise ParameterError(f"ps_bar: the flow model is fitted at {fit_ps_bar:g} bar (Table 4.1); include it")
    for name, band in (("u_fill", inputs.band_fill), ("u_exh", inputs.band_exh)):
        us = getattr(inputs, name)
        inside = [u for u in us if band[0] - 1e-9 <= u <= band[1] + 1e-9]
        if us and len(inside) < 2:
            raise ParameterError(f"{name}: needs at least two signals inside the unstable band "
                                 f"{band[0]:g}–{band[1]:g} V to fit the flow model (has {len(inside)})")


@dataclass
class CPRTest:
    """One CPR experiment: its settled pressure and the transient it came from.

    Attributes:
        mode: ``"filling"`` or ``"exhausting"``.
        u: DCV signal [V].
        ps_bar: Supply pressure set [bar abs].
        a: Cracking pressure ratio [-] (filling P_a/P_s, exhausting P_atm/P_a).
        p_end_bar: Settled chamber pressure [bar abs].
        settled: Whether Ṗ_a ≈ 0 (see :func:`remaining_change`) was reached
            before :data:`MAX_TEST_S`.
        t0: Test start on the engine clock [s].
        p_bar: Chamber pressure samples from the signal step on [bar abs].
        dt: Sample period [s].
        ps_meas: Supply pressure at the DCV port (PS-0) over the test [bar abs].
    """

    mode: str
    u: float
    ps_bar: float
    a: float
    p_end_bar: float
    settled: bool
    t0: float
    p_bar: np.ndarray
    dt: float
    ps_meas: np.ndarray

    @property
    def ps_mean(self) -> float:
        """Mean measured supply pressure over the test [bar abs]."""
        return float(self.ps_meas.mean()) if self.ps_meas.size else self.ps_bar

    @property
    def swing_bar(self) -> float:
        """How far the pressure moved during the test [bar]."""
        return float(np.ptp(self.p_bar)) if self.p_bar.size else 0.0

    def summary(self) -> dict[str, Any]:
        """JSON view without the trace."""
        return {"mode": self.mode, "u": self.u, "ps_bar": self.ps_bar, "a": self.a, "p_end_bar": self.p_end_bar,
                "settled": self.settled, "t0": self.t0, "n_samples": int(self.p_bar.size)}


@dataclass
class CPRData:
    """Every CPR experiment, in run order, with the conditions they ran under."""

    inputs: DCVInputs
    p_atm_bar: float = P_ATM_BAR
    tests: list[CPRTest] = field(default_factory=list)

    def select(self, mode: str, ps_bar: float | None = None) -> list[CPRTest]:
        """Tests of one mode (and supply pressure)."""
        return [t for t in self.tests if t.mode == mode and (ps_bar is None or abs(t.ps_bar - ps_bar) < 1e-6)]

    def cpr_map(self, mode: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u grid, P_s grid, a[u, P_s]) of one mode; NaN where not measured."""
        us = np.array(sorted({t.u for t in self.tests if t.mode == mode}))
        ps = np.array(sorted({t.ps_bar for t in self.tests if t.mode == mode}))
        a = np.full((us.size, ps.size), np.nan)
        for t in self.select(mode):
            a[int(np.searchsorted(us, t.u)), int(np.searchsorted(ps, t.ps_bar))] = t.a
        return us, ps, a

    def as_dict(self) -> dict[str, Any]:
        """JSON view (traces left out)."""
        return {"inputs": asdict(self.inputs), "p_atm_bar": self.p_atm_bar,
                "tests": [t.summary() for t in self.tests]}


class CPRProcedure(Procedure):
    """The CPR mapping of 3.2.3 on the constant-volume set-up (Figure 3.10).

    Args:
        inputs: Validated inputs.
        modes: Which maps to run (both by default).
        fixed_s: If set, every test lasts exactly this long instead of ending
            at Ṗ_a ≈ 0 — the validation runs of 4.1.3 (15 s) [s].
        cases: If set, run these (mode, u, P_s) instead of the full grid.
        validation: (mode, u, P_s) runs of ``validation_s`` each after the
            map (4.1.3, Figures 4.6–4.11), kept apart in :attr:`validation_data`.
        validation_s: Length of each validation run [s] (thesis: 15).
    """

    name = "dcv_cpr"

    def __init__(self, inputs: DCVInputs, modes: tuple[str, ...] = ("filling", "exhausting"),
                 fixed_s: float | None = None, cases: list[tuple[str, float, float]] | None = None,
                 validation: list[tuple[str, float, float]] | None = None, validation_s: float = 15.0) -> None:
        super().__init__(vent_s=0.5)
        self.inputs = inputs
        self.data = CPRData(inputs)
        self.validation_data = CPRData(inputs)
        self.fixed_s = fixed_s
        if cases is None:
            cases = [(m, u, ps) for m in modes for ps in inputs.ps_bar
                     for u in (inputs.u_fill if m == "filling" else inputs.u_exh)]
        validation = validation or []
        for m, u, ps in [*cases, *validation]:
            if m not in ("filling", "exhausting"):
                raise ParameterError(f"mode = {m!r} must be 'filling' or 'exhausting'")
            if not (0.0 <= u <= 10.0 and 1.0 <= ps <= 8.0):
                raise ParameterError(f"case ({m}, {u} V, {ps} bar) outside 0–10 V / 1–8 bar")
        if not (math.isfinite(validation_s) and MIN_TEST_S <= validation_s <= 120.0):
            raise ParameterError(f"validation_s = {validation_s}: must lie in {MIN_TEST_S:g}–120 s")
        self.cases = cases
        self.validation = validation
        self.validation_s = validation_s
        self.progress.total_tests = len(cases) + len(validation)

    def z_for(self, ps_bar: float) -> float:
        """PRV command for supply pressure ``ps_bar`` [V] (P_s = z + P_atm)."""
        return max(0.0, ps_bar - self.data.p_atm_bar)

    @staticmethod
    def cmd(z: float, u: float) -> Command:
        """Port 2 of DCV-a at ``u`` from PRV-a at ``z``; chamber b open to atmosphere."""
        return Command(z, 0.0, u, 0.0)

    def script(self) -> Script:
        """Extend, read P_atm, then every case grouped into blocks of one mode and P_s."""
        yield from self.hold(self.cmd(Z_EXTEND, 0.0), 2.0)
        vent = self.cmd(0.0, 10.0)
        yield from self.hold(vent, 2.0)
        samples: list[float] = []
        for _ in range(int(0.5 / self.dt)):
            yield vent
            samples.append(self.meas.p_a)
        self.data.p_atm_bar = float(np.mean(samples))
        for (m, ps), group in itertools.groupby(self.cases, key=lambda c: (c[0], c[2])):
            block = list(group)
            it = iter(block)
            yield from self.block(f"{m} P_s = {ps:g} bar", len(block), partial(self._next_case, it))
        if self.validation:
            self.validation_data.p_atm_bar = self.data.p_atm_bar
            it = iter(self.validation)
            yield from self.block("validation", len(self.validation), partial(self._next_validation, it))

    def _next_case(self, it: Iterator[tuple[str, float, float]]) -> Script:
        return self.test(*next(it))

    def _next_validation(self, it: Iterator[tuple[str, float, float]]) -> Script:
        return self.test(*next(it), into=self.validation_data, fixed_s=self.validation_s)

    def _settle(self, cmd: Command, target: float, tol: float, timeout: float) -> Script:
        """Hold ``cmd`` until P_a is within ``tol`` of ``target`` and steady [bar]."""
        buf: list[float] = []
        n = max(2, int(0.3 / self.dt))
        t_end = self.meas.t + timeout
        while self.meas.t < t_end:
            yield cmd
            buf.append(self.meas.p_a)
            if len(buf) >= n and abs(float(np.mean(buf[-n:])) - target) < tol and np.ptp(buf[-n:]) < 4 * tol:
                return

    def test(self, mode: str, u: float, ps: float, into: CPRData | None = None,
             fixed_s: float | None = None) -> Script:
        """One CPR experiment (3.2.3 steps 2–4), kept in ``into`` (default :attr:`data`).

        ``fixed_s`` (default the procedure's) makes it last exactly that long [s].
        """
        into = self.data if into is None else into
        fixed_s = self.fixed_s if fixed_s is None else fixed_s
        z = self.z_for(ps)
        if mode == "filling":
            yield from self._settle(self.cmd(z, 10.0), self.data.p_atm_bar, 0.01, 10.0)
        else:
            yield from self._settle(self.cmd(z, 0.0), ps, 0.1, 10.0)
        cmd = self.cmd(z, u)
        limit = fixed_s if fixed_s is not None else MAX_TEST_S
        cap = int(math.ceil(limit / self.dt)) + 1
        p = np.empty(cap)
        s = np.empty(cap)
        n = 0
        t0 = self.meas.t
        settled = False
        next_check = max(1, int(round(MIN_TEST_S / self.dt)))
        while self.meas.t - t0 < limit - 0.5 * self.dt and n < cap:
            yield cmd
            p[n] = self.meas.p_a
            s[n] = self.meas.p_s
            n += 1
            if fixed_s is None and n >= next_check:
                if remaining_change(p[:n], self.dt) < SETTLED_REMAINING_BAR:
                    settled = True
                    break
                # every 0.25 s, or 2 % of the test so far: a minutes-long test ends ≤ 2 % late
                next_check = n + max(int(round(CHECK_EVERY_S / self.dt)), n // 50)
        pa = p[:n].copy()
        psm = s[:n].copy()
        tail = max(1, int(0.5 / self.dt))
        p_end = float(pa[-tail:].mean())
        ps_end = float(psm[-tail:].mean())
        if abs(ps_end - ps) > PS_TAP_TOL_BAR:
            raise RuntimeError(f"PS-0 reads {ps_end:.2f} bar with PRV-a set to {ps:g} bar: in the CPR set-up "
                               "PS-0 must measure the DCV's supply port (Figure 3.10)")
        if fixed_s is not None:
            settled = True
        a = p_end / ps_end if mode == "filling" else self.data.p_atm_bar / p_end
        into.tests.append(CPRTest(mode, float(u), float(ps), float(a), p_end, settled, t0, pa, self.dt, psm))


def remaining_change(p: np.ndarray, dt: float) -> float:
    """How much further a settling pressure trace will move [bar] (the CPR tests' Ṗ ≈ 0).

    The trace's last three quarters are split into three equal windows
    (each at least :data:`MIN_WINDOW_S`) whose means step by d1 = m2 − m1 and
    d2 = m3 − m2. A first-order approach steps by a constant ratio
    r = d2/d1 = e^(−W/τ), so its last window's mean has |d2|·r/(1 − r) left
    to go (Aitken's Δ²) and its last sample the share −ln r/(1/r − 1) of that
    — exact for an exponential whatever τ is. A valve with ε > 1 closes the
    last gap algebraically instead (t^−k), which the same ratio also fits;
    the larger of the two projections is returned. Windows growing with the
    test fit slow approaches as well as fast ones. Near r = 1 that ratio is
    fragile, so the noise is taken against the trace: each step is widened
    by :data:`NOISE_K` of its noise SD (from the scatter of the last
    window's second differences) before r is formed — the estimate is an
    upper bound, and a creep whose slowing is not resolved is never called
    settled. Steps both within that band, and their sum too, are no
    resolved motion: 0.

    Args:
        p: Pressure samples since the signal step [bar].
        dt: Sample period [s].

    Returns:
        The projected further change [bar]; ``inf`` while the trace is not
        resolvably converging or too short to judge.
    """
    n = p.size
    w = max(int(round(MIN_WINDOW_S / dt)), n // 4)
    if 3 * w > n:
        return math.inf
    m1 = float(p[n - 3 * w:n - 2 * w].mean())
    m2 = float(p[n - 2 * w:n - w].mean())
    m3 = float(p[n - w:].mean())
    d1, d2 = abs(m2 - m1), abs(m3 - m2)
    noise = float(np.std(np.diff(p[n - w:], 2))) / math.sqrt(6.0)  # white: var(Δ²) = 6σ², trend-free
    band = NOISE_K * noise * math.sqrt(2.0 / w)  # SD of a difference of two w-sample means, ×K
    if d1 <= band and d2 <= band and abs(m3 - m1) <= band:
        # neither step nor their sum resolved: no motion (the sum matters for a creep too slow
        # to resolve in one step but not in two, which is no sign of having arrived)
        return 0.0
    hi, lo = d2 + band, d1 - band
    if lo <= hi:
        return math.inf
    r = hi / lo
    if r <= 0.0:
        return 0.0
    # m3 trails the trace's end by its window: of the |d2|·r/(1 − r) the mean has left, the
    # last sample has the share (W/τ)/(e^(W/τ) − 1) = −ln r/(1/r − 1) left
    exponential = hi * r / (1.0 - r) * (-math.log(r) / (1.0 / r - 1.0))
    return max(exponential, _power_law_remaining(hi, r, w / n))


def _window_mean_power(a: float, b: float, k: float) -> float:
    """Mean of s^−k over [a, b] [-]."""
    if abs(k - 1.0) < 1e-9:
        return (math.log(b) - math.log(a)) / (b - a)
    return (b ** (1.0 - k) - a ** (1.0 - k)) / ((1.0 - k) * (b - a))


def _power_law_steps(k: float, f: float) -> tuple[float, float]:
    """Steps of window means of s^−k over [1−3f, 1−2f], [1−2f, 1−f], [1−f, 1] (s = t/T)."""
    edges = [max(1.0 - (3 - i) * f, 1e-3) for i in range(4)]  # samples start at t = dt, not 0
    m = [_window_mean_power(edges[i], edges[i + 1], k) for i in range(3)]
    return m[0] - m[1], m[1] - m[2]


def _power_law_remaining(d2: float, r: float, f: float) -> float:
    """What an algebraic approach P∞ − A·t^−k with step ratio ``r`` has left after the last window [bar].

    A valve whose flow goes as |d|^ε with ε > 1 near its stop (the new
    model's exhaust branch, Table 4.1) closes the gap as t^−1/(ε−1), not
    exponentially; read as an exponential such a trace is projected 3–4×
    too close to its end. ``k`` is solved from ``r`` (windows are fractions
    ``f`` of the trace, so r depends on k alone) and the remaining A·T^−k
    follows from the last step ``d2``. 0 where no power law gives ``r``.
    """
    def gap(k: float) -> float:
        s1, s2 = _power_law_steps(k, f)
        return s2 / s1 - r

    k_lo, k_hi = 1e-3, 60.0
    if gap(k_lo) <= 0.0 or gap(k_hi) >= 0.0:
        return 0.0
    k = float(brentq(gap, k_lo, k_hi, xtol=1e-6))
    return d2 / _power_law_steps(k, f)[1]


# --------------------------------------------------------------------------- flow data


def measured_flow(test: CPRTest, inputs: DCVInputs,
                  window_s: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(P_a [Pa], P_s [Pa], ṁ_m [kg/s]) of one test by Eq 4.1 with a moving-average derivative.

    The trace is smoothed by a centred moving average of ``window_s`` and
    differentiated; a window at each end (where the filter is one-sided) is
    dropped. ṁ > 0 flows into the chamber. The default window is
    :data:`MAF_WINDOW_S`, or :data:`MAF_FRACTION` of the test's length if
    that is longer: a test that ran for minutes (a signal in the null zone,
    flows 25× smaller) has a time constant of tens of seconds, and with the
    50 ms window its derivative would be the sensor noise's (≈ 0.1 bar/s
    against flows of ≈ 0.01 bar/s), while a window of 2 % of its length
    still bends the transient by < 0.1 %.
    """
    p = test.p_bar * BAR
    if window_s is None:
        window_s = max(MAF_WINDOW_S, MAF_FRACTION * p.size * test.dt)
    w = max(3, int(round(window_s / test.dt)) | 1)
    if p.size < 3 * w:
        return np.empty(0), np.empty(0), np.empty(0)
    pf = uniform_filter1d(p, w, mode="nearest")
    sf = uniform_filter1d(test.ps_meas * BAR, w, mode="nearest")
    dp = np.gradient(pf, test.dt)
    sl = slice(w, p.size - w)
    mdot = dp[sl] * inputs.volume_m3 / (inputs.polytropic_n * R_AIR * inputs.temperature_k)
    return pf[sl], sf[sl], mdot


# --------------------------------------------------------------------------- models


def _pressures(mode: str, p: np.ndarray, ps: float | np.ndarray, p_atm: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(P_u, P_d, sign) of port 2: filling supply → chamber (+), exhausting chamber → atmosphere (−)."""
    if mode == "filling":
        return np.broadcast_to(ps, p.shape), p, 1.0
    return p, np.full_like(p, p_atm), -1.0


def new_flow(mode: str, p: np.ndarray, ps: float | np.ndarray, p_atm: float, a: float, eps: float, g: float, k: float,
             t: float) -> np.ndarray:
    """Eq 3.10–3.11, signed (flow reverses past the cracking point), into the chamber [kg/s]."""
    pu, pd, s = _pressures(mode, p, ps, p_atm)
    d = pu * a - pd
    return s * np.sign(d) * np.abs(d) ** eps * g / (CP_AIR * t * k)


def _beta_standard(pr: np.ndarray) -> np.ndarray:
    g = GAMMA_AIR
    pr = np.clip(pr, 0.0, 1.0)
    sub = C2_STD * pr ** (1.0 / g) * np.sqrt(np.maximum(1.0 - pr ** ((g - 1.0) / g), 0.0))
    return np.where(pr <= B_STANDARD, C1_STD, sub)


def standard_flow(mode: str, p: np.ndarray, ps: float | np.ndarray, p_atm: float, area: float, t: float) -> np.ndarray:
    """Eq 2.2–2.4 (a = 1, b = 0.528, ε = 0.5) times an effective area [m²] → kg/s into the chamber."""
    pu, pd, s = _pressures(mode, p, ps, p_atm)
    hi = np.maximum(pu, pd)
    lo = np.minimum(pu, pd)
    direction = np.where(pu >= pd, 1.0, -1.0)
    return s * direction * area * hi / math.sqrt(t) * _beta_standard(lo / hi)


def improved_flow(mode: str, p: np.ndarray, ps: float | np.ndarray, p_atm: float, area: float, b: float, eps: float,
                  t: float) -> np.ndarray:
    """Eq 2.5 with a = 1 (σ_lam ignored, as the thesis does) → kg/s into the chamber."""
    pu, pd, s = _pressures(mode, p, ps, p_atm)
    hi = np.maximum(pu, pd)
    lo = np.minimum(pu, pd)
    direction = np.where(pu >= pd, 1.0, -1.0)
    pr = lo / hi
    shape = np.where(pr <= b, 1.0, np.maximum(1.0 - ((pr - b) / (1.0 - b)) ** 2, 0.0) ** eps)
    return s * direction * area * C1_STD * hi / math.sqrt(t) * shape


def bobrow_flow(mode: str, p: np.ndarray, ps: float | np.ndarray, p_atm: float, u: float, c: tuple[float, float],
                t: float) -> np.ndarray:
    """Eq 2.6 (a = 1): (P_u − P_d)^0.5 filling, (P_u − P_d)^1 exhausting → kg/s into the chamber."""
    pu, pd, s = _pressures(mode, p, ps, p_atm)
    d = pu - pd
    e = 0.5 if mode == "filling" else 1.0
    return s * np.sign(d) * np.abs(d) ** e * (c[0] * u + c[1] * u * u) / (CP_AIR * t)


# --------------------------------------------------------------------------- fitted model

TABLE_POINTS = 4001  # chamber-pressure grid of the tabulated model (≈ 150 Pa apart for 6 bar)
INTEGRATION_STEP_S = 5.0e-4


@njit(cache=True, inline="always", error_model="numpy")
def _table(x: float, j: int, w: float, lo: float, step: float, table: np.ndarray) -> float:
    """Linear interpolation on the uniform P_a grid of column pair (j, j+1) weighted ``w``."""
    n = table.shape[0]
    f = (x - lo) / step
    i = min(max(int(f), 0), n - 2)
    r = min(max(f - i, 0.0), 1.0)
    c0 = table[i, j] + r * (table[i + 1, j] - table[i, j])
    if w == 0.0:
        return c0
    c1 = table[i, j + 1] + r * (table[i + 1, j + 1] - table[i, j + 1])
    return c0 + w * (c1 - c0)


@njit(cache=True, error_model="numpy")
def _integrate(pg: np.ndarray, sg: np.ndarray, table: np.ndarray, t: np.ndarray, ps: np.ndarray, p0: float,
               h: float) -> np.ndarray:
    """Trapezoidal integration of Ṗ = table(P, P_s) with P_s held between samples.

    Both grids are uniform. Every model's inflow falls as the chamber
    pressure rises, so each implicit step is a monotone scalar equation,
    solved by bisection.
    """
    out = np.empty(t.size)
    p = p0
    out[0] = p
    lo = pg[0]
    step = pg[1] - pg[0]
    ns = sg.size
    for i in range(1, t.size):
        fs = (ps[i - 1] - sg[0]) / (sg[1] - sg[0])
        j = min(max(int(fs), 0), ns - 2)
        w = min(max(fs - j, 0.0), 1.0)
        n = max(1, int(math.ceil((t[i] - t[i - 1]) / h)))
        hh = (t[i] - t[i - 1]) / n
        for _ in range(n):
            f0 = _table(p, j, w, lo, step, table)
            a = pg[0]
            b = pg[pg.size - 1]
            for _ in range(40):
                x = 0.5 * (a + b)
                if x - p - 0.5 * hh * (f0 + _table(x, j, w, lo, step, table)) > 0.0:
                    b = x
                else:
                    a = x
            p = 0.5 * (a + b)
        out[i] = p
    return out


def compile_integrator() -> None:
    """Compile (or load from the cache) the validation runs' integrator now, not in the first validation."""
    pg = np.linspace(1.0e5, 6.0e5, 8)
    _integrate(pg, np.array([5.0, 5.001]), np.zeros((8, 2)), np.array([0.0, 0.01]), np.array([5.0, 5.0]), 1.0e5,
               INTEGRATION_STEP_S)


@dataclass
class SignalFit:
    """Flow-model parameters of one signal at P_s = 5 bar (Table 4.1 row).

    Attributes:
        u: Signal [V].
        a: CPR at 5 bar used in the fit [-].
        eps: ε(u) [-].
        g: g(u) = α1·u + α2·u² (module unit convention).
        alpha1: g/u.
        alpha2: 0 (see module doc).
        r2: R² of the flow fit [-].
        n: Samples fitted.
        std_area: Standard model's effective area [m²].
        imp_area: Improved model's effective area [m²].
        imp_b: Improved model's critical ratio b [-].
        imp_eps: Improved model's ε [-].
    """

    u: float
    a: float
    eps: float
    g: float
    alpha1: float
    alpha2: float
    r2: float
    n: int
    std_area: float
    imp_area: float
    imp_b: float
    imp_eps: float


@dataclass
class ModeModel:
    """The identified flow model of one mode.

    Attributes:
        mode: ``"filling"`` or ``"exhausting"``.
        u_cpr: CPR map signals [V].
        ps_cpr: CPR map supply pressures [bar abs].
        a: CPR map a[u, P_s] [-].
        signals: Table 4.1 rows (signals with flow to fit).
        skipped: Band signals whose pressure barely moved (Table 4.1's "-") [V].
        k_ps: Supply pressures of the k(P_s) points [bar abs].
        k_val: k(P_s) normalised to k(5 bar) = 1 [-].
        k_poly: Polynomial through them, highest power first (Eq 4.2/4.3 form).
        bobrow: Eq 2.6 constants (c1, c2) or (c3, c4).
    """

    mode: str
    u_cpr: np.ndarray
    ps_cpr: np.ndarray
    a: np.ndarray
    signals: list[SignalFit]
    skipped: list[float]
    k_ps: np.ndarray
    k_val: np.ndarray
    k_poly: np.ndarray
    bobrow: tuple[float, float]

    def cpr(self, u: float, ps: float) -> float:
        """Bilinear a(u, P_s), clipped to the map (the thesis's 2-D lookup)."""
        return float(interp2_clip(u, ps, self.u_cpr, self.ps_cpr, np.nan_to_num(self.a, nan=1.0)))

    def signal_params(self, u: float) -> dict[str, float]:
        """1-D lookups of every per-signal parameter at ``u`` (clipped).

        Between two signals g is not looked up itself: ε and g trade off (the
        flow is g·|d|^ε with |d| ~ 10⁵ Pa), so where ε changes from one
        signal to the next (0.50 → 0.60 between 4.9 and 5.0 V on the
        simulated rig's default valve) a straight line through g predicts
        the midpoint's pressure 6–21 % off. What is looked up is the flow at a 1 bar difference,
        G = g·(1 bar)^ε, on a log scale (it spans decades across the null
        zone); g = G/(1 bar)^ε at the interpolated ε. At the signals
        themselves this is Table 4.1's g.
        """
        us = np.array([s.u for s in self.signals])
        out = {}
        for key in ("eps", "std_area", "imp_area", "imp_b", "imp_eps"):
            out[key] = float(np.interp(u, us, np.array([getattr(s, key) for s in self.signals])))
        eps = np.array([s.eps for s in self.signals])
        log_g_ref = np.log(np.maximum([s.g for s in self.signals], 1e-300)) + eps * math.log(BAR)
        out["g"] = math.exp(float(np.interp(u, us, log_g_ref)) - out["eps"] * math.log(BAR))
        return out

    def k(self, ps: float) -> float:
        """k(P_s) from the fitted polynomial, P_s clipped to the mapped range [-]."""
        return float(np.polyval(self.k_poly, min(max(ps, self.k_ps.min()), self.k_ps.max())))

    def flow(self, model: ModelName, p: np.ndarray, u: float, ps_bar: float, p_atm: float, t: float,
             ps: float | np.ndarray | None = None) -> np.ndarray:
        """Mass flow into the chamber predicted by ``model`` [kg/s].

        Args:
            model: Which model.
            p: Chamber pressures [Pa].
            u: Signal [V].
            ps_bar: Supply pressure for the a(u, P_s) and k(P_s) lookups [bar abs].
            p_atm: Atmospheric pressure [Pa].
            t: Air temperature [K].
            ps: Measured supply pressure (P_u when filling) [Pa], scalar or
                one per ``p``; default ``ps_bar``.
        """
        sp = self.signal_params(u)
        ps = ps_bar * BAR if ps is None else ps
        if model == "new":
            return new_flow(self.mode, p, ps, p_atm, self.cpr(u, ps_bar), sp["eps"], sp["g"], self.k(ps_bar), t)
        if model == "standard":
            return standard_flow(self.mode, p, ps, p_atm, sp["std_area"], t)
        if model == "improved":
            return improved_flow(self.mode, p, ps, p_atm, sp["imp_area"], sp["imp_b"], sp["imp_eps"], t)
        if model == "bobrow":
            return bobrow_flow(self.mode, p, ps, p_atm, u, self.bobrow, t)
        raise ParameterError(f"model = {model!r} must be one of {', '.join(MODELS)}")

    def as_dict(self) -> dict[str, Any]:
        """JSON view (Table 4.1, Eq 4.2/4.3 form, CPR map)."""
        return {"mode": self.mode, "u_cpr": self.u_cpr.tolist(), "ps_cpr": self.ps_cpr.tolist(),
                "a": [[None if math.isnan(v) else v for v in row] for row in self.a.tolist()],
                "table_4_1": [asdict(s) for s in self.signals], "no_flow_signals": self.skipped,
                "k_ps": self.k_ps.tolist(), "k": self.k_val.tolist(), "k_poly": self.k_poly.tolist(),
                "bobrow_c": list(self.bobrow)}


def _r2(y: np.ndarray, yhat: np.ndarray) -> float:
    ss = float(np.sum((y - y.mean()) ** 2))
    return 1.0 - float(np.sum((y - yhat) ** 2)) / ss if ss > 0 else math.nan


class DCVFlowEstimator:
    """Fit the new flow model and the literature models to CPR data (4.1.2).

    Attributes:
        params_: ``{"filling": ModeModel, "exhausting": ModeModel}`` after :meth:`fit`.
        p_atm_: Atmospheric pressure of the data [Pa].
    """

    def __init__(self, fit_ps_bar: float = FIT_PS_BAR) -> None:
        self.fit_ps_bar = fit_ps_bar
        self.params_: dict[str, ModeModel] = {}
        self.p_atm_ = P_ATM_BAR * BAR
        self.inputs_: DCVInputs | None = None

    def fit(self, data: CPRData) -> DCVFlowEstimator:
        """Fit both modes that the data holds."""
        self.p_atm_ = data.p_atm_bar * BAR
        self.inputs_ = data.inputs
        for mode in ("filling", "exhausting"):
            if data.select(mode):
                self.params_[mode] = self._fit_mode(data, mode)
        if not self.params_:
            raise ParameterError("no CPR tests in the data")
        return self

    def _band(self, mode: str) -> tuple[float, float]:
        assert self.inputs_ is not None
        return self.inputs_.band_fill if mode == "filling" else self.inputs_.band_exh

    def _fit_mode(self, data: CPRData, mode: str) -> ModeModel:
        inp = data.inputs
        t = inp.temperature_k
        p_atm = self.p_atm_
        us, pss, amap = data.cpr_map(mode)
        lo, hi = self._band(mode)
        signals: list[SignalFit] = []
        skipped: list[float] = []
        flows: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        for test in data.select(mode, self.fit_ps_bar):
            if not lo - 1e-9 <= test.u <= hi + 1e-9:
                continue
            p, ps, m = measured_flow(test, inp)
            if test.swing_bar < MIN_SWING_BAR or p.size < 10:
                skipped.append(test.u)
                continue
            flows[test.u] = (p, ps, m)
            signals.append(self._fit_signal(mode, test.u, test.a, p, m, ps, p_atm, t))
        signals.sort(key=lambda s: s.u)
        if len(signals) < 2:
            raise ParameterError(f"{mode}: fewer than two signals in the band {lo}–{hi} V show flow at "
                                 f"P_s = {self.fit_ps_bar:g} bar; cannot fit the flow model")
        bob = self._fit_bobrow(mode, flows, p_atm, t)
        model = ModeModel(mode, us, pss, amap, signals, sorted(skipped), np.array([self.fit_ps_bar]),
                          np.array([1.0]), np.array([1.0]), bob)
        k_ps, k_val = self._fit_k(data, model)
        deg = min(3 if mode == "filling" else 4, k_ps.size - 1)
        model.k_ps, model.k_val = k_ps, k_val
        model.k_poly = np.polyfit(k_ps, k_val, deg) if deg >= 1 else np.array([1.0])
        return model

    @staticmethod
    def _fit_signal(mode: str, u: float, a: float, p: np.ndarray, m: np.ndarray, ps: np.ndarray, p_atm: float,
                    t: float) -> SignalFit:
        scale = float(np.max(np.abs(m))) or 1.0

        def proj(s: np.ndarray) -> float:
            den = float(s @ s)
            return max(float(s @ m) / den, 0.0) if den > 0 else 0.0

        def varpro(shape: Any, x0: list[float], lo: list[float], hi: list[float]) -> tuple[np.ndarray, float]:
            """The gain enters linearly: project it out and fit only the shape parameters."""

            def res(x: np.ndarray) -> np.ndarray:
                sh = shape(x)
                return (proj(sh) * sh - m) / scale

            x = least_squares(res, x0, bounds=(lo, hi)).x
            return x, proj(shape(x))

        def new_shape(x: np.ndarray) -> np.ndarray:
            return new_flow(mode, p, ps, p_atm, a, x[0], 1.0, 1.0, t)

        def imp_shape(x: np.ndarray) -> np.ndarray:
            return improved_flow(mode, p, ps, p_atm, 1.0, x[0], x[1], t)

        xn, g = varpro(new_shape, [0.75], [0.2], [3.0])
        eps = float(xn[0])
        r2 = _r2(m, g * new_shape(xn))
        std_area = proj(standard_flow(mode, p, ps, p_atm, 1.0, t))
        si, imp_area = varpro(imp_shape, [0.3, 0.5], [0.0, 0.2], [0.95, 3.0])
        return SignalFit(u, a, eps, g, g / u if u > 0 else 0.0, 0.0, r2, int(p.size), std_area, imp_area,
                         float(si[0]), float(si[1]))

    @staticmethod
    def _fit_bobrow(mode: str, flows: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]], p_atm: float,
                    t: float) -> tuple[float, float]:
        rows, ys = [], []
        for u, (p, ps, m) in flows.items():
            s = bobrow_flow(mode, p, ps, p_atm, 1.0, (1.0, 0.0), t)  # (P_u−P_d)^e/(c_p T), unit gain at u = 1
            rows.append(np.column_stack([s * u, s * u * u]))
            ys.append(m)
        if not rows:
            return (0.0, 0.0)
        coef, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(ys), rcond=None)
        return float(coef[0]), float(coef[1])

    def _fit_k(self, data: CPRData, model: ModeModel) -> tuple[np.ndarray, np.ndarray]:
        """k(P_s)/k(5 bar): the one gain that best scales the 5-bar model to each P_s's band tests."""
        inp = data.inputs
        lo, hi = self._band(model.mode)
        fitted = {s.u for s in model.signals}
        ks, kv = [], []
        for ps_bar in model.ps_cpr:
            num = den = 0.0
            for test in data.select(model.mode, float(ps_bar)):
                if test.u not in fitted or not lo <= test.u <= hi or test.swing_bar < MIN_SWING_BAR:
                    continue
                p, ps, m = measured_flow(test, inp)
                if p.size < 10:
                    continue
                pred = model.flow("new", p, test.u, test.ps_mean, self.p_atm_, inp.temperature_k, ps)  # k = 1 so far
                num += float(pred @ pred)
                den += float(pred @ m)
            if num > 0 and den > 0:
                ks.append(float(ps_bar))
                kv.append(num / den)  # least squares of m ≈ pred/k over 1/k
        k_ps, k_val = np.array(ks), np.array(kv)
        if k_ps.size:
            j = int(np.argmin(np.abs(k_ps - self.fit_ps_bar)))
            k_val = k_val / k_val[j]
        return k_ps, k_val

    # ------------------------------------------------------------ prediction
    def predict_pressure(self, model: ModelName, mode: str, u: float, ps_bar: float, p0_bar: float,
                         t: np.ndarray, ps_meas_bar: np.ndarray | None = None) -> np.ndarray:
        """Integrate the chamber pressure of the constant volume under ``model`` (Figure 4.5) [bar abs].

        Ṗ = n·R·T·ṁ/V from P(0) = ``p0_bar``, like the thesis's Simulink
        validation model, which is fed the measured supply pressure
        ``ps_meas_bar`` (sampled at ``t``) when given.
        """
        if not self.params_ or self.inputs_ is None:
            raise RuntimeError("fit first")
        mm = self.params_[mode]
        inp = self.inputs_
        c = inp.polytropic_n * R_AIR * inp.temperature_k / inp.volume_m3
        ps_series = np.full(t.size, ps_bar) if ps_meas_bar is None else np.asarray(ps_meas_bar, dtype=np.float64)
        # the model's flow tabulated over (P_a, P_s) once: the integrator then runs compiled
        lo = min(self.p_atm_, p0_bar * BAR) * 0.9
        hi = max(float(ps_series.max()) * BAR, p0_bar * BAR) * 1.05
        pg = np.linspace(lo, hi, TABLE_POINTS)
        sg = np.linspace(float(ps_series.min()), float(ps_series.max()) + 1e-3, 5)
        pp, ss = np.meshgrid(pg, sg * BAR, indexing="ij")
        table = c * mm.flow(model, pp, u, ps_bar, self.p_atm_, inp.temperature_k, ss)
        return _integrate(pg, sg, np.ascontiguousarray(table), np.asarray(t, dtype=np.float64), ps_series,
                          p0_bar * BAR, INTEGRATION_STEP_S) / BAR

    def validate(self, data: CPRData, models: tuple[ModelName, ...] = MODELS) -> list[ValidationCase]:
        """Predicted vs measured P_a for every test in ``data`` (4.1.3), per model."""
        out = []
        for test in data.tests:
            tt = np.arange(test.p_bar.size) * test.dt
            row = ValidationCase(test.mode, test.u, test.ps_bar, tt, test.p_bar, {}, {}, {})
            for m in models:
                pred = self.predict_pressure(m, test.mode, test.u, test.ps_mean, float(test.p_bar[0]), tt,
                                             test.ps_meas)
                err = np.abs(pred - test.p_bar) / test.p_bar * 100.0
                row.predicted[m] = pred
                row.mape_pct[m] = float(err.mean())
                row.final_pct[m] = float(err[-max(1, int(0.5 / test.dt)):].mean())
            out.append(row)
        return out

    def score(self, data: CPRData, model: ModelName = "new") -> float:
        """Mean absolute % error of predicted P_a over the tests in ``data`` [%]."""
        cases = self.validate(data, (model,))
        return float(np.mean([c.mape_pct[model] for c in cases]))

    def as_dict(self) -> dict[str, Any]:
        """JSON view of both modes."""
        return {m: mm.as_dict() for m, mm in self.params_.items()} | {"p_atm_bar": self.p_atm_ / BAR}


@dataclass
class ValidationCase:
    """One validation run (Figures 4.6–4.11): measured and predicted P_a per model.

    Attributes:
        mode: ``"filling"`` or ``"exhausting"``.
        u: Signal [V].
        ps_bar: Supply pressure [bar abs].
        t: Time from the signal step [s].
        measured: Measured P_a [bar abs].
        predicted: Predicted P_a per model [bar abs].
        mape_pct: Mean absolute % error over the run per model [%].
        final_pct: % error over the last 0.5 s per model [%].
    """

    mode: str
    u: float
    ps_bar: float
    t: np.ndarray
    measured: np.ndarray
    predicted: dict[str, np.ndarray]
    mape_pct: dict[str, float]
    final_pct: dict[str, float]

    def summary(self) -> dict[str, Any]:
        """JSON view without traces."""
        return {"mode": self.mode, "u": self.u, "ps_bar": self.ps_bar, "mape_pct": self.mape_pct,
                "final_pct": self.final_pct}


THESIS_VALIDATION: list[tuple[str, float, float]] = [
    (m, u, ps) for m in ("filling", "exhausting") for u in (4.7, 5.0, 5.3) for ps in (3.0, 5.0, 6.0)
]
"""Figures 4.6–4.11: u = 4.7, 5.0, 5.3 V at P_s = 3, 5, 6 bar, both modes."""

HELD_OUT: list[tuple[str, float, float]] = [
    (m, u, ps) for m in ("filling", "exhausting") for u in (4.65, 4.95, 5.15, 5.35) for ps in (2.5, 4.5, 6.5)
]
"""Off-grid (u, P_s) points no map entry was measured at: the models must interpolate."""
