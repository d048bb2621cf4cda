"""Issue 7: the safety supervisor, fault injection, the watchdog and the emergency stop.

Every injected fault must end in the fault state's command within one control
period of its detection, with the run log intact; detection latency is
bounded per fault (immediate for NaN, jumps and glitches; the configured
persistence time for stuck channels and supply loss).
"""

from __future__ import annotations

import csv
import json
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.engine.constants import BAR, P_ATM
from app.engine.control.config import ControllerConfig
from app.engine.control.interaction import InteractionController
from app.engine.hardware.base import Command, Measurement
from app.engine.hardware.faults import FaultyRig
from app.engine.hardware.sim import SimulatedRig
from app.engine.human import isotonic
from app.engine.loop import Engine, SimClock, WallClock
from app.engine.params import ParameterError
from app.engine.runlog import RunLogWriter
from app.engine.safety import VENT_COMMAND, SafetyLimits, SafetySupervisor

PERIOD = 0.005
AT = 2.5  # fault time [s]: mid-motion of the isotonic program, chambers at P_w


def _meas(t: float = 0.0, p_a: float = 3.0, p_b: float = 3.0, theta: float = 0.0, torque: float = 0.1,
          p_s: float = 8.0) -> Measurement:
    return Measurement(t, p_a, p_b, p_s, theta, 0.0, torque)


# ---------------------------------------------------------------- the stage alone

def test_commands_are_clipped_to_the_pressure_limit_and_slew_limited() -> None:
    s = SafetySupervisor(SafetyLimits(p_max_bar=5.0, slew_bar_s=100.0), PERIOD)
    out = s.apply(Command(9.0, -1.0, 12.0, 5.0), _meas())
    assert (out.z_a, out.z_b, out.u_a) == (5.0, 0.0, 10.0)
    # 100 bar/s × 5 ms = 0.5 bar per period
    out = s.apply(Command(0.0, 4.0, 0.0, 10.0), _meas(0.005))
    assert out.z_a == pytest.approx(4.5) and out.z_b == pytest.approx(0.5)
    assert s.fault is None


def test_the_no_action_zone_holds_equal_pressures_only_against_outward_commands() -> None:
    s = SafetySupervisor(SafetyLimits(rom_deg=270.0, soft_margin_deg=10.0, slew_bar_s=1e3), PERIOD)
    near_ccw = math.radians(130.0)
    out = s.apply(Command(3.0, 1.0, 0.0, 10.0), _meas(theta=near_ccw))  # p_a > p_b drives CCW: further out
    assert out.z_a == out.z_b == 3.0 and s.no_action
    out = s.apply(Command(1.0, 3.0, 0.0, 10.0), _meas(0.005, theta=near_ccw))  # back towards neutral: passes
    assert (out.z_a, out.z_b) == (1.0, 3.0) and not s.no_action
    assert s.fault is None


@pytest.mark.parametrize(("meas", "code"), [
    (_meas(p_a=math.nan), "sensor_nan"),
    (_meas(p_b=15.0), "sensor_range"),
    (_meas(theta=math.radians(150.0)), "sensor_range"),
    (_meas(torque=9.95), "torque_saturation"),
    (_meas(torque=-8.5), "torque_limit"),
])
def test_an_implausible_measurement_latches_a_fault_and_the_safe_state_at_once(meas: Measurement, code: str) -> None:
    s = SafetySupervisor(period=PERIOD)
    assert s.apply(Command(2.0, 2.0, 0.0, 10.0), meas) == VENT_COMMAND
    assert s.fault is not None and s.fault.code == code and s.fault.t == 0.0
    # latched: a good measurement does not release it
    assert s.apply(Command(2.0, 2.0, 0.0, 10.0), _meas(0.005)) == VENT_COMMAND
    s.reset()
    assert s.apply(Command(2.0, 2.0, 0.0, 10.0), _meas(0.01)) == Command(2.0, 2.0, 0.0, 10.0)


def test_a_pressure_jump_no_chamber_can_make_is_a_glitch_but_the_fastest_real_filling_is_not() -> None:
    s = SafetySupervisor(period=PERIOD)
    s.apply(Command(2.0, 2.0, 0.0, 10.0), _meas(0.0, p_a=1.2))
    # 2.3 bar in one period: the simulator's fastest in the thesis scenarios (SC-1, -1.2 N·m, Cascade PID)
    assert s.apply(Command(2.0, 2.0, 0.0, 10.0), _meas(PERIOD, p_a=3.5)) != VENT_COMMAND and s.fault is None
    assert s.apply(Command(2.0, 2.0, 0.0, 10.0), _meas(2 * PERIOD, p_a=7.9)) == VENT_COMMAND  # 4.4 bar in 5 ms
    assert s.fault is not None and s.fault.code == "pressure_jump" and s.fault.channel == "p_a"


