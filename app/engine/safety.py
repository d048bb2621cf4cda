"""The safety supervisor: the last stage between control and the actuators (issue 7).

Every period the engine hands it the controller's command and the raw
measurement (never the estimator's view: a filter can hide a glitch). It

* checks the measurement — NaN, out of range, stuck analog channels,
  implausible jumps (encoder glitches, sensor dropouts), torque-sensor
  saturation, chamber pressure over the limit, a PRV whose chamber does not
  follow its command, supply loss, the loop running late;
* limits the command — PRV commands within ``[0, p_max]`` and slew-limited,
  and the no-action mode of thesis 3.3.1 (both chambers at equal pressure,
  the DCVs routing) inside the soft range-of-motion limits when the command
  would drive the vane further out.

A failed check *latches* a :class:`Fault`: from that period on the
supervisor returns the safe state, and only :meth:`SafetySupervisor.reset`
(an explicit operator action) releases it. So a fault is acted on in the
very period it is detected.

Safe state (IEC 80601-2-78's "defined safe state", what the rig does on a
fault): both PRVs commanded to 0 V and both DCVs exhausting their chambers
directly (:data:`VENT_COMMAND`). Both chambers vent through identical
orifices at once, so the net torque on the arm falls with the pressures
(simulated, during an isotonic motion at P_w = 3 bar: at most 0.6 bar of
transient difference — the chambers' volumes differ — and none left after
0.3 s, both below 1.2 bar abs within 40 ms). It does not depend on the PRVs:
the idle state (:data:`~app.engine.hardware.base.SAFE_COMMAND`) vents
through the PRV relief ports instead, which a stuck PRV defeats — measured,
a PRV stuck at 6 V kept 6 bar on the arm — while a DCV stuck open to its PRV
still vents through the PRV at 0 V.

The supervisor holds no hardware reference (controllers and safety never
import backends); the engine's watchdog thread (see
:class:`~app.engine.loop.Engine`) covers the one fault a stage inside the
period cannot see — the period itself not coming.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Any

from app.engine.constants import BAR, P_ATM
from app.engine.hardware.base import SAFE_COMMAND, Command, Measurement
from app.engine.params import ParameterError, check_range

VENT_COMMAND = Command(0.0, 0.0, 10.0, 0.0)
"""Both DCVs exhaust their chambers directly (u_a > 5 V: a → exhaust; u_b < 5 V: b → exhaust)."""

RELEASE_S = 0.5
"""A controlled stop lowers both PRV commands to 0 over this long [s] (an exercise's end, STOP, the
diagnosis protocol's end). Dropped at once (the slew limit's 200 bar/s), the smaller chamber vented
in 10 ms and the larger in 50: over twelve exercise ends on the simulator the handle swung at up to
1.8 rad/s and the torque on the arm reversed by up to 2.4 N·m. E-STOP and faults still vent at once."""


def release_command(t: float, t0: float, p_from: tuple[float, float], p_atm_bar: float) -> Command:
    """The controlled stop's command at ``t``: both PRV commands lowered together from the chambers'.

    Each PRV starts at the command that holds its chamber where it was (PRV static map P = z + P_atm,
    SPEC §3), not at the controller's last command: a moving vane holds a chamber above its command,
    and lowering from the command emptied that chamber at once. The DCVs route the chambers to their
    PRVs, so the chambers' difference (the torque on the arm) falls in proportion and no chamber
    empties ahead of the other.

    Args:
        t: Now [s].
        t0: When the stop began [s].
        p_from: Chamber a and b pressures it began from [bar abs].
        p_atm_bar: The atmosphere the PRVs regulate above [bar abs].

    Returns:
        The command; :data:`~app.engine.hardware.base.SAFE_COMMAND` from ``t0 + RELEASE_S`` on.
    """
    left = 1.0 - (t - t0) / RELEASE_S
    if not left > 0.0:
        return SAFE_COMMAND
    return Command(max(p_from[0] - p_atm_bar, 0.0) * left, max(p_from[1] - p_atm_bar, 0.0) * left,
                   SAFE_COMMAND.u_a, SAFE_COMMAND.u_b)

CYLINDER_MAX_BAR = 8.0
"""Rated maximum of the FESTO DRVS-32-270-P [bar gauge] (SPEC §1)."""


@dataclass(frozen=True)
class SafetyLimits:
    """What the supervisor enforces.

    Attributes:
        p_max_bar: Highest PRV command [bar gauge] (at most the cylinder's 8 bar;
            7 bar is the GUI's highest working pressure, 8 bar abs).
        p_margin_bar: How far a measured chamber pressure may exceed
            ``p_max_bar`` before it is a fault [bar].
        slew_bar_s: Fastest PRV command change [bar/s]. 200 bar/s is 1 bar per
            5-ms period: steps of the thesis's controllers pass, a runaway does not.
        torque_max_nm: Largest interaction torque tolerated [N·m] (``None``:
            no torque checks — the linear rig measures a force there).
        torque_range_nm: The torque sensor's range [N·m] (±10 N·m, SPEC §1);
            a reading within 1 % of it is saturation.
        rom_deg: Range of motion between the end stops [deg] (symmetric;
            ``None``: no angle checks and no no-action zone — the linear rig).
        soft_margin_deg: Width of the no-action zone inside each end stop [deg].
        p_range_bar: Plausible measured pressures [bar abs] (low, high).
        max_speed_rad_s: Fastest plausible vane speed [rad/s]; a larger jump
            of the angle in one period is an encoder glitch.
        max_dp_bar_s: Fastest plausible change of a chamber pressure
            [bar/s]; a faster one is a glitch. 800 bar/s (4 bar per 5 ms
            period): the simulator's thesis scenarios reach 2.3 bar in one
            period (SC-1, −1.2 N·m, Cascade PID: the near-empty chamber filling),
            so 1.5 bar per period — the first choice — tripped healthy runs.
        stuck_s: An analog channel (pressures, torque) that repeats its exact
            value this long is stuck [s]: with ADC noise it never does.
        follow_tol_bar: How far a routed chamber may stay above its PRV
            command [bar] before the PRV counts as not following.
        follow_s: For how long [s].
        supply_margin_bar: The supply must exceed the highest PRV command by
            this much [bar] ...
        supply_s: ... or within this time [s] it counts as lost (``None``:
            no supply check — on the CPR rig, Figure 3.10, PS-0 reads the
            DCV's inlet, not the supply).
        late_periods: A period this many periods late counts as an overrun.
        overruns_max: That many overruns in a row latch a fault.
    """

    p_max_bar: float = 7.0
    p_margin_bar: float = 0.8
    slew_bar_s: float = 200.0
    torque_max_nm: float | None = 8.0
    torque_range_nm: float = 10.0
    rom_deg: float | None = 270.0
    soft_margin_deg: float = 10.0
    p_range_bar: tuple[float, float] = (0.3, 11.5)
    max_speed_rad_s: float = 25.0
    max_dp_bar_s: float = 800.0
    stuck_s: float = 0.5
    follow_tol_bar: float = 1.0
    follow_s: float = 0.5
    supply_margin_bar: float = 0.3
    supply_s: float | None = 0.3
    late_periods: float = 1.5
    overruns_max: int = 5

    @classmethod
    def for_rig(cls, kind: str, **overrides: Any) -> SafetyLimits:
        """Limits for a rig kind: the rotary axis gets every check; the linear and
        CPR rigs (position in metres, force in newtons) only the pneumatic ones."""
        if kind != "rotary":
            overrides = {"rom_deg": None, "torque_max_nm": None} | overrides
        if kind == "cpr":
            overrides = {"supply_s": None} | overrides
        return cls(**overrides)

    def __post_init__(self) -> None:
        check_range("p_max_bar", self.p_max_bar, 0.0, CYLINDER_MAX_BAR, lo_open=True, unit="bar")
        check_range("p_margin_bar", self.p_margin_bar, 0.0, 3.0, unit="bar")
        check_range("slew_bar_s", self.slew_bar_s, 0.0, 1e4, lo_open=True, unit="bar/s")
        check_range("torque_range_nm", self.torque_range_nm, 0.0, 1e3, lo_open=True, unit="N·m")
        if self.torque_max_nm is not None:
            check_range("torque_max_nm", self.torque_max_nm, 0.0, self.torque_range_nm, lo_open=True, unit="N·m")
        if self.rom_deg is not None:
            check_range("rom_deg", self.rom_deg, 0.0, 360.0, lo_open=True, unit="deg")
            check_range("soft_margin_deg", self.soft_margin_deg, 0.0, self.rom_deg / 2, unit="deg")
        lo, hi = self.p_range_bar
        if not 0.0 <= lo < hi:
            raise ParameterError(f"p_range_bar = {self.p_range_bar}: needs 0 ≤ low < high [bar abs]")
        check_range("max_speed_rad_s", self.max_speed_rad_s, 0.0, 1e3, lo_open=True, unit="rad/s")
        check_range("max_dp_bar_s", self.max_dp_bar_s, 0.0, 1e5, lo_open=True, unit="bar/s")
        for name in ("stuck_s", "follow_s", "supply_s"):
            if getattr(self, name) is not None:
                check_range(name, getattr(self, name), 0.0, 60.0, lo_open=True, unit="s")
        check_range("follow_tol_bar", self.follow_tol_bar, 0.0, 10.0, lo_open=True, unit="bar")
        check_range("supply_margin_bar", self.supply_margin_bar, -5.0, 5.0, unit="bar")
        check_range("late_periods", self.late_periods, 1.0, 1e3, lo_open=True, unit="periods")
        if not 1 <= self.overruns_max <= 10**6:
            raise ParameterError(f"overruns_max = {self.overruns_max} is outside its allowed range [1, 1e6]")


@dataclass(frozen=True)
class Fault:
    """A latched fault.

    Attributes:
        code: Machine-readable kind (``estop``, ``sensor_nan``, ``sensor_range``,
            ``sensor_stuck``, ``encoder_glitch``, ``pressure_jump``,
            ``torque_limit``, ``torque_saturation``, ``pressure_limit``,
            ``prv_not_following``, ``supply_lost``, ``controller_nan``,
            ``overrun``, ``stall``, ``link_lost``, ``engine_error``, ``log_failed``: the
            log of the work under way cannot be written, e.g. a full disk).
        message: What happened, for the operator.
        t: Engine time of detection [s] (NaN when not known).
        channel: The measurement or actuator concerned ("" if none).
    """

    code: str
    message: str
    t: float = math.nan
    channel: str = ""

    def as_dict(self) -> dict[str, Any]:
        """JSON-able form (NaN time → None)."""
        d = asdict(self)
        d["t"] = self.t if math.isfinite(self.t) else None
        return d


_ANALOG = ("p_a", "p_b", "torque")


class SafetySupervisor:
    """Latched-fault safety stage (the engine's ``safety``).

    Args:
        limits: What to enforce.
        period: Nominal control period [s] (late-period detection, slew).
        safe: The fault state's command (default :data:`VENT_COMMAND`).
        plant_responds: Whether the measurements answer the commands (False for
            a replayed log: the checks that compare them — PRV following,
            supply — would only see the recording disagree with today's commands).
        p_atm_bar: The lab's atmosphere [bar abs]: the pressure limits and the
            supply check are in bar gauge, the sensors read bar abs.
    """

    def __init__(self, limits: SafetyLimits | None = None, period: float = 0.005,
                 safe: Command = VENT_COMMAND, plant_responds: bool = True, p_atm_bar: float = P_ATM / BAR) -> None:
        self.plant_responds = plant_responds
        self.p_atm = p_atm_bar * BAR
        self.limits = limits or SafetyLimits()
        self.period = period
        self.safe = safe
        self._lock = threading.Lock()
        self._fault: Fault | None = None
        self.no_action = False
        self.faults_total = 0
        self._reset_state()

    def _reset_state(self) -> None:
        self._prev: Measurement | None = None
        self._prev_cmd: Command | None = None
        self._same = dict.fromkeys(_ANALOG, 0.0)
        self._follow = [0.0, 0.0]
        self._supply_low = 0.0
        self._pmax_over = [0.0, 0.0]
        self._late = 0

    # ------------------------------------------------------------------ faults

    @property
    def fault(self) -> Fault | None:
        """The latched fault, if any."""
        return self._fault

    @property
    def fault_command(self) -> Command:
        """What the actuators get while a fault is latched."""
        return self.safe

    def trip(self, code: str, message: str, t: float | Callable[[], float] = math.nan, channel: str = "") -> Fault:
        """Latch a fault (the first one wins: it is the cause, later ones are consequences).

        Safe to call from any thread; the engine applies it in its next period.

        Args:
            code: See :class:`Fault`.
            message: See :class:`Fault`.
            t: Engine time of detection [s], or, from a thread other than the engine's, a
                function that reads it: called once the fault is in force, so that every period
                whose measurement is newer than the time returned applies it. A time read before
                the latch could lag it by as long as the calling thread waited to run (an e-stop
                stamped one period early was seen on a loaded machine).
            channel: See :class:`Fault`.
        """
        with self._lock:
            if self._fault is None:
                if callable(t):
                    self._fault = Fault(code, message, math.nan, channel)  # in force from here on
                    self._fault = replace(self._fault, t=t())
                else:
                    self._fault = Fault(code, message, t, channel)
                self.faults_total += 1
            return self._fault

    def reset(self) -> None:
        """Release a latched fault (the operator's explicit acknowledgement).

        The checks start afresh; a condition that persists trips again in the
        next period.
        """
        with self._lock:
            self._fault = None
            self._reset_state()

    # ------------------------------------------------------------------ stage

    def apply(self, cmd: Command, meas: Measurement) -> Command:
        """The command allowed to reach the actuators this period."""
        if self._fault is None:
            self._check(cmd, meas)
        self._prev = meas
        if self._fault is not None:
            self.no_action = False
            self._prev_cmd = self.safe
            return self.safe
        out = self._limit(cmd, meas)
        self._prev_cmd = out
        return out

    def _check(self, cmd: Command, m: Measurement) -> None:
        lim = self.limits
        prev = self._prev
        dt = self.period if prev is None else m.t - prev.t
        vals = {"p_a": m.p_a, "p_b": m.p_b, "p_s": m.p_s, "theta": m.theta, "omega": m.omega, "torque": m.torque}
        for name, v in vals.items():
            if not math.isfinite(v):
                self.trip("sensor_nan", f"{name} reads {v}: sensor or link failure", m.t, name)
                return
        for name in ("z_a", "z_b", "u_a", "u_b"):
            v = getattr(cmd, name)
            if not math.isfinite(v):
                self.trip("controller_nan", f"the controller commanded {name} = {v}", m.t, name)
                return
        lo, hi = lim.p_range_bar
        for name in ("p_a", "p_b", "p_s"):
            v = vals[name]
            if not lo <= v <= hi:
                self.trip("sensor_range", f"{name} = {v:.3f} bar is outside the plausible {lo:g}–{hi:g} bar abs",
                          m.t, name)
                return
        if lim.rom_deg is not None and abs(m.theta) > math.radians(lim.rom_deg / 2 + 5.0):
            self.trip("sensor_range", f"theta = {math.degrees(m.theta):.1f}° is beyond the end stops "
                      f"(±{lim.rom_deg / 2:g}°): encoder fault", m.t, "theta")
            return
        if lim.torque_max_nm is not None and abs(m.torque) >= 0.99 * lim.torque_range_nm:
            self.trip("torque_saturation", f"torque = {m.torque:.2f} N·m saturates the ±{lim.torque_range_nm:g} "
                      "N·m sensor", m.t, "torque")
            return
        if lim.torque_max_nm is not None and abs(m.torque) > lim.torque_max_nm:
            self.trip("torque_limit", f"interaction torque {m.torque:.2f} N·m exceeds the {lim.torque_max_nm:g} "
                      "N·m limit", m.t, "torque")
            return
        p_gauge = ((m.p_a * BAR - self.p_atm) / BAR, (m.p_b * BAR - self.p_atm) / BAR)
        for i, side in enumerate("ab"):
            over = p_gauge[i] > lim.p_max_bar + lim.p_margin_bar
            # two periods in a row: one noisy sample is not a pressure
            self._pmax_over[i] = self._pmax_over[i] + 1 if over else 0
            if self._pmax_over[i] >= 2:
                self.trip("pressure_limit", f"chamber {side} at {p_gauge[i]:.2f} bar exceeds the "
                          f"{lim.p_max_bar:g} bar limit", m.t, f"p_{side}")
                return
        if prev is not None and dt > 0:
            if dt > lim.late_periods * self.period:
                self._late += 1
                if self._late >= lim.overruns_max:
                    self.trip("overrun", f"{self._late} periods in a row came late (last {dt * 1e3:.1f} ms for "
                              f"{self.period * 1e3:.1f} ms)", m.t)
                    return
            else:
                self._late = 0
            # one encoder count of slack: quantisation alone must never trip it
            if lim.rom_deg is not None and abs(m.theta - prev.theta) > lim.max_speed_rad_s * dt + 2 * math.pi / 4096:
                self.trip("encoder_glitch", f"theta jumped {math.degrees(m.theta - prev.theta):.1f}° in "
                          f"{dt * 1e3:.1f} ms (> {lim.max_speed_rad_s:g} rad/s)", m.t, "theta")
                return
            for name in ("p_a", "p_b"):
                dp = vals[name] - getattr(prev, name)
                if abs(dp) > lim.max_dp_bar_s * max(dt, self.period):
                    self.trip("pressure_jump", f"{name} jumped {dp:+.2f} bar in {dt * 1e3:.1f} ms (> "
                              f"{lim.max_dp_bar_s:g} bar/s): a glitch on the channel", m.t, name)
                    return
            for name in _ANALOG if lim.torque_max_nm is not None else _ANALOG[:2]:
                self._same[name] = self._same[name] + dt if vals[name] == getattr(prev, name) else 0.0
                if self._same[name] >= lim.stuck_s:
                    self.trip("sensor_stuck", f"{name} has read exactly {vals[name]:.5g} for "
                              f"{self._same[name]:.2f} s: the sensor or its channel is stuck", m.t, name)
                    return
            # a routed chamber cannot sit well above the pressure its PRV is told to give
            pc = self._prev_cmd
            if pc is not None and self.plant_responds:
                # routed: the DCV clearly open PRV → chamber (its null band seals the chamber)
                routed = (pc.u_a < 4.5, pc.u_b > 5.5)
                zs = (pc.z_a, pc.z_b)
                for i, side in enumerate("ab"):
                    if routed[i] and p_gauge[i] > zs[i] + lim.follow_tol_bar:
                        self._follow[i] += dt
                    else:
                        self._follow[i] = 0.0
                    if self._follow[i] >= lim.follow_s:
                        self.trip("prv_not_following", f"chamber {side} has stayed {p_gauge[i] - zs[i]:.2f} bar "
                                  f"above PRV-{side}'s command for {self._follow[i]:.2f} s: PRV-{side} stuck?",
                                  m.t, f"z_{side}")
                        return
                need = max(pc.z_a, pc.z_b)
                supply_gauge = (m.p_s * BAR - self.p_atm) / BAR
                if lim.supply_s is not None and need > 0.2 and supply_gauge < need + lim.supply_margin_bar:
                    self._supply_low += dt
                    if self._supply_low >= (lim.supply_s or 0.0):
                        self.trip("supply_lost", f"supply at {m.p_s:.2f} bar abs cannot give the commanded "
                                  f"{need:.2f} bar gauge (for {self._supply_low:.2f} s): supply lost?", m.t, "p_s")
                        return
                else:
                    self._supply_low = 0.0

    def _limit(self, cmd: Command, m: Measurement) -> Command:
        lim = self.limits
        zmax = lim.p_max_bar
        za = min(max(cmd.z_a, 0.0), zmax)
        zb = min(max(cmd.z_b, 0.0), zmax)
        ua = min(max(cmd.u_a, 0.0), 10.0)
        ub = min(max(cmd.u_b, 0.0), 10.0)
        pc = self._prev_cmd
        if pc is not None:
            step = lim.slew_bar_s * self.period
            za = min(max(za, pc.z_a - step), pc.z_a + step)
            zb = min(max(zb, pc.z_b - step), pc.z_b + step)
        # no-action zone (thesis 3.3.1): near an end stop a command that drives the vane
        # further out (p_a > p_b turns CCW, +theta) gives way to equal pressures, routed
        outward = False
        if lim.rom_deg is not None:
            edge = math.radians(lim.rom_deg / 2 - lim.soft_margin_deg)
            outward = (m.theta > edge and za > zb) or (m.theta < -edge and zb > za)
        self.no_action = outward
        if outward:
            z = max(za, zb)
            return Command(z, z, SAFE_COMMAND.u_a, SAFE_COMMAND.u_b)
        if (za, zb, ua, ub) == (cmd.z_a, cmd.z_b, cmd.u_a, cmd.u_b):
            return cmd
        return Command(za, zb, ua, ub)

    def status(self) -> dict[str, Any]:
        """Fault (or None), no-action flag and limits, for the API."""
        f = self._fault
        return {"fault": f.as_dict() if f is not None else None, "no_action": self.no_action,
                "faults_total": self.faults_total, "limits": asdict(self.limits)}
