"""Issue 8: the Modbus TCP backend, hardware-in-the-loop against the simulated plant served over Modbus.

The plant side is :class:`PlantServer` (pymodbus) fronting a
:class:`SimulatedRig`: in the paced tests a process of its own on the wall
clock (:class:`PlantProcess`), in the lock-step ones a thread beside the
station on the shared simulated clock. The station side is the
real :class:`ModbusRig`, built from a validated :class:`HardwareConfig` —
every sample crosses a TCP socket as 16-bit register counts and is scaled
back. The simulated person holding the handle lives on the plant side, so
the harness forwards the station's cue to them (``set_program``) — a real
person needs none.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import pytest

from app.engine.hardware.base import Command
from app.engine.hardware.config import HardwareConfig, ModbusLink, load_config, save_config
from app.engine.hardware.modbus import ModbusRig, PlantServer, counts_to_volts, serve_simulated_plant, volts_to_counts
from app.engine.hardware.sim import SimulatedRig
from app.engine.human import HumanProgram
from app.engine.ident.procedure import Script
from app.engine.loop import WallClock
from app.engine.station import RunSpec, Station

pytestmark = pytest.mark.slow


@pytest.fixture(autouse=True)
def _plant_is_another_device() -> Any:
    # in the lock-step tests plant and station share one interpreter, unlike a coupler and its master;
    # with the default 5 ms switch interval each request can wait that long for the lock, several
    # times per round trip
    import sys

    old = sys.getswitchinterval()
    sys.setswitchinterval(2e-4)
    yield
    sys.setswitchinterval(old)


METRICS = ("mae", "iae", "itae", "evar", "rmse", "maxae")  # the thesis's six (app/engine/metrics.py)
T = TypeVar("T")


def _plant_main(conn: Any, period: float) -> None:
    """The plant process: a simulated rig served over Modbus, steered by the harness through ``conn``."""
    from app.engine.loop import make_server_realtime

    # a coupler answers in a bounded time whatever else the station's computer does; where the OS
    # allows it, this process's threads (the server's among them) rank above normal ones as well
    make_server_realtime()
    server = serve_simulated_plant(_config(), period)
    rig = server.rig
    conn.send(server.port)
    while True:
        op, *args = conn.recv()
        if op == "program":  # times from the plant's now [s]
            rel_t, pos = args
            rig.set_program(HumanProgram(rel_t + rig.sim.t, pos))
            conn.send(None)
        elif op == "disturbance":
            rig.set_disturbance(*args)
            conn.send(None)
        elif op == "disconnect":
            server.disconnect()
            conn.send(None)
        elif op == "stats":
            conn.send({"requests": server.requests, "watchdog_trips": server.watchdog_trips,
                       "safe": rig.last_applied == rig.safe_command()})
        else:  # "stop"
            server.stop()
            conn.send(None)
            return


class PlantProcess:
    """A Modbus plant in a process of its own, as a coupler is a box of its own.

    In one interpreter with the station, the plant's server and simulator took
    the interpreter lock from the paced loop often enough to latch the overrun
    fault (five late periods in a row) in about one run in four of the paced
    tests here, on a machine doing nothing else — a harness artefact that a
    rig does not have.

    Args:
        period: The plant's nominal sampling period [s].
    """

    def __init__(self, period: float) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")  # not a fork of a process with threads running
        self._conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_plant_main, args=(child, period), daemon=True)
        self.proc.start()
        assert self._conn.poll(180.0), "the plant process did not start"  # a cold numba cache compiles first
        self.port = int(self._conn.recv())

    def _call(self, *msg: Any) -> Any:
        self._conn.send(msg)
        assert self._conn.poll(30.0), f"the plant process did not answer {msg[0]!r}"
        return self._conn.recv()

    def program_from_now(self, t: Any, pos: Any) -> None:
        """What the simulated person does, times counted from the plant's now [s], angles [rad]."""
        self._call("program", t, pos)

    def set_disturbance(self, dp_a_bar: float, dp_b_bar: float) -> None:
        """PRV-exit pressure disturbances [bar]."""
        self._call("disturbance", dp_a_bar, dp_b_bar)

    def disconnect(self) -> None:
        """Pull the cable: every connection closed, the coupler's watchdog keeps running."""
        self._call("disconnect")

    def stats(self) -> dict[str, Any]:
        """Requests served, watchdog trips, and whether the safe outputs are held."""
        return dict(self._call("stats"))

    def stop(self) -> None:
        """Power the coupler off and end the process."""
        if self.proc.is_alive():
            try:
                self._call("stop")
            except (AssertionError, OSError, EOFError):
                pass
        self.proc.join(10.0)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(5.0)