def test_a_nan_command_is_a_controller_fault_not_a_clipped_value() -> None:
    s = SafetySupervisor(period=PERIOD)
    assert s.apply(Command(math.nan, 2.0, 0.0, 10.0), _meas()) == VENT_COMMAND
    assert s.fault is not None and s.fault.code == "controller_nan" and s.fault.channel == "z_a"


def test_the_first_fault_is_kept_as_the_cause_and_trip_works_from_another_thread() -> None:
    s = SafetySupervisor(period=PERIOD)
    th = threading.Thread(target=s.trip, args=("estop", "emergency stop (test)"))
    th.start()
    th.join()
    s.apply(Command(2.0, 2.0, 0.0, 10.0), _meas(p_a=math.nan))
    assert s.fault is not None and s.fault.code == "estop" and s.faults_total == 1


def test_a_fault_stamped_from_another_thread_reads_the_time_once_it_is_in_force() -> None:
    # An e-stop read the engine's time, then latched: a caller kept waiting in between (a loaded
    # machine) stamped the fault a period or more before the periods that still ran on with the
    # exercise's command. The time is now read once the fault is in force, so every period whose
    # measurement is newer than it writes the safe state.
    s = SafetySupervisor(period=PERIOD)
    safe_when_read: list[bool] = []

    def now() -> float:
        safe_when_read.append(s.apply(Command(2.0, 2.0, 0.0, 10.0), _meas(0.0)) == VENT_COMMAND)
        return 1.25

    f = s.trip("estop", "emergency stop (test)", now)
    assert safe_when_read == [True] and f.t == 1.25 and s.fault == f and s.faults_total == 1
    assert s.trip("stall", "later", lambda: 9.0) is f  # the first fault stays the cause, its time too


@pytest.mark.parametrize(("kw", "words"), [
    ({"p_max_bar": 9.0}, "p_max_bar"),
    ({"torque_max_nm": 12.0}, "torque_max_nm"),
    ({"p_range_bar": (5.0, 1.0)}, "p_range_bar"),
    ({"overruns_max": 0}, "overruns_max"),
])
def test_bad_limits_are_refused_with_the_field_named(kw: dict, words: str) -> None:
    with pytest.raises(ParameterError, match=words):
        SafetyLimits(**kw)


finite = st.floats(-1e3, 1e3)
anyf = st.floats(allow_nan=True, allow_infinity=True)


@settings(max_examples=300, deadline=None)
@given(z_a=anyf, z_b=anyf, u_a=anyf, u_b=anyf, p_a=anyf, p_b=anyf, theta=anyf, torque=anyf)
def test_whatever_comes_in_the_output_is_within_limits_or_the_fault_state(
        z_a: float, z_b: float, u_a: float, u_b: float, p_a: float, p_b: float, theta: float, torque: float) -> None:
    lim = SafetyLimits(p_max_bar=5.0)
    s = SafetySupervisor(lim, PERIOD)
    out = s.apply(Command(z_a, z_b, u_a, u_b), _meas(0.0, p_a, p_b, theta, torque))
    if s.fault is not None:
        assert out == VENT_COMMAND
    else:
        assert 0.0 <= out.z_a <= 5.0 and 0.0 <= out.z_b <= 5.0
        assert 0.0 <= out.u_a <= 10.0 and 0.0 <= out.u_b <= 10.0


# ------------------------------------------------------------ fault injection

def _engine(tmp_path: Path, fault: dict | None, duration: float = 4.5) -> tuple[Engine, SafetySupervisor, Path,
                                                                                  list[tuple[float, ...]]]:
    """An isotonic workout on the Default controller at P_w = 3 bar, faulted at ``AT``, logged."""
    clock = SimClock()
    sim = SimulatedRig(clock, pw_bar=3.0, seed=1)
    sim.set_program(isotonic(+1, repetitions=1, amplitude=math.radians(50.0)))
    rig = FaultyRig(sim)
    if fault:
        rig.inject(at=AT, **fault)
    safety = SafetySupervisor(SafetyLimits(), PERIOD)
    log = RunLogWriter(tmp_path, "run", {"rig": "rotary", "sample_rate_hz": 200.0, "p_atm_bar": P_ATM / BAR,
                                         "working_pressure_bar": 3.0, "experiment": "workout", "human": True})
    truth: list[tuple[float, ...]] = []

    def observe(m: Measurement, c: Command) -> None:
        tr = sim.sim.truth()
        truth.append((m.t, tr["p_a_bar"], tr["p_b_bar"]))

    eng = Engine(rig, InteractionController(ControllerConfig(controller="default", pw_bar=3.0)), clock, 200.0,
                 safety=safety, recorder=log, on_tick=observe)
    rig.activate()
    try:
        eng.run_for(duration)
    except ConnectionError:
        pass  # the link fault: the engine has already written the safe state and latched it
    log.close("fault" if safety.fault else "complete")
    return eng, safety, log.csv_path, truth


