"""The rig's physics as pure, compiled functions of (t, x, u, p).

One kernel serves both rigs: the rotary forearm axis (vane cylinder, angle in
rad, torque in N·m) and the linear identification cylinder (position in m,
force in N); only the geometry constants differ. The state lives outside, in a
float64 vector laid out by the ``I_*`` indices; parameters are a frozen
namedtuple :class:`Kernel` built from :class:`~app.engine.params.PlantParams`.

Pneumatic network, per side j ∈ {a, b}::

    supply ──PRV_j spool──▶ O_j ──DCV_j port──▶ [T_j tube] ──▶ C_j (chamber)
                 │                    │
              exhaust              exhaust

Gas masses are the states, so closed chambers conserve mass exactly and
isothermal compression needs no dV/dt term (p = m·R·T/V). Each substep:

1. valve lags, supply droop and the PRV regulators (explicit, exact
   exponentials);
2. node masses by a linearly implicit Euler step with the analytic flow
   Jacobian — pneumatic time constants of small volumes are far below the
   substep, and this keeps it stable without chatter;
3. chamber temperatures (heat-transfer effect only) by an energy balance;
4. the mechanics with the new pressures: implicit viscous term, Coulomb and
   Stribeck friction as a velocity-level projection (Moreau time stepping), so
   static friction holds the vane exactly (ω = 0) and motion never chatters
   through zero speed; hard end stops as inelastic constraints. With the
   pre-sliding effect, a LuGre bristle state is sub-stepped instead.
"""

from __future__ import annotations

import math
from collections import namedtuple
from functools import lru_cache
from typing import Any

import numpy as np
from numba import njit

from app.engine import tables
from app.engine.constants import BAR, CP_AIR, CV_AIR, R_AIR, RHO0_ISO, T0_ISO
from app.engine.params import PlantParams, RotaryFriction, conductance_si
from app.engine.physics.dcv_maps import derive_new_model_maps
from app.engine.physics.flow import (
    interp2_clip,
    interp_clip,
    iso6358_signed,
    iso6358_signed_k,
    new_model_flow,
    null_scale,
    polyval,
)
from app.engine.physics.jit import NO_REFCOUNT

# ----------------------------------------------------------------- state layout
I_POS = 0  # θ [rad] or x [m]
I_VEL = 1  # ω [rad/s] or v [m/s]
I_M0 = 2  # node masses [kg]: O_a, T_a, C_a, O_b, T_b, C_b
I_TCA = 8  # chamber a gas temperature [K]
I_TCB = 9  # chamber b gas temperature [K]
I_XA = 10  # PRV-a spool opening [-1, 1]
I_XB = 11
I_HA = 12  # PRV-a regulator awake flag {0, 1}
I_HB = 13
I_ZF = 14  # LuGre bristle deflection [rad or m]
I_UA = 15  # effective (lagged) DCV-a command [V]
I_UB = 16
I_ZA = 17  # effective (lagged) PRV-a command [V]
I_ZB = 18
I_PS = 19  # supply pressure [Pa]
NX = 20

# node indices inside the mass block
N_OA, N_TA, N_CA, N_OB, N_TB, N_CB = 0, 1, 2, 3, 4, 5
NN = 6
NWORK = 6 * NN  # floats of scratch :func:`step` needs

# command vector
C_ZA, C_ZB, C_UA, C_UB, C_DPA, C_DPB = 0, 1, 2, 3, 4, 5
NU = 6

# per-step outputs (truth)
O_TI = 0  # interaction torque/force applied by the user [N·m or N]
O_TF = 1  # friction torque/force [N·m or N]
O_TP = 2  # pneumatic torque/force [N·m or N]
O_QS = 3  # supply mass flow [kg/s]
NO = 4

# area_frac indexes the MPYE table directly: its displacement grid must stay uniform
assert np.allclose(np.diff(tables.MPYE_DISPLACEMENT_V), tables.MPYE_DISPLACEMENT_V[1] - tables.MPYE_DISPLACEMENT_V[0])

MU_AIR = 1.81e-5  # dynamic viscosity [Pa·s] for the tube's laminar resistance

_KERNEL_FIELDS = (
    "rotary", "area_a", "area_b", "area_rod", "pos_min", "pos_max", "vd_a", "vd_b", "inertia",
    "fr", "fr_j",
    "lugre_on", "sigma0", "sigma1",
    "p_atm", "t_atm",
    "prv_cs", "prv_bs", "prv_ce", "prv_be", "prv_gain", "prv_tau", "prv_decay",
    "prv_db_on", "prv_db_off", "prv_dz", "prv_vol", "z_max",
    "dcv_new", "dcv_c", "dcv_b", "ul_f", "ul_e", "null_s0", "null_w", "mp",
    "nm_u", "nm_ps", "nm_af", "nm_ae", "nm_ef", "nm_ee", "nm_gf", "nm_ge", "nm_kf", "nm_ke", "nm_usw",
    "ps0", "droop_on", "droop_r", "droop_tau",
    "vl_c", "vl_b", "el_c", "el_b",
    "tube_on", "tube_vol", "tube_g",
    "heat_on", "heat_ha",
    "lag_on", "tau_dcv", "tau_prv",
    "hum_k", "hum_d", "hum_lim",
    "h",
)
_namedtuple: Any = namedtuple  # field list is data-driven; mypy cannot type it
Kernel: Any = _namedtuple("Kernel", _KERNEL_FIELDS)
"""Compiled-loop constants (SI) derived from :class:`PlantParams`."""


def pack_friction(f: RotaryFriction) -> np.ndarray:
    """Table 4.2 in the compiled layout: rows P_w [bar], then T_s, T_c, ω_s, B
    for CCW and the CW magnitudes (the thesis's ×−1 sign unification, B kept)."""
    rows = [f.pw_bar, f.ts_ccw, f.tc_ccw, f.ws_ccw, f.b_ccw]
    rows += [np.abs(np.asarray(v)) for v in (f.ts_cw, f.tc_cw, f.ws_cw)] + [f.b_cw]
    return np.ascontiguousarray(np.vstack([np.asarray(r, dtype=np.float64) for r in rows]))


