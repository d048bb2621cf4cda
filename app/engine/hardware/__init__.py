"""Hardware backends behind one small interface (ros2_control style)."""

from app.engine.hardware.base import Command, HardwareInterface, Measurement

__all__ = ["Command", "HardwareInterface", "Measurement"]
