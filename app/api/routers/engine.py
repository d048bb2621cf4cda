"""The engine's state machine: connect, start, estimate, stop, disconnect, clear; live data."""

from __future__ import annotations

from typing import Any

import numpy as np
from fastapi import APIRouter, Query, Request

from app.api.auth import ADMIN, AUTH_RESPONSES, READ, THERAPIST
from app.api.deps import StationDep, StoreDep
from app.api.models import (
    CalibrateRequest,
    CalibrationResult,
    ConnectRequest,
    DCVIdentRequest,
    EngineStatus,
    Health,
    LinearIdentRequest,
    LiveData,
    PIDTuneRequest,
    ProtocolRunRequest,
    RotaryIdentRequest,
    RunRequest,
    Started,
)
from app.engine.ident.fitting import friction_report
from app.engine.params import ParameterError
from app.engine.station import CONTROL_RATE_HZ, LIVE_COLUMNS, Rig, RunSpec
from app.storage import Store

router = APIRouter(prefix="/api", tags=["engine"])
CONFLICT: dict[int | str, dict[str, Any]] = {409: {"description": "Illegal in the current state (says why)"},
                                             **AUTH_RESPONSES}


@router.get("/health", response_model=Health, summary="Engine state, loop rate, jitter and overruns")
def health(station: StationDep, request: Request) -> Health:
    """Needs no token: the Docker health check and a lab's monitoring read it. Jitter and overruns are
    the paced loop's since it last started (a connect, a procedure's end); `live_plots` says whether
    the viser charts are being fed."""
    plots = getattr(request.app.state, "plots", None)
    return Health(**station.health(), live_plots=plots.status() if plots is not None else None)


@router.get("/engine", dependencies=[READ], responses=AUTH_RESPONSES, response_model=EngineStatus,
            summary="State, allowed actions, progress")
def status(station: StationDep) -> EngineStatus:
    """The state machine (disconnected, idle, running, identifying, stopping, fault), the actions the state
    allows, the running job's progress, the last run's outcome, the safety limits and any latched fault."""
    return EngineStatus(**station.status())


@router.post("/engine/connect", dependencies=[THERAPIST], response_model=EngineStatus, responses=CONFLICT,
             summary="disconnected → idle")
def connect(station: StationDep, body: ConnectRequest | None = None) -> EngineStatus:
    """Starts the paced loop on the configured backend with the chosen set-up: the forearm robot
    (`rotary`, the default), a linear test cylinder or the valve test set-up (`cpr`). 409 unless
    disconnected."""
    body = body or ConnectRequest()
    station.connect(Rig(body.rig, body.cylinder))
    return EngineStatus(**station.status())


@router.post("/engine/disconnect", dependencies=[THERAPIST], response_model=EngineStatus, responses=CONFLICT,
             summary="idle → disconnected")
def disconnect(station: StationDep) -> EngineStatus:
    """Leaves the rig in its safe state (both chambers vented) and stops the loop. 409 unless idle."""
    station.disconnect()
    return EngineStatus(**station.status())


def _person(store: Store, person: str, session_id: int | None) -> str:
    """Who the work is for: the session's person, which a person given too must match."""
    if session_id is None:
        return person
    sess = store.session(session_id)
    if sess is None:
        raise ParameterError(f"session_id: session {session_id} does not exist")
    if person and person != sess["person"]:
        raise ParameterError(f"person: {person!r} differs from session {session_id}'s {sess['person']!r}")
    return str(sess["person"])


@router.post("/engine/start", dependencies=[THERAPIST], response_model=Started, responses=CONFLICT,
             summary="idle → running: a scenario run")
def start(req: RunRequest, station: StationDep, store: StoreDep) -> Started:
    """Pressurises both chambers to P_w (1.5 s), then runs the scenario's isotonic exercise with the chosen
    controller until its program ends or STOP; the run's log is written as it goes and its six metrics are
    stored when it ends. Stored parameter sets may replace the exercise shape, the PID gains or the
    fuzzy universes. 409 unless idle on the forearm robot; 422 names a refused field and nothing moves."""
    person = _person(store, req.person, req.session_id)

    def stored(field: str, set_id: int | None, kind: str) -> dict[str, Any] | None:
        if set_id is None:
            return None
        row = store.param_set(set_id)
        if row is None or row["kind"] != kind:
            raise ParameterError(f"{field}: no stored {kind} parameter set has id {set_id}")
        return dict(row["payload"])

    spec = RunSpec(req.scenario, req.controller, req.target_nm, req.pw_bar, person, req.notes,
                   workout=stored("workout_id", req.workout_id, "workout"),
                   gains=stored("gains_id", req.gains_id, "gains"),
                   fuzzy=stored("fuzzy_id", req.fuzzy_id, "fuzzy"), session_id=req.session_id)
    run_id = station.start(spec)
    return Started(run_id=run_id, status=EngineStatus(**station.status()))