class HILRig(ModbusRig):
    """The Modbus backend plus the harness's line to the simulated person on the plant side."""

    plant: PlantProcess

    def set_program(self, program: HumanProgram) -> None:
        # the station cues on its clock; the plant counts from its own activation
        self.plant.program_from_now(program.t - self.clock.now(), program.pos)

    def set_disturbance(self, dp_a_bar: float = 0.0, dp_b_bar: float = 0.0) -> None:
        self.plant.set_disturbance(dp_a_bar, dp_b_bar)


def _config(**link: Any) -> HardwareConfig:
    return HardwareConfig(backend="modbus", modbus=ModbusLink(watchdog_register=1000, **link))


class HILFactory:
    """Backend factory for the station: starts a Modbus plant (a process of its own) at each connect.

    Args:
        station_config: The station's copy of the configuration (it may be
            miscalibrated); the plant side always scales with the defaults.
    """

    def __init__(self, station_config: HardwareConfig | None = None) -> None:
        self.plants: list[PlantProcess] = []
        self.station_config = station_config

    def __call__(self, clock: WallClock, period: float, rig: Any) -> HILRig:
        plant = PlantProcess(period)
        self.plants.append(plant)
        cfg = _config(port=plant.port)
        if self.station_config is not None:
            cfg = self.station_config.model_copy(update={"modbus": cfg.modbus})
        b = HILRig(cfg, clock, period, rig.kind)
        b.plant = plant
        return b

    def close(self) -> None:
        for p in self.plants:
            p.stop()


def _retrying_overruns(station: Station, attempt: Callable[[], T]) -> T:
    """``attempt()``, retried at most twice when the station's overrun fault ended it.

    The overrun fault (five late periods in a row) is the station's correct
    answer to a stall of the machine, and this 2-core VM stalls 30-40 ms now
    and then (one fresh-clone CI run, plant already in its own process:
    32 ms). Any other failure, or a third overrun, fails at once.
    """
    overran: list[str] = []
    while True:
        try:
            got = attempt()
        except AssertionError:
            fault = station.safety.fault if station.safety is not None else None
            if fault is None or fault.code != "overrun" or len(overran) == 2:
                raise
            overran.append(fault.message)
            station.clear()
            continue
        print("attempts ended by the overrun fault:", overran)
        return got


def _run_sc2(station: Station) -> dict[str, float]:
    station.connect()
    time.sleep(0.5)
    # the Default controller: with Eq 3.26's gains Cascade PID toggles chamber b every period (0.63 bar
    # sample to sample here, docs/controllers.md), and paced on the wall clock that chatter sent 2 of
    # 19 runs to an MAE of 1.2-1.7 N·m (the other 17 under 0.3): the controller's, not the link's. The
    # lock-step test below runs Cascade PID through the same link, deterministically
    station.start(RunSpec(scenario="SC-2", controller="default", target_nm=1.2))
    deadline = time.monotonic() + 60
    while station.state.value == "running":
        assert time.monotonic() < deadline, "the run did not end"
        time.sleep(0.1)
    assert station.state.value == "idle", (station.state, station.fault_message)
    last = station.last_run
    assert last is not None and last["status"] == "complete", last
    return {k: float(last["metrics"][k]) for k in METRICS if k in last["metrics"]}


# ------------------------------------------------------------------ the wire format


@pytest.mark.parametrize("v", [-10.0, -3.3, 0.0, 0.000305, 2.5, 9.9997, 10.0])
def test_register_counts_round_trip_within_one_count(v: float) -> None:
    assert abs(counts_to_volts(volts_to_counts(v)) - v) <= 10.0 / 32767 / 2 + 1e-12
    assert 0 <= volts_to_counts(v) <= 0xFFFF


