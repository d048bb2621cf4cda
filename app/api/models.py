"""Request and response models of the REST API (every body is one of these)."""

from __future__ import annotations

import inspect
import re
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import Query
from pydantic import AfterValidator, BaseModel, ConfigDict, Field
from pydantic_core import PydanticCustomError

from app.engine.constants import P_ATM_BAR


def attribute_docs(doc: str | None) -> dict[str, str]:
    """The entries of a Google-style docstring's ``Attributes:`` section.

    Args:
        doc: A class docstring.

    Returns:
        Each attribute's text, its continuation lines joined with spaces.
    """
    out: dict[str, str] = {}
    lines = inspect.cleandoc(doc or "").splitlines()
    try:
        start = lines.index("Attributes:") + 1
    except ValueError:
        return out
    name = None
    indent = 0
    for line in lines[start:]:
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip())
        if depth == 0:
            break  # the next section
        m = re.match(r"(\w+)(?: \([^)]*\))?: (.*)", line.strip())
        if m and (name is None or depth <= indent):
            name, indent = m.group(1), depth
            out[name] = m.group(2).strip()
        elif name is not None:
            out[name] += " " + line.strip()
    return out


def _describe_fields(schema: dict[str, Any], model: type[BaseModel]) -> None:
    """Give each property of ``model``'s JSON schema the text its docstring's ``Attributes:`` has for it.

    A field a subclass inherits is described by the class that declares it (the subclass's own text wins).
    """
    docs: dict[str, str] = {}
    for cls in reversed(model.__mro__):
        docs |= attribute_docs(cls.__doc__) if issubclass(cls, BaseModel) else {}
    for name, prop in schema.get("properties", {}).items():
        if name in docs:
            prop["description"] = docs[name]


class Documented(BaseModel):
    """A model whose fields are described in the OpenAPI schema by its docstring's ``Attributes:``.

    The meaning and unit of each field are written once, in the docstring the
    code's readers see; this puts the same text where an API's users look
    (``/docs``, ``/openapi.json``). A field's own ``description`` is kept where
    the docstring does not name it. The text is added where pydantic
    generates the schema (``json_schema_extra``), so no model is rebuilt at
    import to carry it. Hand-written rather than a docstring library: our
    docstrings have one shape, and twenty lines read it.
    """

    # allow_inf_nan: Python's json (a script's requests.post(json=...)) sends NaN and Infinity, which
    # JSON has not; refused here, every field says so in the same words, before any check of its own
    model_config = ConfigDict(json_schema_extra=_describe_fields, allow_inf_nan=False)


# who a run is for, as every request that starts one takes it
PERSON_PATTERN = r"^[A-Za-z0-9_.-]*$"
_PERSON_CHARS = re.compile(PERSON_PATTERN)


def check_person(v: str | None) -> str | None:
    """A pseudonymous person id, refused in words a therapist reads rather than as the pattern."""
    if v is not None and not _PERSON_CHARS.fullmatch(v):
        bad = "".join(dict.fromkeys(c for c in v if not _PERSON_CHARS.fullmatch(c)))
        shown = ", ".join("a space" if c == " " else repr(c) for c in bad)
        # a custom error, not a ValueError, so that the message is not prefixed "Value error, "
        raise PydanticCustomError("person_id", "{value} holds {chars}: a person id is a pseudonym such as P-007, "
                                  "made of letters, digits, '-', '_' and '.' (no names)",
                                  {"value": repr(v), "chars": shown})
    return v


# the pattern stays in the schema for the API's users; the validator words the refusal
PersonId = Annotated[str, Field(max_length=64, json_schema_extra={"pattern": PERSON_PATTERN}),
                     AfterValidator(check_person)]
# the ``person`` filter of the runs' and the sessions' listings: the same id, refused in the same words
PersonFilter = Annotated[str | None, Query(max_length=64, json_schema_extra={"pattern": PERSON_PATTERN},
                                           description="Only this person's records (pseudonymous id, exact)"),
                         AfterValidator(check_person)]
