"""Backend by configuration: one place turns a :class:`HardwareConfig` into the station's backend factory.

Nothing else in the station, the controllers or the procedures knows which
backend it drives (issue 8 item 6): they see the ``HardwareInterface`` alone.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from app.engine.hardware.base import HardwareInterface
from app.engine.hardware.config import HardwareConfig

BackendFactory = Callable[[Any, float, Any], HardwareInterface]
"""(clock, period [s], rig) → an inactive backend."""


def make_factory(config: HardwareConfig) -> BackendFactory | None:
    """The backend factory for ``config`` (None: the station's simulator)."""
    if config.backend == "sim":
        return None

    def build(clock: Any, period: float, rig: Any) -> HardwareInterface:
        if config.backend == "modbus":
            from app.engine.hardware.modbus import ModbusRig

            return ModbusRig(config, clock, period, rig.kind)
        if config.backend == "quanser":
            from app.engine.hardware.quanser import QuanserRig

            return QuanserRig(config, clock, period, rig.kind)
        from app.engine.hardware.replay import ReplayRig

        assert config.replay is not None  # the config's validator requires it
        rep = ReplayRig(config.replay.log, clock, config.replay.loop)
        if rep.rig != rig.kind:
            raise ValueError(f"the replayed log is from the {rep.rig} rig, not the {rig.kind} rig")
        return rep

    return build
