"""Compressible flow through restrictions: ISO 6358 and the thesis's new model.

Pure functions, compiled with numba so the same code serves the fixed-step
simulator, ``solve_ivp`` replays, identification and tests. Mass flows are in
kg/s, pressures in Pa (absolute), temperatures in K, conductances in
m³/(s·Pa).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from app.engine import tables
from app.engine.constants import CP_AIR, RHO0_ISO, T0_ISO
from app.engine.physics.jit import NO_REFCOUNT

R_LAMINAR = 0.995
"""Pressure ratio above which ISO 6358 flow is continued linearly to zero.

The ISO subsonic ellipse has an infinite slope at p_d/p_u → 1, which makes any
fixed-step integrator chatter around equilibrium. ISO 6358-3:2014 itself
introduces a laminar region near r = 1; we continue the curve linearly from
r = 0.995 (C¹ in flow, bounded slope), which changes flows by < 0.5 % of the
choked value."""


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def iso6358_flow(pu: float, pd: float, c: float, b: float, tu: float) -> tuple[float, float, float]:
    """ISO 6358 mass flow from ``pu`` to ``pd`` (requires pu ≥ pd > 0).

    Args:
        pu: Upstream pressure [Pa abs].
        pd: Downstream pressure [Pa abs].
        c: Sonic conductance [m³/(s·Pa)].
        b: Critical pressure ratio [-].
        tu: Upstream temperature [K].

    Returns:
        (q, dq/dpu, dq/dpd): mass flow [kg/s] and its partial derivatives
        [kg/(s·Pa)].
    """
    if c <= 0.0:
        return 0.0, 0.0, 0.0
    return iso6358_flow_k(pu, pd, c * RHO0_ISO * math.sqrt(T0_ISO / tu), b)


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def iso6358_flow_k(pu: float, pd: float, k: float, b: float) -> tuple[float, float, float]:
    """:func:`iso6358_flow` with the choked-flow gain precomputed.

    The simulator's inner loop calls this: with isothermal gas the square
    root of the temperature ratio is a constant, so it is not recomputed
    every substep.

    Args:
        pu: Upstream pressure [Pa abs].
        pd: Downstream pressure [Pa abs].
        k: c·ρ0·√(T0/T_u), choked mass flow per pascal upstream [kg/(s·Pa)].
        b: Critical pressure ratio [-].
    """
    if k <= 0.0 or pu <= 0.0:
        return 0.0, 0.0, 0.0
    r = pd / pu
    if r <= b:
        return k * pu, k, 0.0
    one_b = 1.0 - b
    if r < R_LAMINAR:
        s = (r - b) / one_b
        phi = math.sqrt(1.0 - s * s)
        dphi_dr = -s / (one_b * phi)
        q = k * pu * phi
        # r = pd/pu: dr/dpu = -r/pu, dr/dpd = 1/pu
        return q, k * phi - k * dphi_dr * r, k * dphi_dr
    s_l = (R_LAMINAR - b) / one_b
    phi_l = math.sqrt(1.0 - s_l * s_l)
    g = k * phi_l / (1.0 - R_LAMINAR)
    return g * (pu - pd), g, -g


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def iso6358_signed(p1: float, p2: float, c: float, b: float, t1: float, t2: float) -> tuple[float, float, float]:
    """Bidirectional ISO 6358 flow from node 1 to node 2 (negative if reversed).

    Returns:
        (q, dq/dp1, dq/dp2) with q > 0 when gas moves 1 → 2 [kg/s].
    """
    return iso6358_signed_k(p1, p2, c * RHO0_ISO * math.sqrt(T0_ISO / t1), c * RHO0_ISO * math.sqrt(T0_ISO / t2), b)


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def iso6358_signed_k(p1: float, p2: float, k1: float, k2: float, b: float) -> tuple[float, float, float]:
    """:func:`iso6358_signed` with the gains c·ρ0·√(T0/T) of both ends precomputed."""
    if p1 >= p2:
        return iso6358_flow_k(p1, p2, k1, b)
    q, dq_du, dq_dd = iso6358_flow_k(p2, p1, k2, b)
    return -q, -dq_dd, -dq_du


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def interp_clip(x: float, xp: np.ndarray, fp: np.ndarray) -> float:
    """Linear interpolation held constant outside ``xp`` (Simulink lookup)."""
    n = xp.shape[0]
    if x <= xp[0]:
        return fp[0]
    if x >= xp[n - 1]:
        return fp[n - 1]
    lo = 0
    hi = n - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if xp[mid] <= x:
            lo = mid
        else:
            hi = mid
    w = (x - xp[lo]) / (xp[hi] - xp[lo])
    return fp[lo] + w * (fp[hi] - fp[lo])


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def interp2_clip(x: float, y: float, xp: np.ndarray, yp: np.ndarray, fp: np.ndarray) -> float:
    """Bilinear interpolation on a grid ``fp[i, j] = f(xp[i], yp[j])``, clipped."""
    nx = xp.shape[0]
    ny = yp.shape[0]
    x = min(max(x, xp[0]), xp[nx - 1])
    y = min(max(y, yp[0]), yp[ny - 1])
    i = 0
    while i < nx - 2 and xp[i + 1] <= x:
        i += 1
    j = 0
    while j < ny - 2 and yp[j + 1] <= y:
        j += 1
    if nx == 1 or ny == 1:
        return fp[i, j]
    wx = (x - xp[i]) / (xp[i + 1] - xp[i])
    wy = (y - yp[j]) / (yp[j + 1] - yp[j])
    return (
        fp[i, j] * (1 - wx) * (1 - wy)
        + fp[i + 1, j] * wx * (1 - wy)
        + fp[i, j + 1] * (1 - wx) * wy
        + fp[i + 1, j + 1] * wx * wy
    )


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def polyval(coef: np.ndarray, x: float) -> float:
    """Horner evaluation, highest power first (numpy.polyval order)."""
    acc = 0.0
    for k in range(coef.shape[0]):
        acc = acc * x + coef[k]
    return acc


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def new_model_flow(
    pu: float,
    pd: float,
    u: float,
    ps_bar: float,
    a: float,
    eps: float,
    alpha1: float,
    alpha2: float,
    k_ps: float,
    tu: float,
) -> tuple[float, float, float]:
    """Thesis Eq 3.10–3.11, signed so that flow reverses past the cracking point.

    ṁ = sgn(P_u·a − P_d)·|P_u·a − P_d|^ε·(α1·u + α2·u²) / (c_p·T_u·k(P_s)).
    The thesis writes the magnitude only; the sign makes p_d = a·p_u a stable
    equilibrium, which is what the CPR measurement observes. Near zero the
    power law (ε < 1 has infinite slope) is continued linearly below 1 kPa.

    Args:
        pu: Upstream pressure (supply when filling, chamber when exhausting) [Pa].
        pd: Downstream pressure [Pa].
        u: DCV command [V].
        ps_bar: Supply pressure for a(u, P_s) and k(P_s) [bar abs].
        a: Cracking pressure ratio a(u, P_s) [-].
        eps: Subsonic index ε(u) [-].
        alpha1: α1(u) (see DCVParams for units).
        alpha2: α2(u).
        k_ps: k(P_s) [-].
        tu: Upstream temperature [K].

    Returns:
        (q, dq/dpu, dq/dpd) [kg/s, kg/(s·Pa)].
    """
    gain = (alpha1 * u + alpha2 * u * u) / (CP_AIR * tu * k_ps)
    if gain <= 0.0:
        return 0.0, 0.0, 0.0
    d = pu * a - pd
    d0 = 1000.0
    ad = abs(d)
    if ad >= d0:
        mag = ad**eps
        dmag = eps * ad ** (eps - 1.0)
    else:
        slope = d0**eps / d0
        mag = slope * ad
        dmag = slope
    sgn = 1.0 if d >= 0.0 else -1.0
    q = sgn * gain * mag
    dq_dd = gain * dmag  # d q / d(d), sign cancels
    return q, dq_dd * a, -dq_dd


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def null_scale(u: float, s0: float, width_v: float) -> float:
    """Flow scale of both port paths of the MPYE at command ``u`` [V] (1 = unattenuated).

    The thesis's valve has a zero-flow region around 5 V (Δu_null, thesis
    2.1) and yet its CPR maps show both paths leaking across 4.5–5.9 V:
    inside that band the spool lands still overlap, so what flows is
    clearance leakage, far smaller than the orifice flow the same spool
    displacement gives outside it. The thesis's linear rig confirms the
    magnitude: on 25 mm bores 4.2 → 5 V gave 1 → 0 m/s (thesis 3.2.4). Both
    paths share the scale, so the CPR (a ratio of the two) is unchanged.

    Args:
        u: Valve command, port-2 convention [V].
        s0: Scale at 5 V [-] (0 < s0 ≤ 1; 1 switches the attenuation off).
        width_v: Distance from 5 V at which the scale reaches 1 [V].
    """
    if width_v <= 0.0:
        return 1.0
    r = min(abs(u - 5.0) / width_v, 1.0)
    return s0 + (1.0 - s0) * r * r


def area_fraction(displacement_v: np.ndarray | float) -> np.ndarray:
    """MPYE spool-area fraction against spool displacement from closed [V]."""
    return np.interp(displacement_v, tables.MPYE_DISPLACEMENT_V, tables.MPYE_AREA_FRACTION, left=0.0, right=1.0)