Notes = Annotated[str, Field(max_length=2000)]
SessionRef = Annotated[int | None, Field(ge=1, le=2**62, description="therapy session (person taken from it)")]


class LivePlotsHealth(Documented):
    """The viser live plots' publisher.

    Attributes:
        viewers: Pages connected now.
        pushes: Chart updates sent since start-up (one carries all four charts; none while
            nobody watches or no new sample came).
        last_push_age_s: Time since the last update [s]; None before the first.
        errors: Publishes that raised (each kind logged once with its traceback).
        last_error: The last failure's type and message; empty if none.
    """

    viewers: int
    pushes: int
    last_push_age_s: float | None
    errors: int
    last_error: str


class Health(Documented):
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
        switch_interval_ms: The interpreter's switch interval [ms]: how long the woken loop
            waits before it may ask another thread to hand over the interpreter lock.
        heap_frozen: Objects exempted from garbage collection at the last connect.
        heap_refreeze_ms: How long the last periodic collect-and-freeze took [ms].
        live_plots: The viser live plots' publisher; None when the station runs without them.
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
    switch_interval_ms: float = 0.0
    heap_frozen: int = 0
    heap_refreeze_ms: float = 0.0
    live_plots: LivePlotsHealth | None = None


class RigInfo(Documented):
    """The connected rig.

    Attributes:
        kind: ``rotary`` (the forearm robot), ``linear`` (the linear test cylinder) or ``cpr`` (the
            valve test set-up with the cylinder held extended).
        cylinder: The linear rig's cylinder, ``C1``, ``C2`` or ``C3`` (thesis Tables 4.5–4.6).
        stroke_mm: That cylinder's stroke in the catalogue [mm] (null on the forearm robot): the
            piston runs from 0 (retracted) to it.
    """

    kind: str
    cylinder: str
    stroke_mm: float | None = None


class EngineStatus(Documented):
    """The station's state machine as the dashboard sees it.

    Attributes:
        state: ``disconnected``, ``idle``, ``running``, ``identifying``, ``stopping`` or ``fault``.
        allowed: Actions legal now (the dashboard enables exactly these buttons).
        run_id: Stored id of the current or last started run.
        backend: Backend name when connected.
        rig: The connected rig (kind, cylinder, stroke).
        fault: The latched fault's message.
        progress: Progress of the current work.
        last_run: How the last run ended (id, status, metrics or result, the ``warnings`` its result
            carries, e.g. a chamber's pressure toggling every control period, and an exercise's
            ``angle_range_deg``: the lowest and highest angle it reached [deg, positive pronation]).
        safety: The safety supervisor: ``fault`` (code, message, t [s],
            channel, or null), ``no_action`` (the soft ROM limit is holding the
            vane), ``faults_total`` and the ``limits`` in force.
        calibration: Dates of the last torque-zero, pressure-offset and
            encoder-zero calibrations (null for backends without sensor
            scaling, e.g. the simulator).
        p_atm_bar: The atmosphere the station commands and logs in [bar abs]
            (the hardware configuration's ``p_atm_bar``; sea level without one).
    """

    state: str
    allowed: list[str]
    run_id: int | None = None
    backend: str | None = None
    rig: RigInfo | None = None
    fault: str = ""
    progress: dict[str, Any] | None = None
    last_run: dict[str, Any] | None = None
    safety: dict[str, Any] | None = None
    calibration: dict[str, str | None] | None = None
    p_atm_bar: float = P_ATM_BAR


class CalibrateRequest(Documented):
    """Zero one sensor from idle samples (issue 8 item 5).

    Attributes:
        what: ``torque_zero`` (nobody holds the handle), ``pressure_offsets``
            (both chambers vented to atmosphere) or ``encoder_zero`` (handle
            held still at neutral).
        seconds: Averaging time [s].
        p_atm_bar: The local atmosphere [bar abs] (default: the station's, from its hardware configuration).
    """

    model_config = ConfigDict(extra="forbid")
    what: Literal["torque_zero", "pressure_offsets", "encoder_zero"]
    seconds: float = Field(1.0, ge=0.2, le=30.0, description="s")
    p_atm_bar: float | None = Field(None, ge=0.7, le=1.1, description="bar abs; default: the station's "
                                    "(the hardware configuration's p_atm_bar)")


