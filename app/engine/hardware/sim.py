"""The simulated rig as a hardware backend (the embedded default).

The plant advances in *clock* time: ``read()`` first integrates from the last
read to ``clock.now()`` holding the last written command, then samples the
sensors. With a simulated clock this runs as fast as the CPU allows; with the
wall clock it is paced like the real rig — no code change either way.
"""

from __future__ import annotations

from typing import Protocol

from app.engine.hardware.base import Command, HardwareInterface, Measurement
from app.engine.human import HumanProgram
from app.engine.params import PlantParams
from app.engine.physics import sensors as sn
from app.engine.sim import Simulator

# read() unpacks the measurement vector in this order
assert (sn.M_PA, sn.M_PB, sn.M_PS, sn.M_POS, sn.M_VEL, sn.M_TQ, sn.NM) == (0, 1, 2, 3, 4, 5, 6)


class ClockLike(Protocol):
    """Anything that tells the time [s]."""

    def now(self) -> float:
        """Current time [s]."""
        ...


class SimulatedRig(HardwareInterface):
    """Backend driving :class:`~app.engine.sim.Simulator`.

    Args:
        clock: The engine's clock.
        params: Plant parameters.
        seed: Sensor-noise seed.
        period: Nominal sampling period [s] (speed estimator).
        pw_bar: Pressure both sides start at [bar abs] (``None``: atmosphere).
    """

    name = "sim"

    def __init__(
        self,
        clock: ClockLike,
        params: PlantParams | None = None,
        seed: int = 0,
        period: float = 0.005,
        pw_bar: float | None = None,
    ) -> None:
        self.clock = clock
        self.params = params or PlantParams()
        self.rig = self.params.rig
        self.period = period
        self.sim = Simulator(self.params, seed=seed)
        if pw_bar is not None:
            from app.engine.physics.plant import initial_state

            self.sim.x[:] = initial_state(self.params, 0.0, pw_bar, pw_bar)
        self._t0 = 0.0
        self._read_before = False
        self.active = False
        self.last_applied = self.safe_command()
        self._held: Command | None = None  # what the plant's command vector was last set to by write()

    def activate(self) -> None:
        """Start the plant at the current clock time in the safe state."""
        self._t0 = self.clock.now() - self.sim.t
        self.write(self.safe_command())
        self.active = True

    def deactivate(self) -> None:
        """Leave the plant venting."""
        self.write(self.safe_command())
        self.active = False

    def set_program(self, program: HumanProgram) -> None:
        """What the simulated user does, in plant time from now on."""
        self.sim.set_program(program)

    def set_disturbance(self, dp_a_bar: float = 0.0, dp_b_bar: float = 0.0) -> None:
        """PRV-exit pressure disturbances [bar]."""
        self.sim.set_disturbance(dp_a_bar, dp_b_bar)

    def set_supply(self, p_supply_bar: float) -> None:
        """Supply pressure from now on [bar abs] (fault injection: a lost or failing supply).

        Raises:
            ParameterError: ``p_supply_bar`` is not above atmospheric or beyond 12 bar.
        """
        from dataclasses import replace

        from app.engine.physics import plant as pl

        params = replace(self.params, supply=replace(self.params.supply, p_supply_bar=p_supply_bar))
        self.params = params
        self.sim.params = params
        self.sim.kernel = pl.build_kernel(params)

    def read(self) -> Measurement:
        """Integrate up to now, then sample.

        Each read after the first advances the plant by at least one of its
        steps: the plant moves in whole steps (0.5 ms), and a late tick
        followed at once by an on-time one (the paced loop does not burst,
        but a tick late by most of a period leaves the next one less than
        half a step later) would otherwise sample the same instant twice —
        a run log whose time does not increase, which the diagnosis refuses.
        """
        t = self.clock.now() - self._t0
        if self._read_before:
            t = max(t, self.sim.t + self.sim.kernel.h)
        self._read_before = True
        # one conversion of the whole vector (in the order of the Measurement's fields) rather than
        # six element reads: the per-period path, where Python's overhead costs as much as the physics
        pa, pb, ps, pos, vel, tq = self.sim.advance_and_measure(t, self.period).tolist()
        return Measurement(self.sim.t, pa, pb, ps, pos, vel, tq)

    def write(self, command: Command) -> Command:
        """Clip to the valves' input ranges and hold."""
        applied = command.clipped(self.params.prv.z_max_v)
        if applied is not self._held:  # the same (frozen) command again: the plant holds it already
            self.sim.set_command(applied.z_a, applied.z_b, applied.u_a, applied.u_b)
            self._held = applied
        self.last_applied = applied
        return applied
