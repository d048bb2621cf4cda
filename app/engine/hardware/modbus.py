"""Modbus TCP: a backend for remote I/O couplers, and the simulated plant served over the same protocol.

:class:`ModbusRig` drives a rig through a Modbus TCP coupler (pymodbus
client): per period one *read input registers* for the four analog inputs and
the encoder, and one *write multiple registers* for the four valve outputs.
Register layout and scaling come from :class:`~app.engine.hardware.config.HardwareConfig`.

:class:`PlantServer` is the other end for hardware-in-the-loop tests and
demos: a pymodbus server whose registers front a
:class:`~app.engine.hardware.sim.SimulatedRig` on the wall clock — a read of
the inputs integrates the plant up to now and samples its sensors, a write of
the outputs sets the valves. ``cwrr modbus-plant`` serves it.

A lost link (refused, reset or timed-out request) makes ``read``/``write``
raise :class:`LinkLost`; the engine treats that as the ``link_lost`` fault and
the safe state, and the coupler's own watchdog (``watchdog_register``) holds
the safe outputs on the far side. ``activate`` reconnects, so clearing the
fault and connecting again resumes.
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Any

from app.engine.hardware.base import Command, HardwareInterface, Measurement
from app.engine.hardware.config import HardwareConfig, SpeedEstimator, check_rig

FULL_SCALE = 32767
"""Counts at +10 V (signed 16-bit registers, ±10 V inputs; 0–10 V outputs)."""


class LinkLost(ConnectionError):
    """The Modbus link failed (refused, reset, timed out, or an exception response)."""


def volts_to_counts(v: float) -> int:
    """±10 V → a register's two's-complement 16-bit value."""
    c = int(round(max(-10.0, min(10.0, v)) / 10.0 * FULL_SCALE))
    return c & 0xFFFF


def counts_to_volts(c: int) -> float:
    """A register's 16-bit value (two's complement) → volts."""
    if c >= 0x8000:
        c -= 0x10000
    return c * 10.0 / FULL_SCALE


def split32(n: int) -> list[int]:
    """A signed 32-bit count → two registers, high word first."""
    n &= 0xFFFFFFFF
    return [n >> 16, n & 0xFFFF]


def join32(hi: int, lo: int) -> int:
    """Two registers (high word first) → a signed 32-bit count."""
    n = (hi << 16) | lo
    return n - (1 << 32) if n >= (1 << 31) else n


class ModbusRig(HardwareInterface):
    """A rig behind a Modbus TCP coupler.

    Args:
        config: Channel map, scaling and the link.
        clock: The engine's clock (sample times).
        period: Nominal sampling period [s] (speed estimator).
        rig: ``"rotary"`` (angle in rad), ``"linear"`` or ``"cpr"`` (piston
            position in m; the torque input then carries whatever force
            signal the linear rig wires to it, in its own scaling).
    """

    name = "modbus"

    def __init__(self, config: HardwareConfig, clock: Any, period: float, rig: str = "rotary") -> None:
        check_rig(rig, "Modbus")
        self.config = config
        self.link = config.link()
        self.clock = clock
        self.period = period
        self.rig = rig
        self.speed = SpeedEstimator(config.speed_filter_hz, period)
        self.client: Any = None
        # the engine's watchdog thread writes the safe outputs while the loop thread may be inside a
        # request; pymodbus's sync client is not thread-safe, so one request at a time (a blocked
        # request ends within the link's timeout, so the watchdog waits at most that long)
        self._link_lock = threading.Lock()
        self.last_applied = config.safe_outputs.command()
        ins = config.inputs
        chans = [ins.p_a.channel, ins.p_b.channel, ins.p_s.channel, ins.torque.channel]
        self._in_lo, self._in_n = min(chans), max(chans) - min(chans) + 1
        outs = config.outputs
        ochans = [outs.z_a.channel, outs.z_b.channel, outs.u_a.channel, outs.u_b.channel]
        self._out_lo, self._out_n = min(ochans), max(ochans) - min(ochans) + 1

    # ------------------------------------------------------------------ link

    def _connect(self) -> None:
        from pymodbus.client import ModbusTcpClient

        with self._link_lock:
            if self.client is not None:
                self.client.close()
            # retries=0: a period has no time for a retry; a failed request is a lost link
            self.client = ModbusTcpClient(self.link.host, port=self.link.port, timeout=self.link.timeout_s,
                                          retries=0)
            up = self.client.connect()
        if not up:
            raise LinkLost(f"cannot reach the Modbus coupler at {self.link.host}:{self.link.port}")

    def _call(self, what: str, method: str, *args: Any, **kw: Any) -> Any:
        """One request: the client's ``method`` with ``args``; any failure is a lost link."""
        from pymodbus.exceptions import ModbusException

        with self._link_lock:
            if self.client is None:
                raise LinkLost("the Modbus link is closed")
            try:
                r = getattr(self.client, method)(*args, device_id=self.link.device_id, **kw)
            except (ModbusException, OSError) as exc:
                raise LinkLost(f"Modbus {what} failed: {exc}") from None
        if r.isError():
            raise LinkLost(f"Modbus {what}: the coupler answered {r}")
        return r

    def activate(self) -> None:
        """Connect (again), arm the coupler's watchdog, write the safe outputs."""
        self._connect()
        if self.link.watchdog_register:
            self._call("watchdog set-up", "write_register", self.link.watchdog_register,
                       self.link.watchdog_ms)
        self.speed.reset()
        self.write(self.safe_command())

    def deactivate(self) -> None:
        """Safe outputs (if the link still answers), then close."""
        try:
            self.write(self.safe_command())
        except LinkLost:
            pass
        finally:
            with self._link_lock:
                if self.client is not None:
                    self.client.close()
                    self.client = None

    def safe_command(self) -> Command:
        """The configured safe outputs."""
        return self.config.safe_outputs.command()

    # --------------------------------------------------------------- per period

    def read(self) -> Measurement:
        """One request for the analog inputs and the encoder; scaled to bar abs, N·m, rad (m), rad/s (m/s)."""
        ins, enc = self.config.inputs, self.config.encoder
        base = self.link.input_base + self._in_lo
        eaddr = self.link.encoder_base + 2 * enc.channel
        lo = min(base, eaddr)
        hi = max(base + self._in_n, eaddr + 2)
        t_send = self.clock.now()
        regs = self._call("read", "read_input_registers", lo, count=hi - lo).registers
        # the coupler sampled somewhere in the round trip: its middle is the best estimate
        t_sample = 0.5 * (t_send + self.clock.now())

        def volts(ch: int) -> float:
            return counts_to_volts(regs[self.link.input_base + ch - lo])

        theta = enc.to_position(join32(regs[eaddr - lo], regs[eaddr - lo + 1]), self.rig)
        return Measurement(t_sample, ins.p_a.to_physical(volts(ins.p_a.channel)),
                           ins.p_b.to_physical(volts(ins.p_b.channel)), ins.p_s.to_physical(volts(ins.p_s.channel)),
                           theta, self.speed.update(theta, t_sample), ins.torque.to_physical(volts(ins.torque.channel)))

    def write(self, command: Command) -> Command:
        """Clip to each output's range and write the four outputs in one request."""
        outs = self.config.outputs
        applied = outs.apply(command)
        regs = [0] * self._out_n
        for out, v in ((outs.z_a, applied.z_a), (outs.z_b, applied.z_b), (outs.u_a, applied.u_a),
                       (outs.u_b, applied.u_b)):
            regs[out.channel - self._out_lo] = volts_to_counts(v)
        self._call("write", "write_registers", self.link.output_base + self._out_lo, regs)
        self.last_applied = applied
        return applied