FAULTS: list[tuple[dict[str, Any], set[str], float]] = [
    ({"kind": "nan", "channel": "p_a"}, {"sensor_nan"}, PERIOD),
    ({"kind": "dropout", "channel": "p_a"}, {"sensor_range"}, PERIOD),
    ({"kind": "dropout", "channel": "torque"}, {"sensor_stuck"}, 0.5 + 2 * PERIOD),
    ({"kind": "stuck_sensor", "channel": "p_b"}, {"sensor_stuck"}, 0.5 + 2 * PERIOD),
    ({"kind": "encoder_glitch", "counts": 400}, {"encoder_glitch"}, PERIOD),
    # the PRV jams at 6 V: the arm is pushed (torque limit) before the chamber-follow check's 0.5 s
    ({"kind": "stuck_prv", "side": "a", "value": 6.0}, {"torque_limit", "prv_not_following", "pressure_limit"}, 0.6),
    ({"kind": "supply_loss", "value": 1.5}, {"supply_lost"}, 0.3 + 2 * PERIOD),
    ({"kind": "link_lost"}, {"link_lost"}, PERIOD),
]


@pytest.mark.parametrize(("fault", "codes", "latency"), FAULTS, ids=[f[0]["kind"] + "-" + str(f[0].get("channel", ""))
                                                                    for f in FAULTS])
def test_every_injected_fault_ends_in_the_safe_state_within_one_period_with_the_log_intact(
        tmp_path: Path, fault: dict[str, Any], codes: set[str], latency: float) -> None:
    eng, safety, csv_path, truth = _engine(tmp_path, fault)
    f = safety.fault
    assert f is not None and f.code in codes, f
    if f.code == "link_lost":
        # nothing was read in the faulted period; the safe state went out in it
        assert eng.backend.inner.last_applied == VENT_COMMAND  # type: ignore[attr-defined]
        assert eng.error is not None
    else:
        assert AT <= f.t <= AT + latency + 1e-9, f"detected {f.t - AT:.3f} s after the fault"
    with csv_path.open() as fh:
        rows = list(csv.DictReader(fh))
    meta = json.loads(csv_path.with_suffix(".json").read_text())
    assert meta["status"] == "fault" and len(rows) == eng.ticks  # every period logged, none lost
    t = np.array([float(r["t"]) for r in rows])
    assert np.all(np.diff(t) > 0)
    cmd = np.array([[float(r[k]) for k in ("z_a", "z_b", "u_a", "u_b")] for r in rows])
    # a lost link logs no row for the period it failed in
    first = len(t) if f.code == "link_lost" else int(np.searchsorted(t, f.t))
    # the detection period itself writes the safe state, and every later one
    assert np.all(cmd[first:] == [VENT_COMMAND.z_a, VENT_COMMAND.z_b, VENT_COMMAND.u_a, VENT_COMMAND.u_b])
    assert not np.all(cmd[first - 1] == [0.0, 0.0, 10.0, 0.0])  # ... and not before it
    if f.code != "link_lost":
        tr = np.array(truth)
        after = tr[tr[:, 0] >= f.t]
        # no net torque left and the chambers vented: |Δp| < 0.05 bar after 0.3 s, both near atmosphere after 1 s
        assert np.abs(after[after[:, 0] >= f.t + 0.3, 1] - after[after[:, 0] >= f.t + 0.3, 2]).max() < 0.05
        assert after[after[:, 0] >= f.t + 1.0, 1:].max() < 1.2


def test_a_healthy_workout_trips_nothing(tmp_path: Path) -> None:
    """The checks must not fire on the rig they protect (noise, motion, pressurising)."""
    eng, safety, _, _ = _engine(tmp_path, None, duration=8.0)
    assert safety.fault is None and eng.ticks == 1600


