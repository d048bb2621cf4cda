"""The diagnosis protocol: excitation experiments the station runs on the rig or the simulator.

Each experiment is an open-loop command schedule (PRV set points ``z_a``,
``z_b`` and DCV commands ``u_a``, ``u_b`` in volts, wired as in thesis 3.2.4)
plus what the user does with the handle. The isotonic workout is the only
closed-loop one (the Default controller). :data:`VISIBLE` says which effect
each experiment makes visible; :func:`run_protocol` runs them all on a
simulated rig and returns experiments in the station's log format (every
experiment twice, the second repetition at other levels, so that whole
experiments can be held out).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.engine.constants import BAR
from app.engine.diagnosis.core import raise_if_stopped
from app.engine.diagnosis.logs import INPUTS, MEASURED, Experiment, write_log
from app.engine.human import HumanProgram, isotonic
from app.engine.params import PlantParams
from app.engine.sim import LOG_COLUMNS, Simulator, run_workout

RATE_HZ = 200.0

VISIBLE: dict[str, list[str]] = {
    "prv_steps": ["valve_dynamics", "tube_dynamics", "heat_transfer", "sensor_bias", "supply_droop"],
    "dcv_steps": ["tube_dynamics", "valve_dynamics", "supply_droop", "heat_transfer"],
    "hold_closed": ["vane_leakage", "external_leakage", "heat_transfer", "sensor_bias"],
    "fill_shut": ["heat_transfer", "external_leakage", "vane_leakage"],
    "friction_sweep": ["presliding_friction", "inertia", "sensor_bias"],
    "sine_sweep": ["inertia", "presliding_friction"],
    "isotonic": ["inertia", "presliding_friction", "valve_dynamics", "supply_droop"],
}
"""Experiment → the effects it makes visible (the protocol table, issue 6 §6)."""

DESCRIPTION: dict[str, str] = {
    "prv_steps": "PRV set-point steps, one chamber at a time, DCVs open, handle held at neutral",
    "dcv_steps": "DCV steps at constant PRV pressure, handle held at neutral",
    "hold_closed": "fill the chambers to unequal pressures, then DCVs at 5 V (closed) for a hold",
    "fill_shut": "one chamber at a time: fill fast from a pressurised line, shut the DCVs at 5 V at once and hold",
    "friction_sweep": "the user moves the handle back and forth at several speeds, chambers at equal pressure",
    "sine_sweep": "the user rocks the handle at rising frequency (accelerations for the inertia)",
    "isotonic": "a Default-controller isotonic workout (closed loop)",
}


def effect_experiments() -> dict[str, list[str]]:
    """Effect → the protocol experiments that make it visible (inverse of :data:`VISIBLE`)."""
    out: dict[str, list[str]] = {}
    for exp, effs in VISIBLE.items():
        for e in effs:
            out.setdefault(e, []).append(exp)
    return out


@dataclass(frozen=True)
class Schedule:
    """An open-loop experiment.

    Attributes:
        name: Experiment kind (a key of :data:`VISIBLE`).
        duration: Length [s].
        commands: t [s] → (z_a, z_b, u_a, u_b) [V].
        program: What the user does.
        pw_bar: Chamber pressure at the start [bar abs].
        human: Whether the user holds the handle.
    """

    name: str
    duration: float
    commands: Callable[[float], tuple[float, float, float, float]]
    program: HumanProgram
    pw_bar: float
    human: bool


def _steps(t: float, levels: Sequence[float], every: float) -> float:
    return float(levels[min(int(t // every), len(levels) - 1)])


def schedules(rep: int = 0, scale: float = 1.0) -> list[Schedule]:
    """The open-loop protocol experiments; ``rep`` varies levels and speeds between repetitions.

    Args:
        rep: Repetition index (0, 1, …).
        scale: Duration factor (1 = the full protocol, ≈ 81 s of commands per repetition
            with the isotonic run; each open-loop log adds :data:`PREROLL_S` at rest).
    """
    a = 1.0 + 0.15 * rep  # amplitude factor of the repetition
    hold0 = HumanProgram.hold(0.0, 1.0)
    out: list[Schedule] = []

    every = 1.5 * scale
    za = [1.0, 3.0 * a, 1.5, 3.5, 2.0, 2.0, 2.0, 2.0]
    zb = [2.0, 2.0, 2.0, 2.0, 1.0, 3.0 * a, 1.5, 3.5]
    def prv_cmd(t: float, e: float = every) -> tuple[float, float, float, float]:
        return _steps(t, za, e), _steps(t, zb, e), 0.0, 10.0

    out.append(Schedule("prv_steps", every * len(za), prv_cmd, hold0, 3.0, True))

    every = 1.2 * scale
    ua = [0.0, 5.0, 4.2, 5.0, 5.8, 5.0, 0.0, 5.0, 5.0, 5.0]
    ub = [10.0, 5.0, 5.0, 5.0, 5.0, 5.0, 10.0, 5.8, 4.2, 10.0]
    zc = 2.0 * a
    def dcv_cmd(t: float, e: float = every) -> tuple[float, float, float, float]:
        return zc, zc, _steps(t, ua, e), _steps(t, ub, e)

    out.append(Schedule("dcv_steps", every * len(ua), dcv_cmd, hold0, 3.0, True))

    fill = 2.0 * scale
    dur = fill + 8.0 * scale
    zh_a, zh_b = 3.0 * a, 1.0

    def hold_cmd(t: float) -> tuple[float, float, float, float]:
        return (zh_a, zh_b, 0.0, 10.0) if t < fill else (zh_a, zh_b, 5.0, 5.0)

    out.append(Schedule("hold_closed", dur, hold_cmd, hold0, 2.0, True))

    # A fill fast enough to be near-adiabatic, then the DCVs shut at once: the gas, warmed by the
    # compression, cools towards the wall and the pressure sags by up to 1 − 1/γ of its rise. In
    # hold_closed the PRV fills slowly and for 2 s, so the gas has cooled before the shut and a
    # smaller dead volume can mimic what is left; a sag at constant volume it cannot. The shut is
    # possible because the MPYE at 5 V leaks only its null zone's clearance flow.
    vent, fill_s, shut_s = 1.5 * scale, 0.4, 5.0 * scale
    zs = 3.5 * a  # the supply line, pressurised behind the DCV while the chamber vents
    side = vent + fill_s + shut_s

    def fill_cmd(t: float) -> tuple[float, float, float, float]:
        first = t < side  # chamber a first, then chamber b
        tt = t if first else t - side
        if tt >= vent + fill_s:  # shut; each PRV stays where it was, so the null zone's leak barely moves P
            return (zs, 1.0, 5.0, 5.0) if first else (1.0, zs, 5.0, 5.0)
        filling = tt >= vent
        # DCV-a fills below 5 V, DCV-b above (thesis 3.2.4); the other chamber stays on its PRV at 1 V
        if first:
            return (zs, 1.0, 0.0 if filling else 10.0, 10.0)
        return (1.0, zs, 0.0, 10.0 if filling else 0.0)

    out.append(Schedule("fill_shut", 2 * side, fill_cmd, hold0, 2.0, True))

    # the user sweeps ±amp at three speeds, both chambers at equal pressure
    amp = 0.6 * a
    speeds = (0.3, 0.8, 1.6)
    ts, ps = [0.0, 0.5], [0.0, 0.0]
    t = 0.5
    for w in speeds:
        for target in (amp, -amp, 0.0):
            t += abs(target - ps[-1]) / w
            ts.append(t)
            ps.append(target)
        t += 0.3 * scale
        ts.append(t)
        ps.append(0.0)
    zf = 1.5 * a
    out.append(Schedule("friction_sweep", t + 0.5, lambda _t: (zf, zf, 0.0, 10.0),
                        HumanProgram(np.array(ts), np.array(ps)), 2.5, True))

    # rising-frequency rocking (a chirp of the intended angle, breakpoints every 10 ms)
    dur = 8.0 * scale
    tt = np.arange(0.0, dur + 1e-9, 0.01)
    f0, f1 = 0.4, 2.0 + 0.4 * rep
    phase = 2 * math.pi * (f0 * tt + (f1 - f0) * tt**2 / (2 * dur))
    th = 0.25 * np.sin(phase) * np.minimum(1.0, tt / 0.5)
    out.append(Schedule("sine_sweep", dur, lambda _t: (zf, zf, 0.0, 10.0), HumanProgram(tt, th), 2.5, True))
    return out


ISOTONIC_S = 12.0
"""The isotonic experiment's length at scale 1 [s] (a Default-controller workout at 1.2 N·m)."""
ISOTONIC_PW_BAR = 3.0
"""Its working pressure [bar abs]."""