class CalibrationResult(Documented):
    """What a calibration changed.

    Attributes:
        what: Which calibration.
        date: Its date (ISO), now in the configuration.
        samples: Samples averaged.
        before: The scaling values before [bar abs, N·m or counts].
        after: The values after.
        saved_to: The configuration file written (None: not saved, no file given).
    """

    what: str
    date: str
    samples: int
    before: dict[str, float]
    after: dict[str, float]
    saved_to: str | None


class RunRequest(Documented):
    """Start a scenario run (thesis 4.4–4.7).

    Attributes:
        scenario: SC-1 free motion, SC-2 with PDRA/TDRA, SC-3 torque disturbance, SC-4 pressure disturbance.
        controller: PRV controller (default: the Cascade Fuzzy Adaptive PID, the thesis's own; Eq 3.26's
            Cascade PID chatters on the simulated rig's regulators, docs/controllers.md).
        target_nm: Signed target torque [N·m]: positive = pronation (CCW), negative = supination.
        pw_bar: Working pressure [bar abs].
        person: Pseudonymous id of the person exercising (no names).
        notes: Free text for the therapist.
    """

    model_config = ConfigDict(extra="forbid")

    scenario: Literal["SC-1", "SC-2", "SC-3", "SC-4"] = "SC-1"
    controller: Literal["default", "pid", "fuzzy"] = "fuzzy"
    target_nm: float = Field(1.2, ge=-3.0, le=3.0, description="N·m, signed")
    pw_bar: float = Field(3.0, ge=1.5, le=6.0, description="bar abs")
    person: PersonId = ""
    notes: Notes = ""
    session_id: SessionRef = None
    workout_id: int | None = Field(None, ge=1, le=2**62, description="stored workout parameter set")
    gains_id: int | None = Field(None, ge=1, le=2**62, description="stored Cascade PID gain set")
    fuzzy_id: int | None = Field(None, ge=1, le=2**62, description="stored fuzzy MF set")


class ConnectRequest(Documented):
    """Which rig to connect.

    Attributes:
        rig: ``rotary`` (the CWRR forearm axis), ``linear`` (the linear test
            cylinder of thesis 3.2.4) or ``cpr`` (the constant-volume set-up of
            Figure 3.10 for the directional valve's identification).
        cylinder: Cylinder on the simulated linear / CPR rig (the cylinders of thesis Tables 4.5–4.6).
    """

    model_config = ConfigDict(extra="forbid")

    rig: Literal["rotary", "linear", "cpr"] = "rotary"
    cylinder: Literal["C1", "C2", "C3"] = "C3"


class LinearIdentRequest(Documented):
    """Linear friction identification inputs (thesis Figure 3.27, Appendix 2 rules).

    Attributes:
        stroke_mm: Stroke [mm]; omitted, the connected cylinder's catalogue stroke.
        piston_diameter_mm: Piston diameter [mm]; omitted, the connected cylinder's.
        rod_diameter_mm: Rod diameter [mm]; omitted, the connected cylinder's.
        ns: Static experiments per direction (≥ 30).
        nd: Dynamic experiments per direction (≥ 30).
        seed: Seed of the random test positions and levels.
    """

    model_config = ConfigDict(extra="forbid")

    stroke_mm: float | None = None
    piston_diameter_mm: float | None = None
    rod_diameter_mm: float | None = None
    ns: int = 30
    nd: int = 30
    seed: int = Field(0, ge=0, le=2**31 - 1)


class SessionIn(Documented):
    """Open a therapy session.

    Attributes:
        person: Pseudonymous id of the person (letters, digits, ``_.-``; no names).
        notes: Therapist's notes.
    """

    model_config = ConfigDict(extra="forbid")

    person: Annotated[str, Field(min_length=1, max_length=64, json_schema_extra={"pattern": r"^[A-Za-z0-9_.-]+$"}),
                      AfterValidator(check_person)]
    notes: Notes = ""


