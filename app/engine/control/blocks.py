"""The pipeline's blocks as small objects stepped with an explicit ``dt``.

Each wraps the same compiled function the pipeline runs, with its own state,
so it can be unit-tested (and reused, e.g. by identification procedures) on
its own. Units: torque [N·m], pressure [bar abs], speed [rad/s], time [s].
"""

from __future__ import annotations

import numpy as np

from app.engine.control import pipeline as cpl
from app.engine.control.config import ControllerConfig, ControllerName, controller_h
from app.engine.params import ParameterError, RotaryFriction
from app.engine.physics.plant import pack_friction


class IntentionDetector:
    """Three-state user intention detector (thesis Fig 3.29–3.30) with
    hysteresis and dwell (see :mod:`pipeline`).

    Args:
        threshold: Entry threshold [N·m] (thesis: 0.25).
        release: Release threshold [N·m].
        dwell_on: Time beyond the threshold before a direction is entered [s].
        dwell_off: Time inside the release band before it is left [s].
    """

    def __init__(self, threshold: float = 0.25, release: float = 0.10, dwell_on: float = 0.010,
                 dwell_off: float = 0.030) -> None:
        if not 0.0 <= release <= threshold:
            raise ParameterError(f"release = {release} N·m must lie in [0, threshold = {threshold}] N·m")
        self.cp = cpl.default_params()
        self.cp[cpl.P_THR], self.cp[cpl.P_REL] = threshold, release
        self.cp[cpl.P_DWELL_ON], self.cp[cpl.P_DWELL_OFF] = dwell_on, dwell_off
        self.state = np.zeros(cpl.NSTATE)

    def step(self, torque: float, dt: float) -> int:
        """Mode after this sample: 0 none, 1 CCW, 2 CW."""
        return int(cpl.intention_update(float(torque), self.state, self.cp, dt))

    @property
    def k_ccw(self) -> int:
        """k_CCW of thesis Fig 3.30."""
        return int(self.state[cpl.S_MODE] == 1)

    @property
    def k_cw(self) -> int:
        """k_CW of thesis Fig 3.30."""
        return int(self.state[cpl.S_MODE] == 2)


class FrictionEstimator:
    """Friction torque estimator (thesis 3.3.2, Eq 3.20), unified sign.

    Args:
        friction: Table 4.2 (default) or an identified table.
    """

    def __init__(self, friction: RotaryFriction | None = None) -> None:
        self.friction = friction or RotaryFriction()
        self.fr = pack_friction(self.friction)

    def __call__(self, mode: int, omega: float, p_a: float, p_b: float) -> float:
        """Friction magnitude resisting the user's direction [N·m]."""
        return float(cpl.friction_estimate(mode, omega, p_a, p_b, self.fr, self.friction.shape_j))


class PDRA:
    """Pressure disturbance rejection (thesis 3.3.3, Table 3.7).

    Args:
        pw_bar: Working pressure [bar abs].
        threshold: Dead band on the counter chamber's deviation [bar].
    """

    def __init__(self, pw_bar: float = 3.0, threshold: float = 0.1) -> None:
        self.pw = pw_bar
        self.threshold = threshold

    def __call__(self, mode: int, p_a: float, p_b: float) -> float:
        """Correction [P_j]^c of the controlled chamber's reference [bar]."""
        return float(cpl.pdra_correction(mode, p_a, p_b, self.pw, self.threshold))


class TDRA:
    """Torque disturbance rejection (thesis 3.3.4, Eq 3.21), unified sign.

    Args:
        kpp: Proportional gain [bar/(N·m)] (thesis: 0.165).
        kii: Integral gain [bar/(N·m·s)] (thesis: 4).
        kdd: Derivative gain [bar·s/(N·m)] (thesis: 0.0002).
        n: Derivative filter coefficient [1/s].
    """

    def __init__(self, kpp: float = 0.165, kii: float = 4.0, kdd: float = 0.0002, n: float = 100.0) -> None:
        self.cp = cpl.default_params()
        self.cp[cpl.P_KPP], self.cp[cpl.P_KII], self.cp[cpl.P_KDD], self.cp[cpl.P_N] = kpp, kii, kdd, n
        self.state = np.zeros(cpl.NSTATE)

    def reset(self, err: float = 0.0) -> None:
        """Clear the integral and derivative state (direction change)."""
        self.state[cpl.S_TI] = 0.0
        self.state[cpl.S_TDF] = 0.0
        self.state[cpl.S_TEP] = err

    def step(self, err: float, dt: float) -> float:
        """[z]^T [bar] for the unified torque error ``err`` = |target| − s·T_i [N·m]."""
        return float(cpl.tdra_update(float(err), self.state, self.cp, dt))


class PRVController:
    """PRV-a or PRV-b controller switched by h (thesis Fig 3.36).

    Args:
        side: ``"a"`` or ``"b"`` (the gains of Eq 3.26 and Table 3.11 differ).
        controller: ``"default"``, ``"pid"`` or ``"fuzzy"``.
        config: Source of gains, fuzzy configuration and P_atm.
    """

    def __init__(self, side: str = "a", controller: ControllerName = "pid",
                 config: ControllerConfig | None = None) -> None:
        if side not in ("a", "b"):
            raise ParameterError(f"side = {side!r} must be 'a' or 'b'")
        self.side = 0 if side == "a" else 1
        self.config = config or ControllerConfig()
        self.cp, _, self.fz = self.config.pack()
        self.state = np.zeros(cpl.NSTATE)
        self.h = controller_h(controller)
        # compile (or load) the kernel's entry point here, on a scratch state: the first step runs in
        # the paced loop, and compiling there on a fresh install stalled it past its 1 s watchdog
        cpl.prv_controller(self.side, self.h, 0.0, 0.0, 0.0, np.zeros(cpl.NSTATE), self.cp, self.fz, 0.005)

    def switch(self, controller: ControllerName) -> None:
        """Change controller; the command continues without a bump."""
        self.h = controller_h(controller)

    def step(self, p_ref: float, p_meas: float, dt: float) -> float:
        """Raw command [z_j]^r [bar abs] (subtract P_atm for the valve's volts)."""
        z = cpl.prv_controller(self.side, self.h, float(p_ref), float(p_meas), 0.0, self.state, self.cp,
                               self.fz, dt)
        self.state[cpl.S_INIT] = 1.0
        self.state[cpl.S_H] = self.h
        return float(z)

    @property
    def gains(self) -> tuple[float, float, float]:
        """(K_p, K_i, K_d) used on the last step."""
        o = cpl.S_SIDE + self.side * cpl.S_SIDE_N
        return float(self.state[o + cpl.Q_KP]), float(self.state[o + cpl.Q_KI]), float(self.state[o + cpl.Q_KD])