class PlantServer:
    """The simulated plant behind a Modbus TCP server (hardware-in-the-loop).

    Args:
        rig: The simulated rig (on the wall clock for real-time HIL).
        config: The register layout and scaling the client will use.
        host: Bind address.
        port: TCP port (0: any free port; see :attr:`port` after :meth:`start`).
    """

    def __init__(self, rig: Any, config: HardwareConfig, host: str = "127.0.0.1", port: int = 0) -> None:
        self.rig = rig
        self.config = config
        self.host = host
        self.port = port
        self.requests = 0
        self.watchdog_s = 0.0
        self.watchdog_trips = 0
        self._last_write = time.monotonic()
        self._tripped = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._lock = threading.Lock()  # the plant is stepped by one request at a time
        self._off = threading.Event()
        self._dog: threading.Thread | None = None

    def _inputs(self) -> dict[int, int]:
        """Register address → value for every input register, from one sensor sample."""
        m = self.rig.read()
        ins, enc, link = self.config.inputs, self.config.encoder, self.config.link()
        regs = {link.input_base + ins.p_a.channel: volts_to_counts(ins.p_a.to_volts(m.p_a)),
                link.input_base + ins.p_b.channel: volts_to_counts(ins.p_b.to_volts(m.p_b)),
                link.input_base + ins.p_s.channel: volts_to_counts(ins.p_s.to_volts(m.p_s)),
                link.input_base + ins.torque.channel: volts_to_counts(ins.torque.to_volts(m.torque))}
        hi, lo = split32(enc.position_to_counts(m.theta, getattr(self.rig, "rig", "rotary")))
        regs[link.encoder_base + 2 * enc.channel] = hi
        regs[link.encoder_base + 2 * enc.channel + 1] = lo
        return regs

    def _outputs(self, start: int, values: list[int]) -> None:
        outs, link = self.config.outputs, self.config.link()
        held = self.rig.last_applied
        cur = {outs.z_a.channel: held.z_a, outs.z_b.channel: held.z_b, outs.u_a.channel: held.u_a,
               outs.u_b.channel: held.u_b}
        for i, v in enumerate(values):
            ch = start + i - link.output_base
            if ch in cur:
                cur[ch] = counts_to_volts(v)
        self.rig.write(Command(cur[outs.z_a.channel], cur[outs.z_b.channel], cur[outs.u_a.channel],
                               cur[outs.u_b.channel]))

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      current_registers: list[int], set_values: list[int] | list[bool] | None) -> None:
        with self._lock:
            self.requests += 1
            if function_code == 4:  # read input registers: sample the plant now
                regs = self._inputs()
                for i in range(len(current_registers)):
                    current_registers[i] = regs.get(start_address + i, 0)
            elif function_code in (6, 16) and set_values is not None:
                link = self.config.link()
                if link.watchdog_register and address == link.watchdog_register:
                    self.watchdog_s = int(set_values[0]) / 1000.0
                else:
                    self._outputs(address, [int(v) for v in set_values])
                    self._last_write = time.monotonic()
                    self._tripped = False

    def _watchdog(self) -> None:
        """The coupler's watchdog: no output write for ``watchdog_s`` → the safe outputs.

        A thread of its own, so it outlives :meth:`disconnect` as a coupler's
        outlives its network cable.
        """
        while not self._off.wait(0.005):
            with self._lock:
                if self.watchdog_s > 0 and not self._tripped and time.monotonic() - self._last_write > self.watchdog_s:
                    self.rig.write(self.config.safe_outputs.command())
                    self._tripped = True
                    self.watchdog_trips += 1

    async def _main(self) -> None:
        from pymodbus.server import ModbusTcpServer
        from pymodbus.simulator import DataType, SimData, SimDevice

        link = self.config.link()
        bits = [SimData(0, count=16, values=False, datatype=DataType.BITS)]
        device = SimDevice(id=0, simdata=(bits, bits,
                                          [SimData(0, count=max(1024, link.watchdog_register + 1), values=0,
                                                   datatype=DataType.REGISTERS)],
                                          [SimData(0, count=max(64, link.encoder_base + 32), values=0,
                                                   datatype=DataType.REGISTERS)]),
                           action=self._action)
        if self.port == 0:
            import socket

            with socket.socket() as s:
                s.bind((self.host, 0))
                self.port = int(s.getsockname()[1])
        self._server = ModbusTcpServer(device, address=(self.host, self.port))
        self._ready.set()
        await self._server.serve_forever()

    def _run(self) -> None:
        self._loop = asyncio.new_event_loop()
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._main())
        except BaseException as exc:  # reported by start()
            self._error = exc
            self._ready.set()

    def start(self) -> PlantServer:
        """Serve in a background thread; returns when the port is listening."""
        self.rig.activate()
        self.rig.read()  # compiles the plant's kernels now, not inside a client's first request
        self._off.clear()
        self._dog = threading.Thread(target=self._watchdog, name="cwrr-modbus-watchdog", daemon=True)
        self._dog.start()
        self._thread = threading.Thread(target=self._run, name="cwrr-modbus-plant", daemon=True)
        self._thread.start()
        if not self._ready.wait(10) or self._error is not None:
            raise RuntimeError(f"the Modbus plant server did not start: {self._error}")
        deadline = time.monotonic() + 5
        import socket

        while time.monotonic() < deadline:  # listening, not just constructed
            try:
                socket.create_connection((self.host, self.port), timeout=0.2).close()
                break
            except OSError:
                time.sleep(0.02)
        return self

    def stop(self) -> None:
        """Stop serving and the watchdog (the coupler powered off)."""
        self.disconnect()
        self._off.set()
        if self._dog is not None:
            self._dog.join(5)
            self._dog = None

    def disconnect(self) -> None:
        """Close every connection and stop serving; the watchdog keeps running (a pulled cable)."""
        if self._loop is not None and self._server is not None:
            fut = asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop)
            try:
                fut.result(10)
            except Exception:  # already stopping
                pass
        if self._thread is not None:
            self._thread.join(10)
        self._server = None
        self._loop = None
        self._ready.clear()


def serve_simulated_plant(config: HardwareConfig, period: float | None = None, host: str = "127.0.0.1",
                          port: int = 0) -> PlantServer:
    """Serve the simulated rotary rig over Modbus on the wall clock, its person at rest.

    The plant's kernels are loaded before the server listens: a first request
    that waited for them to compile would outlast the station's timeout and
    read as a lost link.

    Args:
        config: The register layout and scaling the station will use.
        period: The plant's nominal sampling period [s] (default ``1 / config.rate_hz``).
        host: Bind address.
        port: TCP port (0: any free port).

    Returns:
        The started server; its simulated rig is ``server.rig``.
    """
    # imported here: the Modbus client side (ModbusRig) must not pull the simulator in
    from app.engine.hardware.sim import SimulatedRig
    from app.engine.human import HumanProgram
    from app.engine.loop import WallClock
    from app.engine.sim import Simulator

    period = 1.0 / config.rate_hz if period is None else period
    rig = SimulatedRig(WallClock(), period=period)
    rig.set_program(HumanProgram.rest())
    Simulator(rig.params).advance_and_measure(0.01, period)
    return PlantServer(rig, config, host=host, port=port).start()
