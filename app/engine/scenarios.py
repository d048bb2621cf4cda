"""The thesis's test scenarios SC-1–SC-4 (4.3–4.7, SPEC §5) on the simulator.

Every run: P_w = 3 bar abs, 200 Hz control; the simulated user (right hand)
rests at neutral, engages at ``t_engage`` and rotates at a low steady speed
(FP: pronation, CCW, positive; FS: supination, CW, negative) through
``amplitude``, then stalls. Metrics are taken on e = [T_i]^t − T_i (measured
torque, as the thesis does) from convergence — or from t_d for SC-3/SC-4 —
to the end of the rotation (the thesis's points "a"/"b" to "c").

Choices the thesis leaves open (it ran with a live user and reports t_d
between 19 and 101 s):

* Steady speed 0.3 rad/s (≈ 17°/s), amplitude 120°, so a rotation lasts 7 s.
* Convergence: the first sample after the intention detector engages with
  |e| ≤ 10 % of the target; if that never happens within 2 s the window
  starts at engagement + 2 s (non-convergence is not rewarded).
* SC-3: at t_d = engagement + 3 s the user abruptly rotates at 1.0 rad/s for
  0.4 s, then resumes the steady speed. SC-4: from t_d = engagement + 3 s,
  [P_b]^d = −0.4 bar at PRV-b's exit until the end.
* The sensor noise of a run is seeded from (seed, case), identical for the
  three controllers of a case (common random numbers).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from app.engine.control.config import ControllerConfig, ControllerName
from app.engine.control.fuzzy import FuzzyConfig
from app.engine.human import HumanProgram, isotonic
from app.engine.metrics import all_metrics, angle_range_deg, toggle_report
from app.engine.params import ParameterError, PlantParams, check_range
from app.engine.sim import WorkoutResult, run_workout

ScenarioName = Literal["SC-1", "SC-2", "SC-3", "SC-4"]
SCENARIOS: tuple[str, ...] = ("SC-1", "SC-2", "SC-3", "SC-4")
CONTROLLERS: tuple[ControllerName, ...] = ("default", "pid", "fuzzy")


@dataclass(frozen=True)
class ScenarioSettings:
    """Workout shape shared by all scenarios.

    Attributes:
        pw_bar: Working pressure [bar abs] (thesis: 3).
        speed: Steady rotation speed [rad/s].
        amplitude_deg: Rotation from neutral [deg].
        t_engage: When the user starts to rotate [s].
        t_dist_after: Disturbance time after engagement [s] (SC-3, SC-4).
        dist_speed: SC-3 abrupt rotation speed [rad/s].
        dist_duration: SC-3 abrupt rotation duration [s].
        dp_b_bar: SC-4 pressure disturbance at PRV-b's exit [bar].
        conv_band: Convergence band as a fraction of |target|.
        conv_timeout: Latest window start after engagement [s].
        rate_hz: Control rate [Hz].
    """

    pw_bar: float = 3.0
    speed: float = 0.3
    amplitude_deg: float = 120.0
    t_engage: float = 1.0
    t_dist_after: float = 3.0
    dist_speed: float = 1.0
    dist_duration: float = 0.4
    dp_b_bar: float = -0.4
    conv_band: float = 0.10
    conv_timeout: float = 2.0
    rate_hz: float = 200.0

    def __post_init__(self) -> None:
        check_range("speed", self.speed, 0.0, 3.0, lo_open=True, unit="rad/s")
        check_range("amplitude_deg", self.amplitude_deg, 0.0, 135.0, lo_open=True, unit="deg")
        check_range("t_engage", self.t_engage, 0.0, 60.0, unit="s")
        rot = math.radians(self.amplitude_deg) / self.speed
        if not 0.0 < self.t_dist_after < rot:
            raise ParameterError(f"t_dist_after = {self.t_dist_after} s must fall inside the rotation (0, {rot:.2f}) s")
        check_range("dp_b_bar", self.dp_b_bar, -3.0, 3.0, unit="bar")
        check_range("conv_band", self.conv_band, 0.0, 1.0, lo_open=True)


@dataclass(frozen=True)
class Case:
    """One scenario case: a scenario, a signed target and the PDRA/TDRA setting.

    Attributes:
        scenario: ``"SC-1"`` … ``"SC-4"``.
        target: Signed target torque [N·m] (positive FP, negative FS).
        pdra: PDRA on.
        tdra: TDRA on.
        ablation: True when PDRA/TDRA differ from the scenario's definition.
    """

    scenario: str
    target: float
    pdra: bool
    tdra: bool
    ablation: bool = False

    @property
    def direction(self) -> str:
        """``"FP"`` (pronation) or ``"FS"`` (supination)."""
        return "FP" if self.target > 0 else "FS"

    @property
    def key(self) -> str:
        """File-name-safe identifier."""
        tag = f"{self.scenario}_{self.direction}_{abs(self.target):.1f}".replace(".", "p")
        if self.ablation:
            tag += f"_pdra{int(self.pdra)}_tdra{int(self.tdra)}"
        return tag


def main_cases() -> list[Case]:
    """The 12 cases of SPEC §5 with PDRA/TDRA as each scenario defines."""
    out: list[Case] = []
    for sc in SCENARIOS:
        on = sc != "SC-1"
        targets = (1.2, -1.2, 0.6, -0.6) if sc in ("SC-1", "SC-2") else (1.2, 0.6)
        out += [Case(sc, t, on, on) for t in targets]
    return out


def ablation_cases() -> list[Case]:
    """SC-3 with TDRA off and SC-4 with PDRA off (the other flag stays on)."""
    return ([Case("SC-3", t, True, False, ablation=True) for t in (1.2, 0.6)]
            + [Case("SC-4", t, False, True, ablation=True) for t in (1.2, 0.6)])


@dataclass
class CaseRun:
    """One simulated run of a case with one controller.

    Attributes:
        case: The case.
        controller: ``"default"``, ``"pid"`` or ``"fuzzy"``.
        metrics: The six metrics on the evaluation window.
        window: (start, end) of the evaluation window [s].
        t_engage: When the intention detector engaged [s] (NaN if never).
        t_d: Disturbance time [s] (SC-3/SC-4), else None.
        result: The full simulated run (log and truth).
    """

    case: Case
    controller: str
    metrics: dict[str, float]
    window: tuple[float, float]
    t_engage: float
    t_d: float | None
    result: WorkoutResult = field(repr=False)

    def record(self) -> dict[str, Any]:
        """The ``results.json`` entry (issue 3's contract plus context)."""
        return {
            "scenario": self.case.scenario, "controller": self.controller, "target": self.case.target,
            "pdra": self.case.pdra, "tdra": self.case.tdra, "metrics": self.metrics,
            "ablation": self.case.ablation, "direction": self.case.direction,
            "window_s": [self.window[0], self.window[1]], "t_engage_s": self.t_engage, "t_d_s": self.t_d,
            **toggle_report(self.result.column("t"), self.result.column("p_a"), self.result.column("p_b"),
                            self.window),
            # how far the simulated arm went, as the station's exercises report it
            "angle_range_deg": angle_range_deg(self.result.column("theta")),
        }


def _case_seed(seed: int, case: Case) -> int:
    # common random numbers across controllers; independent of ablation flags
    base = main_cases()
    idx = next((i for i, c in enumerate(base) if c.scenario == case.scenario and c.target == case.target), None)
    if idx is None:  # a case outside SPEC §5's twelve (`cwrr sim --scenario SC-3 --target -0.9`): its own stream
        key = [seed, SCENARIOS.index(case.scenario), int(case.target > 0), int(round(abs(case.target) * 1e6))]
        return int(np.random.SeedSequence(key).generate_state(1)[0])
    return int(np.random.SeedSequence([seed, idx]).generate_state(1)[0])


def case_program(case: Case, settings: ScenarioSettings | None = None) -> tuple[HumanProgram, float, float | None]:
    """The simulated user's program for ``case``.

    Returns:
        (program, t_end, t_d): the program (time 0 = run start), the end of the
        rotation [s] and the disturbance time [s] (SC-3/SC-4, else None).
    """
    s = settings or ScenarioSettings()
    direction = 1 if case.target > 0 else -1
    t_d = s.t_engage + s.t_dist_after if case.scenario in ("SC-3", "SC-4") else None
    prog = isotonic(direction, speed=s.speed, amplitude=math.radians(s.amplitude_deg), t_engage=s.t_engage,
                    hold=1.0, repetitions=1, rest=1.0,
                    disturbance_at=t_d if case.scenario == "SC-3" else None,
                    disturbance_speed=s.dist_speed, disturbance_duration=s.dist_duration)
    return prog, float(prog.t[-4]), t_d  # t[-4]: the far end of the rotation is reached


def case_controller(case: Case, controller: ControllerName, settings: ScenarioSettings | None = None,
                    pid_gains: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None,
                    fuzzy: FuzzyConfig | None = None) -> ControllerConfig:
    """The controller configuration a case runs with.

    Args:
        case: The case.
        controller: PRV controller.
        settings: Workout shape (P_w).
        pid_gains: Cascade PID gains ((K_p, K_i, K_d) of PRV-a, of PRV-b); None keeps Eq 3.26's.
        fuzzy: Fuzzy scheduler; None keeps the thesis's.
    """
    s = settings or ScenarioSettings()
    return ControllerConfig(controller=controller, target_nm=abs(case.target), pw_bar=s.pw_bar,
                            pdra=case.pdra, tdra=case.tdra, pid_gains=pid_gains,
                            fuzzy=fuzzy if fuzzy is not None else FuzzyConfig())


def score_case(case: Case, t: np.ndarray, torque: np.ndarray, mode: np.ndarray, t_end: float,
               t_d: float | None, settings: ScenarioSettings | None = None
               ) -> tuple[dict[str, float], tuple[float, float], float]:
    """The six metrics of a case over its evaluation window (module doc).

    Args:
        case: The case.
        t: Sample times from the run's start [s].
        torque: Measured interaction torque [N·m].
        mode: Intention-detector state per sample (0, 1 CCW, 2 CW).
        t_end: End of the rotation [s].
        t_d: Disturbance time [s] or None.
        settings: Workout shape.

    Returns:
        (metrics, window, t_engage).
    """
    s = settings or ScenarioSettings()
    e = case.target - torque
    want = 1 if case.target > 0 else 2
    engaged = np.flatnonzero((mode == want) & (t >= s.t_engage - 0.5))
    t_on = float(t[engaged[0]]) if engaged.size else float("nan")
    if t_d is not None:
        t0 = t_d
    elif engaged.size:
        inband = np.flatnonzero((t >= t_on) & (np.abs(e) <= s.conv_band * abs(case.target)))
        t0 = float(t[inband[0]]) if inband.size else t_on + s.conv_timeout
        t0 = min(t0, t_on + s.conv_timeout)
    else:
        t0 = s.t_engage + s.conv_timeout
    w = (t >= t0) & (t <= t_end)
    return all_metrics(t[w], e[w]), (t0, t_end), t_on


def run_case(
    case: Case,
    controller: ControllerName,
    seed: int = 0,
    settings: ScenarioSettings | None = None,
    params: PlantParams | None = None,
    pid_gains: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None,
) -> CaseRun:
    """Simulate one case with one controller and score it.

    Args:
        case: Scenario case.
        controller: PRV controller.
        seed: Base seed (the run's noise depends on it and on the case).
        settings: Workout shape.
        params: Plant parameters (the faithful default if omitted).
        pid_gains: Cascade PID gains ((K_p, K_i, K_d) of PRV-a, of PRV-b); None keeps Eq 3.26's.
    """
    s = settings or ScenarioSettings()
    prog, t_end, t_d = case_program(case, s)
    duration = t_end + 0.5
    n = int(round(duration * s.rate_hz))
    dist = None
    if case.scenario == "SC-4" and t_d is not None:
        dist = np.zeros((n, 2))
        dist[int(round(t_d * s.rate_hz)):, 1] = s.dp_b_bar
    res = run_workout(params, prog, duration=duration, rate_hz=s.rate_hz,
                      control=case_controller(case, controller, s, pid_gains=pid_gains),
                      seed=_case_seed(seed, case), disturbance_bar=dist)
    metrics, window, t_on = score_case(case, res.column("t"), res.column("torque"), res.column("mode"), t_end, t_d, s)
    return CaseRun(case, controller, metrics, window, t_on, t_d, res)


def iter_matrix(
    seed: int = 0, ablations: bool = True, settings: ScenarioSettings | None = None,
    params: PlantParams | None = None,
) -> Iterator[CaseRun]:
    """All main runs (12 cases × 3 controllers), then the ablation runs."""
    cases = main_cases() + (ablation_cases() if ablations else [])
    for case in cases:
        for ctl in CONTROLLERS:
            yield run_case(case, ctl, seed, settings, params)