@router.post("/engine/estimate/rotary", dependencies=[ADMIN], response_model=Started, responses=CONFLICT,
             summary="idle → identifying: rotary friction identification (thesis 3.2.4, 500 Hz)",
             name="estimate_rotary")  # its own operation id beside /engine/estimate's, the same call
@router.post("/engine/estimate", dependencies=[ADMIN], response_model=Started, responses=CONFLICT,
             summary="idle → identifying: rotary friction identification (thesis 3.2.4, 500 Hz)")
def estimate(req: RotaryIdentRequest, station: StationDep) -> Started:
    """Runs the thesis's static and dynamic experiments (Appendix 1, N_s and N_d per direction) and fits
    T_s, T_c, ω_s and B per direction with their 95 % intervals and the Coulomb + viscous alternative
    (the run's `result`). Minutes of rig time; poll `GET /api/engine` for progress. 409 unless idle on
    the forearm robot."""
    from app.engine.ident.gui_rules import RotaryInputs
    from app.engine.ident.rotary import RotaryFrictionEstimator, RotaryFrictionProcedure

    inputs = RotaryInputs(req.rom_deg, req.vane_area_mm2, req.radius_mm, req.ns, req.nd, req.pw_bar)
    return _identify(station, RotaryFrictionProcedure(inputs, seed=req.seed, p_atm_bar=station.p_atm_bar),
                     RotaryFrictionEstimator,
                     "rotary", req.model_dump())


@router.post("/engine/estimate/linear", dependencies=[ADMIN], response_model=Started, responses=CONFLICT,
             summary="idle → identifying: linear friction identification (thesis 3.2.4, 200 Hz, linear rig)")
def estimate_linear(req: LinearIdentRequest, station: StationDep) -> Started:
    """Appendix 2's experiments on the connected linear cylinder; F_s, F_c, v_s and B per direction, as the
    rotary identification reports them, plus the moving mass its inertia correction fitted. A dimension left
    out is the connected cylinder's catalogue value. On the simulator a stroke longer than the simulated
    cylinder's is refused: its static tests would be placed past the end, and none would move."""
    from app.engine.ident.gui_rules import LinearInputs, suggested_values
    from app.engine.ident.linear import LinearFrictionEstimator, LinearFrictionProcedure

    rig = station.rig
    catalogue = suggested_values("linear", rig.cylinder)  # type: ignore[arg-type]  # Rig checks the name
    spec = req.model_dump()
    for k in ("stroke_mm", "piston_diameter_mm", "rod_diameter_mm"):
        if spec[k] is None:
            spec[k] = catalogue[k]
    inputs = LinearInputs(spec["stroke_mm"], spec["piston_diameter_mm"], spec["rod_diameter_mm"], req.ns, req.nd)
    simulated = station.backend is not None and station.backend.name == "sim"
    if simulated and rig.kind == "linear" and inputs.stroke_mm > catalogue["stroke_mm"]:
        raise ParameterError(f"stroke_mm = {inputs.stroke_mm:g}: longer than the simulated cylinder {rig.cylinder}'s "
                             f"stroke ({catalogue['stroke_mm']:g} mm), so its static tests would be placed past the "
                             "end; enter the cylinder's stroke or less")
    return _identify(station, LinearFrictionProcedure(inputs, seed=req.seed, p_atm_bar=station.p_atm_bar),
                     LinearFrictionEstimator, "linear", spec)


@router.post("/engine/estimate/dcv", dependencies=[ADMIN], response_model=Started, responses=CONFLICT,
             summary="idle → identifying: directional-valve CPR map and flow-model fit (thesis 3.2.3, 4.1; cpr rig)")
