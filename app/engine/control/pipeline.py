"""Interaction-torque control pipeline of thesis Fig 3.28, compiled.

One step per control period: intention detector → friction estimator →
reference generator → signal router → PRV controller. The same compiled
function runs inside the batch simulator and behind the engine loop's
controller object, so both give identical commands.

Choices the thesis leaves open (written down here as SPEC asks):

* Intention detector: thresholds ±0.25 N·m (thesis 3.3.1) with hysteresis and
  dwell so sensor noise cannot make it flicker: a direction is entered after
  the torque stays beyond ±0.25 N·m for ``dwell_on`` and left after it stays
  inside ±``release`` for ``dwell_off``.
* Sign unification: CW friction and the CW target enter Eq 3.23 as magnitudes
  (the estimator's ×−1 of thesis Fig 3.32 applied to the target too), so that
  the controlled chamber's reference resists the user in both directions.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from app.engine.constants import BAR, P_ATM
from app.engine.physics.plant import stribeck_params
from app.engine.physics.sensors import M_PA, M_PB, M_TQ, M_VEL

# ------------------------------------------------------------------ parameters
P_PW = 0  # working pressure P_w [bar abs]
P_TARGET = 1  # target interaction torque magnitude |[T_i]^t| [N·m]
P_THR = 2  # intention threshold [N·m]
P_REL = 3  # release threshold [N·m]
P_DWELL_ON = 4  # [s]
P_DWELL_OFF = 5  # [s]
P_TPB = 6  # A_v·r per bar [N·m/bar]
P_H = 7  # PRV controller: 1 Default, 2 Cascade PID, 3 Fuzzy
P_UA_OPEN = 8  # DCV-a command routing PRV-a to chamber a [V]
P_UB_OPEN = 9  # DCV-b command routing PRV-b to chamber b [V]
P_ZMAX = 10  # PRV command limit [V]
P_PATM = 11  # P_atm [bar]
P_FR_J = 12  # Stribeck exponent of the estimator
NP = 16

# ------------------------------------------------------------------ state
S_MODE = 0  # 0 none, 1 CCW, 2 CW
S_CAND = 1  # candidate mode
S_TIMER = 2  # dwell timer [s]
S_PREF_A = 3  # last [P_a]^f [bar abs]
S_PREF_B = 4
S_TF = 5  # last friction estimate [N·m]
NSTATE = 16

# command vector: z_a, z_b, u_a, u_b
K_ZA, K_ZB, K_UA, K_UB = 0, 1, 2, 3


def default_params(
    pw_bar: float = 3.0, target_nm: float = 1.2, controller: int = 1, torque_per_bar: float = 0.0
) -> np.ndarray:
    """Parameter vector with the thesis's defaults (SPEC §4–5)."""
    cp = np.zeros(NP)
    cp[P_PW] = pw_bar
    cp[P_TARGET] = abs(target_nm)
    cp[P_THR] = 0.25
    cp[P_REL] = 0.10
    cp[P_DWELL_ON] = 0.010
    cp[P_DWELL_OFF] = 0.030
    cp[P_TPB] = torque_per_bar if torque_per_bar > 0 else 8.55e-4 * 0.023 * BAR
    cp[P_H] = controller
    cp[P_UA_OPEN] = 0.0
    cp[P_UB_OPEN] = 10.0
    cp[P_ZMAX] = 10.0
    cp[P_PATM] = P_ATM / BAR
    cp[P_FR_J] = 2.0
    return cp


@njit(cache=True, error_model="numpy")
def intention_update(tq: float, st: np.ndarray, cp: np.ndarray, dt: float) -> int:
    """Three-state user intention detector with hysteresis and dwell.

    Args:
        tq: Measured interaction torque [N·m].
        st: Controller state (mode, candidate, timer updated).
        cp: Parameters.
        dt: Control period [s].

    Returns:
        The mode: 0 no intention, 1 CCW, 2 CW.
    """
    mode = int(st[S_MODE])
    thr = cp[P_THR]
    rel = cp[P_REL]
    if mode == 0:
        cand = 1 if tq > thr else (2 if tq < -thr else 0)
        need = cp[P_DWELL_ON]
    elif mode == 1:
        cand = 1 if tq > rel else (2 if tq < -thr else 0)
        need = cp[P_DWELL_OFF] if cand == 0 else cp[P_DWELL_ON]
    else:
        cand = 2 if tq < -rel else (1 if tq > thr else 0)
        need = cp[P_DWELL_OFF] if cand == 0 else cp[P_DWELL_ON]
    if cand == mode:
        st[S_TIMER] = 0.0
        st[S_CAND] = mode
        return mode
    if int(st[S_CAND]) != cand:
        st[S_CAND] = cand
        st[S_TIMER] = 0.0
    st[S_TIMER] += dt
    if st[S_TIMER] >= need - 1e-12:
        st[S_MODE] = cand
        st[S_TIMER] = 0.0
        return cand
    return mode


@njit(cache=True, error_model="numpy")
def friction_estimate(mode: int, omega: float, pa: float, pb: float, fr: np.ndarray, j: float) -> float:
    """Friction torque estimator (thesis 3.3.2, Eq 3.20), unified sign.

    Table lookup on the controlled chamber's measured pressure (P_a for CCW,
    P_b for CW); ω_fric = ω (CCW) or −ω (CW).
    """
    if mode == 0:
        return 0.0
    ccw = mode == 1
    p = pa if ccw else pb
    ts, tc, ws, b = stribeck_params(p, ccw, fr)
    w = omega if ccw else -omega
    return tc + (ts - tc) * math.exp(-((abs(w) / ws) ** j)) + b * w


@njit(cache=True, error_model="numpy")
def control_step(meas: np.ndarray, st: np.ndarray, cp: np.ndarray, fr: np.ndarray, dt: float, cmd: np.ndarray) -> None:
    """One control period: measurements in, PRV/DCV commands out.

    Args:
        meas: Measurement vector (see :mod:`app.engine.physics.sensors`).
        st: Controller state, updated.
        cp: Parameters.
        fr: Estimator friction table, packed like the plant's.
        dt: Control period [s].
        cmd: Output commands z_a, z_b, u_a, u_b [V].
    """
    pa = meas[M_PA]
    pb = meas[M_PB]
    mode = intention_update(meas[M_TQ], st, cp, dt)
    tf = friction_estimate(mode, meas[M_VEL], pa, pb, fr, cp[P_FR_J])
    pw = cp[P_PW]
    # reference generator, Eq 3.23 (magnitudes: see module doc)
    pr = pw + (tf - cp[P_TARGET]) / cp[P_TPB]
    # signal router
    pref_a = pw
    pref_b = pw
    if mode == 1:
        pref_a = pr
    elif mode == 2:
        pref_b = pr
    st[S_PREF_A] = pref_a
    st[S_PREF_B] = pref_b
    st[S_TF] = tf
    # Default controller, Eq 3.25 + Eq 3.22: z = [P]^r − P_atm
    za = pref_a - cp[P_PATM]
    zb = pref_b - cp[P_PATM]
    cmd[K_ZA] = min(max(za, 0.0), cp[P_ZMAX])
    cmd[K_ZB] = min(max(zb, 0.0), cp[P_ZMAX])
    cmd[K_UA] = cp[P_UA_OPEN]
    cmd[K_UB] = cp[P_UB_OPEN]
