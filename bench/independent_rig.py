"""The gap diagnosis on logs from a rig model written apart from ours (issue 6: "do not tune to your own generator").

The issue warns that the tool will be run on logs from an independently
written rig model. This is one, written for that purpose from the thesis and
SPEC's numbers alone, in a different form wherever a modeller has a choice,
and sharing no code with ``app/engine/physics``:

- the PRV's internal regulator is a proportional spool with a symmetric dead
  zone (0.02 bar) and no hysteresis (ours: wake at 0.03, rest at 0.01 bar,
  no dead zone; a form the recalibration may take since the thirty-first
  session);
- every orifice is ISO 6358 with a laminar region (linear below a 2 %
  pressure drop), integrated explicitly at 100 kHz (ours: linearly implicit
  at 2 kHz);
- the DCV opens linearly past a 0.2 V dead band around 5 V and is shut at
  centre by default (``--centre-leak`` opens it to both ports; ours has
  separate fill and exhaust underlaps and a null-leak band: at 5 V 0.34 %
  of its opening to the supply side and 0.10 % to exhaust);
- friction is Karnopp's stick–slip with the Stribeck curve of Table 4.2 at
  3 bar for every pressure (ours: a velocity-level projection, the table
  interpolated at the lower chamber pressure, or as far as the
  recalibration's weight says at 3 bar);
- one node per PRV outlet and line (ours: outlet and tube nodes).

Its nominal values are the datasheet and thesis numbers, and each rig draws
its own ±15 % errors on the dead volumes and flow capacities. Its effects
are written here too: a chamber-to-atmosphere orifice (``external_leakage``),
wall heat exchange with an energy balance per chamber (``heat_transfer``),
pressure- and torque-sensor offsets (``sensor_bias``), a heavier handle
(``inertia``), an orifice across the vane (``vane_leakage``), a supply that
sags with the flow drawn (``supply_droop``) and first-order lags on the
valve commands (``valve_dynamics``); since the twenty-ninth session also
a tube between each DCV port and its chamber, in lumps joined by
compressible Hagen–Poiseuille segments (``tube_dynamics``; ours: one
volume behind a laminar resistance), and a reset-integrator bristle that
holds elastically up to breakaway before the Stribeck curve slides
(``presliding_friction``; ours: LuGre).
The open-loop protocol experiments (all but the isotonic workout, whose
Default controller is ours) are run on it, written as station logs and
diagnosed by ``cwrr diagnose``'s own path; ``--protocol other`` runs
experiments written here instead (:func:`other_protocol`), once each, as
another lab might.

Run: ``python bench/independent_rig.py [--seeds 3] [--scale 1.0] [--protocol other] [--out FILE]`` in the project
environment; prints one JSON object (and writes it to ``--out``).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit

from app.engine.diagnosis.logs import write_log
from app.engine.diagnosis.protocol import PREROLL_S, RATE_HZ, schedules
from app.engine.diagnosis.run import diagnose_dir

P_ATM = 101325.0  # [Pa]
T_ATM = 293.15  # [K]
R = 287.0  # [J/(kg·K)]
CV = 718.0  # [J/(kg·K)]
RHO0 = 1.185  # ISO 6358 reference density [kg/m³]
BAR = 1e5
H = 1e-5  # integration step [s]
A_V_R = 8.55e-4 * 0.023  # vane area × torque radius [m³/rad] (SPEC §1)
THETA_MAX = math.radians(135.0)  # half of the 270° ROM [rad]
# Table 4.2 at 3 bar abs (SPEC §2): T_s, T_c [N·m], ω_s [rad/s], B [N·m·s/rad], CCW then CW
FRICTION = np.array([1.296, 0.627, 0.924, 0.150, 1.316, 0.703, 1.000, 0.123])
MU = 1.81e-5  # air's dynamic viscosity at 20 °C [Pa·s]
TUBE_NODES = 2  # lumps of a tube between a DCV port and its chamber (3 are unstable at 8 bar in 2 m at H)


def lpm_per_bar(c: float) -> float:
    """ISO sonic conductance from l/(s·bar) to m³/(s·Pa)."""
    return c * 1e-3 / BAR


@njit(cache=True)
def _iso(p_u: float, p_d: float, c: float, b: float) -> float:
    """ISO 6358 mass flow from p_u to p_d [kg/s] (negative if p_d > p_u), linear below a 2 % drop."""
    sgn = 1.0
    if p_d > p_u:
        p_u, p_d, sgn = p_d, p_u, -1.0
    r = p_d / p_u
    if r <= b:
        psi = 1.0
    elif r < 0.98:
        s = (r - b) / (1.0 - b)
        psi = math.sqrt(1.0 - s * s)
    else:
        s = (0.98 - b) / (1.0 - b)
        psi = math.sqrt(1.0 - s * s) * (1.0 - r) / 0.02
    return sgn * c * RHO0 * p_u * psi


@njit(cache=True)
def _tube_flow(p1: float, p2: float, conductance: float) -> float:
    """Isothermal laminar (Hagen–Poiseuille) mass flow along a tube segment from p1 to p2 [kg/s].

    ``conductance`` = π·d⁴ / (256·μ·L·R·T) [kg/(s·Pa²)]: compressible, the flow goes with p1² − p2².
    """
    return conductance * (p1 * p1 - p2 * p2)


@njit(cache=True)
def _stribeck(w: float, ccw: bool) -> float:
    """Sliding friction at speed ``w`` [N·m]: Table 4.2's Stribeck curve at 3 bar, signed by the direction."""
    j = 0 if ccw else 4
    sgn = 1.0 if ccw else -1.0
    return sgn * (FRICTION[j + 1] + (FRICTION[j] - FRICTION[j + 1]) * math.exp(-(w / FRICTION[j + 2]) ** 2)) \
        + FRICTION[j + 3] * w


