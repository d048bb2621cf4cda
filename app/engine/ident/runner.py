"""One-call identification runs on the simulated rig (CLI, tests, benchmarks).

On the real rig the same procedures run through the engine service with a
hardware backend and the wall clock; here a :class:`SimClock` makes them run
as fast as the CPU allows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from app.engine.constants import BAR
from app.engine.hardware.sim import SimulatedRig
from app.engine.human import HumanProgram
from app.engine.ident.gui_rules import LinearInputs, RotaryInputs
from app.engine.ident.procedure import Procedure, Progress, RunSummary, run_procedure
from app.engine.loop import SimClock
from app.engine.params import PlantParams

ROTARY_RATE_HZ = 500.0  # thesis 4.2.1
LINEAR_RATE_HZ = 200.0  # thesis 4.2.2


@dataclass
class SimRun:
    """A procedure run on the simulator.

    Attributes:
        procedure: The procedure (holds the data and the progress).
        summary: Rig and wall time.
        params: The plant it ran on (the truth).
    """

    procedure: Any
    summary: RunSummary
    params: PlantParams


def simulate(proc: Procedure, params: PlantParams, rate_hz: float, seed: int = 0, recorder: Any = None,
             on_progress: Callable[[Progress], None] | None = None, max_seconds: float = 1.0e6) -> SimRun:
    """Run ``proc`` on a simulated rig with nobody holding the handle."""
    clock = SimClock()
    rig = SimulatedRig(clock, params, seed=seed, period=1.0 / rate_hz)
    rig.set_program(HumanProgram.absent())
    summary = run_procedure(proc, rig, clock, rate_hz, max_seconds=max_seconds, recorder=recorder,
                            on_progress=on_progress)
    return SimRun(proc, summary, params)


def rotary_inputs_for(params: PlantParams, pw_bar: float, ns: int, nd: int) -> RotaryInputs:
    """The GUI inputs matching the simulated vane cylinder."""
    v = params.vane
    return RotaryInputs(v.rom_deg, v.vane_area * 1e6, v.radius * 1e3, ns, nd, pw_bar)


def linear_inputs_for(params: PlantParams, ns: int, nd: int) -> LinearInputs:
    """The GUI inputs matching the simulated linear cylinder."""
    c = params.linear
    assert c is not None
    return LinearInputs(c.stroke * 1e3, c.bore * 1e3, c.rod * 1e3, ns, nd)


def identify_rotary_sim(pw_bar: float, ns: int, nd: int, seed: int = 0, params: PlantParams | None = None,
                        with_ci: bool = True, on_progress: Callable[[Progress], None] | None = None) -> Any:
    """Run and fit the rotary identification on the simulator.

    Returns:
        (result, run): the :class:`RotaryFrictionResult` and the :class:`SimRun`.
    """
    from app.engine.ident.rotary import RotaryFrictionEstimator, RotaryFrictionProcedure

    params = params or PlantParams()
    inputs = rotary_inputs_for(params, pw_bar, ns, nd)
    proc = RotaryFrictionProcedure(inputs, seed=seed, p_atm_bar=params.p_atm / BAR)
    run = simulate(proc, params, ROTARY_RATE_HZ, seed=seed, on_progress=on_progress)
    est = RotaryFrictionEstimator(with_ci=with_ci).fit(proc.data)
    return est.params_, run


def identify_linear_sim(cylinder: str, ns: int, nd: int, seed: int = 0, params: PlantParams | None = None,
                        with_ci: bool = True, on_progress: Callable[[Progress], None] | None = None) -> Any:
    """Run and fit the linear identification on the simulator.

    Returns:
        (result, run): the :class:`LinearFrictionResult` and the :class:`SimRun`.
    """
    from app.engine.ident.linear import LinearFrictionEstimator, LinearFrictionProcedure

    if cylinder not in ("C1", "C2", "C3"):
        raise ValueError(f"cylinder = {cylinder!r} must be C1, C2 or C3")
    params = params or PlantParams.linear_rig(cylinder)  # type: ignore[arg-type]
    inputs = linear_inputs_for(params, ns, nd)
    proc = LinearFrictionProcedure(inputs, seed=seed, p_atm_bar=params.p_atm / BAR)
    run = simulate(proc, params, LINEAR_RATE_HZ, seed=seed, on_progress=on_progress)
    est = LinearFrictionEstimator(with_ci=with_ci).fit(proc.data)
    return est.params_, run


DCV_RATE_HZ = 200.0  # the linear rig's rate; the thesis validated at 100 Hz (0.01 s samples)


def cpr_volume_cm3(params: PlantParams) -> float:
    """Chamber a's volume with the simulated cylinder fully extended, dead volume included [cm³]."""
    c = params.linear
    if c is None:
        raise ValueError("the CPR set-up needs the linear rig (PlantParams.linear_rig)")
    return (c.area_a * c.stroke + c.dead_volume_a) * 1e6


def dcv_inputs_for(params: PlantParams, **kw: Any) -> Any:
    """CPR inputs matching the simulated constant-volume chamber (cylinder fully extended)."""
    from app.engine.ident.dcv import DCVInputs

    return DCVInputs(chamber_volume_cm3=cpr_volume_cm3(params), temperature_k=params.t_atm, **kw)


def identify_dcv_sim(model: str = "new", seed: int = 0, params: PlantParams | None = None, null_zone: bool = True,
                     inputs: Any = None, validation: list[tuple[str, float, float]] | None = None,
                     on_progress: Callable[[Progress], None] | None = None) -> Any:
    """CPR mapping, flow-model fit and validation runs on the simulated C3 set-up (thesis 4.1).

    Args:
        model: The simulator's DCV model, ``"new"`` (Eq 3.10–3.11 with known
            maps, to check recovery) or ``"iso"`` (ISO 6358 with underlaps).
        seed: Sensor-noise seed.
        params: Plant (default: C3 linear rig with ``model``).
        null_zone: Whether the default plant's valve has its null zone
            (:class:`~app.engine.params.DCVParams`); ignored with ``params``.
        inputs: :class:`DCVInputs` (default: the thesis's grid for this chamber).
        validation: (mode, u, P_s) cases run for 15 s after the fit
            (default: Figures 4.6–4.11 plus the held-out points).

    Returns:
        (estimator, cpr_run, validation_run, cases): the fitted
        :class:`DCVFlowEstimator`, both :class:`SimRun` objects and the
        :class:`ValidationCase` list.
    """
    from app.engine.ident.dcv import HELD_OUT, THESIS_VALIDATION, CPRProcedure, DCVFlowEstimator
    from app.engine.params import DCVParams, SensorParams

    # Figure 3.10: PS-0 measures the DCV's supply port
    if params is None:
        dcv = DCVParams(model=model) if null_zone else DCVParams.without_null_zone(model=model)  # type: ignore[arg-type]
        params = PlantParams.linear_rig("C3", dcv=dcv, sensors=SensorParams(supply_tap="prv_a"))
    inputs = inputs or dcv_inputs_for(params)
    proc = CPRProcedure(inputs)
    run = simulate(proc, params, DCV_RATE_HZ, seed=seed, on_progress=on_progress)
    est = DCVFlowEstimator().fit(proc.data)
    cases = THESIS_VALIDATION + HELD_OUT if validation is None else validation
    vproc = CPRProcedure(inputs, fixed_s=15.0, cases=cases)
    vrun = simulate(vproc, params, DCV_RATE_HZ, seed=seed + 1, on_progress=on_progress)
    return est, run, vrun, est.validate(vproc.data)
