"""The gap diagnosis's report as a typed API answer (``GET /api/runs/{id}/report``).

The engine writes the report as a plain dict (``app.engine.diagnosis.core.diagnose``),
stored as the diagnosis run's ``result``. These models give it a schema in
``/openapi.json``, so that a script or a generated client knows each field's
meaning. Every model keeps fields it does not declare (``extra="allow"``): a
report written by a newer engine, or a family's own additions, pass through
whole. A number a fit could not give is ``null`` (the store keeps strict
JSON), hence the ``| None`` on the fitted values.
"""

from __future__ import annotations

from typing import Any

from pydantic import ConfigDict, Field

from app.api.models import Documented

Num = float | None
"""A fitted or scored value; ``null`` where the fit could not give one (a held parameter's SD)."""


class _Open(Documented):
    """A part of the report: declared fields typed, any other kept as written."""

    model_config = ConfigDict(extra="allow")  # merged with Documented's: the docstring still describes the fields


class Experiments(_Open):
    """Which logs were fitted and which scored, and what the tool noticed about them.

    Attributes:
        calibration: Logs the fits saw.
        held_out: Logs withheld from every fit, on which every score is taken.
        split: How the held-out logs were chosen.
        excites: Per log, the regimes it excites (what the split weighs).
        unshown: Per candidate the held-out logs cannot show, what it needs and which experiment would show it.
        irregular_sampling: Logs with skipped or uneven samples (put on a uniform grid; made-up samples unscored).
        flat_channels: Logs with a channel that reads one value throughout, and that value.
        unscored_channels: Channels no held-out sample could score (left out of every fit and of E).
        unmeasured_channels: Channels a rig may lack that read one value in every log, with that value: taken
            as not measured, left out of every fit and of E.
        torque_sign: Whether the torque was taken with its sign reversed (``reversed``), the share of samples
            whose sign agrees with the one the chamber pressures give it (``agreement``) and how many such
            samples there were (``samples``).
        dcv_wiring: Per DCV (``a``, ``b``), whether its command was taken mirrored about 5 V (``mirrored``), the
            share of settled, fully open samples whose chamber stands where the format's wiring puts it
            (``agreement``) and how many such samples there were (``samples``; under 100 decide nothing).
        pressure_order: Whether p_a and p_b were taken swapped (``swapped``), the share of settled fills
            whose chamber pressures stand in the order of their regulators' commands (``agreement``) and how
            many such samples there were (``samples``; under 100 decide nothing).
        angle_sign: Whether the angle and speed were taken with their signs reversed (``reversed``), the net
            share of the power the torques on the vane lose to its motion (``dissipation``, −1 … 1; friction
            makes it near 1) and over how many samples in motion (``samples``).
        atmosphere: What the chamber sensors read where a DCV vented their chamber, against the logs'
            ``p_atm_bar``: per chamber (``p_a``, ``p_b``) the median offset [bar] and the samples (under 50
            say nothing), the logs' ``p_atm_bar`` and ``note``, the verdict's sentence when a chamber reads
            more than 0.02 bar off ("" otherwise).
    """

    calibration: list[str]
    held_out: list[str]
    split: str | None = None
    excites: dict[str, list[str]] = Field(default_factory=dict)
    unshown: dict[str, Any] = Field(default_factory=dict)
    irregular_sampling: dict[str, Any] = Field(default_factory=dict)
    flat_channels: dict[str, dict[str, Num]] = Field(default_factory=dict)
    unscored_channels: list[str] = Field(default_factory=list)
    unmeasured_channels: dict[str, Num] = Field(default_factory=dict)
    torque_sign: dict[str, Any] | None = None
    dcv_wiring: dict[str, Any] | None = None
    pressure_order: dict[str, Any] | None = None
    angle_sign: dict[str, Any] | None = None
    atmosphere: dict[str, Any] | None = None


class Gap(_Open):
    """The baseline's held-out error above the noise floor.

    Attributes:
        e: The baseline's channel-mean held-out NRMSE.
        e_floor: The same for the sensors' noise.
        e_minus_floor: Their difference.
        ci90: Bootstrap 90 % interval of the difference over the held-out units.
        above_noise: Whether the interval lies above 0.
    """

    e: Num
    e_floor: Num
    e_minus_floor: Num = None
    ci90: list[Num]
    above_noise: bool


class RecalibratedParam(_Open):
    """One recalibrated baseline parameter.

    Attributes:
        name: Parameter name.
        meaning: What it scales or sets.
        value: Fitted value.
        nominal: Nominal value.
        range: The recalibration's range [low, high].
        unit: Unit (``-`` for a scale factor).
        sd: Standard deviation from the fit's Jacobian.
        at_bound: On an end of its range, away from nominal.
        far: Moved past what a tolerance explains (2 × either way, or an end of its range).
        in_model: Its value in the fit of the verdict's last effect.
        in_model_far: That value is past a tolerance too (by the rule of ``far``).
    """

    name: str
    meaning: str | None = None
    value: Num
    nominal: Num
    range: list[Num]
    unit: str | None = None
    sd: Num = None
    at_bound: bool = False
    far: bool = False
    in_model: Num = None
    in_model_far: bool = False