def estimate_dcv(req: DCVIdentRequest, station: StationDep) -> Started:
    """On the valve test set-up (`cpr`): the critical-pressure-ratio map per signal and supply pressure,
    then the new flow model's ε and g per signal of the unstable band at 5 bar and k(P_s), compared with the
    literature models on optional validation runs. The thesis's full grid takes hours of rig time; a grid
    the fit cannot use is refused (422) before anything moves."""
    from dataclasses import asdict

    from app.engine.ident.dcv import CPRProcedure, DCVFlowEstimator, DCVInputs, check_fittable

    station.require("estimate", "cpr")
    from app.engine.ident.runner import cpr_volume_cm3

    volume = req.chamber_volume_cm3
    if volume is None:
        params = getattr(station.backend, "params", None)
        if params is None or getattr(params, "linear", None) is None:
            raise ParameterError("chamber_volume_cm3: give chamber a's volume with the cylinder extended "
                                 "(the connected backend does not know it)")
        volume = cpr_volume_cm3(params)
    inputs = DCVInputs(volume, tuple(req.ps_bar), tuple(req.u_fill), tuple(req.u_exh), req.band_fill,
                       req.band_exh, req.temperature_k, req.polytropic_n)
    check_fittable(inputs, req.fit_ps_bar)
    modes = tuple(m for m, us in (("filling", req.u_fill), ("exhausting", req.u_exh)) if us)
    proc = CPRProcedure(inputs, modes=modes, validation=[(m, float(u), float(ps)) for m, u, ps in req.validation],
                        validation_s=req.validation_s)

    def fit(p: CPRProcedure) -> dict[str, Any]:
        est = DCVFlowEstimator(req.fit_ps_bar).fit(p.data)
        out: dict[str, Any] = {"parameters": est.as_dict(), "inputs": asdict(inputs),
                               "tests": {"cpr": len(p.data.tests), "validation": len(p.validation_data.tests)},
                               "cpr_tests": p.data.as_dict()["tests"]}
        if p.validation_data.tests:
            cases = est.validate(p.validation_data)
            out["validation"] = [c.summary() for c in cases]
            out["validation_mape_pct"] = {m: float(sum(c.mape_pct[m] for c in cases) / len(cases))
                                          for m in cases[0].mape_pct}
        return out

    run_id = station.estimate(proc, "dcv_flow", fit, "cpr", req.model_dump() | {"chamber_volume_cm3": volume})
    return Started(run_id=run_id, status=EngineStatus(**station.status()))


@router.post("/engine/tune/pid", dependencies=[ADMIN], response_model=Started, responses=CONFLICT,
             summary="idle → identifying: frequency-response autotune of one PRV loop (thesis 3.6.2; rotary rig)")
def tune_pid(req: PIDTuneRequest, station: StationDep) -> Started:
    """Sines at ω_c·[1/10, 1/3, 1, 3, 10] on one PRV's command around P_w, the plant's frequency response
    at each, and the PIDF gains (≥ 0) that put the loop's crossover at ω_c with the phase margin asked
    for, beside the thesis's gains on the same response; `result.gains_fields` can be stored as a gain
    set. Nobody may hold the handle."""
    from dataclasses import asdict

    from app.engine.ident import pid_tune as pt

    station.require("estimate", "rotary")
    spec = pt.AutotuneSpec(req.side, req.bandwidth_rad_s, req.phase_margin_deg, req.pw_bar, req.amplitude_bar,
                           req.periods, req.n_filter, req.initial, station.p_atm_bar)

    def fit(p: pt.PIDAutotuneProcedure) -> dict[str, Any]:
        frf = p.frf()
        tuning = pt.tune_pid(frf, spec.bandwidth_rad_s, spec.phase_margin_deg, spec.n_filter)
        thesis = {"thesis autotuner": pt.THESIS_TUNED[spec.side], "thesis Eq 3.26": pt.THESIS_FINAL[spec.side]}
        margins = {k: dict(zip(("crossover_rad_s", "phase_margin_deg"), pt.loop_margins(frf, *g, spec.n_filter),
                               strict=True)) for k, g in thesis.items()}
        side = spec.side
        gains = {"Tuned here": (tuning.kp, tuning.ki, tuning.kd), **thesis}
        return {"parameters": asdict(tuning), "frf": frf.as_dict(),
                "loops": {k: pt.loop_response(frf, *g, spec.n_filter) for k, g in gains.items()},
                "gains_fields": {f"kp_{side}": tuning.kp, f"ki_{side}": tuning.ki, f"kd_{side}": tuning.kd},
                "thesis": {k: dict(zip(("kp", "ki", "kd"), g, strict=True)) for k, g in thesis.items()},
                "thesis_margins": margins}

    run_id = station.estimate(pt.PIDAutotuneProcedure(spec), "pid_tuning", fit, "rotary", req.model_dump(),
                              rate_hz=CONTROL_RATE_HZ)
    return Started(run_id=run_id, status=EngineStatus(**station.status()))


def _identify(station: StationDep, proc: Any, estimator: Any, rig: str, spec: dict[str, Any]) -> Started:
    """Start a friction identification on ``rig``; the run is fitted, with its intervals, when the procedure ends."""

    def fit(p: Any) -> dict[str, Any]:
        return friction_report(p.data, estimator(with_ci=True).fit(p.data).params_)

    run_id = station.estimate(proc, "rotary_friction" if rig == "rotary" else "linear_friction", fit, rig, spec)
    return Started(run_id=run_id, status=EngineStatus(**station.status()))