@pytest.mark.slow
@pytest.mark.parametrize(("scenario", "target", "controller"), [
    ("SC-1", -1.2, "pid"), ("SC-1", -0.6, "pid"), ("SC-2", -0.6, "pid"), ("SC-3", 1.2, "fuzzy"),
    ("SC-4", 0.6, "fuzzy"), ("SC-2", 1.2, "default")])
def test_the_thesis_scenarios_trip_nothing(scenario: str, target: float, controller: str) -> None:
    """The cases with the steepest pressures of the compiled runs (up to 2.3 bar per period) pass the checks."""
    from app.engine.scenarios import ScenarioSettings, case_controller, case_program, main_cases

    case = next(c for c in main_cases() if c.scenario == scenario and c.target == target)
    prog, t_end, t_d = case_program(case)
    clock = SimClock()
    sim = SimulatedRig(clock, pw_bar=ScenarioSettings().pw_bar, seed=2)
    sim.set_program(prog)
    safety = SafetySupervisor(SafetyLimits(), PERIOD)
    eng = Engine(sim, InteractionController(case_controller(case, controller)), clock, 200.0,  # type: ignore[arg-type]
                 safety=safety)
    sim.activate()
    if t_d is not None and scenario == "SC-4":
        eng.run_for(t_d)
        sim.set_disturbance(0.0, ScenarioSettings().dp_b_bar)
        eng.run_for(t_end + 0.5 - t_d)
    else:
        eng.run_for(t_end + 0.5)
    assert safety.fault is None, safety.fault


@pytest.mark.serial
def test_the_watchdog_puts_a_stalled_loop_in_the_safe_state(tmp_path: Path) -> None:
    """A hung DAQ call (``read`` blocks 0.6 s): the watchdog thread writes the fault state itself."""
    clock = WallClock()
    sim = SimulatedRig(clock, pw_bar=3.0)
    rig = FaultyRig(sim)
    safety = SafetySupervisor(period=PERIOD)
    eng = Engine(rig, InteractionController(ControllerConfig(controller="default", pw_bar=3.0)), clock, 200.0,
                 safety=safety, stall_s=0.1)
    rig.activate()
    eng.start()
    try:
        time.sleep(0.3)
        rig.inject("stall", at=sim.sim.t, value=0.6)
        t0 = time.monotonic()
        while sim.last_applied != VENT_COMMAND and time.monotonic() - t0 < 2.0:
            time.sleep(0.002)
        waited = time.monotonic() - t0
    finally:
        eng.stop()
    assert safety.fault is not None and safety.fault.code == "stall", safety.fault
    # stall_s, plus the watchdog's poll (a period), plus one period of slack for the scheduler
    assert waited < 0.1 + 3 * PERIOD + 0.05, waited
    assert eng.stalls == 1


# ------------------------------------------------------------ through the API

def test_the_emergency_stop_acts_from_any_state_and_ends_a_run_as_a_fault(tmp_path: Path) -> None:
    from fastapi.testclient import TestClient

    from app.api.main import create_app
    from app.api.settings import Settings

    app = create_app(Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False))
    with TestClient(app) as c:
        st = c.post("/api/engine/estop").json()  # even disconnected it latches: clear before anything moves
        assert st["state"] == "fault" and st["safety"]["fault"]["code"] == "estop" and st["allowed"] == ["clear"]
        assert c.post("/api/engine/connect").status_code == 409
        assert c.post("/api/engine/clear").json()["state"] == "disconnected"
        c.post("/api/engine/connect")
        rid = c.post("/api/engine/start", json={"scenario": "SC-1", "controller": "default"}).json()["run_id"]
        deadline = time.monotonic() + 30
        while c.get("/api/engine").json()["progress"]["phase"] != "exercising" and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        st = c.post("/api/engine/estop").json()
        assert st["state"] == "fault" and "emergency stop" in st["fault"]
        t_f = st["safety"]["fault"]["t"]
        while c.get("/api/engine").json()["last_run"] is None and time.monotonic() < deadline:
            time.sleep(0.05)
        run = c.get(f"/api/runs/{rid}").json()
        assert run["status"] == "fault" and run["result"]["fault"]["code"] == "estop", run
        rows = list(csv.DictReader(c.get(f"/api/runs/{rid}/export").text.splitlines()))
        t = np.array([float(r["t"]) for r in rows])
        cmd = np.array([[float(r[k]) for k in ("z_a", "z_b", "u_a", "u_b")] for r in rows])
        assert t[-1] > t_f + PERIOD  # the log runs on into the safe state
        # the period under way when it was pressed may still finish its own command; the next one is safe
        assert np.all(cmd[t > t_f + PERIOD + 1e-9] == [0.0, 0.0, 10.0, 0.0])
        assert np.any(cmd[t <= t_f] != [0.0, 0.0, 10.0, 0.0])
        (meta,) = (tmp_path / "runs").glob("*.json")
        assert json.loads(meta.read_text())["status"] == "fault"
        assert c.post("/api/engine/clear").json()["state"] == "disconnected"


