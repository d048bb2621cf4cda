"""Frozen, validated parameter sets of the simulated rig.

Every physical quantity is SI inside the engine (Pa, m, m², m³, kg, s, K, rad);
fields whose name ends in ``_bar`` or ``_v`` are the documented exceptions,
kept in the units the thesis and the datasheets use. Construction rejects
physically impossible values with a :class:`ParameterError` that names the
parameter and its allowed range, so a bad set never reaches the simulator.

The optional effects (all off by default) are exactly the candidates of the
sim-to-real diagnosis (issue 6): each is ``None`` when absent, otherwise a
small dataclass with at most three bounded parameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal

import numpy as np

from app.engine import tables
from app.engine.constants import BAR, P_ATM, SONIC_CONDUCTANCE_UNIT, T_ATM


class ParameterError(ValueError):
    """A parameter is outside its physically meaningful range."""


def validation_reasons(exc: Any, whole: str) -> str:
    """A pydantic ``ValidationError`` as ``field: why; …`` without the input values (they may be secrets).

    Args:
        exc: The error.
        whole: What to call a check on the whole model (an error with no field).
    """
    return "; ".join(f"{'.'.join(map(str, e['loc'])) or whole}: {e['msg'].removeprefix('Value error, ')}"
                     for e in exc.errors(include_input=False))


def check_range(
    name: str,
    value: float,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    unit: str = "",
) -> None:
    """Raise :class:`ParameterError` unless ``lo (<|<=) value (<|<=) hi``.

    Args:
        name: Parameter name shown to the user.
        value: Value to check (any unit; ``unit`` names it).
        lo: Lower bound, or ``None`` for unbounded.
        hi: Upper bound, or ``None`` for unbounded.
        lo_open: Whether the lower bound itself is excluded.
        hi_open: Whether the upper bound itself is excluded.
        unit: Unit string for the message.
    """
    v = float(value)
    ok = math.isfinite(v)
    if ok and lo is not None:
        ok = v > lo if lo_open else v >= lo
    if ok and hi is not None:
        ok = v < hi if hi_open else v <= hi
    if not ok:
        lo_s = "-inf" if lo is None else f"{lo:g}"
        hi_s = "+inf" if hi is None else f"{hi:g}"
        rng = f"{'(' if lo_open or lo is None else '['}{lo_s}, {hi_s}{')' if hi_open or hi is None else ']'}"
        u = f" {unit}" if unit else ""
        raise ParameterError(f"{name} = {value!r}{u} is outside its allowed range {rng}{u}")


def as_dict(obj: Any) -> dict[str, Any]:
    """Nested plain-dict view of a parameter dataclass (tuples become lists)."""
    out: dict[str, Any] = {}
    for f in fields(obj):
        v = getattr(obj, f.name)
        if hasattr(v, "__dataclass_fields__"):
            out[f.name] = as_dict(v)
        elif isinstance(v, tuple):
            out[f.name] = list(v)
        else:
            out[f.name] = v
    return out


# --------------------------------------------------------------------------- actuators


@dataclass(frozen=True)
class VaneCylinder:
    """FESTO DRVS-32-270-P vane cylinder and the parts that rotate with it.

    Attributes:
        d2: Vane hub diameter D2 [m] (thesis 3.2.1: 31 mm).
        h: Vane height H [m] (15 mm).
        w: Vane width W [m] (57 mm).
        rom_deg: Range of motion [deg], symmetric about neutral (0 rad).
        dead_volume_a: Volume of chamber a at its end stop, ports included [m³].
        dead_volume_b: Volume of chamber b at its end stop [m³].
        inertia: Moment of inertia of vane, shaft, flange, sensor, handle and
            hand [kg·m²]; the thesis neglects it (3.2.5), a real arm does not.
    """

    d2: float = 0.031
    h: float = 0.015
    w: float = 0.057
    rom_deg: float = 270.0
    dead_volume_a: float = 3.0e-6
    dead_volume_b: float = 3.0e-6
    inertia: float = 2.5e-3

    def __post_init__(self) -> None:
        for n in ("d2", "h", "w"):
            check_range(n, getattr(self, n), 0.0, 1.0, lo_open=True, unit="m")
        check_range("rom_deg", self.rom_deg, 0.0, 360.0, lo_open=True, unit="deg")
        check_range("dead_volume_a", self.dead_volume_a, 0.0, 1e-2, lo_open=True, unit="m³")
        check_range("dead_volume_b", self.dead_volume_b, 0.0, 1e-2, lo_open=True, unit="m³")
        check_range("inertia", self.inertia, 0.0, 10.0, lo_open=True, unit="kg·m²")

    @property
    def vane_area(self) -> float:
        """A_v = H·W [m²] (Eq 3.3)."""
        return self.h * self.w

    @property
    def radius(self) -> float:
        """Torque radius r = (D2 + H)/2 [m] (Eq 3.2)."""
        return 0.5 * (self.d2 + self.h)

    @property
    def torque_per_pa(self) -> float:
        """A_v·r [N·m/Pa]: pneumatic torque per pascal of P_a − P_b (Eq 3.4)."""
        return self.vane_area * self.radius

    @property
    def theta_max(self) -> float:
        """CCW end stop [rad]."""
        return 0.5 * math.radians(self.rom_deg)

    @property
    def theta_min(self) -> float:
        """CW end stop [rad]."""
        return -self.theta_max


@dataclass(frozen=True)
class StribeckSide:
    """Stribeck parameters of one motion direction, thesis sign convention.

    Attributes:
        fs: Static friction (breakaway) force/torque [N or N·m], signed.
        fc: Coulomb level [N or N·m], signed like ``fs``.
        vs: Stribeck speed [m/s or rad/s], signed like ``fs``.
        b: Viscous coefficient [N·s/m or N·m·s/rad], positive.
    """

    fs: float
    fc: float
    vs: float
    b: float


@dataclass(frozen=True)
class RotaryFriction:
    """Pressure-dependent Stribeck friction of the vane cylinder (Eq 3.14).

    The tables are Table 4.2 indexed by working pressure. The simulator looks
    them up at the *lower* chamber pressure: in the thesis's identification the
    counter chamber is held at P_w while the driving chamber rises above it, so
    the lower pressure is exactly the table's P_w label. The controller's
    estimator (thesis 3.3.2) instead uses the controlled chamber's pressure;
    that mismatch is the thesis's, kept on purpose.

    Attributes:
        pw_bar: Working-pressure grid [bar abs].
        ts_ccw, tc_ccw, ws_ccw, b_ccw: CCW parameters (positive).
        ts_cw, tc_cw, ws_cw, b_cw: CW parameters (negative except B).
        shape_j: Stribeck shape exponent j (thesis: 2).
    """

    pw_bar: tuple[float, ...] = tuple(tables.FRICTION_PW_BAR)
    ts_ccw: tuple[float, ...] = tuple(tables.FRICTION_TS_CCW)
    tc_ccw: tuple[float, ...] = tuple(tables.FRICTION_TC_CCW)
    ws_ccw: tuple[float, ...] = tuple(tables.FRICTION_WS_CCW)
    b_ccw: tuple[float, ...] = tuple(tables.FRICTION_B_CCW)
    ts_cw: tuple[float, ...] = tuple(tables.FRICTION_TS_CW)
    tc_cw: tuple[float, ...] = tuple(tables.FRICTION_TC_CW)
    ws_cw: tuple[float, ...] = tuple(tables.FRICTION_WS_CW)
    b_cw: tuple[float, ...] = tuple(tables.FRICTION_B_CW)
    shape_j: float = 2.0

    def __post_init__(self) -> None:
        n = len(self.pw_bar)
        if n < 1 or any(np.diff(self.pw_bar) <= 0):
            raise ParameterError("pw_bar must be a non-empty, strictly increasing pressure grid [bar abs]")
        for name in ("ts_ccw", "tc_ccw", "ws_ccw", "b_ccw", "ts_cw", "tc_cw", "ws_cw", "b_cw"):
            if len(getattr(self, name)) != n:
                raise ParameterError(f"{name} must have {n} entries (one per pw_bar point)")
        for i in range(n):
            check_range(f"ts_ccw[{i}]", self.ts_ccw[i], 0.0, 100.0, unit="N·m")
            check_range(f"tc_ccw[{i}]", self.tc_ccw[i], 0.0, self.ts_ccw[i], unit="N·m")
            check_range(f"ws_ccw[{i}]", self.ws_ccw[i], 0.0, 100.0, lo_open=True, unit="rad/s")
            check_range(f"b_ccw[{i}]", self.b_ccw[i], 0.0, 100.0, unit="N·m·s/rad")
            check_range(f"ts_cw[{i}]", self.ts_cw[i], -100.0, 0.0, unit="N·m")
            check_range(f"tc_cw[{i}]", self.tc_cw[i], self.ts_cw[i], 0.0, unit="N·m")
            check_range(f"ws_cw[{i}]", self.ws_cw[i], -100.0, 0.0, hi_open=True, unit="rad/s")
            check_range(f"b_cw[{i}]", self.b_cw[i], 0.0, 100.0, unit="N·m·s/rad")
        check_range("shape_j", self.shape_j, 0.5, 2.0, unit="")

    def at(self, p_bar: float) -> tuple[StribeckSide, StribeckSide]:
        """Interpolated (CCW, CW) parameters at pressure ``p_bar`` [bar abs].

        Linear interpolation, held constant outside the table (as Simulink's
        1-D lookup with clipping).
        """
        g = np.asarray(self.pw_bar)

        def f(v: tuple[float, ...]) -> float:
            return float(np.interp(p_bar, g, np.asarray(v)))

        return (
            StribeckSide(f(self.ts_ccw), f(self.tc_ccw), f(self.ws_ccw), f(self.b_ccw)),
            StribeckSide(f(self.ts_cw), f(self.tc_cw), f(self.ws_cw), f(self.b_cw)),
        )


@dataclass(frozen=True)
class LinearCylinder:
    """Double-acting linear cylinder for the friction identification (Eq 3.5–3.6).

    Attributes:
        name: Catalogue designation.
        bore: Piston diameter PD [m].
        rod: Rod diameter RD [m], 0 < RD < PD.
        stroke: Stroke length L [m].
        dead_volume_a: Cap-side volume at full retraction [m³].
        dead_volume_b: Rod-side volume at full extension [m³].
        mass: Moving mass M_p (piston, rod, carriage) [kg].
        extension: Stribeck parameters for extension (positive).
        retraction: Stribeck parameters for retraction (negative except B).
    """

    name: str
    bore: float
    rod: float
    stroke: float
    extension: StribeckSide
    retraction: StribeckSide
    dead_volume_a: float = 4.0e-6
    dead_volume_b: float = 4.0e-6
    mass: float = 0.6

    def __post_init__(self) -> None:
        check_range("bore", self.bore, 0.0, 0.5, lo_open=True, unit="m")
        check_range("rod", self.rod, 0.0, self.bore, lo_open=True, hi_open=True, unit="m")
        check_range("stroke", self.stroke, 0.0, 5.0, lo_open=True, unit="m")
        check_range("dead_volume_a", self.dead_volume_a, 0.0, 1e-2, lo_open=True, unit="m³")
        check_range("dead_volume_b", self.dead_volume_b, 0.0, 1e-2, lo_open=True, unit="m³")
        check_range("mass", self.mass, 0.0, 100.0, lo_open=True, unit="kg")
        e, r = self.extension, self.retraction
        check_range("extension.fs", e.fs, 0.0, 1e4, unit="N")
        check_range("extension.fc", e.fc, 0.0, e.fs, unit="N")
        check_range("extension.vs", e.vs, 0.0, 10.0, lo_open=True, unit="m/s")
        check_range("extension.b", e.b, 0.0, 1e4, unit="N·s/m")
        check_range("retraction.fs", r.fs, -1e4, 0.0, unit="N")
        check_range("retraction.fc", r.fc, r.fs, 0.0, unit="N")
        check_range("retraction.vs", r.vs, -10.0, 0.0, hi_open=True, unit="m/s")
        check_range("retraction.b", r.b, 0.0, 1e4, unit="N·s/m")

    @property
    def area_a(self) -> float:
        """Cap-side piston area A_a [m²]."""
        return math.pi * self.bore**2 / 4.0

    @property
    def area_rod(self) -> float:
        """Rod cross-section A_rod [m²]."""
        return math.pi * self.rod**2 / 4.0

    @property
    def area_b(self) -> float:
        """Rod-side annulus A_b [m²]."""
        return self.area_a - self.area_rod

    @staticmethod
    def catalogue(key: Literal["C1", "C2", "C3"]) -> LinearCylinder:
        """The thesis's cylinders with Tables 4.5–4.6 friction.

        C1/C2: FESTO DSNUP-25-225 (bore 25, rod 10, stroke 225 mm);
        C3: FESTO DSBC-32-300 (bore 32, rod 12, stroke 300 mm).
        """
        fr = tables.LINEAR_FRICTION[key]
        ext = StribeckSide(fr["Fs"][0], fr["Fc"][0], fr["vs"][0], fr["B"][0])
        ret = StribeckSide(fr["Fs"][1], fr["Fc"][1], fr["vs"][1], fr["B"][1])
        if key == "C3":
            return LinearCylinder("FESTO DSBC-32-300", 0.032, 0.012, 0.300, ext, ret, mass=0.9)
        return LinearCylinder(f"FESTO DSNUP-25-225 ({key})", 0.025, 0.010, 0.225, ext, ret, mass=0.5)


# --------------------------------------------------------------------------- valves


@dataclass(frozen=True)
class PRVParams:
    """FESTO VPPM proportional pressure regulator with its internal controller.

    Static map (Eq 3.7–3.9): P_out = z + P_atm with z in volts ≙ bar. The
    dynamics are physical: a 3-way spool (supply→outlet or outlet→exhaust)
    with ISO 6358 capacity, driven through a first-order lag by a proportional
    regulator on the outlet pressure that has a switching hysteresis (it acts
    when |error| exceeds ``deadband_on_bar`` and rests once below
    ``deadband_off_bar``). While the chamber volume changes, pressure drifts
    out of the band, the spool kicks, the lag lets it overshoot: the steady
    error and chattering of the "Default" controller emerge from this.

    Attributes:
        c_supply: Sonic conductance supply→outlet at full opening [l/(s·bar)].
        b_supply: Critical pressure ratio of that path [-].
        c_exhaust: Sonic conductance outlet→exhaust at full opening [l/(s·bar)].
        b_exhaust: Critical pressure ratio of the exhaust path [-].
        gain_per_bar: Spool opening per bar of pressure error [1/bar].
        tau_spool: Spool (pilot) time constant [s].
        deadband_on_bar: Error that wakes the regulator [bar].
        deadband_off_bar: Error below which it rests [bar] (≤ on).
        dead_zone: Share of the rest band the spool's opening starts past [-]:
            0 opens in proportion to the error (nominal), 1 to the error
            beyond ``deadband_off_bar`` (a proportional spool with a dead zone).
        outlet_volume: Regulator outlet plus the line to the DCV [m³].
        z_max_v: Command range upper limit [V] (0–10 V ↔ 0–10 bar gauge).
    """

    c_supply: float = 4.0
    b_supply: float = 0.30
    c_exhaust: float = 4.0
    b_exhaust: float = 0.30
    gain_per_bar: float = 2.0
    tau_spool: float = 0.004
    deadband_on_bar: float = 0.03
    deadband_off_bar: float = 0.01
    dead_zone: float = 0.0
    outlet_volume: float = 6.0e-6
    z_max_v: float = 10.0

    def __post_init__(self) -> None:
        check_range("c_supply", self.c_supply, 0.0, 100.0, lo_open=True, unit="l/(s·bar)")
        check_range("c_exhaust", self.c_exhaust, 0.0, 100.0, lo_open=True, unit="l/(s·bar)")
        check_range("b_supply", self.b_supply, 0.0, 1.0, hi_open=True)
        check_range("b_exhaust", self.b_exhaust, 0.0, 1.0, hi_open=True)
        check_range("gain_per_bar", self.gain_per_bar, 0.0, 1000.0, lo_open=True, unit="1/bar")
        check_range("tau_spool", self.tau_spool, 0.0, 1.0, lo_open=True, unit="s")
        check_range("deadband_on_bar", self.deadband_on_bar, 0.0, 1.0, unit="bar")
        check_range("deadband_off_bar", self.deadband_off_bar, 0.0, self.deadband_on_bar, unit="bar")
        check_range("dead_zone", self.dead_zone, 0.0, 1.0)
        check_range("outlet_volume", self.outlet_volume, 0.0, 1e-2, lo_open=True, unit="m³")
        check_range("z_max_v", self.z_max_v, 0.0, 10.0, lo_open=True, unit="V")


DCVModel = Literal["iso", "new"]


@dataclass(frozen=True)
class DCVParams:
    """FESTO MPYE-5-1/8-HF-010-B proportional directional valve (port 2/4 path).

    ``model="iso"`` (default): two ISO 6358 restrictions, supply→chamber and
    chamber→exhaust, whose openings follow the MPYE spool-area curve. The
    measured valve keeps filling until ``5 + underlap_fill_v`` volts and keeps
    exhausting down to ``5 − underlap_exh_v`` (thesis 4.1.1: 0.7 V and 0.3 V),
    so near 5 V both leak a little and the chamber settles at an intermediate
    pressure — the cracking pressure ratio (CPR) the thesis maps. Setting both
    underlaps to 0 gives an ideal closed centre.

    ``model="new"``: the thesis's flow model (Eq 3.10–3.11) with its maps
    a(u, P_s), ε(u), α1(u), α2(u) and k(P_s) (Eq 4.2–4.3).

    Unit convention of the new model (SPEC §3 asks for one): pressures in Pa,
    c_p in J/(kg·K), T in K, ṁ in kg/s, u in V; so α1 is in
    kg/s · (J/kg) · Pa^−ε / V and α2 per V². Table 4.1's α magnitudes fit no
    unit system, so the defaults are *derived* from the ISO model of the same
    valve (see :func:`app.engine.physics.flow.derive_new_model_maps`) and the
    identification (issue 4) re-fits them. Only the product
    g(u) = α1(u)·u + α2(u)·u² is identifiable at a single u; the maps store
    α1 = g/u and α2 = 0.

    Attributes:
        model: ``"iso"`` or ``"new"``.
        c: Sonic conductance at full opening [l/(s·bar)] (Table 3.3: 3.1).
        b: Critical pressure ratio [-] (Table 3.3: 0.26).
        underlap_fill_v: Δu_p2 filling [V] (thesis 4.1.1: 0.7); negative, an
            overlap: the path stays shut that far past 5 V (a closed-centre spool's
            dead band).
        underlap_exh_v: Δu_p2 exhausting [V] (thesis 4.1.1: 0.3); negative, as above.
        null_leak_fraction: Flow scale of both paths at 5 V [-]: inside the
            null zone only clearance leakage flows (thesis 2.1 Δu_null; see
            :func:`~app.engine.physics.flow.null_scale`). 1 disables it
            (:meth:`without_null_zone`).
        null_width_v: Distance from 5 V where the spool orifices take over
            fully [V].

    The null-zone defaults (0.04, 1.6 V) are calibrated on the thesis's one quantitative
    statement about flow magnitude near 5 V (3.2.4): on 25 mm bores at
    P_s = 2.5 bar abs, u_a = 4.2 → 5 V gave extension speeds of ≈ 1 → 0 m/s
    and u_b = 5 → 6 V gave 0 → −1 m/s. A grid over (s0, width) minimising the
    squared speed error of the simulated C1 at those four end points gave
    width 1.6 V, flat in s0 ∈ [0.03, 0.05]: 0.78 m/s at 4.2 V, 0.05 m/s at
    5 V, −1.19 m/s at 6 V (the rod-side area is 16 % smaller, so one valve
    cannot give ±1 m/s both ways). Without the attenuation the ISO valve ran
    the simulated C1 at 1.8 → 0.8 m/s over 4.2 → 5 V.
    """

    model: DCVModel = "iso"
    c: float = 3.1
    b: float = 0.26
    underlap_fill_v: float = 0.7
    underlap_exh_v: float = 0.3
    null_leak_fraction: float = 0.04
    null_width_v: float = 1.6

    def __post_init__(self) -> None:
        if self.model not in ("iso", "new"):
            raise ParameterError(f"model = {self.model!r} must be 'iso' or 'new'")
        check_range("c", self.c, 0.0, 100.0, lo_open=True, unit="l/(s·bar)")
        check_range("b", self.b, 0.0, 1.0, hi_open=True)
        # below 0: an overlap, the spool's dead band around 5 V before the path opens
        check_range("underlap_fill_v", self.underlap_fill_v, -2.0, 2.0, unit="V")
        check_range("underlap_exh_v", self.underlap_exh_v, -2.0, 2.0, unit="V")
        check_range("null_leak_fraction", self.null_leak_fraction, 0.0, 1.0, lo_open=True)
        check_range("null_width_v", self.null_width_v, 0.0, 5.0, unit="V")

    @classmethod
    def without_null_zone(cls, **kw: Any) -> DCVParams:
        """The plain ISO 6358 valve: its underlaps' full flow right up to 5 V (see class doc).

        The simulator's default until the CPR tests' end criterion learnt to
        wait for the null zone's slow approaches: with it, this valve drives
        C1 at 1.8 → 0.8 m/s over u_a = 4.2 → 5 V, too fast to resolve v_s.
        """
        return cls(null_leak_fraction=1.0, null_width_v=0.0, **kw)


@dataclass(frozen=True)
class SupplyParams:
    """Compressed-air supply upstream of both PRVs.

    Attributes:
        p_supply_bar: Supply pressure [bar abs] (thesis: compressor ≤ 10 bar).
    """

    p_supply_bar: float = 8.0

    def __post_init__(self) -> None:
        check_range("p_supply_bar", self.p_supply_bar, 1.0, 12.0, lo_open=True, unit="bar abs")


# --------------------------------------------------------------------------- sensors & user


@dataclass(frozen=True)
class SensorParams:
    """Sensors as the Q8-USB sees them (Table 3.2).

    Attributes:
        pressure_noise_bar: White noise SD of each pressure channel [bar].
        pressure_full_scale_bar: Sensor span [bar] over ``pressure_span_v``.
        pressure_span_v: Sensor output span [V] (5 V supply, 0–5 V).
        pressure_gain_a: Calibration gain error of PS-a [-] (1 = perfect).
        pressure_gain_b: Calibration gain error of PS-b [-].
        torque_noise_nm: Torque channel noise SD [N·m].
        torque_range_nm: TS70a-10Nm range ±[N·m] (amplifier ±10 V).
        torque_gain: Torque calibration gain error [-].
        encoder_counts: Quadrature counts per revolution (1024 lines × 4).
        adc_bits: DAQ resolution [bit].
        adc_range_v: DAQ input range ±[V].
        supply_tap: Where PS-0 sits: ``"compressor"`` (the interaction rig,
            upstream of both PRVs) or ``"prv_a"`` (the CPR set-up of
            Figure 3.10, at the DCV's supply port, i.e. PRV-a's outlet).
        speed_filter_hz: Cut-off of the first-order filter on the
            differentiated encoder angle [Hz] (thesis: "derivative, then
            transfer-function filter", 3.2.4).
    """

    pressure_noise_bar: float = 0.003
    pressure_full_scale_bar: float = 10.0
    pressure_span_v: float = 5.0
    pressure_gain_a: float = 1.0
    pressure_gain_b: float = 1.0
    torque_noise_nm: float = 0.01
    torque_range_nm: float = 10.0
    torque_gain: float = 1.0
    encoder_counts: int = 4096
    adc_bits: int = 16
    adc_range_v: float = 10.0
    speed_filter_hz: float = 25.0
    supply_tap: Literal["compressor", "prv_a"] = "compressor"

    def __post_init__(self) -> None:
        if self.supply_tap not in ("compressor", "prv_a"):
            raise ParameterError(f"supply_tap = {self.supply_tap!r} must be 'compressor' or 'prv_a'")
        check_range("pressure_noise_bar", self.pressure_noise_bar, 0.0, 1.0, unit="bar")
        check_range("pressure_full_scale_bar", self.pressure_full_scale_bar, 0.0, 100.0, lo_open=True, unit="bar")
        check_range("pressure_span_v", self.pressure_span_v, 0.0, 10.0, lo_open=True, unit="V")
        check_range("pressure_gain_a", self.pressure_gain_a, 0.5, 1.5)
        check_range("pressure_gain_b", self.pressure_gain_b, 0.5, 1.5)
        check_range("torque_noise_nm", self.torque_noise_nm, 0.0, 1.0, unit="N·m")
        check_range("torque_range_nm", self.torque_range_nm, 0.0, 1000.0, lo_open=True, unit="N·m")
        check_range("torque_gain", self.torque_gain, 0.5, 1.5)
        check_range("encoder_counts", self.encoder_counts, 4, 1 << 24)
        check_range("adc_bits", self.adc_bits, 8, 32)
        check_range("adc_range_v", self.adc_range_v, 0.0, 100.0, lo_open=True, unit="V")
        check_range("speed_filter_hz", self.speed_filter_hz, 0.0, 1000.0, lo_open=True, unit="Hz")


@dataclass(frozen=True)
class HumanParams:
    """Arm impedance of the user holding the handle.

    The user follows an intended angle θ_h(t) (see :mod:`app.engine.human`) and
    applies T_i = K_h·(θ_h − θ) + D_h·(ω_h − ω) through the torque sensor.

    Attributes:
        stiffness: K_h [N·m/rad] (forearm pronation/supination, relaxed grip).
        damping: D_h [N·m·s/rad].
        torque_limit: Largest torque the user exerts ±[N·m].
    """

    stiffness: float = 20.0
    damping: float = 0.8
    torque_limit: float = 8.0

    def __post_init__(self) -> None:
        check_range("stiffness", self.stiffness, 0.0, 1000.0, unit="N·m/rad")
        check_range("damping", self.damping, 0.0, 100.0, unit="N·m·s/rad")
        check_range("torque_limit", self.torque_limit, 0.0, 100.0, lo_open=True, unit="N·m")


# --------------------------------------------------------------------------- optional effects


@dataclass(frozen=True)
class InertiaEffect:
    """Extra rotating inertia (heavier hand, unmodelled coupling) [kg·m² or kg]."""

    extra: float = 2.0e-3

    def __post_init__(self) -> None:
        check_range("inertia.extra", self.extra, 0.0, 1.0, unit="kg·m²")


@dataclass(frozen=True)
class LeakageEffect:
    """A leak as an ISO 6358 restriction.

    Attributes:
        c: Sonic conductance [l/(s·bar)].
        b: Critical pressure ratio [-].
    """

    c: float = 0.01
    b: float = 0.5

    def __post_init__(self) -> None:
        check_range("leakage.c", self.c, 0.0, 1.0, unit="l/(s·bar)")
        check_range("leakage.b", self.b, 0.0, 1.0, hi_open=True)


@dataclass(frozen=True)
class HeatTransferEffect:
    """Non-isothermal chamber gas with wall heat exchange (Carneiro & de Almeida).

    Attributes:
        h_a: Heat-transfer coefficient × wall area per chamber [W/K].
    """

    h_a: float = 0.15

    def __post_init__(self) -> None:
        check_range("heat_transfer.h_a", self.h_a, 0.0, 100.0, unit="W/K")


@dataclass(frozen=True)
class TubeEffect:
    """A tube between DCV and chamber: volume plus laminar resistance.

    Attributes:
        length: Tube length [m].
        diameter: Inner diameter [m].
    """

    length: float = 1.0
    diameter: float = 0.004

    def __post_init__(self) -> None:
        check_range("tube.length", self.length, 0.0, 20.0, lo_open=True, unit="m")
        check_range("tube.diameter", self.diameter, 0.0005, 0.05, unit="m")


@dataclass(frozen=True)
class PreslidingEffect:
    """LuGre pre-sliding (bristle) friction on top of the Stribeck curve.

    Attributes:
        sigma0: Bristle stiffness [N·m/rad or N/m].
        sigma1: Bristle damping [N·m·s/rad or N·s/m].
    """

    sigma0: float = 150.0
    sigma1: float = 0.5

    def __post_init__(self) -> None:
        check_range("presliding.sigma0", self.sigma0, 0.0, 1e7, lo_open=True)
        check_range("presliding.sigma1", self.sigma1, 0.0, 1e5)


@dataclass(frozen=True)
class SensorBiasEffect:
    """Constant offsets on the measured channels.

    Attributes:
        p_a_bar: Offset on P_a [bar].
        p_b_bar: Offset on P_b [bar].
        torque_nm: Offset on T_i [N·m].
    """

    p_a_bar: float = 0.0
    p_b_bar: float = 0.0
    torque_nm: float = 0.0

    def __post_init__(self) -> None:
        check_range("sensor_bias.p_a_bar", self.p_a_bar, -1.0, 1.0, unit="bar")
        check_range("sensor_bias.p_b_bar", self.p_b_bar, -1.0, 1.0, unit="bar")
        check_range("sensor_bias.torque_nm", self.torque_nm, -5.0, 5.0, unit="N·m")


@dataclass(frozen=True)
class SupplyDroopEffect:
    """Supply pressure sagging with the flow drawn (long hose, small receiver).

    Attributes:
        droop_bar_per_gps: Static droop [bar per g/s of supply flow].
        tau: Recovery time constant [s].
    """

    droop_bar_per_gps: float = 0.3
    tau: float = 0.05

    def __post_init__(self) -> None:
        check_range("supply_droop.droop_bar_per_gps", self.droop_bar_per_gps, 0.0, 10.0, unit="bar/(g/s)")
        check_range("supply_droop.tau", self.tau, 0.0, 10.0, lo_open=True, unit="s")


@dataclass(frozen=True)
class ValveDynamicsEffect:
    """First-order lags between command and spool (DCV) / set point (PRV).

    Attributes:
        tau_dcv: DCV spool lag [s].
        tau_prv: PRV set-point (pilot) lag [s].
    """

    tau_dcv: float = 0.005
    tau_prv: float = 0.03

    def __post_init__(self) -> None:
        check_range("valve_dynamics.tau_dcv", self.tau_dcv, 0.0, 1.0, unit="s")
        check_range("valve_dynamics.tau_prv", self.tau_prv, 0.0, 5.0, unit="s")


EFFECT_NAMES: tuple[str, ...] = (
    "inertia",
    "vane_leakage",
    "external_leakage",
    "heat_transfer",
    "tube_dynamics",
    "presliding_friction",
    "sensor_bias",
    "supply_droop",
    "valve_dynamics",
)

EFFECT_MEANING: dict[str, str] = {
    "inertia": "the rotating mass of the vane, handle and arm, which the thesis's model leaves out",
    "vane_leakage": "air leaking across the vane's seal from one chamber to the other",
    "external_leakage": "air leaking out of the chambers into the room",
    "heat_transfer": "air warming as it is compressed and cooling as it expands, then exchanging heat with the walls "
                     "(the thesis's model keeps it at room temperature)",
    "tube_dynamics": "the tubes between the valves and the chambers: their volume, restriction and delay",
    "presliding_friction": "the seals' springy give before the vane breaks away",
    "sensor_bias": "pressure or torque sensors reading off zero",
    "supply_droop": "the supply pressure sagging while the valves draw air",
    "valve_dynamics": "valves following their commands with a delay",
}
"""What each candidate effect is on the rotary rig, in plain words (the dashboard shows it beside the name)."""
assert set(EFFECT_MEANING) == set(EFFECT_NAMES)


@dataclass(frozen=True)
class Effects:
    """The optional, unmodelled-by-the-thesis effects; ``None`` means absent."""

    inertia: InertiaEffect | None = None
    vane_leakage: LeakageEffect | None = None
    external_leakage: LeakageEffect | None = None
    heat_transfer: HeatTransferEffect | None = None
    tube_dynamics: TubeEffect | None = None
    presliding_friction: PreslidingEffect | None = None
    sensor_bias: SensorBiasEffect | None = None
    supply_droop: SupplyDroopEffect | None = None
    valve_dynamics: ValveDynamicsEffect | None = None

    def active(self) -> list[str]:
        """Names of the effects switched on."""
        return [n for n in EFFECT_NAMES if getattr(self, n) is not None]


# --------------------------------------------------------------------------- the rig


@dataclass(frozen=True)
class PlantParams:
    """Everything the simulated rig needs; SPEC §1 defaults.

    Attributes:
        rig: ``"rotary"`` (forearm axis) or ``"linear"`` (identification cylinder).
        vane: Vane cylinder (rotary rig).
        friction: Table 4.2 friction (rotary rig).
        linear: Linear cylinder (linear rig); ``None`` on the rotary rig.
        prv: Both PRVs (identical units).
        dcv: Both DCVs (identical units).
        supply: Supply upstream of the PRVs.
        sensors: Sensor models.
        human: User arm impedance (rotary rig).
        effects: Optional effects.
        p_atm: Atmospheric pressure [Pa].
        t_atm: Ambient temperature [K].
        substep_hz: Plant integration rate [Hz] (≥ 1 kHz).
    """

    rig: Literal["rotary", "linear"] = "rotary"
    vane: VaneCylinder = field(default_factory=VaneCylinder)
    friction: RotaryFriction = field(default_factory=RotaryFriction)
    linear: LinearCylinder | None = None
    prv: PRVParams = field(default_factory=PRVParams)
    dcv: DCVParams = field(default_factory=DCVParams)
    supply: SupplyParams = field(default_factory=SupplyParams)
    sensors: SensorParams = field(default_factory=SensorParams)
    human: HumanParams = field(default_factory=HumanParams)
    effects: Effects = field(default_factory=Effects)
    p_atm: float = P_ATM
    t_atm: float = T_ATM
    substep_hz: float = 2000.0

    def __post_init__(self) -> None:
        if self.rig not in ("rotary", "linear"):
            raise ParameterError(f"rig = {self.rig!r} must be 'rotary' or 'linear'")
        if self.rig == "linear" and self.linear is None:
            raise ParameterError("linear: a LinearCylinder is required when rig = 'linear'")
        check_range("p_atm", self.p_atm, 0.5 * BAR, 1.2 * BAR, unit="Pa")
        check_range("t_atm", self.t_atm, 200.0, 350.0, unit="K")
        check_range("substep_hz", self.substep_hz, 1000.0, 1.0e6, unit="Hz")
        if self.supply.p_supply_bar * BAR <= self.p_atm:
            raise ParameterError("p_supply_bar must exceed atmospheric pressure")

    def with_effects(self, **kw: Any) -> PlantParams:
        """A copy with the named effects replaced (``None`` switches one off)."""
        for k in kw:
            if k not in EFFECT_NAMES:
                raise ParameterError(f"unknown effect {k!r}; known: {', '.join(EFFECT_NAMES)}")
        return replace(self, effects=replace(self.effects, **kw))

    @staticmethod
    def linear_rig(key: Literal["C1", "C2", "C3"] = "C3", **kw: Any) -> PlantParams:
        """The linear identification rig with one of the thesis's cylinders."""
        return PlantParams(rig="linear", linear=LinearCylinder.catalogue(key), **kw)


def conductance_si(c_l_per_s_bar: float) -> float:
    """Convert a sonic conductance from l/(s·bar) to m³/(s·Pa)."""
    return c_l_per_s_bar * SONIC_CONDUCTANCE_UNIT


def check_working_pressure(pw_bar: float) -> None:
    """Thesis GUI rule (SPEC §6): P_w in [1, 8] bar abs, same message."""
    if not (math.isfinite(pw_bar) and 1.0 <= pw_bar <= 8.0):
        raise ParameterError("Working pressure can be min. 1 bar and max. 8 bar!")
