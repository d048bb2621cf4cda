"""Quanser HIL boards (the thesis's Q8-USB) through the vendor's ``quanser.hardware`` Python API.

The API ships with QUARC / the Quanser SDK, not PyPI, so it is imported when
the backend is built and a clear message says what to install when it is
absent. Calls used, with the vendor's signatures (``hil.h`` and the SDK's
Python examples):

* ``HIL().open(card_type, card_identifier)``, ``close()``;
* ``read(analog_channels, num_analog, encoder_channels, num_encoder,
  digital_channels, num_digital, other_channels, num_other, voltages, counts,
  digital_values, other_values)`` — one immediate sample of all inputs;
* ``write_analog(channels, num_channels, voltages)``;
* ``watchdog_set_analog_expiration_state(channels, num_channels, voltages)``,
  ``watchdog_start(timeout)``, ``watchdog_reload()`` (False once expired),
  ``watchdog_is_expired()``, ``watchdog_stop()``, ``watchdog_clear()``;
* hardware timing: ``task_create_reader(samples_in_buffer, analog_channels,
  num_analog, encoder_channels, num_encoder, digital_channels, num_digital,
  other_channels, num_other)`` → task, ``task_start(task, clock, frequency,
  num_samples)`` with ``Clock.HARDWARE_CLOCK_0`` and ``HIL.INFINITE``,
  ``task_set_buffer_overflow_mode(task, BufferOverflowMode.OVERWRITE_ON_OVERFLOW)``,
  ``task_read(task, num_samples, analog_buffer, encoder_buffer,
  digital_buffer, other_buffer)`` (blocks until the samples are taken),
  ``task_stop(task)``, ``task_delete(task)``.

Channel and buffer arguments are ``array.array`` of C ``uint32`` / ``double``
/ ``int32``, as in the vendor's examples. The board's watchdog holds the
configured safe outputs if the station stops reloading it (a dead process, a
hung loop). By default (``timing: task``) the board's clock sets the loop
period: a reader task samples the inputs at the loop rate and :meth:`read`
blocks until the next sample, so the computer's sleep accuracy no longer
matters; ``timing: immediate`` reads on the engine's clock instead.
"""

from __future__ import annotations

import array
import threading
from typing import Any

from app.engine.hardware.base import Command, HardwareInterface, Measurement
from app.engine.hardware.config import HardwareConfig, SpeedEstimator, check_rig

MISSING = ("the Quanser backend needs the vendor's Python API (module quanser.hardware), which ships with QUARC or "
           "the Quanser SDK and is not on PyPI: install it from Quanser, or choose backend sim or modbus")


class WatchdogExpired(ConnectionError):
    """The board's watchdog expired: it has already set the safe outputs."""


def load_hil() -> Any:
    """The vendor's ``HIL`` class.

    Raises:
        RuntimeError: The vendor API is not installed (says what to do).
    """
    try:
        from quanser.hardware import HIL  # type: ignore[import-not-found]
    except ImportError:
        raise RuntimeError(MISSING) from None
    return HIL


def load_task_constants() -> tuple[Any, Any]:
    """The vendor's ``Clock.HARDWARE_CLOCK_0`` (the board's first sampling clock) and
    ``BufferOverflowMode.OVERWRITE_ON_OVERFLOW``."""
    try:
        from quanser.hardware import BufferOverflowMode, Clock  # type: ignore[import-not-found]
    except ImportError:
        raise RuntimeError(MISSING) from None
    return Clock.HARDWARE_CLOCK_0, BufferOverflowMode.OVERWRITE_ON_OVERFLOW