def test_the_configuration_round_trips_through_yaml_and_refuses_bad_fields(tmp_path: Path) -> None:
    from app.engine.params import ParameterError

    cfg = _config(host="10.0.0.7", port=1502)
    save_config(cfg, tmp_path / "hw.yaml")
    assert load_config(tmp_path / "hw.yaml") == cfg
    bad = tmp_path / "bad.yaml"
    for text, words in [("backend: serial\n", "backend"),
                        ("inputs: {p_a: {channel: 1}}\n", "share a channel"),
                        ("outputs: {z_a: {channel: 0, v_min: 5, v_max: 1}}\n", "v_min"),
                        ("inputs: {torque: {channel: 3, gain: 0}}\n", "gain must be nonzero"),
                        ("backend: replay\n", "replay"),
                        ("limits: {p_max_bar: 40}\n", "p_max_bar"),
                        ("modbus: {port: 70000}\n", "modbus.port"),
                        ("typo_field: 1\n", "typo_field"),
                        ("- a list\n", "mapping"),
                        ("backend: [unclosed\n", "not valid YAML")]:
        bad.write_text(text)
        with pytest.raises(ParameterError, match=words):
            load_config(bad)
    with pytest.raises(ParameterError, match=r"does not exist|No such file"):
        load_config(tmp_path / "missing.yaml")


# ------------------------------------------------------------------ hardware in the loop


def test_samples_and_commands_cross_the_link_scaled_as_the_simulator_sees_them() -> None:
    clock = WallClock()
    sim = SimulatedRig(clock, pw_bar=3.0)
    sim.set_program(HumanProgram.rest())
    server = PlantServer(sim, _config()).start()
    try:
        rig = ModbusRig(_config(port=server.port), clock, 0.005)
        rig.activate()
        assert server.watchdog_s == pytest.approx(0.1)  # the coupler's watchdog was armed
        for _ in range(100):
            rig.read()
            applied = rig.write(Command(3.0, 1.0, 0.0, 10.0))
            time.sleep(0.004)
        m, direct = rig.read(), sim.read()
        assert applied == Command(3.0, 1.0, 0.0, 10.0)
        assert sim.last_applied.z_a == pytest.approx(3.0, abs=1e-3)  # one count of 10 V / 32767
        # the chamber-a pressure the station reads is the plant sensor's, within one 16-bit count (0.6 mbar)
        assert m.p_a == pytest.approx(direct.p_a, abs=0.02) and m.p_a > 3.5
        assert m.p_b == pytest.approx(direct.p_b, abs=0.02) and m.p_b < 2.5
        assert m.theta == pytest.approx(direct.theta, abs=2e-3)
        # out of range commands are clipped by the configured output ranges before they go out
        assert rig.write(Command(12.0, -1.0, 5.0, float("nan"))) == Command(10.0, 0.0, 5.0, 0.0)
        # the station goes quiet: the coupler's watchdog sets the safe outputs on its own (counted from
        # here: a busy CI neighbour once held the loop above past the watchdog's 0.1 s too, and it tripped)
        trips = server.watchdog_trips
        time.sleep(0.3)
        assert server.watchdog_trips == trips + 1 and sim.last_applied == rig.safe_command()
    finally:
        server.stop()


def test_cwrr_modbus_plant_serves_the_simulated_rig_to_the_station_backend() -> None:
    """``cwrr modbus-plant`` in a process of its own, driven by the station's Modbus backend as
    configured by default: chamber a fills and b vents on command, and Ctrl-C stops it cleanly."""
    import select
    import signal
    import subprocess
    import sys

    from tests.conftest import free_port

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "app", "modbus-plant", "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stderr is not None
        ready, _, _ = select.select([proc.stdout], [], [], 120.0)  # a cold numba cache compiles first
        banner = proc.stdout.readline() if ready else ""
        assert f"modbus://127.0.0.1:{port}" in banner, (banner, proc.poll())
        clock = WallClock()
        rig = ModbusRig(HardwareConfig(backend="modbus", modbus=ModbusLink(port=port)), clock, 0.005)
        rig.activate()
        start = rig.read()
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:
            rig.read()
            rig.write(Command(3.0, 1.0, 0.0, 10.0))
            time.sleep(0.005)
        m = rig.read()
        rig.deactivate()
        assert start.p_a < 1.2 and m.p_a > 3.5 and m.p_b < 2.5, (start, m)  # PRVs at 3 V and 1 V: ≈ 4 and 2 bar
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(20.0)
        except subprocess.TimeoutExpired:  # seen once in a loaded parallel run: say where it hangs
            proc.send_signal(signal.SIGUSR1)  # the plant dumps its threads' stacks (faulthandler)
            time.sleep(1.0)
            proc.kill()
            _, err = proc.communicate()
            pytest.fail(f"the plant did not stop within 20 s of Ctrl-C; its threads:\n{err[-6000:]}")
    assert rc == 0, proc.stderr.read() if proc.stderr else ""