@njit(cache=True)
def _volumes(th: float, k: np.ndarray) -> tuple[float, float]:
    """Chamber volumes [m³] at vane angle ``th`` [rad]."""
    return k[0] + A_V_R * (th + THETA_MAX), k[1] + A_V_R * (THETA_MAX - th)


@njit(cache=True)
def _user(t: float, th: float, w: float, prog_t: np.ndarray, prog_pos: np.ndarray) -> float:
    """The user's torque on the handle [N·m]: a spring-damper towards the program's angle, limited."""
    return min(max(20.0 * (np.interp(t, prog_t, prog_pos) - th) - 0.8 * w, -8.0), 8.0)


@njit(cache=True)
def _simulate(cmds: np.ndarray, prog_t: np.ndarray, prog_pos: np.ndarray, k: np.ndarray, noise: np.ndarray,
              pw: float, out: np.ndarray, rate: float = RATE_HZ, user: bool = True) -> None:
    """Run one experiment sampled at ``rate`` [Hz]; ``out`` (n, 11) gets the log rows.

    ``user``: someone holds the handle and follows the program; without, the handle is free (the
    torque sensor reads its noise and offset only) and the vane goes where the pressures push it.

    k: 0 dead volume a, 1 dead volume b [m³], 2 line volume [m³], 3 PRV C, 4 PRV b, 5 DCV C, 6 DCV b
    [m³/(s·Pa), -], 7 supply [Pa], 8 inertia [kg·m²], 9 leak C [m³/(s·Pa)], 10 h·A [W/K] (0: isothermal),
    11 p_a sensor offset [bar], 12 p_b sensor offset [bar], 13 the DCV's opening at 5 V [-], 14 torque sensor
    offset [N·m], 15 vane leak C [m³/(s·Pa)], 16 supply droop [Pa/(kg/s)], 17 its time constant [s], 18 DCV
    and 19 PRV command lags [s] (0: none), 20 bristle stiffness [N·m/rad] and 21 damping [N·m·s/rad] (0:
    Karnopp's stick), 22 tube length [m] and 23 its inner diameter [m] (0: the port on the chamber).
    """
    n = cmds.shape[0]
    sub = int(round(1.0 / (rate * H)))
    # state: line pressures, chamber masses and temperatures, spools, angle, speed
    po = np.array([pw, pw])
    tc = np.array([T_ATM, T_ATM])
    va0, vb0 = _volumes(0.0, k)
    m = np.array([pw * va0 / (R * T_ATM), pw * vb0 / (R * T_ATM)])
    x = np.zeros(2)
    ps = k[7]
    zf = cmds[0, 0:2].copy()  # the valves' commands as their lags have them
    uf = cmds[0, 2:4].copy()
    th = 0.0
    w = 0.0
    zb = 0.0  # bristle deflection [rad]
    # the tube: TUBE_NODES lumps per side, each a volume at the line's temperature and a laminar segment
    v_node = math.pi * k[23] ** 2 / 4.0 * k[22] / TUBE_NODES
    g_seg = math.pi * k[23] ** 4 / (256.0 * MU * (k[22] / TUBE_NODES + 1e-12) * R * T_ATM)
    pt = np.full((2, TUBE_NODES), pw)
    w_est = 0.0
    th_prev = 0.0
    a_f = 1.0 - math.exp(-2.0 * math.pi * 25.0 / rate)  # the station's 25 Hz speed filter
    q = 10.0 / 65536.0 * 2.0  # 16-bit over ±10 V, 5 V for 10 bar: bar per count
    t = 0.0
    for i in range(n):
        # sample at the start of the period, then hold the commands over it
        vol = _volumes(th, k)
        pa = m[0] * R * tc[0] / vol[0]
        pb = m[1] * R * tc[1] / vol[1]
        ti = _user(t, th, w, prog_t, prog_pos) if user else 0.0
        th_q = round(th / (2.0 * math.pi / 4096.0)) * (2.0 * math.pi / 4096.0)
        if i > 0:
            w_est += a_f * ((th_q - th_prev) * rate - w_est)
        th_prev = th_q
        out[i, 0] = t
        out[i, 1:5] = cmds[i]
        out[i, 5] = round((pa / BAR + k[11] + 0.003 * noise[i, 0]) / q) * q
        out[i, 6] = round((pb / BAR + k[12] + 0.003 * noise[i, 1]) / q) * q
        out[i, 7] = round((ps / BAR + 0.003 * noise[i, 2]) / q) * q
        out[i, 8] = th_q
        out[i, 9] = w_est
        out[i, 10] = ti + k[14] + 0.01 * noise[i, 3]
        for _ in range(sub):
            for s in range(2):
                zf[s] = cmds[i, s] if k[19] <= 0.0 else zf[s] + (cmds[i, s] - zf[s]) * H / k[19]
                uf[s] = cmds[i, 2 + s] if k[18] <= 0.0 else uf[s] + (cmds[i, 2 + s] - uf[s]) * H / k[18]
            vol = _volumes(th, k)
            dvol = (A_V_R * w, -A_V_R * w)
            pc = (m[0] * R * tc[0] / vol[0], m[1] * R * tc[1] / vol[1])
            q_vl = _iso(pc[0], pc[1], k[15], 0.5) if k[15] > 0.0 else 0.0  # across the vane, a → b
            q_sup = 0.0
            for s in range(2):
                # PRV: proportional spool past a ±0.02 bar dead zone, 4 ms lag
                e = (P_ATM + min(max(zf[s], 0.0), 10.0) * BAR) - po[s]
                ez = e - 0.02 * BAR if e > 0.02 * BAR else (e + 0.02 * BAR if e < -0.02 * BAR else 0.0)
                xc = min(max(2.0 * ez / BAR, -1.0), 1.0)
                x[s] += (xc - x[s]) * H / 0.004
                q_prv = _iso(ps, po[s], k[3] * x[s], k[4]) if x[s] > 0.0 else -_iso(po[s], P_ATM, -k[3] * x[s], k[4])
                if x[s] > 0.0:
                    q_sup += q_prv
                # DCV: chamber a fills below 5 V, chamber b above; linear past a 0.2 V dead band, a
                # clearance leak at centre to both ports
                d = (5.0 - uf[s]) if s == 0 else (uf[s] - 5.0)
                a_fill = k[13] + (1.0 - k[13]) * min(max((d - 0.2) / 4.8, 0.0), 1.0)
                a_exh = k[13] + (1.0 - k[13]) * min(max((-d - 0.2) / 4.8, 0.0), 1.0)
                # the valve's port sees the tube's first lump, or the chamber itself without a tube
                pport = pt[s, 0] if k[22] > 0.0 else pc[s]
                q_in = _iso(po[s], pport, k[5] * a_fill, k[6])
                q_out = _iso(pport, P_ATM, k[5] * a_exh, k[6])
                q_leak = _iso(pc[s], P_ATM, k[9], 0.5) if k[9] > 0.0 else 0.0
                po[s] += (q_prv - q_in) * R * T_ATM / k[2] * H
                if k[22] > 0.0:
                    # along the tube, lump by lump; what reaches the chamber is the last segment's flow
                    q_seg = np.empty(TUBE_NODES)
                    for j in range(TUBE_NODES):
                        q_seg[j] = _tube_flow(pt[s, j], pt[s, j + 1] if j + 1 < TUBE_NODES else pc[s], g_seg)
                    for j in range(TUBE_NODES):
                        q_node = (q_in - q_out if j == 0 else q_seg[j - 1]) - q_seg[j]
                        pt[s, j] += q_node * R * T_ATM / v_node * H
                    q_in, q_out = max(q_seg[TUBE_NODES - 1], 0.0), max(-q_seg[TUBE_NODES - 1], 0.0)
                dm = q_in - q_out - q_leak + (-q_vl if s == 0 else q_vl)
                if k[10] > 0.0:
                    # energy balance: inflow brings the line's temperature, outflow takes the chamber's
                    t_in = T_ATM if q_in > 0.0 else tc[s]
                    h_in = 1.4 * CV * (q_in * t_in) - 1.4 * CV * (q_out + q_leak) * tc[s]
                    du = h_in - pc[s] * dvol[s] + k[10] * (T_ATM - tc[s])
                    m_new = m[s] + dm * H
                    tc[s] = (m[s] * CV * tc[s] + du * H) / (m_new * CV)
                    m[s] = m_new
                else:
                    m[s] += dm * H
            # the shop supply sags with the flow drawn, through a first-order lag
            if k[16] > 0.0:
                ps += ((k[7] - k[16] * q_sup) - ps) * H / k[17]
            # mechanics: Karnopp stick-slip with the Stribeck curve, end stops
            tp = (pc[0] - pc[1]) * A_V_R
            drive = tp + (_user(t, th, w, prog_t, prog_pos) if user else 0.0)
            if k[20] > 0.0:
                # pre-sliding: a reset-integrator bristle (Haessig & Friedland) in place of Karnopp's
                # stick; it holds elastically up to the breakaway torque, then the Stribeck curve slides
                z_hi, z_lo = FRICTION[0] / k[20], -FRICTION[4] / k[20]
                if (zb >= z_hi and w > 0.0) or (zb <= z_lo and w < 0.0):
                    tf = _stribeck(w, w > 0.0)
                else:
                    tf = k[20] * zb + k[21] * w + FRICTION[3 if w >= 0.0 else 7] * w
                    zb = min(max(zb + w * H, z_lo), z_hi)
            else:
                if abs(w) < 1e-3:
                    ts = FRICTION[0] if drive > 0.0 else FRICTION[4]
                    if abs(drive) <= ts:
                        w = 0.0
                        t += H
                        continue
                tf = _stribeck(w, w > 0.0 or (w == 0.0 and drive > 0.0))
            w += (drive - tf) / k[8] * H
            th += w * H
            if th > THETA_MAX:
                th, w = THETA_MAX, min(w, 0.0)
            elif th < -THETA_MAX:
                th, w = -THETA_MAX, max(w, 0.0)
            t += H
        t = (i + 1) / rate