def isotonic_program(rep: int) -> HumanProgram:
    """What the user does in the isotonic experiment's repetition ``rep`` (0, 1, …): one push of 50°,
    pronation and supination in turn, a little faster each time."""
    return isotonic(+1 if rep % 2 == 0 else -1, speed=0.35 * (1 + 0.3 * rep), repetitions=1,
                    amplitude=math.radians(50.0))


PREROLL_S = 0.25
"""Rest before an experiment's first step, logged [s].

The rig holds the start pressure on its PRVs with the DCVs shut; the log
begins there, so every command step is inside it. A replay cannot know
the valves' state before a log begins and starts them at its first
command: a log that began on a step would put a lagging valve's first
50 ms beyond any model (with a 10 ms DCV lag, 90 % of the true model's
held-out error).
"""


def run_schedule(params: PlantParams, s: Schedule, seed: int = 0) -> np.ndarray:
    """Run one open-loop experiment on a simulated rig; returns the (n, 11) log.

    The log starts with :data:`PREROLL_S` at rest, then ``s.commands``. The
    user's program is not shifted: the holds and the friction sweep stay
    still that long; the sine sweep starts rocking within it, its amplitude
    ramping up from zero over 0.5 s.
    """
    from app.engine.physics import plant as pl

    dt = 1.0 / RATE_HZ
    n = int(round((s.duration + PREROLL_S) / dt))
    z_rest = s.pw_bar - params.p_atm / BAR  # 1 V ≙ 1 bar gauge (Eq 3.7)
    rest = (z_rest, z_rest, 5.0, 5.0)
    x0 = pl.initial_state(params, 0.0, s.pw_bar, s.pw_bar)
    x0[pl.I_ZA], x0[pl.I_ZB], x0[pl.I_UA], x0[pl.I_UB] = rest
    sim = Simulator(params, seed=seed, program=s.program, x0=x0)
    sim.set_command(*rest)
    log = np.empty((n, len(LOG_COLUMNS)))
    for i in range(n):
        t = i * dt
        m = sim.advance_and_measure(t, dt)
        cmd = rest if t < PREROLL_S - 1e-9 else s.commands(t - PREROLL_S)
        log[i, 0] = t
        log[i, 1:5] = cmd
        log[i, 5:] = m  # p_a, p_b, p_s, θ, ω, T_i: the measurement vector's order
        sim.set_command(*cmd)
    return log