@pytest.mark.serial  # paced: neighbours' load would be measured
def test_a_closed_link_mid_run_ends_in_the_safe_state_and_reconnecting_resumes(tmp_path: Path) -> None:
    factory = HILFactory()
    st = Station(factory, data_dir=tmp_path)

    def run_paced() -> int | None:
        st.connect()
        run_id = st.start(RunSpec(scenario="SC-1", controller="pid", target_nm=1.2))
        time.sleep(3.0)
        assert st.state.value == "running", st.fault_message
        return run_id

    try:
        run_id = _retrying_overruns(st, run_paced)
        plant = factory.plants[-1]
        t_cut = time.monotonic()
        plant.disconnect()  # the cable is pulled; the coupler stays powered
        deadline = time.monotonic() + 5
        while st.state.value != "fault":
            assert time.monotonic() < deadline, "no fault after the link closed"
            time.sleep(0.005)
        detected = time.monotonic() - t_cut
        fault = st.safety.fault
        assert fault is not None and fault.code == "link_lost", fault
        assert detected < 0.5, detected  # the next period's request fails (50 ms timeout at most)
        # on the plant side the coupler's watchdog (100 ms) sets the safe outputs: it lost its master
        time.sleep(0.15)
        stats = plant.stats()
        assert stats["watchdog_trips"] >= 1 and stats["safe"], stats
        # the run is recorded as ended by the fault, its log kept
        deadline = time.monotonic() + 5
        while st.last_run is None or st.last_run.get("run_id") != run_id:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert st.last_run["status"] == "fault"
        # clear, connect again (a new plant stands in for the repaired link): the station resumes
        st.clear()
        st.connect()
        assert st.state.value == "idle"
        time.sleep(0.3)
        assert factory.plants[-1].stats()["requests"] > 20
    finally:
        st.close()
        factory.close()


def _lockstep_sc2(through_modbus: bool) -> dict[str, float]:
    """SC-2 (Cascade PID, 1.2 N·m) on a simulated clock: deterministic, so two paths compare exactly."""
    import numpy as np

    from app.engine.control.interaction import InteractionController
    from app.engine.loop import Engine, SimClock
    from app.engine.safety import SafetyLimits, SafetySupervisor
    from app.engine.scenarios import ScenarioSettings, case_controller, case_program, main_cases, score_case

    settings = ScenarioSettings()
    case = next(c for c in main_cases() if c.scenario == "SC-2" and c.target == 1.2)
    prog, t_end, t_d = case_program(case, settings)
    clock = SimClock()
    sim = SimulatedRig(clock, pw_bar=settings.pw_bar, seed=5)
    sim.set_program(prog)
    server = None
    backend: Any = sim
    if through_modbus:
        server = PlantServer(sim, _config()).start()
        backend = ModbusRig(_config(port=server.port, timeout_s=1.0), clock, 0.005)
    ctl = InteractionController(case_controller(case, "pid", settings))
    rows: list[tuple[float, float, float]] = []
    safety = SafetySupervisor(SafetyLimits(), 0.005)
    eng = Engine(backend, ctl, clock, 200.0, safety=safety,
                 on_tick=lambda m, c: rows.append((m.t, m.torque, float(ctl.mode))))
    try:
        backend.activate()
        eng.run_for(t_end + 0.5)
    finally:
        if server is not None:
            backend.deactivate()
            server.stop()
    assert safety.fault is None, safety.fault
    a = np.asarray(rows)
    metrics, _w, _t_on = score_case(case, a[:, 0] - a[0, 0], a[:, 1], a[:, 2], t_end, t_d, settings)
    if server is not None:
        assert server.requests >= 2 * len(rows)  # every period read and wrote through the link
    return {k: float(metrics[k]) for k in METRICS}


def test_a_full_sc2_run_through_modbus_scores_within_10_percent_of_the_direct_simulator() -> None:
    # lock-step (simulated clock) so the only difference is the protocol path: 16-bit register
    # counts both ways, scaling by the configuration, speed estimated on the station side
    ref, got = _lockstep_sc2(False), _lockstep_sc2(True)
    print({k: (round(ref[k], 4), round(got[k], 4)) for k in ref})
    for k in METRICS:
        assert got[k] == pytest.approx(ref[k], rel=0.10), (k, got[k], ref[k])


@pytest.mark.serial  # paced: neighbours' load would be measured
def test_the_station_runs_sc2_over_modbus_in_real_time(tmp_path: Path) -> None:
    # paced on the wall clock, as on a rig: the run completes unfaulted and is scored; its figures
    # are not compared with a paced direct run's, which differ by 10-50 % from run to run (timing)
    factory = HILFactory()
    hil = Station(factory, data_dir=tmp_path)
    try:
        got = _retrying_overruns(hil, lambda: _run_sc2(hil))
        assert factory.plants[-1].stats()["requests"] > 2 * 200 * 8
    finally:
        hil.close()
        factory.close()
    assert set(got) == set(METRICS) and 0.0 < got["mae"] < 0.3, got