def build_kernel(p: PlantParams) -> Any:
    """Flatten a :class:`PlantParams` into the kernel's namedtuple (SI units)."""
    return _build_kernel_cached(p)


@lru_cache(maxsize=64)
def _build_kernel_cached(p: PlantParams) -> Any:
    eff = p.effects
    if p.rig == "rotary":
        v = p.vane
        a = v.torque_per_pa
        area_a, area_b, area_rod = a, a, 0.0
        pos_min, pos_max = v.theta_min, v.theta_max
        vd_a, vd_b = v.dead_volume_a, v.dead_volume_b
        inertia = v.inertia
        fr_packed = pack_friction(p.friction)
        fr_j = p.friction.shape_j
        hum_k, hum_d, hum_lim = p.human.stiffness, p.human.damping, p.human.torque_limit
    else:
        assert p.linear is not None
        c = p.linear
        area_a, area_b, area_rod = c.area_a, c.area_b, c.area_rod
        # "volume per unit displacement" equals the piston areas; the vane's
        # equals A_v·r, so chamber volumes use area_a/area_b in both rigs.
        pos_min, pos_max = 0.0, c.stroke
        vd_a, vd_b = c.dead_volume_a, c.dead_volume_b
        inertia = c.mass
        e, r = c.extension, c.retraction
        fr_packed = np.array([[1.0], [e.fs], [e.fc], [e.vs], [e.b], [abs(r.fs)], [abs(r.fc)], [abs(r.vs)], [r.b]])
        fr_j = 2.0
        hum_k = hum_d = 0.0
        hum_lim = 1.0
    if eff.inertia is not None:
        inertia += eff.inertia.extra
    pre = eff.presliding_friction
    dcv = p.dcv
    dcv_c = conductance_si(dcv.c)
    maps = derive_new_model_maps_cached(dcv_c, dcv.b, dcv.underlap_fill_v, dcv.underlap_exh_v, p.p_atm, p.t_atm,
                                        dcv.null_leak_fraction, dcv.null_width_v)
    tube = eff.tube_dynamics
    if tube is not None:
        tube_vol = math.pi * tube.diameter**2 / 4.0 * tube.length
        tube_g = math.pi * tube.diameter**4 / (128.0 * MU_AIR * tube.length)
    else:
        tube_vol, tube_g = 1e-6, 0.0
    lag = eff.valve_dynamics
    droop = eff.supply_droop
    return Kernel(
        rotary=p.rig == "rotary",
        area_a=area_a, area_b=area_b, area_rod=area_rod, pos_min=pos_min, pos_max=pos_max,
        vd_a=vd_a, vd_b=vd_b, inertia=inertia,
        fr=fr_packed, fr_j=fr_j,
        lugre_on=pre is not None, sigma0=pre.sigma0 if pre else 0.0, sigma1=pre.sigma1 if pre else 0.0,
        p_atm=p.p_atm, t_atm=p.t_atm,
        prv_cs=conductance_si(p.prv.c_supply), prv_bs=p.prv.b_supply,
        prv_ce=conductance_si(p.prv.c_exhaust), prv_be=p.prv.b_exhaust,
        prv_gain=p.prv.gain_per_bar / BAR, prv_tau=p.prv.tau_spool,
        prv_decay=math.exp(-(1.0 / p.substep_hz) / p.prv.tau_spool),
        prv_db_on=p.prv.deadband_on_bar * BAR, prv_db_off=p.prv.deadband_off_bar * BAR,
        prv_dz=p.prv.dead_zone * p.prv.deadband_off_bar * BAR,
        prv_vol=p.prv.outlet_volume, z_max=p.prv.z_max_v,
        dcv_new=dcv.model == "new", dcv_c=dcv_c, dcv_b=dcv.b,
        ul_f=dcv.underlap_fill_v, ul_e=dcv.underlap_exh_v, null_s0=dcv.null_leak_fraction, null_w=dcv.null_width_v,
        mp=np.ascontiguousarray(np.vstack([tables.MPYE_DISPLACEMENT_V, tables.MPYE_AREA_FRACTION])),
        nm_u=maps.u_grid, nm_ps=maps.ps_grid_bar, nm_af=maps.a_fill, nm_ae=maps.a_exh,
        nm_ef=maps.eps_fill, nm_ee=maps.eps_exh, nm_gf=maps.g_fill, nm_ge=maps.g_exh,
        nm_kf=np.asarray(tables.K_FILL_POLY, dtype=np.float64),
        nm_ke=np.asarray(tables.K_EXH_POLY, dtype=np.float64), nm_usw=maps.u_switch,
        ps0=p.supply.p_supply_bar * BAR,
        droop_on=droop is not None,
        droop_r=droop.droop_bar_per_gps * BAR * 1e3 if droop else 0.0,
        droop_tau=droop.tau if droop else 1.0,
        vl_c=conductance_si(eff.vane_leakage.c) if eff.vane_leakage else 0.0,
        vl_b=eff.vane_leakage.b if eff.vane_leakage else 0.5,
        el_c=conductance_si(eff.external_leakage.c) if eff.external_leakage else 0.0,
        el_b=eff.external_leakage.b if eff.external_leakage else 0.5,
        tube_on=tube is not None, tube_vol=tube_vol, tube_g=tube_g,
        heat_on=eff.heat_transfer is not None, heat_ha=eff.heat_transfer.h_a if eff.heat_transfer else 0.0,
        lag_on=lag is not None, tau_dcv=lag.tau_dcv if lag else 0.0, tau_prv=lag.tau_prv if lag else 0.0,
        hum_k=hum_k, hum_d=hum_d, hum_lim=hum_lim,
        h=1.0 / p.substep_hz,
    )


@lru_cache(maxsize=16)
def derive_new_model_maps_cached(c: float, b: float, ulf: float, ule: float, p_atm: float, t: float,
                                 null_s0: float = 1.0, null_w: float = 0.0) -> Any:
    """Memoised :func:`derive_new_model_maps` (it solves ~600 equilibria)."""
    return derive_new_model_maps(c, b, ulf, ule, p_atm, t, null_s0, null_w)