@router.post("/engine/protocol", dependencies=[ADMIN], response_model=Started, responses=CONFLICT,
             summary="idle → identifying: the diagnosis protocol's experiments on the connected rotary rig")
def run_protocol(req: ProtocolRunRequest, station: StationDep, store: StoreDep) -> Started:
    """Runs the experiments of ``GET /api/diagnoses/protocol`` through the engine on the rig
    (or the simulated one), at the station's rate; the progress says what the person at the handle should
    do. Each experiment that runs to its end is stored as a run of kind ``protocol`` with its log; the
    protocol's own run lists them in ``result.run_ids``, what ``POST /api/diagnoses`` takes. The person
    and session are kept with every one of those runs and in each log's metadata."""
    person = _person(store, req.person, req.session_id)
    try:
        run_id = station.run_protocol(req.repetitions, req.scale, list(dict.fromkeys(req.kinds or [])) or None,
                                      person=person, notes=req.notes, session_id=req.session_id)
    except ValueError as exc:
        raise ParameterError(str(exc)) from None
    return Started(run_id=run_id, status=EngineStatus(**station.status()))


@router.post("/engine/stop", dependencies=[THERAPIST], response_model=EngineStatus, responses=CONFLICT,
             summary="running/identifying → idle, keeping what was recorded")
def stop(station: StationDep) -> EngineStatus:
    """An exercise ends with a controlled stop: both chambers' pressures fall together to atmosphere over
    0.5 s (state `stopping`), and the answer comes once the run has ended. An identification stops at
    its next step and vents. The emergency stop vents at once instead."""
    station.stop()
    return EngineStatus(**station.status())


@router.post("/engine/estop", response_model=EngineStatus,
             summary="Emergency stop from any state: safe outputs within one control period, fault latched")
def estop(station: StationDep) -> EngineStatus:
    """Needs no token: anyone at the station may stop the rig. Both chambers vent at once (no controlled
    release), the job ends and the fault `estop` latches until `POST /api/engine/clear`."""
    station.estop("API")
    return EngineStatus(**station.status())


@router.post("/engine/clear", dependencies=[THERAPIST], response_model=EngineStatus, responses=CONFLICT,
             summary="fault → disconnected")
def clear(station: StationDep) -> EngineStatus:
    """Acknowledges a latched fault (its cause stays in `GET /api/engine` until then); the station is then
    disconnected, and a connect starts it again. 409 unless in fault."""
    station.clear()
    return EngineStatus(**station.status())


@router.post("/engine/calibrate", dependencies=[ADMIN], response_model=CalibrationResult, responses=CONFLICT,
             summary="idle: zero the torque sensor, the chamber pressure offsets or the encoder; saved with a date")
def calibrate(body: CalibrateRequest, station: StationDep) -> CalibrationResult:
    """Averages the chosen sensor at rest and stores its new zero with the date; for backends with a
    scaling (Modbus, Quanser), not the simulator (409 there)."""
    return CalibrationResult(**station.calibrate(body.what, body.seconds, body.p_atm_bar))


@router.get("/live", dependencies=[READ], responses=AUTH_RESPONSES, response_model=LiveData,
            summary="Samples newer than `since` from the live buffer")
def live(station: StationDep,
         since: float = Query(-1.0, ge=-1.0, le=1e9, allow_inf_nan=False, description=(
             "Engine time [s] of the last sample already seen (the previous answer's t_last); -1: the newest "
             "samples")),
         max_rows: int = Query(2000, ge=1, le=15000, description="At most this many samples, the newest")
         ) -> LiveData:
    """The engine's recent periods (the last 15 000: 75 s at 200 Hz) with torque, target, pressures and
    their references, speed and angle: poll with the previous answer's `t_last` as `since` to get each
    sample once. A reconnect restarts the engine's clock: `t_last` then comes back smaller than `since`."""
    rows = station.live.since(since, max_rows)
    # NaN (no target outside an exercise) becomes null. Built from floats and None, the rows need no
    # validation, which would hold the interpreter lock in pydantic's core while the engine waits for
    # it (0.4 ms per 2000 rows, 5–8 ms at 15 000); with numpy doing the NaN test a 2000-row answer
    # costs 1.5–1.7 ms, not 4.7–6.9 ms (measured here)
    cells = rows.astype(object)
    cells[~np.isfinite(rows)] = None
    out = cells.tolist()
    return LiveData.model_construct(columns=list(LIVE_COLUMNS), rows=out,
                                    t_last=float(rows[-1, 0]) if len(rows) else since)