EFFECTS: dict[str, tuple[dict[int, float], dict[int, float]]] = {
    "none": ({}, {}),
    # (smaller, larger): the larger as the withheld-effect suite's larger magnitude, the smaller below its smaller
    "external_leakage": ({9: lpm_per_bar(0.005)}, {9: lpm_per_bar(0.06)}),
    "heat_transfer": ({10: 0.3}, {10: 0.05}),
    "sensor_bias": ({11: 0.05, 12: -0.03}, {11: 0.15, 12: 0.1, 14: -0.3}),
    "inertia": ({8: 0.0025 + 0.005}, {8: 0.0025 + 0.015}),
    "vane_leakage": ({15: lpm_per_bar(0.02)}, {15: lpm_per_bar(0.06)}),
    "supply_droop": ({16: 0.3 * BAR / 1e-3, 17: 0.05}, {16: 1.0 * BAR / 1e-3, 17: 0.1}),
    "valve_dynamics": ({18: 0.01, 19: 0.03}, {18: 0.03, 19: 0.1}),
    "tube_dynamics": ({22: 2.0, 23: 0.004}, {22: 5.0, 23: 0.004}),
    "presliding_friction": ({20: 150.0, 21: 0.5}, {20: 50.0, 21: 0.5}),
}


def rig_constants(seed: int, effect: str, centre_leak: float = 0.005, magnitude: int = 1) -> np.ndarray:
    """Nominal datasheet values with ±15 % errors of the rig's own, plus ``effect``.

    Args:
        seed: The rig's errors.
        effect: A key of :data:`EFFECTS`.
        magnitude: 1 (smaller) or 2 (larger).
        centre_leak: The DCV's opening at 5 V, to each port [-] (SPEC §1: "≈5 V is the closed
            centre").
    """
    rng = np.random.default_rng(1000 + seed)

    def err() -> float:
        return float(1.0 + rng.uniform(-0.15, 0.15))

    dv = err()
    k = np.array([3e-6 * dv, 3e-6 * dv, 8e-6, lpm_per_bar(4.0 * err()), 0.3, lpm_per_bar(3.1 * err()), 0.26,
                  8.0 * BAR, 0.0025, 0.0, 0.0, 0.0, 0.0, centre_leak, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0,
                  0.0, 0.004])
    for i, v in EFFECTS[effect][magnitude - 1].items():
        k[i] = v
    return k