# ----------------------------------------------------------------- helpers


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def _vol_temps(
    x: np.ndarray, pos: float, v_o: float, v_t: float, vd_a: float, vd_b: float, area_a: float, area_b: float,
    pos_min: float, pos_max: float, heat_on: bool, t_atm: float, vol: np.ndarray, tn: np.ndarray
) -> None:
    """Node volumes [m³] and temperatures [K] without touching the constants tuple."""
    vol[N_OA] = v_o
    vol[N_OB] = v_o
    vol[N_TA] = v_t
    vol[N_TB] = v_t
    vol[N_CA] = vd_a + area_a * (pos - pos_min)
    vol[N_CB] = vd_b + area_b * (pos_max - pos)
    for i in range(NN):
        tn[i] = t_atm
    if heat_on:
        tn[N_CA] = x[I_TCA]
        tn[N_CB] = x[I_TCB]


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def vol_temps(x: np.ndarray, k: Any, vol: np.ndarray, tn: np.ndarray) -> None:
    """Node volumes [m³] and temperatures [K] of state ``x`` (6 entries each)."""
    _vol_temps(x, x[I_POS], k.prv_vol, k.tube_vol, k.vd_a, k.vd_b, k.area_a, k.area_b, k.pos_min, k.pos_max,
               k.heat_on, k.t_atm, vol, tn)


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def chamber_pressures(x: np.ndarray, k: Any) -> tuple[float, float]:
    """(p_a, p_b) chamber pressures [Pa] of state ``x``."""
    va = k.vd_a + k.area_a * (x[I_POS] - k.pos_min)
    vb = k.vd_b + k.area_b * (k.pos_max - x[I_POS])
    ta = x[I_TCA] if k.heat_on else k.t_atm
    tb = x[I_TCB] if k.heat_on else k.t_atm
    return x[I_M0 + N_CA] * R_AIR * ta / va, x[I_M0 + N_CB] * R_AIR * tb / vb


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def supply_sensor_pressure(x: np.ndarray, k: Any, at_prv_a: bool) -> float:
    """Pressure at PS-0 [Pa]: the compressor line, or PRV-a's outlet (CPR set-up)."""
    if at_prv_a:
        return x[I_M0 + N_OA] * R_AIR * k.t_atm / k.prv_vol
    return x[I_PS]


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def area_frac(disp_v: float, mp: np.ndarray) -> float:
    """MPYE area fraction at spool displacement ``disp_v`` [V] (0 when closed).

    ``mp`` rows: displacement grid [V], area fraction [-].
    """
    if disp_v <= 0.0:
        return 0.0
    # the MPYE table is on a uniform grid: index it directly, no search
    g = mp[0]
    n = g.shape[0]
    if disp_v >= g[n - 1]:
        return mp[1, n - 1]
    step = g[1] - g[0]
    i = min(int((disp_v - g[0]) / step), n - 2)
    w = (disp_v - g[i]) / step
    return mp[1, i] + w * (mp[1, i + 1] - mp[1, i])


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def stribeck_params(p_lookup_bar: float, positive: bool, fr: np.ndarray) -> tuple[float, float, float, float]:
    """(T_s, T_c, ω_s, B) magnitudes for one direction at ``p_lookup_bar``.

    ``fr`` rows: pressure grid [bar abs], then T_s, T_c, ω_s, B for the
    positive (CCW/extension) and the negative direction as magnitudes.
    """
    o = 1 if positive else 5
    g = fr[0]
    n = g.shape[0]
    # one search for the four rows: they share the pressure grid
    if n == 1 or p_lookup_bar <= g[0]:
        return fr[o, 0], fr[o + 1, 0], fr[o + 2, 0], fr[o + 3, 0]
    if p_lookup_bar >= g[n - 1]:
        return fr[o, n - 1], fr[o + 1, n - 1], fr[o + 2, n - 1], fr[o + 3, n - 1]
    lo = 0
    while lo < n - 2 and g[lo + 1] <= p_lookup_bar:
        lo += 1
    w = (p_lookup_bar - g[lo]) / (g[lo + 1] - g[lo])
    return (
        fr[o, lo] + w * (fr[o, lo + 1] - fr[o, lo]),
        fr[o + 1, lo] + w * (fr[o + 1, lo + 1] - fr[o + 1, lo]),
        fr[o + 2, lo] + w * (fr[o + 2, lo + 1] - fr[o + 2, lo]),
        fr[o + 3, lo] + w * (fr[o + 3, lo + 1] - fr[o + 3, lo]),
    )


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def stribeck_curve(speed: float, ts: float, tc: float, ws: float, b: float, j: float) -> float:
    """Stribeck magnitude T_c + (T_s − T_c)·exp(−(|ω|/ω_s)^j) + B·|ω| (Eq 3.12)."""
    s = abs(speed)
    return tc + (ts - tc) * stribeck_decay(s / ws, j) + b * s


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def stribeck_decay(s: float, j: float) -> float:
    """exp(−s^j) for s = |ω|/ω_s ≥ 0; j = 2 (the thesis's shape) without ``pow``."""
    if j == 2.0:
        return math.exp(-s * s)
    return math.exp(-(s**j))


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def friction_lookup_pressure(pa: float, pb: float) -> float:
    """Pressure [bar abs] at which Table 4.2 is read: the lower chamber pressure."""
    return min(pa, pb) / BAR


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def human_target(t: float, prog_t: np.ndarray, prog_pos: np.ndarray) -> tuple[float, float]:
    """Intended position and speed of the user at time ``t`` (piecewise linear)."""
    n = prog_t.shape[0]
    if n == 0:
        return 0.0, 0.0
    if t <= prog_t[0]:
        return prog_pos[0], 0.0
    if t >= prog_t[n - 1]:
        return prog_pos[n - 1], 0.0
    lo = 0
    hi = n - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if prog_t[mid] <= t:
            lo = mid
        else:
            hi = mid
    dt = prog_t[hi] - prog_t[lo]
    if dt <= 0.0:
        return prog_pos[hi], 0.0
    sp = (prog_pos[hi] - prog_pos[lo]) / dt
    return prog_pos[lo] + sp * (t - prog_t[lo]), sp


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def human_torque(
    t: float, pos: float, vel: float, prog_t: np.ndarray, prog_pos: np.ndarray, kh: float, dh: float, lim: float
) -> float:
    """Torque the user applies through the sensor [N·m] (arm impedance).

    Args:
        t: Time [s].
        pos: Handle angle [rad].
        vel: Handle speed [rad/s].
        prog_t: Program breakpoints [s].
        prog_pos: Intended angle at the breakpoints [rad].
        kh: Arm stiffness [N·m/rad].
        dh: Arm damping [N·m·s/rad].
        lim: Largest torque the user exerts [N·m].
    """
    if kh == 0.0 and dh == 0.0:
        return 0.0
    th, wh = human_target(t, prog_t, prog_pos)
    if th != th:  # NaN intended angle: the user has let go of the handle
        return 0.0
    ti = kh * (th - pos) + dh * (wh - vel)
    return min(max(ti, -lim), lim)


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def _edge(i: int, j: int, q: float, dqi: float, dqj: float, f: np.ndarray, jac: np.ndarray) -> None:
    """Add a flow q from node i to node j (−1 = fixed-pressure boundary)."""
    if i >= 0:
        f[i] -= q
        jac[i, i] -= dqi
        if j >= 0:
            jac[i, j] -= dqj
    if j >= 0:
        f[j] += q
        jac[j, j] += dqj
        if i >= 0:
            jac[j, i] += dqi


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def pneumatic_flows(
    p: np.ndarray, tn: np.ndarray, x: np.ndarray, k: Any, f: np.ndarray, jac: np.ndarray
) -> float:
    """Net mass inflow of every node and its Jacobian w.r.t. node pressures.

    Args:
        p: Node pressures [Pa] (6).
        tn: Node temperatures [K] (6).
        x: State (spools, effective commands, supply pressure are read).
        k: Kernel constants.
        f: Output, net inflow per node [kg/s].
        jac: Output, ∂f/∂p [kg/(s·Pa)].

    Returns:
        Mass flow drawn from the supply [kg/s].
    """
    for i in range(NN):
        f[i] = 0.0
        for j in range(NN):
            jac[i, j] = 0.0
    ps = x[I_PS]
    patm = k.p_atm
    ta = k.t_atm
    q_sup = 0.0
    # √(T0/T) per end: only the chambers leave atmospheric temperature
    rta = math.sqrt(T0_ISO / ta)
    for side in range(2):
        o = 3 * side
        n_o, n_t, n_c = o + N_OA, o + N_TA, o + N_CA
        rtc = math.sqrt(T0_ISO / tn[n_c]) if k.heat_on else rta
        spool = x[I_XA + side]
        # PRV: supply → O (spool > 0) or O → exhaust (spool < 0)
        if spool > 0.0:
            kq = k.prv_cs * spool * RHO0_ISO * rta
            q, d1, d2 = iso6358_signed_k(ps, p[n_o], kq, kq, k.prv_bs)
            _edge(-1, n_o, q, d1, d2, f, jac)
            q_sup += q
        elif spool < 0.0:
            kq = k.prv_ce * (-spool) * RHO0_ISO * rta
            q, d1, d2 = iso6358_signed_k(p[n_o], patm, kq, kq, k.prv_be)
            _edge(n_o, -1, q, d1, d2, f, jac)
        # DCV port: O ↔ D and D → exhaust, D = tube node or chamber
        n_d = n_t if k.tube_on else n_c
        rtd = rta if k.tube_on else rtc
        u = x[I_UA + side]
        if side == 1:
            u = 10.0 - u  # port 4 of DCV-b fills above 5 V: mirror onto port-2 convention
        if k.dcv_new:
            ps_bar = p[n_o] / BAR
            if u < k.nm_usw:
                a = interp2_clip(u, ps_bar, k.nm_u, k.nm_ps, k.nm_af)
                eps = interp_clip(u, k.nm_u, k.nm_ef)
                g = interp_clip(u, k.nm_u, k.nm_gf)
                kps = polyval(k.nm_kf, min(max(ps_bar, 2.0), 7.0))
                q, d1, d2 = new_model_flow(p[n_o], p[n_d], 1.0, ps_bar, a, eps, g, 0.0, kps, tn[n_o])
                _edge(n_o, n_d, q, d1, d2, f, jac)
            else:
                a = interp2_clip(u, ps_bar, k.nm_u, k.nm_ps, k.nm_ae)
                eps = interp_clip(u, k.nm_u, k.nm_ee)
                g = interp_clip(u, k.nm_u, k.nm_ge)
                kps = polyval(k.nm_ke, min(max(ps_bar, 2.0), 7.0))
                q, d1, d2 = new_model_flow(p[n_d], patm, 1.0, ps_bar, a, eps, g, 0.0, kps, tn[n_d])
                _edge(n_d, -1, q, d1, d2, f, jac)
        else:
            s_null = null_scale(u, k.null_s0, k.null_w)
            fr_f = s_null * area_frac(5.0 + k.ul_f - u, k.mp)
            fr_e = s_null * area_frac(u - (5.0 - k.ul_e), k.mp)
            if fr_f > 0.0:
                kq = k.dcv_c * fr_f * RHO0_ISO
                q, d1, d2 = iso6358_signed_k(p[n_o], p[n_d], kq * rta, kq * rtd, k.dcv_b)
                _edge(n_o, n_d, q, d1, d2, f, jac)
            if fr_e > 0.0:
                kq = k.dcv_c * fr_e * RHO0_ISO
                q, d1, d2 = iso6358_signed_k(p[n_d], patm, kq * rtd, kq * rta, k.dcv_b)
                _edge(n_d, -1, q, d1, d2, f, jac)
        # tube: laminar resistance between tube node and chamber
        if k.tube_on:
            rt = 2.0 * R_AIR * ta
            rho = (p[n_t] + p[n_c]) / rt
            dp = p[n_t] - p[n_c]
            q = k.tube_g * rho * dp
            _edge(n_t, n_c, q, k.tube_g * (rho + dp / rt), k.tube_g * (-rho + dp / rt), f, jac)
        # leak to atmosphere
        if k.el_c > 0.0:
            q, d1, d2 = iso6358_signed(p[n_c], patm, k.el_c, k.el_b, tn[n_c], ta)
            _edge(n_c, -1, q, d1, d2, f, jac)
    # leak across the vane / piston seal
    if k.vl_c > 0.0:
        q, d1, d2 = iso6358_signed(p[N_CA], p[N_CB], k.vl_c, k.vl_b, tn[N_CA], tn[N_CB])
        _edge(N_CA, N_CB, q, d1, d2, f, jac)
    return q_sup


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def _solve_network(jac: np.ndarray, dpdm: np.ndarray, h: float, f: np.ndarray, dm: np.ndarray) -> None:
    """The gas mass changes of one linearly implicit step: dm = (I − h·∂f/∂m)⁻¹·h·f.

    Gaussian elimination of ``I + jac·diag(−h·dpdm)`` in node order without
    pivoting: mass conservation makes ∂f/∂m a compartment matrix
    (non-positive diagonal, non-negative off-diagonal, column sums ≤ 0), so
    the matrix is a column-diagonally-dominant M-matrix, for which that is
    stable. Only the entries the network can make non-zero are touched. Its
    edges form the path O_a – T_a – C_a – C_b – T_b – O_b, with O_j – C_j
    instead of the tube when the tubes are off; eliminating in node order
    fills in nothing outside that pattern. The other entries are zeros that
    a dense elimination only ever multiplies and subtracts, so this gives
    its result to the bit (``tests/test_physics_properties.py`` compares
    them); zero multipliers (uncoupled nodes) are skipped.
    A vane-leak replay of the gap diagnosis took 1.95 instead of 2.28 µs per
    sample with it.

    Args:
        jac: ∂f/∂p of :func:`pneumatic_flows` [kg/(s·Pa)] (read only).
        dpdm: ∂p/∂m per node [Pa/kg].
        h: Step [s].
        f: Net inflow per node [kg/s].
        dm: Output, mass change per node [kg].
    """
    g0, g1, g2 = -h * dpdm[0], -h * dpdm[1], -h * dpdm[2]
    g3, g4, g5 = -h * dpdm[3], -h * dpdm[4], -h * dpdm[5]
    a00, a01, a02 = jac[0, 0] * g0 + 1.0, jac[0, 1] * g1, jac[0, 2] * g2
    a10, a11, a12 = jac[1, 0] * g0, jac[1, 1] * g1 + 1.0, jac[1, 2] * g2
    a20, a21, a22, a25 = jac[2, 0] * g0, jac[2, 1] * g1, jac[2, 2] * g2 + 1.0, jac[2, 5] * g5
    a33, a34, a35 = jac[3, 3] * g3 + 1.0, jac[3, 4] * g4, jac[3, 5] * g5
    a43, a44, a45 = jac[4, 3] * g3, jac[4, 4] * g4 + 1.0, jac[4, 5] * g5
    a52, a53, a54, a55 = jac[5, 2] * g2, jac[5, 3] * g3, jac[5, 4] * g4, jac[5, 5] * g5 + 1.0
    b0, b1, b2, b3, b4, b5 = h * f[0], h * f[1], h * f[2], h * f[3], h * f[4], h * f[5]
    if a10 != 0.0:
        m = a10 / a00
        a11 -= m * a01
        a12 -= m * a02
        b1 -= m * b0
    if a20 != 0.0:
        m = a20 / a00
        a21 -= m * a01
        a22 -= m * a02
        b2 -= m * b0
    if a21 != 0.0:
        m = a21 / a11
        a22 -= m * a12
        b2 -= m * b1
    if a52 != 0.0:
        m = a52 / a22
        a55 -= m * a25
        b5 -= m * b2
    if a43 != 0.0:
        m = a43 / a33
        a44 -= m * a34
        a45 -= m * a35
        b4 -= m * b3
    if a53 != 0.0:
        m = a53 / a33
        a54 -= m * a34
        a55 -= m * a35
        b5 -= m * b3
    if a54 != 0.0:
        m = a54 / a44
        a55 -= m * a45
        b5 -= m * b4
    b5 = b5 / a55
    b4 = (b4 - a45 * b5) / a44
    b3 = (b3 - a34 * b4 - a35 * b5) / a33
    b2 = (b2 - a25 * b5) / a22
    b1 = (b1 - a12 * b2) / a11
    b0 = (b0 - a01 * b1 - a02 * b2) / a00
    dm[0], dm[1], dm[2], dm[3], dm[4], dm[5] = b0, b1, b2, b3, b4, b5


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def regulator_update(
    x: np.ndarray, side: int, p_set: float, p_out: float, gain: float, db_on: float, db_off: float, dz: float,
    decay: float,
) -> None:
    """Advance PRV ``side``'s internal regulator and spool by one substep.

    Args:
        x: State (spool and awake flag of ``side`` are updated).
        side: 0 for PRV-a, 1 for PRV-b.
        p_set: Set pressure [Pa abs].
        p_out: Outlet pressure the regulator senses [Pa abs].
        gain: Spool opening per pascal of error [1/Pa].
        db_on: Error that wakes the regulator [Pa].
        db_off: Error below which it rests [Pa].
        dz: The spool opens in proportion to the error beyond this [Pa].
        decay: exp(−h/τ_spool) [-].
    """
    e = p_set - p_out
    ae = abs(e)
    awake = x[I_HA + side]
    if awake > 0.5:
        if ae < db_off:
            awake = 0.0
    elif ae > db_on:
        awake = 1.0
    x[I_HA + side] = awake
    xc = 0.0
    if awake > 0.5:
        xc = min(max(gain * spool_error(e, dz), -1.0), 1.0)
    x[I_XA + side] = xc + (x[I_XA + side] - xc) * decay


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def spool_error(e: float, dz: float) -> float:
    """The regulator's error past its dead zone ``dz`` [Pa] (``e`` itself for none)."""
    if e > dz:
        return e - dz
    if e < -dz:
        return e + dz
    return 0.0


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def step_pneumatics(x: np.ndarray, cmd: np.ndarray, k: Any, work: np.ndarray, jac: np.ndarray) -> float:
    """Advance the valves, gas masses, supply and chamber temperatures of ``x`` by ``k.h``.

    The first part of :func:`step`, with the vane held where ``x`` has it:
    the log replay of the gap diagnosis moves the vane along the measured
    angle itself, and the mechanics it would overwrite are a fifth of a
    replayed substep's time.

    Args:
        x: State vector (NX), modified in place (not position or speed).
        cmd: Commands held over the substep: z_a, z_b [V], u_a, u_b [V],
            PRV exit disturbances dp_a, dp_b [Pa].
        k: Kernel constants.
        work: Scratch, at least NWORK floats; on return it holds the gas
            mass changes ``work[4·NN:5·NN]`` [kg] and the node pressures at
            the start ``work[2·NN:3·NN]`` [Pa].
        jac: Scratch NN×NN.

    Returns:
        The mass flow drawn from the supply [kg/s].
    """
    h = k.h
    # 1. valve command lags and supply pressure
    if k.lag_on:
        for s in range(2):
            ad = 1.0 - math.exp(-h / k.tau_dcv) if k.tau_dcv > 0.0 else 1.0
            ap = 1.0 - math.exp(-h / k.tau_prv) if k.tau_prv > 0.0 else 1.0
            x[I_UA + s] += (cmd[C_UA + s] - x[I_UA + s]) * ad
            x[I_ZA + s] += (cmd[C_ZA + s] - x[I_ZA + s]) * ap
    else:
        x[I_UA] = cmd[C_UA]
        x[I_UB] = cmd[C_UB]
        x[I_ZA] = cmd[C_ZA]
        x[I_ZB] = cmd[C_ZB]
    vol = work[0:NN]
    tn = work[NN : 2 * NN]
    p = work[2 * NN : 3 * NN]
    f = work[3 * NN : 4 * NN]
    dpdm = work[5 * NN : 6 * NN]
    _vol_temps(x, x[I_POS], k.prv_vol, k.tube_vol, k.vd_a, k.vd_b, k.area_a, k.area_b, k.pos_min, k.pos_max,
               k.heat_on, k.t_atm, vol, tn)
    for i in range(NN):
        dpdm[i] = R_AIR * tn[i] / vol[i]
        p[i] = x[I_M0 + i] * dpdm[i]
    decay = k.prv_decay
    for s in range(2):
        p_set = k.p_atm + min(max(x[I_ZA + s], 0.0), k.z_max) * BAR + cmd[C_DPA + s]
        regulator_update(x, s, p_set, p[N_OA + 3 * s], k.prv_gain, k.prv_db_on, k.prv_db_off, k.prv_dz, decay)
    # 2. gas masses, linearly implicit Euler
    q_sup = pneumatic_flows(p, tn, x, k, f, jac)
    dm = work[4 * NN : 5 * NN]
    if k.tube_on or k.vl_c > 0.0:
        _solve_network(jac, dpdm, h, f, dm)
    else:
        # Without tubes or vane leakage the network is two uncoupled pairs
        # (O_j, C_j) and two idle tube nodes: solve each 2×2 by Cramer's rule
        # (same result as the general elimination, a third of its time).
        for s in range(2):
            o = 3 * s + N_OA
            c = 3 * s + N_CA
            go = -h * dpdm[o]
            gc = -h * dpdm[c]
            a00 = 1.0 + jac[o, o] * go
            a01 = jac[o, c] * gc
            a10 = jac[c, o] * go
            a11 = 1.0 + jac[c, c] * gc
            b0 = h * f[o]
            b1 = h * f[c]
            inv = 1.0 / (a00 * a11 - a01 * a10)
            dm[o] = (b0 * a11 - a01 * b1) * inv
            dm[c] = (a00 * b1 - a10 * b0) * inv
            dm[3 * s + N_TA] = h * f[3 * s + N_TA]
    for i in range(NN):
        m_new = x[I_M0 + i] + dm[i]
        x[I_M0 + i] = m_new if m_new > 1e-12 else 1e-12
    if k.droop_on:
        target = k.ps0 - k.droop_r * q_sup
        x[I_PS] = target + (x[I_PS] - target) * math.exp(-h / k.droop_tau)
    else:
        x[I_PS] = k.ps0
    # 3. chamber energy balance (heat-transfer effect)
    vel0 = x[I_VEL]
    if k.heat_on:
        dv = vel0 * h
        for s in range(2):
            n_c = N_CA + 3 * s
            it = I_TCA + s
            m_new = x[I_M0 + n_c]
            m_old = m_new - dm[n_c]
            tc = x[it]
            dvol = k.area_a * dv if s == 0 else -k.area_b * dv
            u_old = m_old * CV_AIR * tc
            dmc = dm[n_c]
            enth = dmc * CP_AIR * (k.t_atm if dmc > 0.0 else tc)
            t_adiabatic = (u_old + enth - p[n_c] * dvol) / (m_new * CV_AIR)
            # the wall's exchange, dT/dt = -h·A/(m·c_v)·(T - T_wall), solved exactly over the substep:
            # an explicit Euler step overshot the wall's temperature where h·A·h > 2·m·c_v, and this
            # stays stable for any h·A and tends to the isothermal model as h·A grows
            relax = math.exp(-k.heat_ha * h / (m_new * CV_AIR))
            tc_new = k.t_atm + (t_adiabatic - k.t_atm) * relax
            x[it] = min(max(tc_new, 150.0), 600.0)
    return q_sup


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def step(
    t: float,
    x: np.ndarray,
    cmd: np.ndarray,
    k: Any,
    prog_t: np.ndarray,
    prog_pos: np.ndarray,
    out: np.ndarray,
    work: np.ndarray,
    jac: np.ndarray,
) -> None:
    """Advance state ``x`` in place by one substep ``k.h`` from time ``t``.

    Args:
        t: Time at the start of the substep [s].
        x: State vector (NX), modified in place.
        cmd: Commands held over the substep: z_a, z_b [V], u_a, u_b [V],
            PRV exit disturbances dp_a, dp_b [Pa].
        k: Kernel constants.
        prog_t: User program time breakpoints [s].
        prog_pos: Intended position at those times [rad or m].
        out: Outputs (NO): T_i, T_f, T_p [N·m or N], supply flow [kg/s].
        work: Scratch, at least NWORK floats.
        jac: Scratch NN×NN.
    """
    h = k.h
    pos0 = x[I_POS]
    vel0 = x[I_VEL]
    q_sup = step_pneumatics(x, cmd, k, work, jac)
    vol = work[0:NN]
    tn = work[NN : 2 * NN]
    # 4. mechanics with the updated pressures
    _vol_temps(x, pos0, k.prv_vol, k.tube_vol, k.vd_a, k.vd_b, k.area_a, k.area_b, k.pos_min, k.pos_max,
               k.heat_on, k.t_atm, vol, tn)
    pa = x[I_M0 + N_CA] * R_AIR * tn[N_CA] / vol[N_CA]
    pb = x[I_M0 + N_CB] * R_AIR * tn[N_CB] / vol[N_CB]
    fp = pa * k.area_a - pb * k.area_b - k.p_atm * k.area_rod
    ti = human_torque(t + h, pos0, vel0, prog_t, prog_pos, k.hum_k, k.hum_d, k.hum_lim)
    drive = fp + ti
    p_lu = friction_lookup_pressure(pa, pb) if k.rotary else 1.0
    if k.lugre_on:
        tf = _lugre_mech(x, drive, p_lu, k.fr, k.fr_j, k.inertia, k.pos_min, k.pos_max, k.sigma0, k.sigma1, h)
    else:
        tf = _moreau_mech(x, drive, p_lu, k.fr, k.fr_j, k.inertia, k.pos_min, k.pos_max, h)
    out[O_TI] = ti
    out[O_TF] = tf
    out[O_TP] = fp
    out[O_QS] = q_sup


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def _end_stops(x: np.ndarray, pos_min: float, pos_max: float) -> None:
    """Inelastic end stops: clamp the position, kill speed into the stop."""
    if x[I_POS] >= pos_max:
        x[I_POS] = pos_max
        if x[I_VEL] > 0.0:
            x[I_VEL] = 0.0
    elif x[I_POS] <= pos_min:
        x[I_POS] = pos_min
        if x[I_VEL] < 0.0:
            x[I_VEL] = 0.0


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def _moreau_mech(
    x: np.ndarray, drive: float, p_lu: float, fr: np.ndarray, fr_j: float, inertia: float,
    pos_min: float, pos_max: float, h: float,
) -> float:
    """Velocity-level friction projection; returns the friction torque [N·m].

    Args:
        x: State (position and speed are updated).
        drive: Pneumatic plus user torque [N·m or N].
        p_lu: Friction lookup pressure [bar abs].
        fr: Packed friction table (see :func:`stribeck_params`).
        fr_j: Stribeck shape exponent j.
        inertia: Moment of inertia [kg·m²] or mass [kg].
        pos_min: Lower end stop [rad or m].
        pos_max: Upper end stop [rad or m].
        h: Step [s].
    """
    w = x[I_VEL]
    at_max = x[I_POS] >= pos_max and drive > 0.0
    at_min = x[I_POS] <= pos_min and drive < 0.0
    if w == 0.0:
        if at_max or at_min:
            return 0.0
        ts_p = interp_clip(p_lu, fr[0], fr[1])
        ts_n = interp_clip(p_lu, fr[0], fr[5])
        if -ts_n <= drive <= ts_p:
            return drive  # static friction holds: exactly balances the drive
    direction = w > 0.0 or (w == 0.0 and drive > 0.0)
    sgn = 1.0 if direction else -1.0
    ts, tc, ws, b = stribeck_params(p_lu, direction, fr)
    tcs = tc + (ts - tc) * stribeck_decay(abs(w) / ws, fr_j)
    w_free = w + h * drive / inertia
    w_new = (w_free - sgn * h * tcs / inertia) / (1.0 + h * b / inertia)
    if w_new * sgn <= 0.0:
        w_new = 0.0  # friction can stop the motion, never reverse it
        tf = (w_free * inertia) / h  # the friction impulse that stopped it
    else:
        tf = sgn * tcs + b * w_new
    x[I_VEL] = w_new
    x[I_POS] += h * w_new
    _end_stops(x, pos_min, pos_max)
    return tf


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def _lugre_mech(
    x: np.ndarray, drive: float, p_lu: float, fr: np.ndarray, fr_j: float, inertia: float,
    pos_min: float, pos_max: float, sigma0: float, sigma1: float, h: float,
) -> float:
    """LuGre friction with bristle state, sub-stepped for the bristle stiffness.

    Arguments as :func:`_moreau_mech`, plus bristle stiffness ``sigma0``
    [N·m/rad] and damping ``sigma1`` [N·m·s/rad].
    """
    n = int(math.ceil(h * math.sqrt(sigma0 / inertia) * 8.0)) + 1
    dt = h / n
    tf = 0.0
    for _ in range(n):
        w = x[I_VEL]
        direction = w > 0.0 or (w == 0.0 and drive > 0.0)
        ts, tc, ws, b = stribeck_params(p_lu, direction, fr)
        g = tc + (ts - tc) * stribeck_decay(abs(w) / ws, fr_j)
        z = x[I_ZF]
        # implicit in z for the |ω|-dependent relaxation (stiff at speed)
        z_new = (z + dt * w) / (1.0 + dt * sigma0 * abs(w) / g)
        zdot = (z_new - z) / dt
        tf = sigma0 * z_new + sigma1 * zdot
        w_new = (w + dt * (drive - tf) / inertia) / (1.0 + dt * b / inertia)
        tf += b * w_new
        x[I_ZF] = z_new
        x[I_VEL] = w_new
        x[I_POS] += dt * w_new
        _end_stops(x, pos_min, pos_max)
    return tf


