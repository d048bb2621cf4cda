"""Engine loop, simulated backend, run logs, and the workout runner."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from app.engine.control.interaction import HoldController, InteractionController
from app.engine.hardware.base import SAFE_COMMAND, Command, Measurement
from app.engine.hardware.sim import SimulatedRig
from app.engine.human import HumanProgram, isotonic
from app.engine.loop import Engine, SimClock
from app.engine.params import ParameterError, PlantParams
from app.engine.runlog import RunLogWriter
from app.engine.sim import LOG_COLUMNS, run_workout

META = {"rig": "rotary", "sample_rate_hz": 200.0, "p_atm_bar": 1.01325, "working_pressure_bar": 3.0,
        "experiment": "test", "human": False}


def test_hold_command_reaches_prv_set_pressures(tmp_path: Path) -> None:
    clock = SimClock()
    rig = SimulatedRig(clock, period=0.005)
    rec = RunLogWriter(tmp_path, "hold", META)
    eng = Engine(rig, HoldController(Command(2.0, 2.0, 0.0, 10.0)), clock, 200.0, recorder=rec)
    rig.activate()
    eng.run_for(2.0)
    rec.close()
    assert eng.ticks == 400 and eng.overruns == 0
    m = eng.last_measurement
    assert m is not None
    # Eq 3.7–3.9: P = z + P_atm, within the regulator's rest band and sensor noise
    assert m.p_a == pytest.approx(3.013, abs=0.03)
    assert m.p_b == pytest.approx(3.013, abs=0.03)
    lines = (tmp_path / "hold.csv").read_text().splitlines()
    assert lines[0] == ",".join(LOG_COLUMNS)
    assert len(lines) == 401
    meta = json.loads((tmp_path / "hold.json").read_text())
    assert meta["status"] == "complete" and meta["rows"] == 400


def test_write_returns_the_clipped_command() -> None:
    rig = SimulatedRig(SimClock())
    applied = rig.write(Command(12.0, -1.0, float("nan"), 11.0))
    assert applied == Command(10.0, 0.0, 0.0, 10.0)


def test_safe_state_vents_both_chambers_equally() -> None:
    clock = SimClock()
    rig = SimulatedRig(clock, pw_bar=4.0)
    eng = Engine(rig, HoldController(SAFE_COMMAND), clock, 200.0)
    rig.activate()
    eng.run_for(1.5)
    m = eng.last_measurement
    assert m is not None
    assert m.p_a == pytest.approx(1.013, abs=0.03) and m.p_b == pytest.approx(1.013, abs=0.03)
    assert abs(m.theta) < 1e-3


def test_user_at_rest_keeps_no_action_mode_and_working_pressure() -> None:
    clock = SimClock()
    rig = SimulatedRig(clock, pw_bar=3.0)
    rig.set_program(HumanProgram.rest(10.0))
    ctl = InteractionController(controller="default", pw_bar=3.0, target_nm=1.2)
    eng = Engine(rig, ctl, clock, 200.0)
    rig.activate()
    modes = []
    for _ in range(600):
        eng.run_for(0.005)
        modes.append(ctl.mode)
    m = eng.last_measurement
    assert m is not None
    assert set(modes) == {0}
    assert m.p_a == pytest.approx(3.013, abs=0.04) and m.p_b == pytest.approx(3.013, abs=0.04)
    assert abs(m.theta) < 2e-3


def test_engine_loop_equals_batch_runner_statistically() -> None:
    # Same plant, controller code and program through the Python engine loop
    # and through the compiled batch runner: same behaviour.
    prog = isotonic(+1, repetitions=1)
    res = run_workout(PlantParams(), prog, duration=6.0, pw_bar=3.0)
    clock = SimClock()
    rig = SimulatedRig(clock, pw_bar=3.0)
    rig.set_program(prog)
    eng = Engine(rig, InteractionController(controller="default", pw_bar=3.0, target_nm=1.2), clock, 200.0)
    rig.activate()
    thetas = []
    for _ in range(1200):
        eng.run_for(0.005)
        assert eng.last_measurement is not None
        thetas.append(eng.last_measurement.theta)
    th_batch = res.column("theta")
    assert np.max(np.abs(np.asarray(thetas[:-1]) - th_batch[1:])) < 0.05


def test_workout_tracks_user_and_respects_rom() -> None:
    res = run_workout(duration=20.0)
    th = res.column("theta")
    assert th.max() > math.radians(50)
    assert th.max() <= math.radians(135) + 1e-9
    assert np.all(np.isfinite(res.log))


def test_run_workout_rejects_rate_not_dividing_substep() -> None:
    with pytest.raises(ParameterError, match="rate_hz"):
        run_workout(duration=1.0, rate_hz=300.0)


def test_runlog_rejects_bad_names_and_missing_meta(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="log name"):
        RunLogWriter(tmp_path, "../evil", META)
    with pytest.raises(ValueError, match="lacks rig"):
        RunLogWriter(tmp_path, "ok", {k: v for k, v in META.items() if k != "rig"})


def test_runlog_is_durable_before_close(tmp_path: Path) -> None:
    w = RunLogWriter(tmp_path, "live", META, flush_every_s=0.0)
    for i in range(10):
        w.append([i * 0.005] + [0.0] * 10)
    # not closed: a reader (or a crash) sees every row already
    assert len((tmp_path / "live.csv").read_text().splitlines()) == 11
    assert json.loads((tmp_path / "live.json").read_text())["status"] == "running"
    w.close("interrupted")
    assert json.loads((tmp_path / "live.json").read_text())["status"] == "interrupted"


def test_a_stalled_fsync_does_not_hold_rows_back_from_the_kernel(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 7 item 5: a disk busy elsewhere can stall ``fsync`` for most of a second (a CI
    machine installing packages beside the station did: a killed server lost 1.05 s). The
    threaded writer keeps handing rows to the kernel, where a killed process's rows survive."""
    import os
    import threading
    import time

    from app.engine import runlog

    release = threading.Event()
    syncing = threading.Event()
    real_fsync = os.fsync

    def stalled_fsync(fd: int) -> None:
        syncing.set()
        release.wait(10.0)
        real_fsync(fd)

    w = RunLogWriter(tmp_path, "busy", META, threaded=True, flush_every_s=0.3, write_every_s=0.05)
    monkeypatch.setattr(runlog.os, "fsync", stalled_fsync)
    try:
        assert syncing.wait(5.0), "the sync thread never synced"
        for i in range(20):
            w.append([i * 0.005] + [0.0] * 10)
        deadline = time.monotonic() + 5.0
        while len((tmp_path / "busy.csv").read_text().splitlines()) < 21:
            assert time.monotonic() < deadline, "rows waited for the stalled fsync"
            time.sleep(0.01)
    finally:
        release.set()
        w.close()
    assert len((tmp_path / "busy.csv").read_text().splitlines()) == 21


