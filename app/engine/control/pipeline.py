"""Interaction-torque control pipeline of thesis Fig 3.28, compiled.

One step per control period: intention detector → friction estimator →
reference generator (Eq 3.23) → PDRA (Eq 3.24) → signal router → PRV
controllers (Default / Cascade PID / Cascade Fuzzy Adaptive PID, switched by
h) → TDRA (Eq 3.21–3.22). The same compiled functions run inside the batch
simulator, behind the engine loop's controller object, and inside the block
objects of :mod:`app.engine.control.blocks` that the unit tests step.

Choices the thesis leaves open (written down here, as SPEC asks):

* Intention detector: thresholds ±0.25 N·m (thesis 3.3.1) with hysteresis and
  dwell so sensor noise cannot make it flicker: a direction is entered after
  the torque stays beyond ±0.25 N·m for ``dwell_on`` (10 ms) and left after
  it stays inside ±``release`` (0.10 N·m) for ``dwell_off`` (30 ms). A
  sample counts for the time since the previous one, at most one period
  (``S_SEEN``): after a late period the engine's catch-up tick reads the
  rig again a millisecond later, and counted as a whole period the two
  samples met the 10 ms dwell on one disturbance (a paced SC-2 run over
  Modbus then tracked the opposite direction to its end).
* Sign unification: CW friction and the CW target enter Eq 3.23 as
  magnitudes (the estimator's ×−1 of thesis Fig 3.32 applied to the target
  too), so the controlled chamber's reference resists the user both ways.
* PDRA (Table 3.7): while moving, the counter chamber's deviation
  P_dif = P_w − P_counter is watched; beyond ±0.1 bar the controlled
  chamber's reference is shifted by −P_dif, the sign that keeps the intended
  difference P_a − P_b (SPEC §4).
* TDRA (Eq 3.21): PID on the torque error in unified magnitudes,
  e^T = |[T_i]^t| − s·T_i (s = +1 CCW, −1 CW). Its output lowers the
  controlled chamber's pressure when the user pushes less than the target —
  the stabilising sign (a larger target lowers P^r in Eq 3.23 too). It acts
  on the controlled chamber only (applied to both chambers it would cancel in
  P_a − P_b) and is reset when the direction changes.
* Eq 3.22 adds [z_j]^T after the PRV controller. With an integrating PRV
  controller (PID, fuzzy) the two integrators then chase different set-points
  — pressure and torque — and drift apart without bound. By default
  (``tdra_into_reference``) [z_j]^T also shifts the pressure reference the
  PRV controller tracks, so both loops agree on one set-point and Eq 3.22's
  direct path remains as feed-forward. For Default the two forms coincide.
  Setting the flag to 0 gives the literal Eq 3.22.
* Cascade PID (Eq 3.26): the output is the PRV command in bar abs (the PRV's
  static map is unity, Eq 3.8), parallel form, derivative on the error through
  the filter N/(1 + N/s), N = 100 (thesis 3.6.2). The integral is kept as a
  term (K_i·∫e summed with the current K_i), so gain scheduling and
  controller switching do not bump the output; it starts at the reference.
  Anti-windup by conditional integration: no integration while the command
  is saturated and the error drives it further.
* Bumpless switching: entering PID/fuzzy, the integral term is set so the
  command continues from its last value; entering Default (which has no
  state), the difference decays with ``bumpless_tau`` (0.2 s).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from app.engine.constants import BAR, P_ATM
from app.engine.control.fuzzy import fuzzy_gains
from app.engine.physics.plant import stribeck_decay, stribeck_params
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
P_PDRA = 13  # PDRA on (1) / off (0)
P_TDRA = 14  # TDRA on / off
P_PDRA_THR = 15  # PDRA dead band [bar] (Table 3.7: 0.1)
P_KPP = 16  # TDRA K_pp [bar/(N·m)]
P_KII = 17  # TDRA K_ii [bar/(N·m·s)]
P_KDD = 18  # TDRA K_dd [bar·s/(N·m)]
P_N = 19  # derivative filter coefficient N [1/s]
P_KP = 20  # Cascade PID K_p a, b (20, 21) [-]
P_KI = 22  # K_i a, b (22, 23) [1/s]
P_KD = 24  # K_d a, b (24, 25) [s]
P_FKP_MIN = 26  # fuzzy regulation (Table 3.11): K_p min a, b (26, 27)
P_FKP_MAX = 28  # K_p max a, b
P_FKI_MIN = 30
P_FKI_MAX = 32
P_FKD_MIN = 34
P_FKD_MAX = 36
P_TDRA_REF = 38  # 1: [z]^T also shifts the PRV controller's reference
P_TDRA_ILIM = 39  # TDRA integral term limit [bar]
P_BUMP_TAU = 40  # Default's bumpless blend time constant [s]
NP = 48

# ------------------------------------------------------------------ state
S_MODE = 0  # 0 none, 1 CCW, 2 CW
S_CAND = 1  # candidate mode
S_TIMER = 2  # dwell timer [s]
S_PREF_A = 3  # last [P_a]^f [bar abs]
S_PREF_B = 4
S_TF = 5  # last friction estimate [N·m]
S_INIT = 6  # 1 once the PRV controllers have been initialised
S_H = 7  # controller active on the last tick
S_PC = 8  # last PDRA correction on the controlled chamber [bar]
S_ZT = 9  # last TDRA output [bar]
S_TI = 10  # TDRA integral term [bar]
S_TEP = 11  # TDRA previous torque error [N·m]
S_TDF = 12  # TDRA filtered error rate [N·m/s]
S_TMODE = 13  # mode the TDRA state belongs to
S_SEEN = 14  # time between this measurement and the previous one [s] (0: not known, one period)
S_SIDE = 16  # per-side PRV controller blocks at 16 (a) and 16 + S_SIDE_N (b)
S_SIDE_N = 10
# offsets inside a side block
Q_I = 0  # integral term [bar]
Q_EP = 1  # previous error [bar]
Q_DF = 2  # filtered error rate ė_p [bar/s]
Q_ZR = 3  # last raw command [z]^r [bar abs]
Q_BLEND = 4  # Default's bumpless offset [bar]
Q_KP = 5  # gains in use (for display)
Q_KI = 6
Q_KD = 7
NSTATE = S_SIDE + 2 * S_SIDE_N

# command vector: z_a, z_b, u_a, u_b
K_ZA, K_ZB, K_UA, K_UB = 0, 1, 2, 3

H_DEFAULT, H_PID, H_FUZZY = 1, 2, 3


def default_params(
    pw_bar: float = 3.0,
    target_nm: float = 1.2,
    controller: int = 1,
    torque_per_bar: float = 0.0,
    pdra: bool = False,
    tdra: bool = False,
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
    cp[P_PDRA] = 1.0 if pdra else 0.0
    cp[P_TDRA] = 1.0 if tdra else 0.0
    cp[P_PDRA_THR] = 0.1
    # TDRA gains (thesis 3.3.4)
    cp[P_KPP] = 0.165
    cp[P_KII] = 4.0
    cp[P_KDD] = 0.0002
    cp[P_N] = 100.0
    # Cascade PID gains (thesis 3.6.2): a, b
    cp[P_KP], cp[P_KP + 1] = 0.45, 0.55
    cp[P_KI], cp[P_KI + 1] = 2.034, 2.042
    cp[P_KD], cp[P_KD + 1] = 0.0098, 0.0107
    # Table 3.11: a, b
    cp[P_FKP_MIN], cp[P_FKP_MIN + 1] = 0.005, 0.005
    cp[P_FKP_MAX], cp[P_FKP_MAX + 1] = 0.760, 0.600
    cp[P_FKI_MIN], cp[P_FKI_MIN + 1] = 1.850, 1.750
    cp[P_FKI_MAX], cp[P_FKI_MAX + 1] = 2.030, 2.040
    cp[P_FKD_MIN], cp[P_FKD_MIN + 1] = 0.0, 0.0
    cp[P_FKD_MAX], cp[P_FKD_MAX + 1] = 0.01, 0.0108
    cp[P_TDRA_REF] = 1.0
    cp[P_TDRA_ILIM] = 2.0
    cp[P_BUMP_TAU] = 0.2
    return cp


# ------------------------------------------------------------------ blocks
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
    seen = st[S_SEEN]
    st[S_TIMER] += seen if 0.0 < seen < 0.999 * dt else dt
    if st[S_TIMER] >= need - 1e-12:
        st[S_MODE] = cand
        st[S_TIMER] = 0.0
        return cand
    return mode


@njit(cache=True, error_model="numpy")
def friction_estimate(mode: int, omega: float, pa: float, pb: float, fr: np.ndarray, j: float) -> float:
    """Friction torque estimator (thesis 3.3.2, Eq 3.20), unified sign [N·m].

    Table lookup on the controlled chamber's measured pressure (P_a for CCW,
    P_b for CW) [bar abs]; ω_fric = ω (CCW) or −ω (CW) [rad/s].
    """
    if mode == 0:
        return 0.0
    ccw = mode == 1
    p = pa if ccw else pb
    ts, tc, ws, b = stribeck_params(p, ccw, fr)
    w = omega if ccw else -omega
    return tc + (ts - tc) * stribeck_decay(abs(w) / ws, j) + b * w


@njit(cache=True, error_model="numpy")
def reference_pressure(pw: float, tf: float, target: float, tpb: float) -> float:
    """Reference generator, Eq 3.23: P^r = P_w + (T_f − |[T_i]^t|)/(A_v·r) [bar abs]."""
    return pw + (tf - target) / tpb


@njit(cache=True, error_model="numpy")
def pdra_correction(mode: int, pa: float, pb: float, pw: float, thr: float) -> float:
    """PDRA (Table 3.7): correction [P_j]^c of the controlled chamber [bar].

    The counter chamber (b for CCW, a for CW) is compared with P_w; outside
    the ±``thr`` band the controlled chamber follows its deviation, which
    keeps P_a − P_b as intended.
    """
    if mode == 0:
        return 0.0
    p_counter = pb if mode == 1 else pa
    p_dif = pw - p_counter
    if p_dif >= thr or p_dif <= -thr:
        return -p_dif
    return 0.0


@njit(cache=True, error_model="numpy")
def tdra_update(err: float, st: np.ndarray, cp: np.ndarray, dt: float) -> float:
    """TDRA (Eq 3.21) on the unified torque error ``err`` [N·m] → [z]^T [bar].

    Negative for a positive error (user pushes less than the target), see the
    module notes. Derivative through the N-filter; integral term clamped to
    ±``P_TDRA_ILIM``.
    """
    n = cp[P_N]
    df = (st[S_TDF] + n * (err - st[S_TEP])) / (1.0 + n * dt)
    st[S_TDF] = df
    st[S_TEP] = err
    lim = cp[P_TDRA_ILIM]
    ti = st[S_TI] + cp[P_KII] * err * dt
    st[S_TI] = min(max(ti, -lim), lim)
    return -(cp[P_KPP] * err + st[S_TI] + cp[P_KDD] * df)


@njit(cache=True, error_model="numpy")
def prv_controller(
    side: int, h: int, pref: float, pm: float, ff: float, st: np.ndarray, cp: np.ndarray, fz: np.ndarray, dt: float
) -> float:
    """PRV-j controller (thesis 3.4–3.7): raw command [z_j]^r [bar abs].

    Args:
        side: 0 for PRV-a, 1 for PRV-b.
        h: 1 Default (Eq 3.25), 2 Cascade PID (Eq 3.26), 3 Cascade Fuzzy
            Adaptive PID (Eq 3.26–3.30).
        pref: Reference pressure [P_j]^r [bar abs].
        pm: Measured chamber pressure [bar abs].
        ff: Feed-forward added after this block (TDRA) [bar]; used only for
            the saturation test of the anti-windup.
        st: Controller state.
        cp: Parameters.
        fz: Packed fuzzy configuration.
        dt: Control period [s].
    """
    o = S_SIDE + side * S_SIDE_N
    e = pref - pm
    n = cp[P_N]
    if st[S_INIT] == 0.0:
        st[o + Q_EP] = e
        st[o + Q_DF] = 0.0
        st[o + Q_I] = pref
        st[o + Q_ZR] = pref
    df = (st[o + Q_DF] + n * (e - st[o + Q_EP])) / (1.0 + n * dt)
    st[o + Q_DF] = df
    st[o + Q_EP] = e
    prev_h = int(st[S_H])
    if h == H_DEFAULT:
        if prev_h != H_DEFAULT and st[S_INIT] != 0.0:
            st[o + Q_BLEND] = st[o + Q_ZR] - pref
        st[o + Q_BLEND] *= math.exp(-dt / cp[P_BUMP_TAU]) if cp[P_BUMP_TAU] > 0.0 else 0.0
        zr = pref + st[o + Q_BLEND]
        st[o + Q_KP] = 0.0
        st[o + Q_KI] = 0.0
        st[o + Q_KD] = 0.0
        st[o + Q_I] = zr  # tracks, so a later switch to PID starts here
        st[o + Q_ZR] = zr
        return zr
    if h == H_PID:
        kp = cp[P_KP + side]
        ki = cp[P_KI + side]
        kd = cp[P_KD + side]
    else:
        g = np.empty(3)
        fuzzy_gains(e, df, fz, g)
        kp = (cp[P_FKP_MAX + side] - cp[P_FKP_MIN + side]) * g[0] + cp[P_FKP_MIN + side]
        ki = (cp[P_FKI_MAX + side] - cp[P_FKI_MIN + side]) * g[1] + cp[P_FKI_MIN + side]
        kd = (cp[P_FKD_MAX + side] - cp[P_FKD_MIN + side]) * g[2] + cp[P_FKD_MIN + side]
    st[o + Q_KP] = kp
    st[o + Q_KI] = ki
    st[o + Q_KD] = kd
    if prev_h != h and st[S_INIT] != 0.0:
        # bumpless: continue from the last command
        st[o + Q_I] = st[o + Q_ZR] - kp * e - kd * df
    i_new = st[o + Q_I] + ki * e * dt
    lo = cp[P_PATM]
    hi = cp[P_PATM] + cp[P_ZMAX]
    u = kp * e + i_new + kd * df + ff
    if (u > hi and e > 0.0) or (u < lo and e < 0.0):
        i_new = st[o + Q_I]
    st[o + Q_I] = i_new
    zr = kp * e + i_new + kd * df
    st[o + Q_ZR] = zr
    return zr


@njit(cache=True, error_model="numpy")
def control_step(
    meas: np.ndarray, st: np.ndarray, cp: np.ndarray, fr: np.ndarray, fz: np.ndarray, dt: float, cmd: np.ndarray
) -> None:
    """One control period: measurements in, PRV/DCV commands out.

    Args:
        meas: Measurement vector (see :mod:`app.engine.physics.sensors`).
        st: Controller state, updated.
        cp: Parameters.
        fr: Estimator friction table, packed like the plant's.
        fz: Packed fuzzy configuration (:meth:`FuzzyConfig.pack`).
        dt: Control period [s].
        cmd: Output commands z_a, z_b, u_a, u_b [V].
    """
    pa = meas[M_PA]
    pb = meas[M_PB]
    tq = meas[M_TQ]
    mode = intention_update(tq, st, cp, dt)
    tf = friction_estimate(mode, meas[M_VEL], pa, pb, fr, cp[P_FR_J])
    pw = cp[P_PW]
    pr = reference_pressure(pw, tf, cp[P_TARGET], cp[P_TPB])
    pc = pdra_correction(mode, pa, pb, pw, cp[P_PDRA_THR]) if cp[P_PDRA] > 0.0 else 0.0
    prf = pr + pc  # Eq 3.24
    # TDRA on the controlled chamber
    zt = 0.0
    err = cp[P_TARGET] - (tq if mode == 1 else -tq) if mode != 0 else 0.0
    if int(st[S_TMODE]) != mode:
        # new direction: fresh integral, no derivative kick
        st[S_TI] = 0.0
        st[S_TDF] = 0.0
        st[S_TEP] = err
        st[S_TMODE] = mode
    if mode != 0 and cp[P_TDRA] > 0.0:
        zt = tdra_update(err, st, cp, dt)
    # signal router
    pref_a = pw
    pref_b = pw
    if mode == 1:
        pref_a = prf
    elif mode == 2:
        pref_b = prf
    st[S_PREF_A] = pref_a
    st[S_PREF_B] = pref_b
    st[S_TF] = tf
    st[S_PC] = pc
    st[S_ZT] = zt
    h = int(cp[P_H])
    into_ref = cp[P_TDRA_REF] > 0.0
    zt_a = zt if mode == 1 else 0.0
    zt_b = zt if mode == 2 else 0.0
    za = _side(0, h, pref_a, pa, zt_a, into_ref, st, cp, fz, dt)
    zb = _side(1, h, pref_b, pb, zt_b, into_ref, st, cp, fz, dt)
    st[S_INIT] = 1.0
    st[S_H] = h
    cmd[K_ZA] = min(max(za, 0.0), cp[P_ZMAX])
    cmd[K_ZB] = min(max(zb, 0.0), cp[P_ZMAX])
    cmd[K_UA] = cp[P_UA_OPEN]
    cmd[K_UB] = cp[P_UB_OPEN]


@njit(cache=True, error_model="numpy")
def _side(
    side: int, h: int, pref: float, pm: float, zt: float, into_ref: bool,
    st: np.ndarray, cp: np.ndarray, fz: np.ndarray, dt: float,
) -> float:
    """PRV controller plus TDRA for one side → z_j [V] (Eq 3.22), unclamped."""
    if h == H_DEFAULT:
        # Default: [z]^r = [P]^r; the TDRA term enters once either way
        zr = prv_controller(side, h, pref + zt, pm, 0.0, st, cp, fz, dt)
        return zr - cp[P_PATM]
    ref = pref + zt if into_ref else pref
    zr = prv_controller(side, h, ref, pm, zt, st, cp, fz, dt)
    return zr + zt - cp[P_PATM]