@njit(cache=True, error_model="numpy")
def advance(
    t: float,
    x: np.ndarray,
    cmd: np.ndarray,
    k: Any,
    n: int,
    prog_t: np.ndarray,
    prog_pos: np.ndarray,
    out: np.ndarray,
) -> float:
    """Advance ``n`` substeps holding ``cmd`` (zero-order hold); returns new t."""
    work = np.empty(NWORK)
    jac = np.empty((NN, NN))
    for i in range(n):
        step(t + i * k.h, x, cmd, k, prog_t, prog_pos, out, work, jac)
    return t + n * k.h


# ----------------------------------------------------------------- continuous form


@njit(cache=True, error_model="numpy")
def rhs(t: float, x: np.ndarray, cmd: np.ndarray, k: Any, prog_t: np.ndarray, prog_pos: np.ndarray) -> np.ndarray:
    """Continuous-time derivative ẋ = f(t, x, u, p) of the same model.

    Used for ``solve_ivp`` cross-checks and replay. The regulator's hysteresis
    flag is held at its value in ``x``; stiction uses a Karnopp band.
    """
    dx = np.zeros(NX)
    vol = np.empty(NN)
    tn = np.empty(NN)
    p = np.empty(NN)
    f = np.empty(NN)
    jac = np.empty((NN, NN))
    vol_temps(x, k, vol, tn)
    for i in range(NN):
        p[i] = x[I_M0 + i] * R_AIR * tn[i] / vol[i]
    xx = x.copy()
    if not k.lag_on:
        xx[I_UA] = cmd[C_UA]
        xx[I_UB] = cmd[C_UB]
        xx[I_ZA] = cmd[C_ZA]
        xx[I_ZB] = cmd[C_ZB]
    else:
        dx[I_UA] = (cmd[C_UA] - x[I_UA]) / max(k.tau_dcv, 1e-6)
        dx[I_UB] = (cmd[C_UB] - x[I_UB]) / max(k.tau_dcv, 1e-6)
        dx[I_ZA] = (cmd[C_ZA] - x[I_ZA]) / max(k.tau_prv, 1e-6)
        dx[I_ZB] = (cmd[C_ZB] - x[I_ZB]) / max(k.tau_prv, 1e-6)
    if not k.droop_on:
        xx[I_PS] = k.ps0
    q_sup = pneumatic_flows(p, tn, xx, k, f, jac)
    for i in range(NN):
        dx[I_M0 + i] = f[i]
    if k.droop_on:
        dx[I_PS] = (k.ps0 - k.droop_r * q_sup - x[I_PS]) / k.droop_tau
    for s in range(2):
        z = min(max(xx[I_ZA + s], 0.0), k.z_max)
        e = k.p_atm + z * BAR + cmd[C_DPA + s] - p[N_OA + 3 * s]
        xc = min(max(k.prv_gain * spool_error(e, k.prv_dz), -1.0), 1.0) if x[I_HA + s] > 0.5 else 0.0
        dx[I_XA + s] = (xc - x[I_XA + s]) / k.prv_tau
    w = x[I_VEL]
    if k.heat_on:
        for s in range(2):
            n_c = N_CA + 3 * s
            tc = x[I_TCA + s]
            m = x[I_M0 + n_c]
            dm = f[n_c]
            vdot = k.area_a * w if s == 0 else -k.area_b * w
            hin = dm * CP_AIR * (k.t_atm if dm > 0.0 else tc)
            du = hin - p[n_c] * vdot + k.heat_ha * (k.t_atm - tc)
            dx[I_TCA + s] = (du - CV_AIR * tc * dm) / (m * CV_AIR)
    pa, pb = p[N_CA], p[N_CB]
    fp = pa * k.area_a - pb * k.area_b - k.p_atm * k.area_rod
    ti = human_torque(t, x[I_POS], w, prog_t, prog_pos, k.hum_k, k.hum_d, k.hum_lim)
    drive = fp + ti
    p_lu = friction_lookup_pressure(pa, pb) if k.rotary else 1.0
    dx[I_POS] = w
    if abs(w) < 1e-9:
        ts_p = interp_clip(p_lu, k.fr[0], k.fr[1])
        ts_n = interp_clip(p_lu, k.fr[0], k.fr[5])
        if -ts_n <= drive <= ts_p:
            return dx
    direction = w > 0.0 or (w == 0.0 and drive > 0.0)
    ts, tc, ws, b = stribeck_params(p_lu, direction, k.fr)
    tfr = stribeck_curve(w, ts, tc, ws, b, k.fr_j)
    dx[I_VEL] = (drive - (tfr if direction else -tfr)) / k.inertia
    return dx