def _stop_with_the_handle_out(st: Any, theta_rad: float) -> float:
    """Connect, start SC-1 and stop it once the handle is ``theta_rad`` out; returns |θ| then [rad]."""
    from app.engine.station import LIVE_COLUMNS, RunSpec

    th = LIVE_COLUMNS.index("theta")
    st.connect()
    st.start(RunSpec(scenario="SC-1", controller="pid", target_nm=1.2))
    deadline = time.monotonic() + 30
    while (last := st.live.latest()) is None or abs(last[th]) < theta_rad:
        assert time.monotonic() < deadline and st.state.value == "running"
        time.sleep(0.05)
    st.stop()
    return abs(float(last[th]))


@pytest.mark.slow
def test_a_run_started_right_after_one_that_ended_far_from_neutral_does_not_yank_the_arm(tmp_path: Path) -> None:
    # found by the torque limit: the simulated user used to jump from where the handle was
    # back to neutral at the next program start, an 8 N·m yank on the arm
    from app.engine.station import LIVE_COLUMNS, RunSpec, Station

    st = Station(data_dir=tmp_path)
    try:
        th, tq = LIVE_COLUMNS.index("theta"), LIVE_COLUMNS.index("torque")
        _stop_with_the_handle_out(st, 1.0)
        newest = st.live.latest()
        assert newest is not None
        t_start = float(newest[0])
        st.start(RunSpec(scenario="SC-1", controller="pid", target_nm=1.2))
        time.sleep(5.0)  # the return to neutral (≤ 4 s from ±1.5 rad) and the program's start
        assert st.state.value == "running" and st.safety.fault is None, st.safety.fault
        rows = st.live.since(t_start, 100_000)
        assert len(rows) > 500 and np.max(np.abs(rows[:, tq])) < 3.0, np.max(np.abs(rows[:, tq]))
        assert abs(rows[-1, th]) < abs(rows[0, th])  # the handle came back towards neutral
        st.stop()
    finally:
        st.close()


def test_a_runs_end_lowers_both_chambers_together_from_where_they_are() -> None:
    # a controlled stop: dropped at once (the slew limit's 200 bar/s), the smaller chamber vented in
    # 10 ms and the larger in 50, and up to 2.5 N·m swung onto the arm at the end of every exercise
    from app.engine.control.interaction import InteractionController
    from app.engine.hardware.base import SAFE_COMMAND
    from app.engine.station import RELEASE_S, RunJob, RunSpec

    spec = RunSpec(scenario="SC-1", controller="pid", target_nm=1.2)
    starts: list[float] = []
    job = RunJob(spec, InteractionController(spec.controller_config()), t_end=5.0, t_d=None,
                 on_program_start=starts.append, on_disturbance=lambda: None, pressurise_s=0.1)
    dt, p_atm = 0.005, spec.controller_config().p_atm_bar

    def meas(t: float, p_a: float, p_b: float) -> Measurement:
        return Measurement(t=t, p_a=p_a, p_b=p_b, p_s=8.0, theta=0.5, omega=0.0, torque=1.2)

    t = 0.0
    for k in range(200):  # exercising; chamber b toggles 1.4 bar from one period to the next
        t = k * dt
        job.step(meas(t, 3.4, 3.0 if k % 2 else 4.4), dt)
    assert starts and not job.done and job.t_release is None
    job.request_stop()
    t += dt
    first = job.step(meas(t, 3.4, 3.0), dt)  # the sample it starts on is a low one: the average counts
    assert job.t_release == t and job.ending == "stopped"
    # near b's mean (3.7), not the sample's 3.0: two low samples in a row leave the average 0.1 under it
    assert first.z_a == pytest.approx(3.4 - p_atm, abs=0.01) and first.z_b == pytest.approx(3.7 - p_atm, abs=0.15)
    cmds = [first]
    while not job.done:
        t += dt
        cmds.append(job.step(meas(t, 9.9, 0.1), dt))  # what it reads now no longer matters
    z = np.array([[c.z_a, c.z_b] for c in cmds])
    assert all((c.u_a, c.u_b) == (SAFE_COMMAND.u_a, SAFE_COMMAND.u_b) for c in cmds)  # the PRVs vent them
    assert np.all(np.diff(z, axis=0) <= 1e-12)  # only ever lower
    ratio = z[:-1, 1] / z[:-1, 0]
    assert np.ptp(ratio) < 1e-9  # together: the difference falls with the pressures
    assert (len(cmds) - 1) * dt == pytest.approx(RELEASE_S, abs=1.5 * dt)
    assert cmds[-1] == SAFE_COMMAND and job.step(meas(t + dt, 3.0, 3.0), dt) == SAFE_COMMAND
    # a run stopped before its first period has nothing to lower; a failing cue does not stop the release
    def broken(_t: float) -> None:
        raise RuntimeError("no user")

    idle = RunJob(spec, InteractionController(spec.controller_config()), 5.0, None, starts.append, lambda: None,
                  on_release=broken)
    idle.request_stop()
    assert idle.step(meas(0.0, 1.0, 1.0), dt) == SAFE_COMMAND and idle.done