class Recalibration(_Open):
    """What the recalibration made of each nominal value.

    Attributes:
        params: Every recalibrated parameter.
        far: Those moved past a tolerance.
        unaccounted: Those of ``far`` that the verdict's effect does not bring back.
        note: In words: what the flagged values may stand in for, and how to test it (``null`` when none).
    """

    params: list[RecalibratedParam]
    far: list[str] = Field(default_factory=list)
    unaccounted: list[str] = Field(default_factory=list)
    note: str | None = None


class Baseline(_Open):
    """The recalibrated baseline (the thesis's model) every candidate is judged against.

    Attributes:
        nrmse: Held-out NRMSE per channel.
        e: Channel-mean held-out NRMSE.
        identifiability: Fitted values, SDs, parameters on a bound, condition number, correlated pairs.
        gap: Its error above the noise floor.
        recalibration: What it made of each nominal value.
        form: The model's form the recalibration found beside the nominal one, and whether it was kept.
        bounds: The recalibration's range per parameter [low, high].
    """

    nrmse: dict[str, Num]
    e: Num
    identifiability: dict[str, Any] = Field(default_factory=dict)
    gap: Gap | None = None
    recalibration: Recalibration | None = None
    form: dict[str, Any] | None = None
    bounds: dict[str, list[Num]] = Field(default_factory=dict)


class NoiseFloor(_Open):
    """What the sensors' noise alone leaves a right model.

    Attributes:
        nrmse: Per channel.
        e: Channel mean (E_floor).
    """

    nrmse: dict[str, Num]
    e: Num


class Where(_Open):
    """Where the baseline's held-out error lies, for one channel.

    Attributes:
        channel: Channel name.
        rms: RMS error [the channel's unit].
        bias: Mean error.
        noise: The sensor's noise SD.
        floor: What the noise leaves a right model.
        autocorr_lag1_10: Residual autocorrelation at lags 1–10.
        ljung_box_p: Ljung–Box whiteness p-value.
        regimes: RMS (and samples) per regime: standstill, motion onset/reversal, speed bands, transients, levels.
        input_xcorr: Per input (a command, the speed), the residual's largest cross-correlation with it over
            lags 0–49 scored samples: ``max_abs``, ``lag_samples``, ``lag_s`` [s], its standard error ``se``
            for two autocorrelated series (Bartlett), ``z``, the standard errors it had to pass, and
            ``significant`` (past them: a 5 % test over the 50 lags and every input the channel is tested
            against, 3.72 for the rotary rig's five). An error that follows a command a fixed time later
            points at what that command drives.
        experiments: Per held-out log, its RMS and its share of the channel's squared error.
    """

    channel: str
    rms: Num
    bias: Num = None
    noise: Num = None
    floor: Num = None
    autocorr_lag1_10: list[Num] = Field(default_factory=list)
    ljung_box_p: Num = None
    regimes: dict[str, Any] = Field(default_factory=dict)
    input_xcorr: dict[str, Any] = Field(default_factory=dict)
    experiments: dict[str, Any] = Field(default_factory=dict)


class CandidateScore(_Open):
    """One candidate effect fitted beside the baseline and scored on the held-out logs.

    Attributes:
        effect: Effect name.
        gap_closure: GC = (E_base − E_with)/(E_base − E_floor).
        gap_closure_ci90: Bootstrap 90 % interval of GC.
        rebased_gap_closure: GC of its fit with the effect taken out (the baseline values it refitted);
            ``null`` when it refitted none.
        delta_bic: ΔBIC on the calibration fit.
        significant: Passed every significance test.
        relevant: Lowered some channel's held-out RMS by what matters on the rig.
        switched_off: Its fit left it at its "off" value.
        not_significant_because: The tests it failed, with their numbers.
        params: Its fitted parameters.
        params_sd: Their standard deviations.
        params_at_bound: Its parameters on a bound of their range.
        baseline_params: The baseline values fitted beside it.
        nrmse: Held-out NRMSE per channel with it.
        rms_improvement: Held-out RMS gain per channel [the channel's unit].
        dropped_for: The alternatives that took its place in the verdict, where any did.
    """

    effect: str
    gap_closure: Num
    gap_closure_ci90: list[Num]
    rebased_gap_closure: Num = None
    delta_bic: Num
    significant: bool
    relevant: bool = False
    switched_off: bool = False
    not_significant_because: list[str] = Field(default_factory=list)
    params: dict[str, Num] = Field(default_factory=dict)
    params_sd: dict[str, Num] = Field(default_factory=dict)
    params_at_bound: list[str] = Field(default_factory=list)
    baseline_params: dict[str, Num] = Field(default_factory=dict)
    nrmse: dict[str, Num] = Field(default_factory=dict)
    rms_improvement: dict[str, Num] = Field(default_factory=dict)
    dropped_for: list[str] | None = None


