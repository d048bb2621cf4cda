"""The one interface every backend implements, and its two message types.

Per control period the engine calls ``read()`` once and ``write()`` once;
``write`` returns the command actually applied after the backend's own limits
(the value that goes into the run log). ``safe_command()`` is the documented
safe state: both PRVs to 0 V (atmosphere) with both DCVs routing the PRVs to
the chambers, so the chambers vent through the PRV exhausts at equal
pressure — no net torque on the arm, then no pressure at all.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Measurement:
    """One sample of every sensor.

    Attributes:
        t: Sample time on the engine clock [s].
        p_a: Chamber a pressure [bar abs].
        p_b: Chamber b pressure [bar abs].
        p_s: Supply pressure [bar abs].
        theta: Vane angle [rad], CCW positive, 0 = neutral (linear rig: x [m]).
        omega: Speed [rad/s] (linear rig: [m/s]).
        torque: Interaction torque [N·m] (linear rig: force [N]).
    """

    t: float
    p_a: float
    p_b: float
    p_s: float
    theta: float
    omega: float
    torque: float

    def is_finite(self) -> bool:
        """Whether every channel is a finite number."""
        vals = (self.t, self.p_a, self.p_b, self.p_s, self.theta, self.omega, self.torque)
        return all(math.isfinite(v) for v in vals)


@dataclass(frozen=True, slots=True)
class Command:
    """Valve commands.

    Attributes:
        z_a: PRV-a command [V] (0–10 V ↔ 0–10 bar gauge).
        z_b: PRV-b command [V].
        u_a: DCV-a command [V] (< 5 V fills chamber a, > 5 V exhausts it).
        u_b: DCV-b command [V] (> 5 V fills chamber b, < 5 V exhausts it).
    """

    z_a: float
    z_b: float
    u_a: float
    u_b: float

    def clipped(self, z_max: float = 10.0) -> Command:
        """The command within the valves' input ranges (NaN → safe value)."""
        za, zb, ua, ub = self.z_a, self.z_b, self.u_a, self.u_b
        if 0.0 <= za <= z_max and 0.0 <= zb <= z_max and 0.0 <= ua <= 10.0 and 0.0 <= ub <= 10.0:
            return self  # the common case on the hot path: nothing to clip (NaN fails every comparison)
        isf = math.isfinite
        return Command(min(max(za, 0.0), z_max) if isf(za) else 0.0, min(max(zb, 0.0), z_max) if isf(zb) else 0.0,
                       min(max(ua, 0.0), 10.0) if isf(ua) else 0.0, min(max(ub, 0.0), 10.0) if isf(ub) else 10.0)


SAFE_COMMAND = Command(0.0, 0.0, 0.0, 10.0)
"""Both PRVs vent, both DCVs route PRV ↔ chamber: equal, falling pressures."""


RIG_KINDS = ("rotary", "linear", "cpr")
"""The rigs the station drives (the CPR set-up is the linear cylinder held extended)."""


class HardwareInterface(abc.ABC):
    """A rig the engine can drive: the simulator, a DAQ card, a fieldbus."""

    name: str = "abstract"
    rig: str = "rotary"
    responds_to_commands: bool = True
    """False where the measurements do not answer the commands (a replayed log)."""
    paced_by_hardware: bool = False
    """True where :meth:`read` blocks until the device's own clock takes the next
    sample (a hardware-timed DAQ task): the engine then does not sleep, the
    device sets the period."""

    @abc.abstractmethod
    def activate(self) -> None:
        """Open the link and put the outputs in the safe state."""

    @abc.abstractmethod
    def deactivate(self) -> None:
        """Put the outputs in the safe state and close the link."""

    @abc.abstractmethod
    def read(self) -> Measurement:
        """Sample every sensor once (called once per control period)."""

    @abc.abstractmethod
    def write(self, command: Command) -> Command:
        """Apply ``command``; return what was applied after the limits."""

    def safe_command(self) -> Command:
        """The backend's safe outputs (default: :data:`SAFE_COMMAND`)."""
        return SAFE_COMMAND