class NotesIn(Documented):
    """New notes for a session or a run (they replace the old ones).

    Attributes:
        notes: Therapist's notes.
    """

    model_config = ConfigDict(extra="forbid")

    notes: Notes


class Session(Documented):
    """A therapy session.

    Attributes:
        id: Id.
        person: Pseudonymous person id.
        notes: Notes.
        created: When [Unix s].
        notes_edited: When the notes were last changed after the session opened [Unix s]; None: never.
        notes_at_open: The notes it opened with, once they have been changed; None: never changed.
        runs: Ids of the runs recorded in it, newest first.
    """

    id: int
    person: str
    notes: str
    created: float
    notes_edited: float | None = None
    notes_at_open: str | None = None
    runs: list[int] = []


class RotaryIdentRequest(Documented):
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


class ProtocolRunRequest(Documented):
    """The diagnosis protocol on the connected rotary rig (issue 6 §6), through the engine like a workout.

    Attributes:
        repetitions: Runs of every experiment (the last one of each is held out).
        scale: Duration factor (1 ≈ 83 s of logs per repetition; each experiment
            also waits 1.5 s while the chambers reach its start pressure). Under 1 the
            logs pin the model's nominal values down less, and the recalibration may take
            values far from nominal (the report flags them); 1 or more for a diagnosis to act on.
        kinds: Experiments to run (default all seven, in the protocol's order).
        person: Pseudonymous id of the person at the handle (no names); three of the
            experiments have them move it.
        notes: Free text.
        session_id: The therapy session the protocol belongs to (the person is taken from it).
    """

    model_config = ConfigDict(extra="forbid")

    repetitions: int = Field(2, ge=1, le=3)
    scale: float = Field(1.0, ge=0.2, le=10.0)
    kinds: list[Literal["prv_steps", "dcv_steps", "hold_closed", "fill_shut", "friction_sweep", "sine_sweep",
                        "isotonic"]] | None = Field(None, min_length=1, max_length=7)
    person: PersonId = ""
    notes: Notes = ""
    session_id: SessionRef = None


Triple = tuple[Literal["filling", "exhausting"], float, float]


class DCVIdentRequest(Documented):
    """Directional-valve identification inputs (thesis 3.2.3 and 4.1; SPEC §3 grid by default).

    Attributes:
        ps_bar: Supply pressures to map [bar abs]; must include ``fit_ps_bar``.
        u_fill: Filling signals [V] (empty: map exhausting only).
        u_exh: Exhausting signals [V] (empty: map filling only).
        band_fill: Unstable band fitted for filling [V].
        band_exh: Unstable band fitted for exhausting [V].
        fit_ps_bar: Supply pressure the flow model is fitted at [bar abs] (Table 4.1: 5).
        chamber_volume_cm3: Chamber a's volume, cylinder extended, dead volume
            included [cm³]; default the connected simulated cylinder's (required
            on a real rig).
        temperature_k: Air temperature [K].
        polytropic_n: n of Eq 4.1 (1 isothermal … 1.4 adiabatic).
        validation: (mode, u [V], P_s [bar abs]) runs after the map, each
            ``validation_s`` long: predicted vs measured P_a for all four
            flow models (Figures 4.6–4.11).
        validation_s: Length of each validation run [s] (thesis: 15).
    """

    model_config = ConfigDict(extra="forbid")

    ps_bar: list[float] = Field(default_factory=lambda: [2.0, 3.0, 4.0, 5.0, 6.0, 7.0], min_length=1,
                                max_length=20)
    u_fill: list[float] = Field(default_factory=lambda: [round(0.1 * i, 1) for i in range(60)], max_length=200)
    u_exh: list[float] = Field(default_factory=lambda: [round(4.0 + 0.1 * i, 1) for i in range(61)],
                               max_length=200)
    band_fill: tuple[float, float] = (4.5, 5.7)
    band_exh: tuple[float, float] = (4.5, 5.9)
    fit_ps_bar: float = 5.0
    chamber_volume_cm3: float | None = None
    temperature_k: float = 293.15
    polytropic_n: float = 1.0
    validation: list[Triple] = Field(default_factory=list, max_length=100)
    validation_s: float = 15.0