def test_a_log_written_late_in_a_long_session_keeps_every_sample_time_apart(tmp_path: Path) -> None:
    """The station's clock counts from connect: after a morning of therapy a 500 Hz run's times
    are ~10⁴ s, where six significant digits would round neighbouring samples together (and the
    diagnosis would refuse the log for time not increasing)."""
    from app.engine.diagnosis.logs import read_log

    w = RunLogWriter(tmp_path, "late", META | {"sample_rate_hz": 500.0}, flush_every_s=0.0)
    t0 = 14_400.0 + 1.0 / 3.0
    w.append_many(np.array([[t0 + i * 0.002, 1.0, 1.0, 0.0, 10.0, 3.0, 3.0, 8.0, 0.1, 0.0, 0.5]
                            for i in range(50)]))
    w.close()
    exp = read_log(tmp_path / "late.csv")  # checks that time increases and matches the rate
    np.testing.assert_allclose(np.diff(exp.t), 0.002, atol=2e-6)


@pytest.mark.parametrize("rate_hz", [200.0, 500.0])  # HIL control; rotary friction identification
def test_paced_engine_thread_reports_timing(rate_hz: float) -> None:
    from app.engine.loop import WallClock

    clock = WallClock()
    rig = SimulatedRig(clock, pw_bar=3.0)
    eng = Engine(rig, HoldController(Command(2.0, 2.0, 0.0, 10.0)), clock, rate_hz)
    rig.activate()
    eng.start()
    import time

    time.sleep(0.5)
    eng.stop()
    st = eng.stats()
    assert 0.3 * rate_hz * 0.5 <= st.ticks <= 1.4 * rate_hz * 0.5
    assert st.rate_hz == rate_hz
    assert st.jitter_p99_ms >= 0.0 and st.measured_rate_hz > 0.5 * rate_hz
    assert rig.last_applied == SAFE_COMMAND
    # the plant followed the held command: chambers pressurised towards 3 bar abs
    assert eng.last_measurement is not None and eng.last_measurement.p_a > 2.0


