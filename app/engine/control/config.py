"""One frozen description of the interaction controller, packed for the
compiled pipeline. The batch simulator, the engine loop and the API all build
their controllers from it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from app.engine.constants import BAR, P_ATM
from app.engine.control import pipeline as cpl
from app.engine.control.fuzzy import FuzzyConfig
from app.engine.params import ParameterError, RotaryFriction, VaneCylinder, check_range, check_working_pressure
from app.engine.physics.plant import pack_friction

ControllerName = Literal["default", "pid", "fuzzy"]
CONTROLLER_H: dict[str, int] = {"default": cpl.H_DEFAULT, "pid": cpl.H_PID, "fuzzy": cpl.H_FUZZY}


TABLE_4_3_GAINS: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.715, 7.25, 0.016),
                                                                                (0.715, 7.0, 0.012))
"""Thesis Table 4.3: PID-a / PID-b gains of the closed-loop friction validation (4.2.1)."""


def controller_h(name: str) -> int:
    """Switch value h of thesis Fig 3.36 for a controller name.

    Raises:
        ParameterError: For an unknown name.
    """
    if name not in CONTROLLER_H:
        raise ParameterError(f"controller = {name!r} must be one of {', '.join(CONTROLLER_H)}")
    return CONTROLLER_H[name]


@dataclass(frozen=True)
class ControllerConfig:
    """Interaction-torque controller of thesis Fig 3.28.

    Attributes:
        controller: PRV controller h: ``"default"`` (Eq 3.25), ``"pid"``
            (Cascade PID, Eq 3.26) or ``"fuzzy"`` (Cascade Fuzzy Adaptive PID).
        target_nm: Target interaction torque [N·m]; its magnitude is tracked
            in whichever direction the user moves.
        pw_bar: Working pressure P_w [bar abs], 1–8 (thesis GUI rule).
        pdra: Pressure disturbance rejection (thesis 3.3.3) on.
        tdra: Torque disturbance rejection (thesis 3.3.4) on.
        tdra_into_reference: TDRA also shifts the PRV controller's reference
            (see :mod:`pipeline`); ``False`` is the literal Eq 3.22.
        fuzzy: Membership functions and defuzzifier of the scheduler.
        friction: Friction table of the estimator (Table 4.2 by default).
        vane: Cylinder geometry (A_v·r).
        pid_gains: Cascade PID gains ((K_p, K_i, K_d) of PRV-a, of PRV-b)
            [-, 1/s, s]; ``None`` keeps Eq 3.26's. Table 4.3's trial-and-error
            set is :data:`TABLE_4_3_GAINS`; an autotuned set comes from
            :mod:`app.engine.ident.pid_tune`.
        p_atm_bar: The atmosphere [bar abs] the PRVs regulate above (P = z +
            P_atm, Eq 3.7): the lab's, from the hardware configuration.
    """

    controller: ControllerName = "fuzzy"
    target_nm: float = 1.2
    pw_bar: float = 3.0
    pdra: bool = False
    tdra: bool = False
    tdra_into_reference: bool = True
    fuzzy: FuzzyConfig = field(default_factory=FuzzyConfig)
    friction: RotaryFriction = field(default_factory=RotaryFriction)
    vane: VaneCylinder = field(default_factory=VaneCylinder)
    pid_gains: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    p_atm_bar: float = P_ATM / BAR

    def __post_init__(self) -> None:
        check_working_pressure(self.pw_bar)
        check_range("p_atm_bar", self.p_atm_bar, 0.5, 1.2, unit="bar abs")  # as PlantParams.p_atm allows
        if self.pid_gains is not None:
            if len(self.pid_gains) != 2 or any(len(g) != 3 for g in self.pid_gains):
                raise ParameterError("pid_gains must be ((K_p, K_i, K_d) of PRV-a, (K_p, K_i, K_d) of PRV-b)")
            for side, g in zip("ab", self.pid_gains, strict=True):
                for name, v in zip(("K_p", "K_i", "K_d"), g, strict=True):
                    check_range(f"pid_gains {name},{side}", v, 0.0, 100.0)
        check_range("target_nm", self.target_nm, -5.0, 5.0, unit="N·m")
        controller_h(self.controller)

    @property
    def h(self) -> int:
        """Switch value h of thesis Fig 3.36."""
        return CONTROLLER_H[self.controller]

    def pack(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(parameter vector, friction table, fuzzy table) for the pipeline."""
        cp = cpl.default_params(self.pw_bar, self.target_nm, self.h, self.vane.torque_per_pa * BAR,
                                self.pdra, self.tdra)
        cp[cpl.P_FR_J] = self.friction.shape_j
        cp[cpl.P_PATM] = self.p_atm_bar
        cp[cpl.P_TDRA_REF] = 1.0 if self.tdra_into_reference else 0.0
        if self.pid_gains is not None:
            for side, (kp, ki, kd) in enumerate(self.pid_gains):
                cp[cpl.P_KP + side], cp[cpl.P_KI + side], cp[cpl.P_KD + side] = kp, ki, kd
        return cp, pack_friction(self.friction), self.fuzzy.pack()