@pytest.mark.slow
def test_stop_and_a_runs_end_leave_the_arm_where_it_is(tmp_path: Path) -> None:
    # STOP mid-exercise and an exercise run to its end: the handle swung at up to 1.8 rad/s and the
    # torque on the arm reversed by up to 2.4 N·m when both chambers were dropped at once and the
    # simulated user let go of their push within one period
    from app.engine.station import LIVE_COLUMNS, RELEASE_S, RunSpec, Station

    tq, om = (LIVE_COLUMNS.index(c) for c in ("torque", "omega"))
    st = Station(data_dir=tmp_path)
    try:
        st.connect()
        for scenario, stop_after in (("SC-1", 6.0), ("SC-2", None)):
            st.start(RunSpec(scenario=scenario, controller="pid", target_nm=1.2))
            job = st._job
            assert job is not None
            if stop_after is not None:
                time.sleep(stop_after)
                t0 = time.monotonic()
                st.stop()  # answers once the run has ended, the release included
                assert RELEASE_S <= time.monotonic() - t0 < RELEASE_S + 1.0
                assert st.state.value == "idle" and st.last_run is not None
                assert st.last_run["status"] == "stopped"
            else:
                deadline = time.monotonic() + 30
                while st.state.value != "idle":
                    assert time.monotonic() < deadline and st.state.value in ("running", "stopping")
                    time.sleep(0.02)
                assert st.last_run is not None and st.last_run["status"] == "complete"
            time.sleep(1.0)
            assert job.t_release is not None
            rows = st.live.since(job.t_release - 0.2, 100_000)
            before = rows[rows[:, 0] <= job.t_release]
            after = rows[(rows[:, 0] > job.t_release + 0.02) & (rows[:, 0] < job.t_release + 1.0)]
            assert len(after) > 150  # the live buffer holds the loop's 200 Hz during a run
            # measured on 12 ends (SC-1–4, three runs each): ≤ 0.02 rad/s and ≤ 0.15 N·m of reversal; the
            # code before, 0.0–1.8 rad/s and up to 2.4 N·m
            assert np.max(np.abs(after[:, om])) < 0.2, (scenario, np.max(np.abs(after[:, om])))
            # no reversal onto the arm: the torque stays within what it was and nothing
            lo, hi = min(0.0, float(before[-20:, tq].min())), max(0.0, float(before[-20:, tq].max()))
            assert lo - 0.4 < after[:, tq].min() and after[:, tq].max() < hi + 0.4, (scenario, lo, hi)
            if scenario == "SC-1":
                time.sleep(6.0)  # the user back at neutral before the next
    finally:
        st.close()


@pytest.mark.slow
def test_after_a_run_the_simulated_user_brings_the_handle_back_and_relaxes(tmp_path: Path) -> None:
    # the vented vane's static friction stops it short of neutral; a user pressing on there had
    # shown about 1.2 N·m on the idle station's live plot until the next run
    from app.engine.station import LIVE_COLUMNS, Station

    st = Station(data_dir=tmp_path)
    try:
        th, tq = LIVE_COLUMNS.index("theta"), LIVE_COLUMNS.index("torque")
        theta_end = _stop_with_the_handle_out(st, 0.8)
        # 1 s for the chambers to vent, the move back (π/2 · θ / 0.5 rad/s), the relax, a margin
        time.sleep(1.0 + math.pi / 2 * theta_end / 0.5 + 1.5)
        assert st.state.value == "idle"
        newest = st.live.latest()
        assert newest is not None
        rows = st.live.since(float(newest[0]) - 0.5, 100_000)
        assert abs(float(np.mean(rows[:, th]))) < 0.15 * theta_end  # back near neutral
        assert abs(float(np.mean(rows[:, tq]))) < 0.1, np.mean(rows[:, tq])  # and nobody pressing
    finally:
        st.close()


