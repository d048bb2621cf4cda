"""The station's single engine: backend + controller + paced loop, in one object
the server owns. The full state machine arrives with issue 5; this is the
always-on simulated workout the dashboard shows."""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from app.engine.control.interaction import InteractionController
from app.engine.hardware.sim import SimulatedRig
from app.engine.human import isotonic
from app.engine.loop import Engine, WallClock


class Station:
    """Owns one engine thread on the configured backend (simulator by default).

    Args:
        rate_hz: Control rate [Hz].
        pw_bar: Working pressure [bar abs].
        target_nm: Target interaction torque [N·m].
    """

    def __init__(self, rate_hz: float = 200.0, pw_bar: float = 3.0, target_nm: float = 1.2) -> None:
        self.clock = WallClock()
        self.backend = SimulatedRig(self.clock, period=1.0 / rate_hz, pw_bar=pw_bar)
        self.backend.set_program(isotonic(+1, repetitions=1000))  # ≈ 2.5 h of exercise
        self.controller = InteractionController(pw_bar=pw_bar, target_nm=target_nm)
        self.engine = Engine(self.backend, self.controller, self.clock, rate_hz)

    def start(self) -> None:
        """Compile the kernels, activate the backend and start the paced loop.

        The first read/step of a fresh install compiles the numba kernels
        (seconds); doing it here keeps that stall out of the paced loop's
        jitter and overrun counts.
        """
        self.controller.step(self.backend.read(), self.engine.period)
        self.controller.reset()
        self.backend.activate()
        self.engine.start()

    def stop(self) -> None:
        """Stop the loop and leave the rig in its safe state."""
        self.engine.stop()
        self.backend.deactivate()

    def health(self) -> dict[str, Any]:
        """Loop health for ``/api/health``."""
        st = self.engine.stats()
        return {"state": "running" if self.engine.running else "idle", "backend": self.backend.name, **asdict(st)}