def _experiment(name: str, log: np.ndarray, meta: dict[str, object]) -> Experiment:
    cols = {c: log[:, i] for i, c in enumerate(LOG_COLUMNS)}
    return Experiment(name, cols["t"] - cols["t"][0], {c: cols[c] for c in INPUTS},
                      {c: cols[c] for c in MEASURED}, dict(meta))


def check_outdir(outdir: str | Path, names: Sequence[str]) -> None:
    """Refuse ``outdir`` if it is not a directory, or if it holds a log under one of ``names`` already.

    A log is never overwritten (the writer opens it exclusively), so without this a clash found
    at the fifth experiment would leave four new logs beside the old ones.
    """
    d = Path(outdir)
    if d.exists() and not d.is_dir():
        raise ValueError(f"{d} is a file, not a directory for the protocol's logs")
    taken = [f"{n}{ext}" for n in names for ext in (".csv", ".json") if (d / f"{n}{ext}").exists()]
    if taken:
        shown = ", ".join(taken[:4]) + (f" and {len(taken) - 4} more" if len(taken) > 4 else "")
        raise ValueError(f"{d} already holds {shown}: the protocol writes its logs under those names and never "
                         "overwrites one; pick an empty directory, or move those logs away")


def run_protocol(params: PlantParams | None = None, seed: int = 0, repetitions: int = 2, scale: float = 1.0,
                 kinds: Sequence[str] | None = None, outdir: str | Path | None = None,
                 stop: threading.Event | None = None,
                 progress: Callable[[str], None] | None = None) -> list[Experiment]:
    """Run the whole protocol on a simulated rig.

    Args:
        params: The simulated rig (effects included).
        seed: Sensor-noise seed (each experiment gets its own stream).
        repetitions: Runs of every experiment (the last one is for holding out).
        scale: Duration factor.
        kinds: Experiments to run (default all of :data:`VISIBLE`).
        outdir: Also write every log there in the station's format.
        stop: Once set, the protocol ends before its next experiment with
            :class:`~app.engine.diagnosis.core.Cancelled`.
        progress: Told which experiment is being simulated, e.g.
            ``"simulating experiment 3 of 14 (hold_closed-1)"``.

    Returns:
        The experiments, named ``KIND-REP`` (e.g. ``hold_closed-2``).

    Raises:
        ValueError: An unknown experiment, or an ``outdir`` that is a file or
            already holds a log under a name the protocol writes (checked before
            anything runs, so a refused call writes nothing).
    """
    params = params or PlantParams()
    kinds = list(kinds or VISIBLE)
    unknown = [k for k in kinds if k not in VISIBLE]
    if unknown:
        raise ValueError(f"no protocol experiment {', '.join(unknown)}; known: {', '.join(VISIBLE)}")
    if outdir is not None:
        check_outdir(outdir, [f"{kind}-{rep + 1}" for rep in range(repetitions) for kind in kinds])
    exps: list[Experiment] = []
    for rep in range(repetitions):
        sch = {s.name: s for s in schedules(rep, scale)}
        for j, kind in enumerate(kinds):
            raise_if_stopped(stop, "protocol")
            sd = seed * 1000 + rep * 100 + j
            name = f"{kind}-{rep + 1}"
            if progress is not None:
                progress(f"simulating experiment {len(exps) + 1} of {repetitions * len(kinds)} ({name})")
            if kind == "isotonic":
                res = run_workout(params, isotonic_program(rep), duration=ISOTONIC_S * scale, rate_hz=RATE_HZ,
                                  seed=sd, pw_bar=ISOTONIC_PW_BAR)
                log, human, pw = res.log, True, ISOTONIC_PW_BAR
            else:
                s = sch[kind]
                log, human, pw = run_schedule(params, s, sd), s.human, s.pw_bar
            meta = {"rig": "rotary", "sample_rate_hz": RATE_HZ, "p_atm_bar": params.p_atm / BAR,
                    "working_pressure_bar": pw, "experiment": kind, "human": human, "repetition": rep + 1,
                    "protocol": True, "scale": scale}
            exps.append(_experiment(name, log, meta))
            if outdir is not None:
                write_log(outdir, name, log, meta)
    return exps