class _FullDisk:
    """A log file on a disk that fills after ``budget`` characters (writes then fail with ENOSPC)."""

    def __init__(self, fh: Any, budget: int) -> None:
        self.fh, self.left = fh, budget

    @property
    def closed(self) -> bool:
        return bool(self.fh.closed)

    def write(self, text: str) -> int:
        import errno

        if len(text) > self.left:
            self.left = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self.left -= len(text)
        return int(self.fh.write(text))

    def flush(self) -> None:
        self.fh.flush()

    def fileno(self) -> int:
        return int(self.fh.fileno())

    def close(self) -> None:
        self.fh.close()


class _Sink:
    """A run store that records how each run ended, or, ``full``, cannot record it (a full disk)."""

    def __init__(self, full: bool = False) -> None:
        self.full = full
        self.ended: list[tuple[str, Any, Any]] = []

    def run_started(self, kind: str, spec: dict[str, Any], log_csv: str) -> int:
        return 1

    def run_finished(self, run_id: int, status: str, metrics: Any, result: Any) -> None:
        if self.full:
            raise OSError(28, "database or disk is full")
        self.ended.append((status, metrics, result))


@pytest.mark.parametrize("store_full", [False, True])
def test_a_full_disk_mid_run_ends_it_as_a_fault_and_the_station_comes_back(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, store_full: bool) -> None:
    """The log's writer thread died on ENOSPC and the run went on unrecorded; STOP then raised the
    same error and left the station running. Now the station latches ``log_failed`` (safe state),
    ends the run as a fault, and a store that cannot record that either does not hold it up."""
    import app.engine.station as station_mod
    from app.engine.station import RunSpec, Station

    class OnFullDisk(RunLogWriter):
        def __init__(self, *a: Any, **kw: Any) -> None:
            super().__init__(*a, **kw)
            self._fh = _FullDisk(self._fh, 20_000)  # type: ignore[assignment]  # ≈ 1.2 s of rows

    monkeypatch.setattr(station_mod, "RunLogWriter", OnFullDisk)
    sink = _Sink(full=store_full)
    st = Station(data_dir=tmp_path, sink=sink)  # type: ignore[arg-type]
    try:
        st.connect()
        st.start(RunSpec("SC-1", "default", 1.2, 3.0, "P-full"))
        deadline = time.monotonic() + 10.0
        while st.state.value != "fault":
            assert time.monotonic() < deadline, "the run went on unrecorded"
            time.sleep(0.05)
        f = st.safety.fault
        assert f is not None and f.code == "log_failed" and "No space left on device" in f.message, f
        assert "free space in the data folder" in f.message
        while st.status()["last_run"] is None:  # the watcher ends the run once a safe period is logged
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert st.status()["last_run"]["status"] == "fault" and st._job is None
        assert [e[0] for e in sink.ended] == ([] if store_full else ["fault"])
        st.clear()
        assert st.state.value == "disconnected"
    finally:
        st.close()


def test_a_log_on_a_full_disk_closes_without_raising_and_says_why(tmp_path: Path) -> None:
    """STOP closes the run's log: on a full disk that close raised, and the station stayed running."""
    w = RunLogWriter(tmp_path, "full", {"rig": "rotary", "sample_rate_hz": 200.0, "p_atm_bar": 1.01325,
                                        "working_pressure_bar": 3.0, "experiment": "workout", "human": True},
                     threaded=True, write_every_s=0.02)
    w._fh = _FullDisk(w._fh, 3000)  # type: ignore[assignment]
    for i in range(400):
        w.append([i / 200, 2, 2, 5, 5, 2, 2, 6, 0, 0, 0.1])
        time.sleep(0.0005)
    deadline = time.monotonic() + 5.0
    while not w.error:  # the writer thread, not the loop, meets the full disk
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert w.error.startswith("No space left on device") and any(t.is_alive() for t in w._threads)
    w.close("stopped")  # does not raise
    meta = json.loads((tmp_path / "full.json").read_text())
    assert meta["status"] == "stopped" and meta["write_error"].startswith("No space left on device")


