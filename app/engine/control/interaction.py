"""Controller objects for the engine loop, wrapping the compiled pipeline."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from app.engine.control import pipeline as cpl
from app.engine.control.config import ControllerConfig, ControllerName
from app.engine.hardware.base import Command, Measurement
from app.engine.physics import sensors as sn

__all__ = ["ControllerName", "HoldController", "InteractionController"]

MAX_STEP_PERIODS = 10.0
"""Longest interval a step integrates over, in periods (a longer gap counts as this)."""


class InteractionController:
    """Interaction-torque control of the forearm axis (thesis Fig 3.28).

    Args:
        config: The controller; a default :class:`ControllerConfig` if omitted.
        **overrides: Fields of :class:`ControllerConfig` (``controller``,
            ``target_nm``, ``pw_bar``, ``pdra``, ``tdra`` …) replacing those of
            ``config``.
    """

    def __init__(self, config: ControllerConfig | None = None, **overrides: Any) -> None:
        config = config or ControllerConfig()
        self.config = dataclasses.replace(config, **overrides) if overrides else config
        self.cp, self.fr, self.fz = self.config.pack()
        self.state = np.zeros(cpl.NSTATE)
        self._meas = np.zeros(sn.NM)
        self._cmd = np.zeros(4)
        self._t_prev = math.nan

    def reset(self) -> None:
        """Forget the detector and controller state."""
        self.state[:] = 0.0
        self._t_prev = math.nan

    def reconfigure(self, **changes: Any) -> None:
        """Change controller, target, P_w or PDRA/TDRA during a run, bumplessly.

        The new configuration is validated before anything changes; the
        compiled state is kept, so the PRV controllers continue from their
        last command (see :mod:`pipeline`).

        Raises:
            ParameterError: On invalid values (nothing is changed).
        """
        new = dataclasses.replace(self.config, **changes)
        cp, fr, fz = new.pack()
        self.config, self.cp, self.fr, self.fz = new, cp, fr, fz

    @property
    def mode(self) -> int:
        """Intention: 0 none, 1 CCW, 2 CW."""
        return int(self.state[cpl.S_MODE])

    def internals(self) -> dict[str, float]:
        """Reference pressures [bar abs], friction estimate [N·m], PDRA/TDRA
        outputs [bar] and the gains in use (dashboard and logs)."""
        st = self.state
        a, b = cpl.S_SIDE, cpl.S_SIDE + cpl.S_SIDE_N
        return {
            "mode": float(st[cpl.S_MODE]), "p_ref_a": float(st[cpl.S_PREF_A]), "p_ref_b": float(st[cpl.S_PREF_B]),
            "friction_nm": float(st[cpl.S_TF]), "pdra_bar": float(st[cpl.S_PC]), "tdra_bar": float(st[cpl.S_ZT]),
            "kp_a": float(st[a + cpl.Q_KP]), "ki_a": float(st[a + cpl.Q_KI]), "kd_a": float(st[a + cpl.Q_KD]),
            "kp_b": float(st[b + cpl.Q_KP]), "ki_b": float(st[b + cpl.Q_KI]), "kd_b": float(st[b + cpl.Q_KD]),
        }

    def step(self, meas: Measurement, dt: float) -> Command:
        """Commands for this control period.

        Args:
            meas: The sample, stamped with its time ``meas.t`` [s].
            dt: The control period [s]. A sample more than a quarter period
                early or late is stepped over the time since the previous
                one instead (at most :data:`MAX_STEP_PERIODS` periods).
        """
        m = self._meas
        m[sn.M_PA], m[sn.M_PB], m[sn.M_PS] = meas.p_a, meas.p_b, meas.p_s
        m[sn.M_POS], m[sn.M_VEL], m[sn.M_TQ] = meas.theta, meas.omega, meas.torque
        gap = meas.t - self._t_prev
        seen = gap if gap > 0.0 else 0.0  # NaN (first sample) compares False: 0
        # how much time this sample stands for: the detector's dwell counts it, at most one period (see pipeline)
        self.state[cpl.S_SEEN] = min(seen, dt)
        # a sample more than a quarter period late (a late tick) or early (the catch-up after it): the
        # integrators and derivative filters run over the time that passed. Over the period, a 65 ms
        # stall's pressure change was differentiated as if it had happened in 5 ms (the PRV command
        # jumped 1.8-2 times as far; tests/test_engine.py). Past 10 periods the
        # error read now says little about the whole gap, so an integrator is charged for 10 at most.
        h = min(seen, MAX_STEP_PERIODS * dt) if seen > 0.0 and abs(seen - dt) > 0.25 * dt else dt
        self._t_prev = meas.t
        cpl.control_step(m, self.state, self.cp, self.fr, self.fz, h, self._cmd)
        c = self._cmd
        return Command(float(c[0]), float(c[1]), float(c[2]), float(c[3]))


class HoldController:
    """Holds one command (commissioning, tests, identification steps)."""

    def __init__(self, command: Command) -> None:
        self.command = command

    def step(self, meas: Measurement, dt: float) -> Command:
        """The held command."""
        return self.command