class PIDTuneRequest(Documented):
    """Frequency-response autotune of one PRV pressure loop (thesis 3.6.2), on the rotary rig.

    Attributes:
        side: ``a`` (PRV-a) or ``b`` (PRV-b).
        bandwidth_rad_s: Target crossover [rad/s] (thesis: 2).
        phase_margin_deg: Target phase margin [deg] (thesis: 60).
        pw_bar: Operating pressure [bar abs].
        amplitude_bar: Amplitude of each injected sine [bar].
        periods: Whole periods of the slowest sine analysed (the experiment
            lasts periods + 1 of them: 94 s at the thesis's 2 rad/s and 2 periods).
        n_filter: Derivative filter coefficient N [1/s] (thesis: 100).
        initial: Gains (K_p [-], K_i [1/s], K_d [s]) the loop runs with during the experiment.
    """

    model_config = ConfigDict(extra="forbid")

    side: Literal["a", "b"] = "a"
    bandwidth_rad_s: float = 2.0
    phase_margin_deg: float = 60.0
    pw_bar: float = 3.0
    amplitude_bar: float = 0.05
    periods: int = Field(2, ge=1, le=20)
    n_filter: float = Field(100.0, gt=0.0, le=1e4)
    initial: tuple[float, float, float] = (0.25, 1.5, 0.0005)


class Started(Documented):
    """Work accepted.

    Attributes:
        run_id: Stored id of the run.
        status: The engine state after the action.
    """

    run_id: int | None
    status: EngineStatus


class LiveData(Documented):
    """Recent samples from the live buffer.

    Attributes:
        columns: Column names (s, N·m, N·m, bar, bar, bar, bar, rad/s, rad).
        rows: Samples, oldest first.
        t_last: Time of the newest sample [s] (pass it back as ``since``).
    """

    columns: list[str]
    rows: list[list[float | None]]
    t_last: float


class RunInfo(Documented):
    """A stored run.

    Attributes:
        id: Run id.
        kind: ``workout`` or an identification kind.
        status: ``running``, ``complete``, ``stopped``, ``interrupted``, ``fault``, ``finished``, ``cancelled``.
        started: Start [Unix s].
        ended: End [Unix s].
        spec: What was asked for.
        metrics: The six metrics (workouts); a metric the run could not give is null.
        result: Evaluation window or identified parameters.
        person: Pseudonymous person id.
        notes: Notes.
        notes_edited: When the notes were last changed after the start [Unix s]; None: never.
        session_id: The therapy session it belongs to.
        station: The station that ran it: its lasting id, then its host and
            data folder ("" for runs stored before stations were named).
        has_series: Whether a time-series log exists.
        progress: What a running gap diagnosis is doing now, in words (e.g.
            "candidate 4 of 9 fitted (heat_transfer)"); None for any other run,
            and once it has ended.
    """

    id: int
    kind: str
    status: str
    started: float
    ended: float | None
    spec: dict[str, Any]
    metrics: dict[str, float | None] | None
    result: dict[str, Any] | None
    person: str
    notes: str
    notes_edited: float | None = None
    session_id: int | None = None
    station: str = ""
    has_series: bool
    progress: str | None = None

    @classmethod
    def from_row(cls, r: dict[str, Any], progress: str | None = None) -> RunInfo:
        """The run as the store holds it (``Store.run``), with whether its log is on disk and, while it runs,
        what its job says it is doing."""
        return cls(**{k: r[k] for k in ("id", "kind", "status", "started", "ended", "metrics", "result", "person",
                                        "notes", "session_id")}, spec=r["spec"] or {},
                   notes_edited=r.get("notes_edited"), station=r.get("station") or "",
                   has_series=bool(r["log_csv"]) and Path(r["log_csv"]).is_file(), progress=progress)


