"""A recorded run log played back as if it were the rig (demos, training, the gap diagnosis).

``read()`` returns the logged sample at the clock's time since activation
(paced or simulated clock alike), so live plots, the dashboard and the
station's state machine behave as with a rig. The log does not react to
commands: ``write()`` clips and reports what would have been applied, and
:attr:`ReplayRig.logged_command` says what the recorded controller sent then,
so a controller can be compared against the one in the log. Looping plays
the log forwards, then backwards (speed negated), and so on: the signals stay
continuous at the turns, where a jump back to the start would look like a
sensor glitch to the safety checks.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from app.engine.hardware.base import Command, HardwareInterface, Measurement


class ReplayRig(HardwareInterface):
    """Plays ``NAME.csv`` + ``NAME.json`` (a station run log or any log in that format).

    Args:
        log: Path of the log (either file or the stem).
        clock: The engine's clock.
        loop: Play back and forth instead of holding the last sample.

    Raises:
        LogFormatError: The log is missing, malformed or holds fewer than two samples.
    """

    name = "replay"
    responds_to_commands = False

    def __init__(self, log: Path | str, clock: Any, loop: bool = False) -> None:
        from app.engine.diagnosis.logs import LogFormatError, read_log

        exp = read_log(log)
        if exp.t.size < 2:
            raise LogFormatError(f"{exp.name}: a replay needs at least two samples")
        self.experiment = exp
        self.rig = str(exp.meta.get("rig", "rotary"))
        self.clock = clock
        self.loop = loop
        self.t = exp.t
        ch = exp.channels
        self._rows = np.column_stack([ch["p_a"], ch["p_b"], ch["p_s"], ch["theta"], ch["omega"], ch["torque"]])
        self._cmds = np.column_stack([exp.inputs[k] for k in ("z_a", "z_b", "u_a", "u_b")])
        self._t0 = 0.0
        self._i = 0
        self.last_applied = self.safe_command()

    @property
    def duration(self) -> float:
        """Length of the log [s]."""
        return float(self.t[-1])

    @property
    def logged_command(self) -> Command:
        """The command the recorded controller sent at the current sample."""
        z_a, z_b, u_a, u_b = (float(v) for v in self._cmds[self._i])
        return Command(z_a, z_b, u_a, u_b)

    def activate(self) -> None:
        """Start playing from the log's first sample."""
        self._t0 = self.clock.now()
        self._i = 0

    def deactivate(self) -> None:
        """Nothing to release."""

    def read(self) -> Measurement:
        """The logged sample at the time since activation."""
        el = self.clock.now() - self._t0
        backwards = False
        if self.loop:
            lap, el = divmod(el, self.duration)
            backwards = int(lap) % 2 == 1
            if backwards:
                el = self.duration - el
        i = int(np.searchsorted(self.t, el, side="right")) - 1
        self._i = min(max(i, 0), self.t.size - 1)
        p_a, p_b, p_s, theta, omega, torque = (float(v) for v in self._rows[self._i])
        return Measurement(self.clock.now(), p_a, p_b, p_s, theta, -omega if backwards else omega, torque)

    def write(self, command: Command) -> Command:
        """Clip (the log does not react); returns what a rig would have applied."""
        self.last_applied = command.clipped()
        return self.last_applied
