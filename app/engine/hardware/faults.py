"""Fault injection around any backend (issue 7's fault-injection tests, and drills on the simulator).

:class:`FaultyRig` wraps a backend and, from a given rig time on, corrupts
what it reads or what it does with the commands, the way real faults do:

``nan``            a channel reads NaN (ADC or driver failure)
``dropout``        a channel reads what 0 V means (broken wire): 0 bar abs
                   on the 0–5 V absolute pressure sensors, zero torque
``stuck_sensor``   a channel repeats the value it had
``encoder_glitch`` the angle loses ``counts`` encoder counts (noise on the
                   quadrature lines), and keeps the offset
``stuck_prv``      PRV-``side`` stays at ``value`` [V] whatever it is told
                   (``write`` still returns the command: the rig does not know)
``supply_loss``    the supply falls to ``value`` [bar abs] (needs ``set_supply``)
``link_lost``      ``read`` raises :class:`ConnectionError`
``stall``          one ``read`` blocks for ``value`` [s] (a hung DAQ call)

The wrapper changes nothing until a fault's time comes; it is a backend
like any other, so the engine, the safety supervisor and the log see
exactly what they would on a rig with that fault.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

from app.engine.hardware.base import Command, HardwareInterface, Measurement

FAULT_KINDS = ("nan", "dropout", "stuck_sensor", "encoder_glitch", "stuck_prv", "supply_loss", "link_lost", "stall")
CHANNELS = ("p_a", "p_b", "p_s", "theta", "omega", "torque")
_ZERO_VOLT = {"p_a": 0.0, "p_b": 0.0, "p_s": 0.0, "theta": 0.0, "omega": 0.0, "torque": 0.0}


@dataclass
class InjectedFault:
    """One scheduled fault.

    Attributes:
        kind: One of :data:`FAULT_KINDS`.
        at: Rig time it starts [s].
        channel: Measurement channel (sensor faults).
        side: ``"a"`` or ``"b"`` (``stuck_prv``).
        value: Stuck PRV output [V], supply [bar abs] or stall length [s].
        counts: Encoder counts lost (``encoder_glitch``).
    """

    kind: str
    at: float
    channel: str = "p_a"
    side: str = "a"
    value: float = 0.0
    counts: int = 400
    fired: bool = False
    held: float = math.nan

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"kind = {self.kind!r}: must be one of {', '.join(FAULT_KINDS)}")
        if self.channel not in CHANNELS:
            raise ValueError(f"channel = {self.channel!r}: must be one of {', '.join(CHANNELS)}")
        if self.side not in ("a", "b"):
            raise ValueError(f"side = {self.side!r}: must be 'a' or 'b'")


class FaultyRig(HardwareInterface):
    """A backend with faults scheduled on it.

    Args:
        inner: The real backend (usually :class:`~app.engine.hardware.sim.SimulatedRig`).
        faults: Faults to inject.
    """

    def __init__(self, inner: HardwareInterface, faults: list[InjectedFault] | None = None) -> None:
        self.inner = inner
        self.faults = list(faults or [])
        self.name = f"{inner.name}+faults"
        self.rig = inner.rig
        self.paced_by_hardware = inner.paced_by_hardware
        self._t = -math.inf

    def __getattr__(self, name: str) -> Any:  # set_program, set_disturbance, period … of the inner rig
        return getattr(self.inner, name)

    def inject(self, kind: str, at: float, **kw: Any) -> InjectedFault:
        """Schedule a fault (see :class:`InjectedFault`)."""
        f = InjectedFault(kind, at, **kw)
        self.faults.append(f)
        return f

    def activate(self) -> None:
        """Activate the inner backend."""
        self.inner.activate()

    def deactivate(self) -> None:
        """Deactivate the inner backend."""
        self.inner.deactivate()

    def safe_command(self) -> Command:
        """The inner backend's safe command."""
        return self.inner.safe_command()

    def _active(self) -> list[InjectedFault]:
        return [f for f in self.faults if self._t >= f.at]

    def read(self) -> Measurement:
        """The inner reading, corrupted by the faults whose time has come."""
        for f in self._active():
            if f.kind == "link_lost":
                raise ConnectionError("the DAQ link is lost (injected)")
            if f.kind == "stall" and not f.fired:
                f.fired = True
                time.sleep(f.value)
            if f.kind == "supply_loss" and not f.fired:
                f.fired = True
                self.inner.set_supply(f.value)  # type: ignore[attr-defined]
        m = self.inner.read()
        self._t = m.t
        vals = {c: getattr(m, c) for c in CHANNELS}
        for f in self._active():
            if f.kind == "nan":
                vals[f.channel] = math.nan
            elif f.kind == "dropout":
                vals[f.channel] = _ZERO_VOLT[f.channel]
            elif f.kind == "stuck_sensor":
                if math.isnan(f.held):
                    f.held = vals[f.channel]
                vals[f.channel] = f.held
            elif f.kind == "encoder_glitch":
                vals["theta"] -= f.counts * 2.0 * math.pi / 4096
        return Measurement(m.t, **vals)

    def write(self, command: Command) -> Command:
        """Pass the command on (a stuck PRV ignores its part); return what the rig was told."""
        stuck = {f"z_{f.side}": f.value for f in self._active() if f.kind == "stuck_prv"}
        applied = self.inner.write(replace(command, **stuck) if stuck else command)
        # the rig believes it applied the command; only the valve disobeys
        told = command.clipped()
        return replace(applied, **{k: getattr(told, k) for k in stuck})