def run_rig(outdir: Path, seed: int, effect: str, scale: float, centre_leak: float = 0.005,
            magnitude: int = 1) -> None:
    """Write the open-loop protocol's logs (two repetitions) of one rig to ``outdir``."""
    k = rig_constants(seed, effect, centre_leak, magnitude)
    for rep in range(2):
        for j, s in enumerate(schedules(rep, scale)):
            dt = 1.0 / RATE_HZ
            n = int(round((s.duration + PREROLL_S) / dt))
            z_rest = s.pw_bar - P_ATM / BAR
            cmds = np.array([(z_rest, z_rest, 5.0, 5.0) if i * dt < PREROLL_S - 1e-9
                             else s.commands(i * dt - PREROLL_S) for i in range(n)], dtype=float)
            noise = np.random.default_rng(seed * 1000 + rep * 100 + j).standard_normal((n, 4))
            log = np.empty((n, 11))
            _simulate(cmds, s.program.t, s.program.pos, k, noise, s.pw_bar * BAR, log)
            meta = {"rig": "rotary", "sample_rate_hz": RATE_HZ, "p_atm_bar": P_ATM / BAR,
                    "working_pressure_bar": s.pw_bar, "experiment": s.name, "human": s.human,
                    "repetition": rep + 1, "protocol": True, "generator": "bench/independent_rig.py"}
            write_log(outdir, f"{s.name}-{rep + 1}", log, meta)


