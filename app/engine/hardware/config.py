"""The rig's hardware configuration: which backend, which channel carries what, and how to scale it.

One YAML file (``CWRR_HARDWARE=path``) says everything a lab changes when it
wires its own station (issue 8): the backend (``sim``, ``modbus``,
``quanser``, ``replay``), the channel map, sensor scaling and offsets, valve
output ranges, the loop rate, safety limits and the safe outputs the DAQ's own
watchdog holds if the process dies. It is validated on load: a wrong value is
refused with the field named and nothing starts.

Conventions (SI inside, volts and counts at the edge):

* pressure [bar abs] = ``gain`` × V + ``offset``; default 2 bar/V and 0 bar
  (a 0–5 V, 0–10 bar abs sensor, SPEC §2 / Table 3.2);
* torque [N·m] = ``gain`` × V + ``offset``; default 1 N·m/V (TS70a-10Nm with
  its ±10 V amplifier);
* angle [rad] = ``sign`` × 2π × (counts − ``zero_counts``) / ``counts_per_rev``
  (1024 lines × 4 = 4096) on the rotary rig; position [m] = ``sign`` ×
  ``m_per_count`` × (counts − ``zero_counts``) on the linear and CPR rigs
  (thesis 3.2.4's ESKON linear encoder: 0.01 mm);
* speed: the backward difference of the angle through a first-order low-pass
  (``speed_filter_hz``), as the simulator's sensors and the thesis derive it.

Example::

    backend: modbus
    rate_hz: 200
    modbus: {host: 192.168.0.20, port: 502, device_id: 1}
    inputs:
      p_a: {channel: 0}
      torque: {channel: 3, offset: -0.012}
    encoder: {channel: 0, zero_counts: 117}
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from app.engine.constants import P_ATM_BAR
from app.engine.hardware.base import RIG_KINDS, SAFE_COMMAND, Command
from app.engine.params import ParameterError, validation_reasons

Volt = Annotated[float, Field(ge=-10.0, le=10.0, description="V")]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class AnalogIn(_Strict):
    """One analog input: physical = gain × volts + offset.

    Attributes:
        channel: Input channel number on the backend.
        gain: Physical units per volt (bar/V or N·m/V), nonzero.
        offset: Physical value at 0 V (bar abs or N·m); set by calibration.
    """

    channel: Annotated[int, Field(ge=0, le=255)]
    gain: Annotated[float, Field(ge=-1e4, le=1e4)] = 2.0
    offset: Annotated[float, Field(ge=-1e4, le=1e4)] = 0.0

    @model_validator(mode="after")
    def _nonzero(self) -> AnalogIn:
        if self.gain == 0.0:
            raise ValueError("gain must be nonzero (physical units per volt)")
        return self

    def to_physical(self, volts: float) -> float:
        """Volts → bar abs or N·m."""
        return self.gain * volts + self.offset

    def to_volts(self, value: float) -> float:
        """Bar abs or N·m → volts (what the sensor would output)."""
        return (value - self.offset) / self.gain


LINEAR_RIGS = ("linear", "cpr")
"""Rigs whose encoder reads a piston position [m]."""


def check_rig(rig: str, backend: str) -> None:
    """Refuse a rig kind no hardware mapping exists for.

    Raises:
        ValueError: Naming the kinds that are mapped.
    """
    if rig not in RIG_KINDS:
        raise ValueError(f"the {backend} backend maps the rigs {', '.join(RIG_KINDS)}, not {rig!r}")


class EncoderIn(_Strict):
    """The quadrature encoder.

    Attributes:
        channel: Encoder channel number.
        counts_per_rev: Counts per revolution (lines × 4), rotary rig.
        m_per_count: Metres per count, linear and CPR rigs (ESKON: 1e-5).
        sign: +1 or −1 so that CCW (pronation) or extension is positive.
        zero_counts: Count at the neutral position (rotary) or at the
            retracted end (linear); set by calibration.
    """

    channel: Annotated[int, Field(ge=0, le=255)] = 0
    counts_per_rev: Annotated[int, Field(ge=4, le=1 << 24)] = 4096
    m_per_count: Annotated[float, Field(gt=0.0, le=0.01)] = 1.0e-5
    sign: Literal[1, -1] = 1
    zero_counts: Annotated[int, Field(ge=-(1 << 31), le=(1 << 31) - 1)] = 0

    def to_position(self, counts: int, rig: str = "rotary") -> float:
        """Counts → angle [rad] (rotary) or piston position [m] (linear, CPR)."""
        if rig in LINEAR_RIGS:
            return self.sign * self.m_per_count * (counts - self.zero_counts)
        return self.to_rad(counts)

    def position_to_counts(self, position: float, rig: str = "rotary") -> int:
        """Angle [rad] or position [m] → counts (what the encoder would read)."""
        if rig in LINEAR_RIGS:
            return int(round(self.sign * position / self.m_per_count)) + self.zero_counts
        return self.to_counts(position)

    def to_rad(self, counts: int) -> float:
        """Counts → angle [rad] from neutral."""
        return self.sign * 2.0 * math.pi * (counts - self.zero_counts) / self.counts_per_rev

    def to_counts(self, theta: float) -> int:
        """Angle [rad] → counts (what the encoder would read)."""
        return int(round(self.sign * theta * self.counts_per_rev / (2.0 * math.pi))) + self.zero_counts


class AnalogOut(_Strict):
    """One valve command output.

    Attributes:
        channel: Output channel number.
        v_min: Lowest voltage the output may take [V].
        v_max: Highest voltage [V].
    """

    channel: Annotated[int, Field(ge=0, le=255)]
    v_min: Volt = 0.0
    v_max: Volt = 10.0

    @model_validator(mode="after")
    def _ordered(self) -> AnalogOut:
        if not self.v_min < self.v_max:
            raise ValueError(f"v_min = {self.v_min} V must be below v_max = {self.v_max} V")
        return self

    def clip(self, v: float) -> float:
        """The voltage within this output's range (NaN → v_min)."""
        return min(max(v, self.v_min), self.v_max) if math.isfinite(v) else self.v_min