class ComparedRun(Documented):
    """One exercise in a comparison.

    Attributes:
        controller: ``default``, ``pid`` or ``fuzzy``.
        run_id: Run id.
        status: How it ended (the others compared are ``complete``).
        started: Start [Unix s].
        metrics: The six metrics: MAE [N·m], IAE [N·m·s], ITAE [N·m·s²], e_var [N²·m²], RMSE [N·m],
            Max AE [N·m].
    """

    controller: str
    run_id: int
    status: str
    started: float
    metrics: dict[str, float]


class Comparison(Documented):
    """An exercise beside the latest complete run of each other controller, like with like (thesis Fig 4.26).

    Attributes:
        run_id: The exercise compared.
        scenario: Its scenario, which every run compared shares.
        target_nm: Its target torque [N·m], which every run compared shares.
        person: Its person, whom every run compared shares ("" for none named).
        runs: The exercise first, then one run per other controller that has a complete one, the
            latest (among the person's newest 200 exercises).
        scale: Each metric's largest value among ``runs``: a radar chart's rim, as the thesis scales
            its axes (the worst controller touches it).
        best: Each metric's lowest value's controller (every metric is an error: lower is better).
        missing: Controllers with no complete run to compare.
    """

    run_id: int
    scenario: str | None
    target_nm: float | None
    person: str
    runs: list[ComparedRun]
    scale: dict[str, float]
    best: dict[str, str]
    missing: list[str]


class Series(Documented):
    """A run's time series.

    Attributes:
        columns: Column names (the run-log format: s, V, bar, rad, rad/s, N·m).
        rows: Samples.
        every: Decimation factor applied.
        rows_total: Samples stored (before decimation).
        meta: The log's JSON header as stored beside it (``rig``, ``sample_rate_hz``,
            ``p_atm_bar`` [bar abs], ``working_pressure_bar`` [bar abs], ``experiment``,
            ``human``, …); empty if it is missing or unreadable; a value no JSON answer
            may carry (NaN) reads as null.
    """

    columns: list[str]
    rows: list[list[float]]
    every: int
    rows_total: int
    meta: dict[str, Any] = {}


class ParamSetIn(Documented):
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


class ParamSet(Documented):
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


class FormCheckIn(Documented):
    """Values typed so far into a thesis GUI form, in entry order.

    Attributes:
        values: Field → value, in the order typed.
        cylinder: The linear rig's cylinder, whose catalogue geometry the linear form suggests
            (``C1``, ``C2`` or ``C3``; the rotary form ignores it).
    """

    model_config = ConfigDict(extra="forbid")

    values: dict[str, float]
    cylinder: Literal["C1", "C2", "C3"] = "C3"


class FieldState(Documented):
    """One field of a guided form.

    Attributes:
        name: Field key.
        label: Label with unit.
        valid: Turned green.
        editable: Open for input now.
        suggested: What the field suggests before anything is typed, in its unit: the forearm
            robot's geometry, the chosen cylinder's catalogue geometry, the GUIs' 30 tests.
    """

    name: str
    label: str
    valid: bool
    editable: bool
    suggested: float


class FormState(Documented):
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


class ViserInfo(Documented):
    """Where the viser live plots are.

    Attributes:
        url: Address of the viser live plots (None when they are off). On a station with
            tokens it carries a single-use ticket that signs the browser in for viewing.
        expires_s: How long the ticket in ``url`` stays valid [s] (None: the link needs none).
    """

    url: str | None
    expires_s: float | None = None


class AuthInfo(Documented):
    """Whether this station asks for a token, and what the presented one allows.

    Attributes:
        required: Whether API calls need ``Authorization: Bearer <token>``.
        role: ``therapist`` or ``admin`` for a valid token (``admin`` for the
            local user of a station without tokens); None otherwise.
    """

    required: bool
    role: Literal["therapist", "admin"] | None