def test_linear_rig_extends_under_pressure_difference() -> None:
    from app.engine.physics import plant as pl

    p = PlantParams.linear_rig("C3")
    k = pl.build_kernel(p)
    x = pl.initial_state(p, 0.05, 3.0, 1.01325)
    cmd = np.array([2.0, 0.0, 0.0, 10.0, 0.0, 0.0])
    out = np.zeros(pl.NO)
    pl.advance(0.0, x, cmd, k, 2000, np.zeros(0), np.zeros(0), out)
    assert x[pl.I_POS] > 0.06
    assert 0.0 <= x[pl.I_POS] <= 0.300


def test_connect_settles_the_heap_before_the_loop_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A collection of the oldest generation holds the interpreter lock while it scans every
    object (≈ 280 000 in a served station; 290–400 ms here): connect collects and freezes the
    survivors before the loop starts, so a later full collection only visits what was allocated
    since, and what it froze and later died is reclaimed at the next connect."""
    import gc
    import time
    import weakref

    from app.engine.station import Station

    class Node:
        me: object = None

    cyc = Node()
    cyc.me = cyc  # reclaimable by the cycle collector only
    ref = weakref.ref(cyc)
    monkeypatch.setattr("app.engine.station.REFREEZE_S", 0.1)
    st = Station(data_dir=tmp_path)
    try:
        st.connect()
        late = Node()  # allocated beside the running loop: frozen by the watcher's next refreeze
        frozen = gc.get_freeze_count()
        deadline = time.monotonic() + 10.0
        while st.heap_refreeze_ms == 0.0 or gc.get_freeze_count() <= frozen:
            assert time.monotonic() < deadline, "the watcher never refroze the heap"
            time.sleep(0.05)
        assert all(o is not late for o in gc.get_objects())  # frozen: outside every generation
        assert st.heap_frozen > 10_000 and gc.get_freeze_count() > 0.9 * st.heap_frozen
        assert len(gc.get_objects()) < 0.2 * st.heap_frozen  # what a full collection now scans
        del cyc
        gc.collect()
        assert ref() is not None  # frozen while the loop runs
        st.disconnect()
        st.connect()
        assert ref() is None  # returned to the collector by the next connect
    finally:
        st.close()
        gc.unfreeze()


def test_live_window_is_thinned_on_a_fixed_grid_and_ends_at_the_newest_row() -> None:
    from app.engine.station import LiveBuffer

    buf = LiveBuffer(seconds=4.0, rate_hz=500.0)  # 2000 rows: the ring wraps below
    assert buf.window(10.0, 400)[1].shape == (0, 9)
    dt = 0.002
    for k in range(3001):
        buf.append((k * dt,) + (float(k),) * 8)
    written, rows = buf.window(1.0, 100)
    assert written == 3001
    idx = rows[:, 1].astype(int)
    # 1 s at 500 Hz is 501 rows (both ends inclusive): every 6th, counted from row 0, then the newest
    assert idx[-1] == 3000 and rows[0, 0] >= 3000 * dt - 1.0 - 1e-12
    assert len(rows) <= 101 and np.all(idx[:-1] % 6 == 0) and np.all(np.diff(idx[:-1]) == 6)
    for k in range(3001, 3004):  # a later window keeps the same samples where they overlap
        buf.append((k * dt,) + (float(k),) * 8)
    later = buf.window(1.0, 100)[1][:, 1].astype(int)
    assert set(later[:-1]) >= set(idx[2:-1])
    whole = buf.window(100.0, 10_000)[1][:, 1].astype(int)  # longer than the ring: what it holds
    assert whole[0] == 3004 - 2000 and np.all(np.diff(whole) == 1)
    buf.clear()
    assert buf.window(1.0, 10)[0] == 0


def test_the_warm_up_runs_its_parts_and_refuses_an_unknown_one(capsys: pytest.CaptureFixture[str]) -> None:
    """``python -m app.engine.warm``: what the Docker build and ``./dev test`` run before anything else."""
    from app.engine.warm import PARTS, main, warm

    assert set(warm(["replay"])) == {"replay"} and set(PARTS) == {"sim", "replay"}
    assert main(["sim"]) == 0 and "compiled: sim" in capsys.readouterr().out
    assert main(["all"]) == 2 and "no warm-up part all; known: sim, replay" in capsys.readouterr().err


def test_a_part_that_ran_to_its_end_marks_the_cache_warm(monkeypatch: pytest.MonkeyPatch,
                                                          tmp_path: Path) -> None:
    """What ``cwrr serve`` asks before it starts: a part is cold until it has run against this
    cache directory (keyed by the sources' hash), and a part that failed stays cold."""
    from app.engine import warm as w

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setitem(w.PARTS, "ok", lambda: None)

    def broken() -> None:
        raise RuntimeError("compile failed")

    monkeypatch.setitem(w.PARTS, "broken", broken)
    assert w.cold(["ok", "broken"]) == ["ok", "broken"]
    w.warm(["ok"])
    with pytest.raises(RuntimeError, match="compile failed"):
        w.warm(["broken"])
    assert w.cold(["ok", "broken"]) == ["broken"]
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "another version"))
    assert w.cold(["ok"]) == ["ok"]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_asked_for_while_the_first_start_compiles_ends_cwrr_serve_at_once(
        tmp_path: Path, sig: signal.Signals) -> None:
    """A version's first ``cwrr serve`` compiles the engine's kernels (about a minute); it did so
    inside uvicorn's startup, which acts on a signal only once it ends, so a stop (``docker stop``,
    Ctrl-C) waited out the compile. It now compiles before the server starts, where a stop ends it."""
    from tests.conftest import ServedStation, free_port

    env = dict(os.environ, PYTHONPATH=str(ServedStation.ROOT), NUMBA_CACHE_DIR=str(tmp_path / "cold cache"))
    env.pop("CWRR_DATA_DIR", None)
    proc = subprocess.Popen([sys.executable, "-m", "app", "serve", "--port", str(free_port()), "--viser-port", "0",
                             "--data-dir", str(tmp_path / "data")], cwd=ServedStation.ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # blocks until the first line: imports take a few seconds
        assert "compiling the simulator and controllers for this version" in line, line
        time.sleep(1.0)  # into the compile
        proc.send_signal(sig)
        rc = proc.wait(timeout=5.0)
    finally:
        proc.kill()
    rest = proc.stderr.read()
    if sig == signal.SIGINT:
        assert rc == 130 and "stopped while compiling" in rest, (rc, rest)
    else:
        assert rc == -signal.SIGTERM, (rc, rest)
    assert not (tmp_path / "cold cache" / "warm-sim.done").exists()


class _ManualClock:
    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t


def test_a_late_sample_reports_the_speed_over_the_time_that_passed() -> None:
    """A stalled loop's next sample saw the vane move for 60 ms, not one 5 ms period: the speed
    divides by what passed (it divided by the period, which reported a 65 ms stall's 0.5 rad/s as
    3.6 rad/s on the paced station, and the controllers acted on that)."""
    clock = _ManualClock()
    rig = SimulatedRig(clock, period=0.005)
    rig.set_program(HumanProgram.move(0.0, 1.0, 0.0, speed=0.5))
    rig.activate()
    rig.write(SAFE_COMMAND)
    m = rig.read()
    while clock.t < 1.5:  # on time, into the middle of the move (peak 0.5 rad/s)
        clock.t += 0.005
        m = rig.read()
    clock.t += 0.060
    late = rig.read()
    mean = (late.theta - m.theta) / (late.t - m.t)  # the encoder's own mean over the gap
    assert late.t - m.t == pytest.approx(0.060)
    assert 0.35 < mean < 0.65
    # 60 ms is 9 time constants of the 25 Hz filter: what is left is the mean over the gap
    assert late.omega == pytest.approx(mean, rel=0.02), (late.omega, mean)


@pytest.mark.parametrize("controller", ["pid", "fuzzy"])
def test_a_late_sample_is_differentiated_and_integrated_over_the_time_that_passed(controller: str) -> None:
    """The engine steps its controller with the period; a sample that came 40 ms after the one
    before is stepped over 40 ms, as if that interval had been given, and a longer gap over ten
    periods at most. Over the period, the derivative of 65 ms of pressure change was taken as if
    it had happened in 5 ms, and the PRV command jumped 1.8 (PID) and 2.0 (fuzzy, whose gains read
    the derivative) times as far."""
    def z_a(times: list[float], dts: list[float], stamps: list[float] | None = None) -> list[float]:
        c = InteractionController(controller=controller)
        out = []
        for t, dt, stamp in zip(times, dts, stamps or times, strict=True):
            p = 3.0 + 0.3 * math.sin(2.0 * math.pi * t)  # chamber a swings ±0.3 bar at 1 Hz
            out.append(c.step(Measurement(stamp, p, 3.0, 7.0, 0.0, 0.0, 0.0), dt).z_a)
        return out

    on_time = [0.005 * k for k in range(100)]
    for gap, stepped in ((0.040, 0.040), (0.065, 0.050)):
        times = [*on_time, on_time[-1] + gap]
        engine = z_a(times, [0.005] * len(times))
        # the same pressures stepped with the interval given explicitly (and stamped to match)
        given = z_a(times, [0.005] * len(on_time) + [stepped], stamps=[*on_time, on_time[-1] + stepped])
        assert engine[-1] == pytest.approx(given[-1], abs=1e-12), (gap, engine[-1], given[-1])
    # a controller that could not tell (samples stamped one period apart) kicks
    blind = z_a(times, [0.005] * len(times), stamps=[0.005 * k for k in range(len(times))])
    assert abs(blind[-1] - blind[-2]) > 1.5 * abs(engine[-1] - engine[-2]), (blind[-2:], engine[-2:])
    # and on time nothing changes: the same commands as stepping with the period alone
    jitter = [t + 0.0004 * (-1) ** k for k, t in enumerate(on_time)]  # ±0.4 ms: within a quarter period
    assert z_a(jitter, [0.005] * 100) == pytest.approx(z_a(jitter, [0.005] * 100, stamps=on_time), abs=1e-12)


def test_the_hardware_speed_estimator_divides_by_the_time_between_samples() -> None:
    from app.engine.hardware.config import SpeedEstimator

    est, per = SpeedEstimator(25.0, 0.005), SpeedEstimator(25.0, 0.005)
    t = np.arange(0.0, 0.5, 0.005)
    for ti in t:  # 0.4 rad/s, on time: the same with or without the samples' times
        assert est.update(float(0.4 * ti), float(ti)) == pytest.approx(per.update(float(0.4 * ti)), abs=1e-12)
    assert est.update(0.4 * (t[-1] + 0.065), float(t[-1] + 0.065)) == pytest.approx(0.4, rel=1e-3)
    assert per.update(0.4 * (t[-1] + 0.065)) > 7 * 0.4  # a period's step: 13 × the speed, half of it filtered
    est.reset()
    assert est.update(1.0, 2.0) == 0.0 and est.update(1.0, 2.0) == 0.0  # a repeated time: the period, no ÷0
