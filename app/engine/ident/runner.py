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