def other_protocol(rng: np.random.Generator, rate: float = RATE_HZ,
                   free: bool = False) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray, bool]]:
    """Experiments of a protocol other than ours, each run once at ``rate`` [Hz].

    Returns:
        Per experiment: name, commands (n, 4) [V], the user's program (times [s], angles [rad]),
        and whether someone holds the handle.

    Written for this bench, not from :mod:`app.engine.diagnosis.protocol`, as
    another lab might excite its rig: a PRV staircase on both chambers, a
    hold with the DCVs shut at equal pressures, a swing the user leads with
    the pressures following it, a chirp on the DCVs through their partial
    openings, random PRV pulses while the user rocks the handle. No log
    shuts a chamber after a fast fill, none holds the chambers apart. With
    ``free``, two logs more of PRV steps on a free handle (``human``
    false), which throw the vane from end stop to end stop.
    """
    out = []

    def add(name: str, dur: float, cmd: Any, angle: Any, user: bool = True) -> None:
        t = np.arange(int(round(dur * rate))) / rate
        pt = np.linspace(0.0, dur, 400)
        out.append((name, np.array([cmd(x) for x in t], dtype=float), pt, np.array([angle(x) for x in pt]), user))

    stair = [0.5, 1.5, 2.5, 3.5, 2.5, 1.5, 2.0]
    add("staircase", 17.5, lambda x: (stair[min(int(x / 2.5), 6)],
                                      2.0 if x < 8.0 else stair[min(int((x - 8.0) / 2.5), 6)], 0.0, 10.0),
        lambda x: 0.0)
    add("blocked_hold", 20.0, lambda x: (2.0, 2.0, 0.0, 10.0) if x < 3.0 else
        ((2.0, 2.0, 5.0, 5.0) if x < 18.0 else (2.0, 2.0, 10.0, 0.0)), lambda x: 0.0)
    add("swing", 15.0, lambda x: (2.0 + math.sin(0.6 * math.pi * x), 2.0 - math.sin(0.6 * math.pi * x), 0.0, 10.0),
        lambda x: 0.8 * math.sin(0.6 * math.pi * x))
    add("valve_chirp", 15.0, lambda x: (2.0, 2.0, 5.0 - 2.5 * math.sin(2.0 * math.pi * (0.2 + 0.06 * x) * x),
                                        5.0 + 2.5 * math.sin(2.0 * math.pi * (0.2 + 0.06 * x) * x)), lambda x: 0.0)
    ends = np.cumsum(rng.uniform(0.3, 1.5, 40))
    levels = rng.uniform(0.5, 3.5, (40, 2))
    add("pulses", 15.0, lambda x: (*levels[np.searchsorted(ends, x)], 0.0, 10.0),
        lambda x: 0.3 * math.sin(0.2 * math.pi * x))
    if free:
        for name, lv in (("free_steps_1", [(2.0, 1.0), (1.0, 2.5), (3.0, 1.0), (1.0, 3.0)]),
                         ("free_steps_2", [(1.0, 2.0), (2.5, 1.0), (1.0, 3.0), (3.0, 1.5)])):
            add(name, 12.0, lambda x, lv=lv: (*lv[min(int(x / 3.0), 3)], 0.0, 10.0), lambda x: 0.0, user=False)
    return out


