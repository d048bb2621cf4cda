"""Controller objects for the engine loop, wrapping the compiled pipeline."""

from __future__ import annotations

from typing import Literal

import numpy as np

from app.engine.constants import BAR
from app.engine.control import pipeline as cpl
from app.engine.hardware.base import Command, Measurement
from app.engine.params import ParameterError, RotaryFriction, VaneCylinder, check_range, check_working_pressure
from app.engine.physics import sensors as sn
from app.engine.physics.plant import pack_friction

ControllerName = Literal["default", "pid", "fuzzy"]
_H = {"default": 1, "pid": 2, "fuzzy": 3}


class InteractionController:
    """Interaction-torque control of the forearm axis (thesis Fig 3.28).

    Args:
        pw_bar: Working pressure P_w [bar abs], 1–8 (thesis GUI rule).
        target_nm: Target interaction torque [N·m]; its magnitude is tracked
            in whichever direction the user moves.
        controller: PRV controller (``"default"`` implemented here; the
            cascade PID and fuzzy controllers arrive with issue 3).
        friction: Friction table used by the estimator (Table 4.2 by default).
        vane: Cylinder geometry (A_v·r).
    """

    def __init__(
        self,
        pw_bar: float = 3.0,
        target_nm: float = 1.2,
        controller: ControllerName = "default",
        friction: RotaryFriction | None = None,
        vane: VaneCylinder | None = None,
    ) -> None:
        check_working_pressure(pw_bar)
        check_range("target_nm", target_nm, -5.0, 5.0, unit="N·m")
        if controller not in _H:
            raise ParameterError(f"controller = {controller!r} must be one of {', '.join(_H)}")
        if controller != "default":
            raise ParameterError(f"controller {controller!r} is not available yet (issue 3)")
        vane = vane or VaneCylinder()
        fr = friction or RotaryFriction()
        self.fr = pack_friction(fr)
        self.cp = cpl.default_params(pw_bar, target_nm, _H[controller], vane.torque_per_pa * BAR)
        self.cp[cpl.P_FR_J] = fr.shape_j
        self.state = np.zeros(cpl.NSTATE)
        self._meas = np.zeros(sn.NM)
        self._cmd = np.zeros(4)

    def reset(self) -> None:
        """Forget the detector and controller state (bumpless restart)."""
        self.state[:] = 0.0

    @property
    def mode(self) -> int:
        """Intention: 0 none, 1 CCW, 2 CW."""
        return int(self.state[cpl.S_MODE])

    def step(self, meas: Measurement, dt: float) -> Command:
        """Commands for this control period."""
        m = self._meas
        m[sn.M_PA], m[sn.M_PB], m[sn.M_PS] = meas.p_a, meas.p_b, meas.p_s
        m[sn.M_POS], m[sn.M_VEL], m[sn.M_TQ] = meas.theta, meas.omega, meas.torque
        cpl.control_step(m, self.state, self.cp, self.fr, dt, self._cmd)
        c = self._cmd
        return Command(float(c[0]), float(c[1]), float(c[2]), float(c[3]))


class HoldController:
    """Holds one command (commissioning, tests, identification steps)."""

    def __init__(self, command: Command) -> None:
        self.command = command

    def step(self, meas: Measurement, dt: float) -> Command:
        """The held command."""
        return self.command