class QuanserRig(HardwareInterface):
    """A rig on a Quanser HIL board.

    Args:
        config: Channel map, scaling, the card and its watchdog.
        clock: The engine's clock (sample times).
        period: Nominal sampling period [s] (speed estimator).
        rig: ``"rotary"`` (angle in rad), ``"linear"`` or ``"cpr"`` (position in m).
        hil_class: The vendor's ``HIL`` class (looked up when omitted).
        task_constants: The vendor's clock id and overwrite-on-overflow mode
            for the reader task (looked up when omitted and the timing is
            ``task``).
    """

    name = "quanser"

    def __init__(self, config: HardwareConfig, clock: Any, period: float, rig: str = "rotary",
                 hil_class: Any = None, task_constants: tuple[Any, Any] | None = None) -> None:
        check_rig(rig, "Quanser")
        self.config = config
        self.clock = clock
        self.period = period
        self.rig = rig
        self._hil_class = hil_class or load_hil()
        self.paced_by_hardware = config.card().timing == "task"
        if self.paced_by_hardware and task_constants is None:
            task_constants = load_task_constants()
        consts: tuple[Any, Any] = task_constants or (None, None)
        self._hw_clock: Any = consts[0]
        self._overwrite: Any = consts[1]
        self._task: Any = None
        self.card: Any = None
        # the engine's watchdog thread may write the safe outputs while the loop thread waits in a read:
        # one call on the board at a time, and the watchdog gives up after a while (the board's own
        # watchdog holds the safe outputs if the link is truly hung)
        self._board_lock = threading.Lock()
        self._lock_wait_s = max(4.0 * period, config.card().watchdog_s)
        self.speed = SpeedEstimator(config.speed_filter_hz, period)
        ins, outs = config.inputs, config.outputs
        self._ai = array.array("I", [ins.p_a.channel, ins.p_b.channel, ins.p_s.channel, ins.torque.channel])
        self._enc = array.array("I", [config.encoder.channel])
        self._ao = array.array("I", [outs.z_a.channel, outs.z_b.channel, outs.u_a.channel, outs.u_b.channel])
        self._volts = array.array("d", [0.0] * 4)
        self._counts = array.array("i", [0])
        self._out = array.array("d", [0.0] * 4)
        self.last_applied = config.safe_outputs.command()

    def safe_command(self) -> Command:
        """The configured safe outputs."""
        return self.config.safe_outputs.command()

    def activate(self) -> None:
        """Open the board, set the watchdog's expiration outputs to the safe state, start it, write safe outputs."""
        card = self._hil_class()
        card.open(self.config.card().card_type, self.config.card().card_id)
        self.card = card
        safe = self.safe_command()
        states = array.array("d", [safe.z_a, safe.z_b, safe.u_a, safe.u_b])
        card.watchdog_set_analog_expiration_state(self._ao, len(self._ao), states)
        card.watchdog_clear()
        card.watchdog_start(self.config.card().watchdog_s)
        self.speed.reset()
        self.write(safe)
        if self.paced_by_hardware:
            buffered = max(2, int(round(self.config.card().task_buffer_s / self.period)))
            self._task = card.task_create_reader(buffered, self._ai, len(self._ai), self._enc, len(self._enc),
                                                 None, 0, None, 0)
            # a loop held up (a first-call compile, a long pause) then reads the newest buffered
            # samples instead of failing on the overflow; the watchdog bounds how late it may be
            card.task_set_buffer_overflow_mode(self._task, self._overwrite)
            card.task_start(self._task, self._hw_clock, 1.0 / self.period, getattr(self._hil_class, "INFINITE", -1))

    def deactivate(self) -> None:
        """Safe outputs, stop the watchdog, close the board."""
        if self.card is None:
            return
        try:
            if self._task is not None:
                self.card.task_stop(self._task)
                self.card.task_delete(self._task)
                self._task = None
            if not self.card.watchdog_is_expired():  # expired: the board already holds the safe outputs
                self._write_raw(self.safe_command())
            self.card.watchdog_stop()
        finally:
            self.card.close()
            self.card = None

    def read(self) -> Measurement:
        """The four analog inputs and the encoder, scaled: the reader task's next
        sample (blocks until the board takes it), or one immediate sample."""
        with self._board_lock:
            if self._task is not None:
                self.card.task_read(self._task, 1, self._volts, self._counts, None, None)
            else:
                self.card.read(self._ai, len(self._ai), self._enc, 1, None, 0, None, 0, self._volts, self._counts,
                               None, None)
            timed = self._task is not None
        ins, v = self.config.inputs, self._volts
        theta = self.config.encoder.to_position(int(self._counts[0]), self.rig)
        t = self.clock.now()
        # the reader task's samples are one period apart on the board's clock, however late they are read
        w = self.speed.update(theta, None if timed else t)
        return Measurement(t, ins.p_a.to_physical(v[0]), ins.p_b.to_physical(v[1]),
                           ins.p_s.to_physical(v[2]), theta, w, ins.torque.to_physical(v[3]))

    def _write_raw(self, c: Command) -> None:
        self._out[0], self._out[1], self._out[2], self._out[3] = c.z_a, c.z_b, c.u_a, c.u_b
        self.card.write_analog(self._ao, len(self._ao), self._out)

    def write(self, command: Command) -> Command:
        """Reload the watchdog, then write the clipped outputs.

        Raises:
            WatchdogExpired: The board already holds the safe outputs (the loop was too late).
        """
        if not self._board_lock.acquire(timeout=self._lock_wait_s):
            raise TimeoutError(f"the HIL board did not answer within {self._lock_wait_s * 1e3:.0f} ms; "
                               "its watchdog holds the safe outputs")
        try:
            if not self.card.watchdog_reload():
                raise WatchdogExpired("the HIL board's watchdog expired; it holds the safe outputs")
            applied = self.config.outputs.apply(command)
            self._write_raw(applied)
        finally:
            self._board_lock.release()
        self.last_applied = applied
        return applied