def run_rig_other(outdir: Path, seed: int, effect: str, magnitude: int = 1, centre_leak: float = 0.0,
                  rate: float = RATE_HZ, free: bool = False) -> None:
    """Write :func:`other_protocol`'s logs (each once, sampled at ``rate`` [Hz]) of one rig to ``outdir``."""
    k = rig_constants(seed, effect, centre_leak, magnitude)
    for j, (name, cmds, prog_t, prog_pos, user) in enumerate(other_protocol(np.random.default_rng(7), rate, free)):
        n = cmds.shape[0]
        noise = np.random.default_rng(seed * 1000 + j).standard_normal((n, 4))
        log = np.empty((n, 11))
        _simulate(cmds, prog_t, prog_pos, k, noise, 3.0 * BAR, log, rate, user)
        meta = {"rig": "rotary", "sample_rate_hz": rate, "p_atm_bar": P_ATM / BAR, "working_pressure_bar": 3.0,
                "experiment": name, "human": user, "generator": "bench/independent_rig.py --protocol other"}
        write_log(outdir, name, log, meta)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3, help="effect-free rigs (seeds 0, 1, …)")
    ap.add_argument("--effect-seed", type=int, default=0, help="the rig's errors and noise for the effect cases")
    ap.add_argument("--scale", type=float, default=1.0, help="protocol duration factor")
    ap.add_argument("--effects", nargs="*", default=[e for e in EFFECTS if e != "none"])
    ap.add_argument("--centre-leak", type=float, default=0.0, help="the DCV's opening at 5 V [-]")
    ap.add_argument("--magnitudes", type=int, nargs="*", default=[1, 2], choices=[1, 2])
    ap.add_argument("--protocol", choices=["ours", "other"], default="ours",
                    help="our protocol's open-loop experiments run twice, or other_protocol()'s run once each")
    ap.add_argument("--rate", type=float, default=RATE_HZ,
                    help="--protocol other: the logs' sample rate [Hz] (a divisor of the rig's 100 kHz step)")
    ap.add_argument("--free-handle", action="store_true",
                    help="--protocol other: two logs more, PRV steps on a free handle thrown from stop to stop")
    ap.add_argument("--out", default=None, help="also write the JSON here")
    args = ap.parse_args(argv)
    steps = 1.0 / (args.rate * H) if args.rate > 0.0 else 0.0
    if steps < 1.0 or abs(steps - round(steps)) > 1e-9:
        ap.error(f"--rate {args.rate:g}: must divide the rig's {1.0 / H:g} Hz step (e.g. 100, 200, 500, 1000)")
    cases = [("none", s, 1) for s in range(args.seeds)] + [(e, args.effect_seed, m) for m in args.magnitudes
                                                                 for e in args.effects]
    rows = []
    for effect, seed, mag in cases:
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            if args.protocol == "other":
                run_rig_other(Path(d), seed, effect, mag, args.centre_leak, args.rate, args.free_handle)
            else:
                run_rig(Path(d), seed, effect, args.scale, args.centre_leak, mag)
            t1 = time.perf_counter()
            rep = diagnose_dir(d)
            t2 = time.perf_counter()
        ranking = [c["effect"] for c in rep["ranking"]]
        first = rep["ranking"][0]
        row = {"effect": effect, "magnitude": mag, "seed": seed, "verdict": rep["verdict"]["effects"],
               "confusable_with": rep["verdict"]["confusable_with"],
               "alternatives": rep["verdict"].get("alternatives", []),
               "rank": ranking.index(effect) + 1 if effect in ranking else None,
               "gap_closure": next((c["gap_closure"] for c in rep["ranking"] if c["effect"] == effect), None),
               "first": {"effect": first["effect"], "gap_closure": first["gap_closure"],
                         "significant": first["significant"], "params": first["params"],
                         "not_significant_because": first.get("not_significant_because", [])},
               "e_before": rep["how_far"]["e_before"], "e_after": rep["how_far"]["e_after"],
               "e_floor": rep["how_far"]["e_floor"], "baseline_params": rep["baseline"].get("params"),
               "held_out": rep["experiments"]["held_out"], "untested": rep["verdict"].get("untested", []),
               "sim_s": round(t1 - t0, 1), "diagnose_s": round(t2 - t1, 1)}
        rows.append(row)
        print(json.dumps({k: row[k] for k in ("effect", "magnitude", "seed", "verdict", "confusable_with", "rank",
                                              "gap_closure", "e_before", "e_after", "e_floor")}), flush=True)
    nulls = [r for r in rows if r["effect"] == "none"]
    withe = [r for r in rows if r["effect"] != "none"]
    summary = {"false_positives": sum(bool(r["verdict"]) for r in nulls), "null_cases": len(nulls),
               "ranked_first": sum(r["rank"] == 1 for r in withe), "effect_cases": len(withe),
               "in_verdict_first": sum(bool(r["verdict"]) and r["verdict"][0] == r["effect"] for r in withe),
               "gap_closures": [r["gap_closure"] for r in withe], "centre_leak": args.centre_leak,
               "protocol": args.protocol, "free_handle": args.free_handle,
               "rate_hz": args.rate if args.protocol == "other" else RATE_HZ, "rows": rows}
    if args.out:
        Path(args.out).write_text(json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))
    return summary


if __name__ == "__main__":
    main()