def _distinct_channels(kind: str, group: BaseModel) -> None:
    """Refuse two signals of ``group`` on one channel (a copy-paste slip in a wiring file)."""
    chans = {name: getattr(group, name).channel for name in type(group).model_fields}
    if len(set(chans.values())) != len(chans):
        raise ValueError(f"two {kind} share a channel: {', '.join(f'{k}={v}' for k, v in chans.items())}")


class Inputs(_Strict):
    """The analog inputs (thesis Table 3.2: PS-a, PS-b, PS-0, the torque amplifier)."""

    p_a: AnalogIn = AnalogIn(channel=0)
    p_b: AnalogIn = AnalogIn(channel=1)
    p_s: AnalogIn = AnalogIn(channel=2)
    torque: AnalogIn = AnalogIn(channel=3, gain=1.0)

    @model_validator(mode="after")
    def _distinct(self) -> Inputs:
        _distinct_channels("inputs", self)
        return self


class Outputs(_Strict):
    """The valve outputs: PRV-a/b (VPPM, 0–10 V ↔ 0–10 bar gauge), DCV-a/b (MPYE, 5 V closed)."""

    z_a: AnalogOut = AnalogOut(channel=0)
    z_b: AnalogOut = AnalogOut(channel=1)
    u_a: AnalogOut = AnalogOut(channel=2)
    u_b: AnalogOut = AnalogOut(channel=3)

    @model_validator(mode="after")
    def _distinct(self) -> Outputs:
        _distinct_channels("outputs", self)
        return self

    def apply(self, c: Command) -> Command:
        """``c`` within every output's range."""
        return Command(self.z_a.clip(c.z_a), self.z_b.clip(c.z_b), self.u_a.clip(c.u_a), self.u_b.clip(c.u_b))


class SafeOutputs(_Strict):
    """The outputs the DAQ's watchdog holds when the station stops talking to it [V].

    Default: the station's safe state (both PRVs vent, DCVs route PRV ↔ chamber).
    """

    z_a: Volt = SAFE_COMMAND.z_a
    z_b: Volt = SAFE_COMMAND.z_b
    u_a: Volt = SAFE_COMMAND.u_a
    u_b: Volt = SAFE_COMMAND.u_b

    def command(self) -> Command:
        """As a :class:`Command`."""
        return Command(self.z_a, self.z_b, self.u_a, self.u_b)


class ModbusLink(_Strict):
    """A Modbus TCP remote I/O coupler (e.g. a FESTO CPX terminal, a WAGO or Beckhoff bus coupler).

    Register layout (zero-based addresses): input registers ``input_base +
    channel`` hold the analog inputs as signed 16-bit counts on ±10 V
    (32767 ↔ +10 V); ``encoder_base + 2·channel`` holds a 32-bit count, high
    word first; holding registers ``output_base + channel`` take the outputs
    as counts on 0–10 V (32767 ↔ 10 V).

    Attributes:
        host: The coupler's address.
        port: Its Modbus TCP port.
        device_id: Modbus unit / device id.
        timeout_s: Per-request timeout [s]; a request past it is a lost link.
        input_base: First analog-input register.
        encoder_base: First encoder register.
        output_base: First analog-output holding register.
        watchdog_register: Holding register of the coupler's own watchdog
            time [ms] (0: the coupler has none); written on activate.
        watchdog_ms: The coupler watchdog's time [ms]: with no output write
            for this long it sets the safe outputs itself.
    """

    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 502
    device_id: Annotated[int, Field(ge=0, le=247)] = 1
    timeout_s: Annotated[float, Field(gt=0.0, le=10.0)] = 0.05
    input_base: Annotated[int, Field(ge=0, le=65000)] = 0
    encoder_base: Annotated[int, Field(ge=0, le=65000)] = 16
    output_base: Annotated[int, Field(ge=0, le=65000)] = 0
    watchdog_register: Annotated[int, Field(ge=0, le=65000)] = 0
    watchdog_ms: Annotated[int, Field(ge=1, le=60000)] = 100


