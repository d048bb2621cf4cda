"""Default maps of the thesis's new DCV flow model, derived from the ISO valve.

Table 4.1's α1/α2 magnitudes fit no single unit system (SPEC §3), so the
simulator's default new-model maps are derived from the ISO 6358 description
of the same valve (datasheet C and b, MPYE spool-area curve, thesis 4.1.1
underlaps):

* a(u, P_s): the pressure ratio at which the chamber settles when the fill
  and exhaust leaks balance — exactly what the thesis's CPR experiment
  measures (filling: P_a/P_s; exhausting: P_atm/P_a);
* ε(u): Table 4.1 where it has values (dimensionless), clipped outside;
* g(u) = α1·u + α2·u²: least-squares match of the model to the ISO net flow
  over the chamber-pressure range at P_s = 5 bar. Only g is identifiable at a
  single u, so α1 = g/u and α2 = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from app.engine import tables
from app.engine.constants import BAR, CP_AIR
from app.engine.physics.flow import area_fraction, iso6358_flow, null_scale


@dataclass(frozen=True)
class NewModelMaps:
    """Lookup tables of the new flow model (Eq 3.10–3.11).

    Attributes:
        u_grid: DCV command grid [V].
        ps_grid_bar: Supply-pressure grid [bar abs].
        a_fill: CPR a(u, P_s) for filling, shape (len(u), len(ps)) [-].
        a_exh: CPR for exhausting [-].
        eps_fill: ε(u) filling [-].
        eps_exh: ε(u) exhausting [-].
        alpha1_fill: α1(u) filling (units: DCVParams docstring).
        alpha2_fill: α2(u) filling.
        alpha1_exh: α1(u) exhausting.
        alpha2_exh: α2(u) exhausting.
        g_fill: Identifiable gain g(u) = α1·u + α2·u² filling; at u = 0, where
            the thesis's polynomial vanishes although the port is wide open,
            the derived gain itself.
        g_exh: Same for exhausting.
        u_switch: Command above which the port exhausts [V].
    """

    u_grid: np.ndarray
    ps_grid_bar: np.ndarray
    a_fill: np.ndarray
    a_exh: np.ndarray
    eps_fill: np.ndarray
    eps_exh: np.ndarray
    alpha1_fill: np.ndarray
    alpha2_fill: np.ndarray
    alpha1_exh: np.ndarray
    alpha2_exh: np.ndarray
    g_fill: np.ndarray
    g_exh: np.ndarray
    u_switch: float


def openings(u: float, underlap_fill_v: float, underlap_exh_v: float, null_s0: float = 1.0,
             null_width_v: float = 0.0) -> tuple[float, float]:
    """(fill, exhaust) effective area fractions of port 2 at command ``u`` [V] (see :func:`null_scale`)."""
    s = null_scale(u, null_s0, null_width_v)
    f = s * float(area_fraction(5.0 + underlap_fill_v - u))
    e = s * float(area_fraction(u - (5.0 - underlap_exh_v)))
    return f, e


def _net_iso(p: float, ps: float, f: float, e: float, c: float, b: float, p_atm: float, t: float) -> float:
    qf = iso6358_flow(ps, p, c * f, b, t)[0] if ps >= p else -iso6358_flow(p, ps, c * f, b, t)[0]
    qe = iso6358_flow(p, p_atm, c * e, b, t)[0] if p >= p_atm else -iso6358_flow(p_atm, p, c * e, b, t)[0]
    return qf - qe


def derive_new_model_maps(
    c_si: float, b: float, underlap_fill_v: float, underlap_exh_v: float, p_atm: float, t: float,
    null_s0: float = 1.0, null_width_v: float = 0.0,
) -> NewModelMaps:
    """Build the new-model maps that best mimic the ISO valve (see module doc).

    Args:
        c_si: Full-opening sonic conductance [m³/(s·Pa)].
        b: Critical pressure ratio [-].
        underlap_fill_v: Filling underlap [V].
        underlap_exh_v: Exhausting underlap [V].
        p_atm: Atmospheric pressure [Pa].
        t: Gas temperature [K].
        null_s0: Null-zone flow scale at 5 V [-] (:func:`~app.engine.physics.flow.null_scale`).
        null_width_v: Null-zone half width [V].
    """
    u_grid = np.round(np.arange(0.0, 10.0001, 0.1), 10)
    ps_grid = np.arange(2.0, 7.0001, 1.0)
    a_f = np.ones((u_grid.size, ps_grid.size))
    a_e = np.ones_like(a_f)
    for i, u in enumerate(u_grid):
        f, e = openings(float(u), underlap_fill_v, underlap_exh_v, null_s0, null_width_v)
        for j, ps_bar in enumerate(ps_grid):
            ps = float(ps_bar) * BAR
            if f <= 0.0:
                p_eq = p_atm
            elif e <= 0.0:
                p_eq = ps
            else:
                p_eq = brentq(_net_iso, p_atm, ps, args=(ps, f, e, c_si, b, p_atm, t), xtol=1.0)
            a_f[i, j] = p_eq / ps
            a_e[i, j] = p_atm / p_eq
    eps_f = np.interp(u_grid, tables.TABLE41_U_FILL, tables.TABLE41_EPS_FILL)
    eps_e = np.interp(u_grid, tables.TABLE41_U_EXH, tables.TABLE41_EPS_EXH)
    k5_f = float(np.polyval(tables.K_FILL_POLY, 5.0))
    k5_e = float(np.polyval(tables.K_EXH_POLY, 5.0))
    g_f = np.zeros(u_grid.size)
    g_e = np.zeros(u_grid.size)
    ps = float(5.0 * BAR)
    j5 = int(np.argmin(np.abs(ps_grid - 5.0)))
    for i, u in enumerate(u_grid):
        f, e = openings(float(u), underlap_fill_v, underlap_exh_v, null_s0, null_width_v)
        p_lo, p_hi = p_atm, ps
        pr = np.linspace(p_lo, p_hi, 41)
        q = np.array([_net_iso(p, ps, f, e, c_si, b, p_atm, t) for p in pr])
        # shape functions of the new model with unit gain
        s_f = np.sign(ps * a_f[i, j5] - pr) * np.abs(ps * a_f[i, j5] - pr) ** eps_f[i] / (CP_AIR * t * k5_f)
        s_e = np.sign(pr * a_e[i, j5] - p_atm) * np.abs(pr * a_e[i, j5] - p_atm) ** eps_e[i] / (CP_AIR * t * k5_e)
        if np.dot(s_f, s_f) > 0:
            g_f[i] = max(0.0, float(np.dot(q, s_f) / np.dot(s_f, s_f)))
        if np.dot(s_e, s_e) > 0:
            g_e[i] = max(0.0, float(np.dot(-q, s_e) / np.dot(s_e, s_e)))
    u_safe = np.where(u_grid > 0, u_grid, 1.0)
    return NewModelMaps(
        u_grid=u_grid,
        ps_grid_bar=ps_grid,
        a_fill=a_f,
        a_exh=a_e,
        eps_fill=eps_f,
        eps_exh=eps_e,
        alpha1_fill=g_f / u_safe,
        alpha2_fill=np.zeros_like(g_f),
        alpha1_exh=g_e / u_safe,
        alpha2_exh=np.zeros_like(g_e),
        g_fill=g_f,
        g_exh=g_e,
        u_switch=5.0 + 0.5 * (underlap_fill_v - underlap_exh_v),
    )