class Alternative(CandidateScore):
    """A baseline of another form weighed against an effect in the verdict.

    Attributes:
        explanation: The alternative's name (e.g. ``friction_per_direction``).
        instead_of: The effect it is weighed against.
        description: What it is, in words.
        separate_by: The step that would tell the two apart.
        effect_gap_closure: The effect's own GC.
        gc_difference_ci90: Paired bootstrap 90 % interval of GC(effect) − GC(alternative).
        confusable: The logs cannot tell the two apart.
        better: The alternative closes clearly more.
        dropped: The effect adds nothing significant beside it and left the verdict.
        also: Both are significant together.
    """

    explanation: str
    instead_of: str
    description: str | None = None
    separate_by: str | None = None
    effect_gap_closure: Num = None
    gc_difference_ci90: list[Num] = Field(default_factory=list)
    confusable: bool = False
    better: bool = False
    dropped: bool = False
    also: bool = False


class Separation(_Open):
    """Two effects the logs cannot tell apart, and the experiments that would.

    Attributes:
        effects: The two effects.
        experiments: Protocol experiments that show the first and not the second.
    """

    effects: list[str]
    experiments: list[str]


class Verdict(_Open):
    """What the diagnosis concludes.

    Attributes:
        effects: The selected effects, in the order they were added; empty when none is significant.
        confusable_with: Effects the held-out logs cannot tell from the first.
        separating_experiments: For each, the experiments that would.
        alternatives: Baselines of another form the logs favour or cannot rule out.
        baseline_beaten: Set when a candidate's fit showed the baseline could fit better.
        untested: Candidates no held-out log could show (not ruled out).
        summary: The verdict in one line.
    """

    effects: list[str]
    confusable_with: list[str] = Field(default_factory=list)
    separating_experiments: list[Separation] = Field(default_factory=list)
    alternatives: list[str] = Field(default_factory=list)
    baseline_beaten: dict[str, Any] | None = None
    untested: list[str] = Field(default_factory=list)
    summary: str


class HowFar(_Open):
    """The held-out gap before and after the verdict's model.

    Attributes:
        before: Baseline NRMSE per channel.
        after: NRMSE per channel with the verdict's model.
        model: The effects (and alternatives) of that model.
        e_before: Channel-mean before.
        e_after: Channel-mean after.
        e_floor: The noise floor's.
        unexplained_share: Share of the gap above the floor that remains.
    """

    before: dict[str, Num]
    after: dict[str, Num]
    model: list[str] = Field(default_factory=list)
    e_before: Num
    e_after: Num
    e_floor: Num
    unexplained_share: Num = None


class DiagnosisReport(_Open):
    """A gap diagnosis's report: where the gap lies, which effect causes it, how far it shrinks.

    Attributes:
        run_id: The diagnosis run it belongs to.
        family: The model family diagnosed (``rotary`` for station logs).
        adapter: How the logs were read (``station``).
        experiments: The logs and how they were split.
        baseline: The recalibrated baseline.
        noise_floor: What the sensors' noise leaves.
        where: Per channel, where the baseline's error lies.
        ranking: Every candidate alone against the baseline, best first.
        combination: The greedy rounds, each against the model with the effects before it.
        alternatives: Baselines of another form weighed against the verdict's effects.
        verdict: The conclusion.
        how_far: The gap before and after.
    """

    run_id: int
    family: str
    adapter: str | None = None
    experiments: Experiments
    baseline: Baseline
    noise_floor: NoiseFloor
    where: list[Where]
    ranking: list[CandidateScore]
    combination: list[CandidateScore] = Field(default_factory=list)
    alternatives: list[Alternative] = Field(default_factory=list)
    verdict: Verdict
    how_far: HowFar


class ChannelTrace(Documented):
    """One channel of one held-out log over time: block means, null where a block scores no sample.

    Attributes:
        measured: What the rig's sensor read (the channel's unit: bar abs, N·m, N).
        baseline: What the recalibrated baseline predicts.
        after: What the model the verdict ends with predicts (absent when no effect is significant).
        confusable: Per effect the verdict cannot tell from its own, what that effect alone predicts
            (where in time the two differ, if anywhere).
    """

    measured: list[Num]
    baseline: list[Num]
    after: list[Num] | None = None
    confusable: dict[str, list[Num]] = Field(default_factory=dict)


class LogTrace(Documented):
    """A held-out log's channels over time.

    Attributes:
        log: The log's name.
        t: Each block's mean time from the log's start [s].
        channels: Channel → its measured and predicted series.
    """

    log: str
    t: list[Num]
    channels: dict[str, ChannelTrace]


class DiagnosisTraces(Documented):
    """Where in time the gap lies: each held-out log as measured, beside the baseline's and the verdict model's
    predictions (at most 300 block means per series, four significant digits).

    Attributes:
        run_id: The diagnosis run they belong to.
        model: The effects the ``after`` series adds to the baseline (empty: none was significant).
        confusable: The effects whose own predictions are under each channel's ``confusable``.
        logs: One entry per held-out log.
    """

    run_id: int
    model: list[str]
    confusable: list[str] = Field(default_factory=list)
    logs: list[LogTrace]