class QuanserCard(_Strict):
    """A Quanser HIL board (the thesis's Q8-USB).

    Attributes:
        card_type: HIL card type name as the vendor API spells it (``q8_usb``).
        card_id: Board identifier (``"0"`` for the first).
        watchdog_s: HIL watchdog timeout [s]: if the station stops reloading
            it, the board itself sets the safe outputs.
        timing: ``"task"`` (default): the board samples the inputs on its own
            hardware clock at the loop rate (a HIL reader task) and the loop
            runs once per sample, as QUARC's timebase blocks do;
            ``"immediate"``: the engine paces immediate-mode reads on the
            computer's clock.
        task_buffer_s: How much of the reader task's samples the driver
            buffers while the loop is late [s]; a late loop works the backlog
            off sample by sample.
    """

    card_type: str = "q8_usb"
    card_id: str = "0"
    watchdog_s: Annotated[float, Field(gt=0.0, le=10.0)] = 0.1
    timing: Literal["task", "immediate"] = "task"
    task_buffer_s: Annotated[float, Field(gt=0.0, le=10.0)] = 0.1


class ReplaySource(_Strict):
    """A recorded run log played back as if it were the rig.

    Attributes:
        log: Path of the run log CSV (its ``.json`` beside it).
        loop: Play back and forth instead of holding the last sample.
    """

    log: str
    loop: bool = False


class Calibration(_Strict):
    """When each calibration was last made (ISO dates; None: never)."""

    torque_zero: str | None = None
    pressure_offsets: str | None = None
    encoder_zero: str | None = None


class HardwareConfig(_Strict):
    """Everything about the station's I/O.

    Attributes:
        backend: ``sim`` (the embedded simulator), ``modbus``, ``quanser`` or ``replay``.
        rate_hz: Control loop rate [Hz].
        inputs: Analog input map and scaling.
        encoder: Encoder channel and scaling.
        outputs: Valve output map and ranges.
        safe_outputs: What the DAQ watchdog holds if the process dies.
        speed_filter_hz: Speed estimator low-pass cut-off [Hz].
        p_atm_bar: The lab's atmosphere [bar abs] (1.013 at sea level, ≈ 0.95
            at 500 m, 0.90 at 1000 m): the PRVs regulate above it (Eq 3.7), so
            the controllers command with it, the logs record it and the gap
            diagnosis replays in it; with ``sim``, the simulated rig's too.
        limits: Safety-limit overrides (``SafetyLimits`` field → value).
        modbus: The Modbus link (backend ``modbus``).
        quanser: The HIL board (backend ``quanser``).
        replay: The log to play (backend ``replay``).
        calibration: Dates of the last calibrations.
    """

    backend: Literal["sim", "modbus", "quanser", "replay"] = "sim"
    rate_hz: Annotated[float, Field(ge=10.0, le=2000.0)] = 200.0
    inputs: Inputs = Inputs()
    encoder: EncoderIn = EncoderIn()
    outputs: Outputs = Outputs()
    safe_outputs: SafeOutputs = SafeOutputs()
    speed_filter_hz: Annotated[float, Field(gt=0.0, le=500.0)] = 25.0
    p_atm_bar: Annotated[float, Field(ge=0.7, le=1.1)] = P_ATM_BAR
    limits: dict[str, float] = {}
    modbus: ModbusLink | None = None
    quanser: QuanserCard | None = None
    replay: ReplaySource | None = None
    calibration: Calibration = Calibration()

    @model_validator(mode="before")
    @classmethod
    def _replayed_atmosphere(cls, data: Any) -> Any:
        # A replayed log is the rig, so its atmosphere is the lab's: the station's controllers,
        # its logs and a diagnosis of them had taken sea level for a log recorded at 0.9 bar.
        # A value set here wins (a log whose JSON is wrong); an unreadable log is left to the
        # backend, which names what is wrong with it when the station connects.
        if not (isinstance(data, dict) and data.get("backend") == "replay" and "p_atm_bar" not in data):
            return data
        src = data.get("replay")
        log = src.get("log") if isinstance(src, dict) else getattr(src, "log", None)
        if not isinstance(log, str):
            return data
        from app.engine.diagnosis.logs import log_paths

        try:
            p_atm = json.loads(log_paths(log)[1].read_text(encoding="utf-8-sig")).get("p_atm_bar")
        except (OSError, ValueError, AttributeError):
            return data
        if isinstance(p_atm, int | float) and 0.7 <= p_atm <= 1.1:
            return {**data, "p_atm_bar": float(p_atm)}
        return data

    @model_validator(mode="after")
    def _backend_section(self) -> HardwareConfig:
        if self.backend == "replay" and self.replay is None:
            raise ValueError("backend replay needs a 'replay: {log: PATH}' section")
        if self.limits:
            from app.engine.safety import SafetyLimits

            try:
                SafetyLimits.for_rig("rotary", **self.limits)
            except (TypeError, ParameterError) as exc:
                raise ValueError(f"limits: {exc}") from None
        return self

    def link(self) -> ModbusLink:
        """The Modbus section (defaults when absent)."""
        return self.modbus or ModbusLink()

    def card(self) -> QuanserCard:
        """The Quanser section (defaults when absent)."""
        return self.quanser or QuanserCard()

    def calibrated(self, what: str, **changes: Any,
                   ) -> HardwareConfig:
        """A copy with ``changes`` applied and ``what`` (a :class:`Calibration` field) dated today."""
        if what not in Calibration.model_fields:
            raise ParameterError(f"calibration {what!r}: must be one of {', '.join(Calibration.model_fields)}")
        cal = self.calibration.model_copy(update={what: _dt.date.today().isoformat()})
        return self.model_copy(update={**changes, "calibration": cal})


