"""What the simulated user intends to do: a piecewise-linear angle program.

The arm impedance in :mod:`app.engine.physics.plant` turns the program into
an interaction torque. Programs are plain arrays so the compiled loop can read
them; builders here produce the thesis's isotonic workouts (SPEC §5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.engine.params import ParameterError, check_range


@dataclass(frozen=True)
class HumanProgram:
    """Intended handle angle against time.

    Attributes:
        t: Breakpoint times [s], non-decreasing.
        pos: Intended angle at each breakpoint [rad] (CCW positive).
    """

    t: np.ndarray
    pos: np.ndarray

    def __post_init__(self) -> None:
        # the compiled plant reads these as float64 C arrays (see sim._compiled_entry)
        object.__setattr__(self, "t", np.ascontiguousarray(self.t, dtype=np.float64))
        object.__setattr__(self, "pos", np.ascontiguousarray(self.pos, dtype=np.float64))
        if self.t.shape != self.pos.shape or self.t.ndim != 1:
            raise ParameterError("human program: t and pos must be 1-D arrays of equal length")
        if self.t.size and np.any(np.diff(self.t) < 0):
            raise ParameterError("human program: breakpoint times must be non-decreasing")

    def target(self, t: float) -> float:
        """Intended angle at time ``t`` [rad]."""
        return float(np.interp(t, self.t, self.pos))

    def stop_at(self, t_stop: float, relax_s: float = 0.3) -> HumanProgram:
        """The user stops where they are at ``t_stop`` and relaxes (holds still).

        Args:
            t_stop: Time the user is asked to stop [s].
            relax_s: Time to come to rest [s].
        """
        keep = self.t < t_stop
        pos_stop = self.target(t_stop)
        t = np.concatenate([self.t[keep], [t_stop, t_stop + relax_s]])
        pos = np.concatenate([self.pos[keep], [pos_stop, pos_stop]])
        return HumanProgram(t, pos)

    def let_go(self, t_release: float) -> HumanProgram:
        """The user releases the handle at ``t_release`` [s]: no torque after it."""
        keep = self.t < t_release
        t = np.concatenate([self.t[keep], [t_release, t_release + 1e-9, t_release + 1.0]])
        pos = np.concatenate([self.pos[keep], [self.target(t_release), np.nan, np.nan]])
        return HumanProgram(t, pos)

    @staticmethod
    def absent() -> HumanProgram:
        """Nobody holds the handle (identification runs): no interaction torque."""
        return HumanProgram(np.array([0.0, 1.0]), np.array([np.nan, np.nan]))

    @staticmethod
    def rest(duration: float = 1.0) -> HumanProgram:
        """The user holds the handle at neutral and does nothing."""
        return HumanProgram(np.array([0.0, duration]), np.array([0.0, 0.0]))

    @staticmethod
    def move(theta_from: float, theta_to: float, t0: float, speed: float = 0.5, wait_s: float = 0.0,
             ) -> HumanProgram:
        """The user holds ``theta_from`` for ``wait_s``, then moves smoothly to ``theta_to`` and stays.

        A raised-cosine profile (peak speed ``speed``), so the arm never jumps:
        a new intended angle far from the handle would make the arm impedance
        yank it.

        Args:
            theta_from: Where the handle is [rad].
            theta_to: Where the user takes it [rad].
            t0: Start time of the program [s] (rig time).
            speed: Peak angular speed [rad/s], > 0.
            wait_s: Hold before moving [s].
        """
        if not speed > 0.0 or not wait_s >= 0.0:
            raise ParameterError(f"human move: speed = {speed} rad/s must be > 0 and wait_s = {wait_s} s ≥ 0")
        dur = HumanProgram.move_time(theta_from, theta_to, speed)
        u = np.linspace(0.0, 1.0, 17)
        t = np.concatenate([[t0], t0 + wait_s + dur * u])
        pos = np.concatenate([[theta_from], theta_from + (theta_to - theta_from) * 0.5 * (1.0 - np.cos(np.pi * u))])
        return HumanProgram(t, pos)

    @staticmethod
    def move_time(theta_from: float, theta_to: float, speed: float = 0.5) -> float:
        """Duration of :meth:`move`'s motion [s] (a raised cosine peaks at π/2 × the mean speed)."""
        return float(np.pi / 2.0 * abs(theta_to - theta_from) / speed)

    @staticmethod
    def hold(theta: float, duration: float = 1.0) -> HumanProgram:
        """The user stops where the handle is and holds it there.

        Args:
            theta: Angle to hold [rad].
            duration: Program length [s] (the last position holds beyond it).
        """
        return HumanProgram(np.array([0.0, duration]), np.array([theta, theta]))


def isotonic(
    direction: int,
    *,
    speed: float = 0.35,
    amplitude: float = math.radians(70.0),
    t_engage: float = 1.0,
    hold: float = 1.0,
    repetitions: int = 1,
    rest: float = 1.0,
    disturbance_at: float | None = None,
    disturbance_speed: float = 1.2,
    disturbance_duration: float = 0.6,
) -> HumanProgram:
    """The thesis's isotonic workout (SPEC §5): engage from neutral, rotate at
    a low steady speed, stall, return, rest.

    Args:
        direction: +1 pronation (FP, CCW) or −1 supination (FS, CW).
        speed: Steady rotation speed [rad/s].
        amplitude: Angle reached from neutral [rad].
        t_engage: Time at which the user starts to move [s].
        hold: Stall at the far end [s].
        repetitions: Out-and-back cycles.
        rest: Rest at neutral between repetitions [s].
        disturbance_at: SC-3: time the user abruptly rotates faster [s].
        disturbance_speed: SC-3 speed during the disturbance [rad/s].
        disturbance_duration: SC-3 duration of the faster rotation [s].
    """
    if direction not in (1, -1):
        raise ParameterError("direction must be +1 (pronation) or -1 (supination)")
    check_range("speed", speed, 0.0, 5.0, lo_open=True, unit="rad/s")
    check_range("amplitude", amplitude, 0.0, math.radians(135.0), lo_open=True, unit="rad")
    check_range("t_engage", t_engage, 0.0, 3600.0, unit="s")
    check_range("repetitions", repetitions, 1, 1000)
    ts: list[float] = [0.0, t_engage]
    ps: list[float] = [0.0, 0.0]
    t = t_engage
    for _ in range(repetitions):
        t_out = amplitude / speed
        if disturbance_at is not None and t < disturbance_at < t + t_out:
            # steady until t_d, then faster for a while, then steady again
            a_d = direction * speed * (disturbance_at - t)
            a_f = a_d + direction * disturbance_speed * disturbance_duration
            if abs(a_f) >= amplitude:
                a_f = direction * amplitude
                t_f = disturbance_at + (amplitude - abs(a_d)) / disturbance_speed
            else:
                t_f = disturbance_at + disturbance_duration
            ts += [disturbance_at, t_f]
            ps += [a_d, a_f]
            t_end = t_f + (amplitude - abs(a_f)) / speed
        else:
            t_end = t + t_out
        ts += [t_end, t_end + hold, t_end + hold + t_out, t_end + hold + t_out + rest]
        ps += [direction * amplitude, direction * amplitude, 0.0, 0.0]
        t = ts[-1]
    return HumanProgram(np.array(ts), np.array(ps))
