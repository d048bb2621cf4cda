"""Request and response models of the REST API (every body is one of these)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


class Health(BaseModel):
    """Engine health.

    Attributes:
        state: Engine state.
        backend: Backend name (``none`` when disconnected).
        rate_hz: Nominal loop rate [Hz].
        measured_rate_hz: Achieved rate over the recent window [Hz].
        ticks: Periods executed.
        overruns: Periods that missed their deadline.
        jitter_p50_ms: Median start jitter [ms].
        jitter_p99_ms: 99th-percentile start jitter [ms].
        jitter_max_ms: Largest start jitter [ms].
        realtime: Whether the loop thread runs at SCHED_FIFO priority.
        realtime_note: Why not, when it does not.
    """

    state: str
    backend: str
    rate_hz: float
    measured_rate_hz: float
    ticks: int
    overruns: int
    jitter_p50_ms: float
    jitter_p99_ms: float
    jitter_max_ms: float
    realtime: bool = False
    realtime_note: str = ""


class EngineStatus(BaseModel):
    """The station's state machine as the dashboard sees it.

    Attributes:
        state: ``disconnected``, ``idle``, ``running``, ``identifying``, ``stopping`` or ``fault``.
        allowed: Actions legal now (the dashboard enables exactly these buttons).
        run_id: Stored id of the current or last started run.
        backend: Backend name when connected.
        rig: The connected rig (kind, cylinder).
        fault: The latched fault's message.
        progress: Progress of the current work.
        last_run: How the last run ended (id, status, metrics or result).
    """

    state: str
    allowed: list[str]
    run_id: int | None = None
    backend: str | None = None
    rig: dict[str, str] | None = None
    fault: str = ""
    progress: dict[str, Any] | None = None
    last_run: dict[str, Any] | None = None


class RunRequest(BaseModel):
    """Start a scenario run (thesis 4.4–4.7).

    Attributes:
        scenario: SC-1 free motion, SC-2 with PDRA/TDRA, SC-3 torque disturbance, SC-4 pressure disturbance.
        controller: PRV controller.
        target_nm: Signed target torque [N·m]: positive = pronation (CCW), negative = supination.
        pw_bar: Working pressure [bar abs].
        person: Pseudonymous id of the person exercising (no names).
        notes: Free text for the therapist.
    """

    model_config = ConfigDict(extra="forbid")

    scenario: Literal["SC-1", "SC-2", "SC-3", "SC-4"] = "SC-1"
    controller: Literal["default", "pid", "fuzzy"] = "pid"
    target_nm: float = Field(1.2, ge=-3.0, le=3.0, description="N·m, signed")
    pw_bar: float = Field(3.0, ge=1.5, le=6.0, description="bar abs")
    person: str = Field("", max_length=64, pattern=r"^[A-Za-z0-9_.-]*$")
    notes: str = Field("", max_length=2000)
    session_id: int | None = Field(None, ge=1, le=2**62, description="therapy session (person taken from it)")
    workout_id: int | None = Field(None, ge=1, le=2**62, description="stored workout parameter set")
    gains_id: int | None = Field(None, ge=1, le=2**62, description="stored Cascade PID gain set")
    fuzzy_id: int | None = Field(None, ge=1, le=2**62, description="stored fuzzy MF set")


class ConnectRequest(BaseModel):
    """Which rig to connect.

    Attributes:
        rig: ``rotary`` (the CWRR forearm axis) or ``linear`` (the linear test cylinder of thesis 3.2.4).
        cylinder: Cylinder on the simulated linear rig (thesis Table 3.3).
    """

    model_config = ConfigDict(extra="forbid")

    rig: Literal["rotary", "linear"] = "rotary"
    cylinder: Literal["C1", "C2", "C3"] = "C3"


class LinearIdentRequest(BaseModel):
    """Linear friction identification inputs (thesis Figure 3.27, Appendix 2 rules).

    Attributes:
        stroke_mm: Stroke [mm].
        piston_diameter_mm: Piston diameter [mm].
        rod_diameter_mm: Rod diameter [mm].
        ns: Static experiments per direction (≥ 30).
        nd: Dynamic experiments per direction (≥ 30).
        seed: Seed of the random test positions and levels.
    """

    model_config = ConfigDict(extra="forbid")

    stroke_mm: float = 300.0
    piston_diameter_mm: float = 32.0
    rod_diameter_mm: float = 12.0
    ns: int = 30
    nd: int = 30
    seed: int = Field(0, ge=0, le=2**31 - 1)


class SessionIn(BaseModel):
    """Open a therapy session.

    Attributes:
        person: Pseudonymous id of the person (letters, digits, ``_.-``; no names).
        notes: Therapist's notes.
    """

    model_config = ConfigDict(extra="forbid")

    person: str = Field(..., min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    notes: str = Field("", max_length=2000)


class Session(BaseModel):
    """A therapy session.

    Attributes:
        id: Id.
        person: Pseudonymous person id.
        notes: Notes.
        created: When [Unix s].
        runs: Ids of the runs recorded in it, newest first.
    """

    id: int
    person: str
    notes: str
    created: float
    runs: list[int] = []


class RotaryIdentRequest(BaseModel):
    """Rotary friction identification inputs (thesis Figure 3.19, Appendix 1 rules).

    Attributes:
        rom_deg: Range of motion [deg].
        vane_area_mm2: Vane area [mm²].
        radius_mm: Torque radius [mm].
        ns: Static experiments per direction (≥ 30).
        nd: Dynamic experiments per direction (≥ 30).
        pw_bar: Working pressure [bar abs], 1–8.
        seed: Seed of the random test positions and levels.
    """

    model_config = ConfigDict(extra="forbid")

    rom_deg: float = 270.0
    vane_area_mm2: float = 855.0
    radius_mm: float = 23.0
    ns: int = 30
    nd: int = 30
    pw_bar: float = 3.0
    seed: int = Field(0, ge=0, le=2**31 - 1)


class Started(BaseModel):
    """Work accepted.

    Attributes:
        run_id: Stored id of the run.
        status: The engine state after the action.
    """

    run_id: int | None
    status: EngineStatus


class LiveData(BaseModel):
    """Recent samples from the live buffer.

    Attributes:
        columns: Column names (s, N·m, N·m, bar, bar, bar, bar, rad/s, rad).
        rows: Samples, oldest first.
        t_last: Time of the newest sample [s] (pass it back as ``since``).
    """

    columns: list[str]
    rows: list[list[float | None]]
    t_last: float


class RunInfo(BaseModel):
    """A stored run.

    Attributes:
        id: Run id.
        kind: ``workout`` or an identification kind.
        status: ``running``, ``complete``, ``stopped``, ``interrupted``, ``fault``, ``finished``, ``cancelled``.
        started: Start [Unix s].
        ended: End [Unix s].
        spec: What was asked for.
        metrics: The six metrics (workouts).
        result: Evaluation window or identified parameters.
        person: Pseudonymous person id.
        notes: Notes.
        session_id: The therapy session it belongs to.
        has_series: Whether a time-series log exists.
    """

    id: int
    kind: str
    status: str
    started: float
    ended: float | None
    spec: dict[str, Any]
    metrics: dict[str, float] | None
    result: dict[str, Any] | None
    person: str
    notes: str
    session_id: int | None = None
    has_series: bool


class Series(BaseModel):
    """A run's time series.

    Attributes:
        columns: Column names (the run-log format: s, V, bar, rad, rad/s, N·m).
        rows: Samples.
        every: Decimation factor applied.
    """

    columns: list[str]
    rows: list[list[float]]
    every: int


class ParamSetIn(BaseModel):
    """A parameter set to validate and store.

    Attributes:
        kind: ``rotary`` / ``linear`` identification inputs (every field), ``workout`` shape,
            Cascade PID ``gains`` (all six) or ``fuzzy`` scheduler (any of its fields).
        name: Label.
        values: Field values in the GUI's units (``GET /api/params/fields`` lists them).
    """

    model_config = ConfigDict(extra="forbid")

    kind: Literal["rotary", "linear", "workout", "gains", "fuzzy"]
    name: str = Field(..., min_length=1, max_length=80)
    values: dict[str, float | str]


class ParamSet(BaseModel):
    """A stored parameter set.

    Attributes:
        id: Id.
        kind: Kind.
        name: Label.
        payload: The validated values.
        created: When [Unix s].
    """

    id: int
    kind: str
    name: str
    payload: dict[str, Any]
    created: float


class FormCheckIn(BaseModel):
    """Values typed so far into a thesis GUI form, in entry order.

    Attributes:
        values: Field → value, in the order typed.
    """

    model_config = ConfigDict(extra="forbid")

    values: dict[str, float]


class FieldState(BaseModel):
    """One field of a guided form.

    Attributes:
        name: Field key.
        label: Label with unit.
        valid: Turned green.
        editable: Open for input now.
    """

    name: str
    label: str
    valid: bool
    editable: bool


class FormState(BaseModel):
    """A guided form after replaying the typed values.

    Attributes:
        fields: Every field in order.
        message: The GUI's message box text.
        ready: All fields valid.
        refused: The first refused field, if any.
    """

    fields: list[FieldState]
    message: str
    ready: bool
    refused: str | None


class ViserInfo(BaseModel):
    """Where the viser live plots are.

    Attributes:
        url: Address of the viser server (None when it is off).
    """

    url: str | None