# ------------------------------------------------------------------ the linear rig over the same link


def _linear_tests_over(through_modbus: bool) -> Any:
    """Two static and two dynamic tests of the linear friction procedure on the C3 cylinder, lock-step."""
    from app.engine.ident.linear import LinearFrictionProcedure
    from app.engine.ident.procedure import run_procedure
    from app.engine.ident.runner import linear_inputs_for
    from app.engine.loop import SimClock
    from app.engine.params import PlantParams

    class FewTests(LinearFrictionProcedure):
        def script(self) -> Script:
            for d in ("extension", "retraction"):
                yield from self.static_test(d)
            for d in ("extension", "retraction"):
                yield from self.dynamic_test(d)

    params = PlantParams.linear_rig("C3")
    clock = SimClock()
    sim = SimulatedRig(clock, params, seed=3, period=0.005)
    sim.set_program(HumanProgram.absent())
    backend: Any = sim
    server = None
    if through_modbus:
        server = PlantServer(sim, _config()).start()
        backend = ModbusRig(_config(port=server.port, timeout_s=1.0), clock, 0.005, rig="linear")
    proc = FewTests(linear_inputs_for(params, 30, 30), seed=3, p_atm_bar=params.p_atm / 1e5)
    try:
        summary = run_procedure(proc, backend, clock, 200.0)
    finally:
        if server is not None:
            server.stop()
    assert summary.state == "finished", summary
    return proc.data


def test_the_linear_rig_runs_its_identification_tests_through_modbus_as_on_the_simulator() -> None:
    """Issue 8 item 6: the same procedures on every backend — the linear cylinder's encoder crosses
    the link in 0.01 mm counts and comes back in metres; breakaway forces and run speeds agree with
    the direct simulator's within the register grid's and the station-side speed estimate's reach."""
    ref, got = _linear_tests_over(False), _linear_tests_over(True)
    assert len(got.static) == len(ref.static) == 2 and len(got.dynamic) == len(ref.dynamic) == 2
    for a, b in zip(ref.static, got.static, strict=True):
        assert math.isfinite(a.fs) and b.fs == pytest.approx(a.fs, rel=0.05), (a, b)
        # the moves to the random test position (metres on both paths) took as long
        assert b.t_start == pytest.approx(a.t_start, rel=0.05, abs=0.05), (a.t_start, b.t_start)
    for a, b in zip(ref.dynamic, got.dynamic, strict=True):
        assert math.isfinite(a.v) and b.v == pytest.approx(a.v, rel=0.05), (a.v, b.v)
        assert b.ff == pytest.approx(a.ff, rel=0.05), (a.ff, b.ff)


def test_a_watchdog_write_waits_for_the_request_under_way_instead_of_interleaving() -> None:
    """The engine's watchdog thread writes the safe outputs while the loop thread may be inside a
    request; the sync pymodbus client is not thread-safe, so the backend runs one request at a time."""
    import threading

    class Reply:
        registers = [0] * 64

        @staticmethod
        def isError() -> bool:  # pymodbus spells it so
            return False

    class SlowClient:
        def __init__(self) -> None:
            self.busy = False
            self.overlaps = 0
            self.calls: list[str] = []

        def _req(self, name: str) -> Reply:
            if self.busy:
                self.overlaps += 1
            self.busy = True
            self.calls.append(name)
            if name == "read":
                reading.set()
            time.sleep(0.05 if name == "read" else 0.0)
            self.busy = False
            return Reply()

        def read_input_registers(self, *a: Any, **k: Any) -> Reply:
            return self._req("read")

        def write_registers(self, *a: Any, **k: Any) -> Reply:
            return self._req("write")

        def close(self) -> None:
            pass

    reading = threading.Event()
    rig = ModbusRig(_config(), WallClock(), 0.005)
    client = SlowClient()
    rig.client = client
    reader = threading.Thread(target=rig.read)
    reader.start()
    assert reading.wait(10)  # the read is under way
    rig.write(rig.safe_command())  # the watchdog's write
    reader.join()
    assert client.overlaps == 0 and client.calls == ["read", "write"]
    rig.deactivate()
    with pytest.raises(Exception, match="link is closed"):
        rig.read()  # a closed link is a lost link, not an AttributeError