def parse_config(data: Any, source: str = "hardware configuration") -> HardwareConfig:
    """Validate a mapping (parsed YAML) as a :class:`HardwareConfig`.

    Raises:
        ParameterError: Naming each wrong field and why.
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ParameterError(f"{source}: expected a mapping of settings, got {type(data).__name__}")
    try:
        return HardwareConfig.model_validate(data)
    except ValidationError as exc:
        raise ParameterError(f"{source}: {validation_reasons(exc, 'config')}") from None


def load_config(path: Path | str) -> HardwareConfig:
    """Read and validate a YAML hardware configuration.

    Raises:
        ParameterError: The file is missing, not YAML, or a field is wrong.
    """
    import yaml

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ParameterError(f"hardware configuration {p}: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ParameterError(f"hardware configuration {p} is not valid YAML: {exc}") from None
    return parse_config(data, f"hardware configuration {p}")


def save_config(config: HardwareConfig, path: Path | str) -> None:
    """Write ``config`` as YAML atomically (a crash leaves the old file or the new, never half)."""
    import yaml

    from app.engine.runlog import atomic_write_text

    body = yaml.safe_dump(config.model_dump(mode="json", exclude_none=True), sort_keys=False)
    head = "# CWRR hardware configuration (validated on load; see app/engine/hardware/config.py)\n"
    atomic_write_text(Path(path), head + body)


class SpeedEstimator:
    """Speed from a quantised angle: backward difference through a first-order low-pass.

    The same estimator as the simulator's sensors (``physics/sensors.py``),
    so a real backend reports speed the way the simulated one does. Given the
    samples' times, both divide by the time that passed between them, not by
    the period: after a late sample (a stalled loop, a slow network round
    trip) the angle moved for longer, and dividing by the period reported a
    65 ms stall's 0.5 rad/s as 3.6 rad/s.

    Args:
        cutoff_hz: Low-pass cut-off [Hz].
        dt: Sampling period [s]: the step between samples given without a
            time (a board's hardware-timed samples), or with one that does not
            advance.
    """

    def __init__(self, cutoff_hz: float, dt: float) -> None:
        self.wc = 2.0 * math.pi * cutoff_hz
        self.alpha = 1.0 - math.exp(-self.wc * dt)
        self.dt = dt
        self._prev: float | None = None
        self._t_prev = math.nan
        self._w = 0.0

    def reset(self) -> None:
        """Forget the history (after a gap in the samples)."""
        self._prev = None
        self._t_prev = math.nan
        self._w = 0.0

    def update(self, theta: float, t: float | None = None) -> float:
        """Feed one angle sample [rad] taken at ``t`` [s] (None: one period after the last); returns [rad/s]."""
        t_prev, self._t_prev = self._t_prev, (math.nan if t is None else t)
        if self._prev is None:
            self._prev = theta
            return 0.0
        dt, alpha = self.dt, self.alpha
        if t is not None and t - t_prev > 0.0:  # NaN (no earlier time) compares false
            dt = t - t_prev
            alpha = 1.0 - math.exp(-self.wc * dt)
        raw = (theta - self._prev) / dt
        self._w += alpha * (raw - self._w)
        self._prev = theta
        return self._w