def test_a_run_that_cannot_be_recorded_does_not_start_and_changes_nothing(tmp_path: Path) -> None:
    """A store that refuses the run (a full disk): the exception had come through as a 500, with the
    run's log left open and its threads running; an identification had stopped the loop first."""
    import sqlite3

    from app.engine.station import RunSpec, Station, TransitionError

    class FullStore:
        def run_started(self, kind: str, spec: dict[str, Any], log_csv: str) -> int:
            raise sqlite3.OperationalError("database or disk is full")

        def run_finished(self, run_id: int, status: str, metrics: Any, result: Any) -> None:
            raise AssertionError("nothing started")

    st = Station(data_dir=tmp_path, sink=FullStore())  # type: ignore[arg-type]
    try:
        st.connect()
        time.sleep(0.3)
        threads = {t.name for t in threading.enumerate()}
        with pytest.raises(TransitionError, match=r"cannot start while idle: the run cannot be recorded "
                                                  r"\(database or disk is full\); free space"):
            st.start(RunSpec("SC-1", "default", 1.2, 3.0, "P"))
        with pytest.raises(TransitionError, match=r"cannot estimate while idle: the run cannot be recorded"):
            st.run_protocol(scale=0.2)
        assert st.state.value == "idle" and st._job is None and st._proc is None and st._log is None
        assert not list((tmp_path / "runs").glob("*.csv")) if (tmp_path / "runs").exists() else True
        assert {t.name for t in threading.enumerate()} - threads == set()  # no log writer left running
        before = st.live.latest()
        time.sleep(0.2)
        after = st.live.latest()
        assert before is not None and after is not None and after[0] > before[0]  # the loop runs on
        assert st.engine is not None and st.engine.period == pytest.approx(1 / 200)
    finally:
        st.close()


def test_a_run_whose_scoring_fails_still_ends_and_is_recorded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A bug in scoring (anything but the short window's ValueError) had come out of STOP, leaving the
    station running; from the watcher it would have ended the watcher thread."""
    import app.engine.station as station_mod
    from app.engine.station import RunSpec, Station

    def broken(*a: Any, **kw: Any) -> Any:
        raise KeyError("mae")

    monkeypatch.setattr(station_mod, "score_case", broken)
    sink = _Sink()
    st = Station(data_dir=tmp_path, sink=sink)  # type: ignore[arg-type]
    try:
        st.connect()
        st.start(RunSpec("SC-1", "default", 1.2, 3.0, "P"))
        deadline = time.monotonic() + 10.0
        while st._job is None or len(st._job.rows) <= 10:  # past pressurising: rows to score
            assert time.monotonic() < deadline
            time.sleep(0.05)
        st.stop()
        assert st.state.value == "idle" and st.last_run is not None and st.last_run["status"] == "stopped"
        ((status, metrics, result),) = sink.ended
        assert status == "stopped" and metrics is None and result["note"] == "scoring failed (KeyError: 'mae')"
        (meta,) = (tmp_path / "runs").glob("run-*.json")
        assert json.loads(meta.read_text())["status"] == "stopped"
    finally:
        st.close()


def test_a_failure_ending_a_run_takes_it_off_the_station_and_the_watcher_goes_on(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The watcher thread ends runs that end by themselves or by a fault; an unforeseen error in it had
    ended the thread, and the station could then never end a run again."""
    from app.engine.station import RunSpec, Station

    def broken(self: Station, status: str) -> None:
        raise RuntimeError("ending failed")

    sink = _Sink()
    st = Station(data_dir=tmp_path, sink=sink)  # type: ignore[arg-type]
    try:
        st.connect()
        st.start(RunSpec("SC-1", "default", 1.2, 3.0, "P"))
        time.sleep(0.3)
        monkeypatch.setattr(Station, "_finish_run", broken)
        st.estop("test")
        deadline = time.monotonic() + 5.0
        while st._job is not None:
            assert time.monotonic() < deadline, "the run was never taken off the station"
            time.sleep(0.05)
        assert st.state.value == "fault" and st.safety.fault is not None and st.safety.fault.code == "estop"
        ((status, metrics, result),) = sink.ended
        assert status == "fault" and metrics is None
        assert result == {"error": "ending the work under way failed (RuntimeError: ending failed)"}
        (meta,) = (tmp_path / "runs").glob("run-*.json")
        assert json.loads(meta.read_text())["status"] == "fault"
        assert st._watch is not None and st._watch.is_alive()
        monkeypatch.undo()
        st.clear()
        st.connect()  # and the station works again: a run starts and ends as ever
        st.start(RunSpec("SC-1", "default", 1.2, 3.0, "P"))
        st.stop()
        assert [e[0] for e in sink.ended] == ["fault", "stopped"]
    finally:
        st.close()