def initial_state(
    p: PlantParams, pos: float = 0.0, pa_bar: float | None = None, pb_bar: float | None = None
) -> np.ndarray:
    """A consistent state at rest: all nodes at the given pressures [bar abs].

    Args:
        p: Plant parameters.
        pos: Position [rad or m]; default neutral (rotary) or 0 (linear).
        pa_bar: Side-a pressure (line and chamber) [bar abs]; default atmosphere.
        pb_bar: Side-b pressure [bar abs]; default atmosphere.
    """
    k = build_kernel(p)
    x = np.zeros(NX)
    x[I_POS] = pos
    vol = np.empty(NN)
    vol_temps(x, k, vol, np.empty(NN))
    pa = (pa_bar * BAR) if pa_bar is not None else p.p_atm
    pb = (pb_bar * BAR) if pb_bar is not None else p.p_atm
    for i in range(NN):
        pres = pa if i < 3 else pb
        x[I_M0 + i] = pres * vol[i] / (R_AIR * p.t_atm)
    x[I_TCA] = x[I_TCB] = p.t_atm
    x[I_PS] = p.supply.p_supply_bar * BAR
    x[I_UA] = x[I_UB] = 5.0
    return x


def node_pressures(x: np.ndarray, k: Any) -> np.ndarray:
    """All six node pressures [Pa] of state ``x``."""
    vol = np.empty(NN)
    tn = np.empty(NN)
    vol_temps(x, k, vol, tn)
    return np.asarray(x[I_M0 : I_M0 + NN] * R_AIR * tn / vol)
