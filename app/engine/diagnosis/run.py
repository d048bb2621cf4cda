"""Diagnosis of a directory of logs: choose the reader and the family, split, run the core."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from app.engine.diagnosis import rotary
from app.engine.diagnosis.core import checked_candidates, diagnose
from app.engine.diagnosis.families import ChamberFamily, DriveFamily, split_time
from app.engine.diagnosis.logs import (
    Experiment,
    LogFormatError,
    flat_channels,
    read_chamber_leak,
    read_emps,
    read_logdir,
    speed_of,
)
from app.engine.diagnosis.protocol import effect_experiments
from app.engine.diagnosis.rotary import RotaryFamily

PROTOCOL: dict[str, list[str]] = effect_experiments() | {
    # outside the rotary protocol: the refdata adapters' own experiments
    "external_leakage": [*effect_experiments()["external_leakage"], "closed-chamber decay"],
}
"""Diagnosis protocol: effect → the experiments that make it visible (the table of
:data:`~app.engine.diagnosis.protocol.VISIBLE`; used to name the experiment that
separates two confusable effects)."""


def _detect(d: Path) -> str:
    if any(d.glob("*.mat")):
        return "emps"
    csvs = sorted(d.glob("*.csv"))
    if csvs and not any(d.glob("*.json")):
        first = csvs[0].read_text(encoding="utf-8", errors="replace").split("\n", 1)[0]
        if first.count(";") == 2:
            return "chamber_leak"
    return "station"


def _split(exps: list[Experiment], held_out: list[str] | None) -> tuple[list[Experiment], list[Experiment]]:
    if held_out:
        unknown = [h for h in held_out if h not in {e.name for e in exps}]
        if unknown:
            raise LogFormatError(f"--held-out: no experiment named {', '.join(unknown)}; have "
                                 f"{', '.join(e.name for e in exps)}")
        held = [e for e in exps if e.name in held_out]
        calib = [e for e in exps if e.name not in held_out]
        if not calib:
            raise LogFormatError("--held-out: every experiment is held out; none is left to fit on")
        return calib, held
    if len(exps) == 1:
        a, b = split_time(exps[0])
        return [a], [b]
    return split_last_third(exps)


def split_last_third(exps: list[Experiment]) -> tuple[list[Experiment], list[Experiment]]:
    """Fit on the first two thirds of several experiments, hold out the rest (at least one)."""
    n_held = max(1, math.ceil(len(exps) / 3))
    return exps[:-n_held], exps[-n_held:]


def diagnose_dir(logdir: str | Path, adapter: str = "auto", held_out: list[str] | None = None,
                 stop: threading.Event | None = None,
                 bounds: dict[str, tuple[float, float]] | None = None, traces: bool = False,
                 candidates: Sequence[str] | None = None,
                 progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The report for the logs in ``logdir``.

    Args:
        logdir: Directory of logs.
        adapter: ``station`` (the fixed NAME.csv + NAME.json format),
            ``chamber_leak`` or ``emps`` (refdata adapters), or ``auto``.
        held_out: Experiment names withheld from fitting.
        stop: Once set, the diagnosis ends with
            :class:`~app.engine.diagnosis.core.Cancelled`.
        bounds: The recalibration's range per baseline parameter of the
            rotary rig (:class:`~app.engine.diagnosis.rotary.RotaryFamily`),
            for station logs only; the report lists every range used under
            ``baseline.bounds``.
        traces: Add each held-out log's measured and predicted channels over
            time (``traces``, :func:`~app.engine.diagnosis.core.traces`).
        candidates: The effects to try (default: all the family's); the
            baseline's recalibration is the same either way.
        progress: Told what the diagnosis is doing (see
            :func:`~app.engine.diagnosis.core.diagnose`); a closed chamber's
            messages start with its record's name.

    Raises:
        ValueError: ``bounds`` for an adapter's logs, or a bound the family
            refuses (checked before any log is read).

    Returns:
        The report (one per chamber under ``"reports"`` for ``chamber_leak``,
        each chamber being a different physical object).
    """
    d = Path(logdir)
    if not d.is_dir():
        raise LogFormatError(f"{d}: not a directory")
    kind = _detect(d) if adapter == "auto" else adapter
    if bounds and kind != "station":
        raise ValueError(f"bounds apply to the rotary rig's station logs; {d} holds {kind} logs, whose family has "
                         "its own fixed ranges")
    # refused before a log is read, by the rule core.diagnose applies
    family_class: type[RotaryFamily | DriveFamily | ChamberFamily] = RotaryFamily
    if kind in ("emps", "chamber_leak"):
        family_class = DriveFamily if kind == "emps" else ChamberFamily
    checked_candidates(family_class.name, family_class.candidates, candidates)
    if kind == "emps":
        mats = sorted(d.glob("*.mat"))
        if not mats:
            raise LogFormatError(f"{d}: no .mat records for the emps adapter (e.g. DATA_EMPS.mat and "
                                 "DATA_EMPS_PULSES.mat)")
        exps = [read_emps(p) for p in mats]
        calib, held = _split(exps, held_out)
        rep = diagnose(DriveFamily(), calib, held, candidates, protocol=PROTOCOL, stop=stop, with_traces=traces,
                       progress=progress)
        return rep | {"adapter": "emps"}
    if kind == "chamber_leak":
        records = sorted(d.glob("*.csv"))
        if not records:
            raise LogFormatError(f"{d}: no records for the chamber_leak adapter (NAME.csv, ';'-separated: t [ms], "
                                 "p [V], p [bar])")
        reports = {}
        for p in records:
            a, b = split_time(read_chamber_leak(p))
            fam = ChamberFamily()
            said = None if progress is None else (lambda msg, on=progress, n=p.stem: on(f"{n}: {msg}"))
            rep = diagnose(fam, [a], [b], candidates, protocol=PROTOCOL, stop=stop, with_traces=traces, progress=said)
            reports[p.stem] = rep | {"leak_on_the_rig": fam.leak_on_the_rig(rep)}
        return {"adapter": "chamber_leak", "reports": reports}
    family = RotaryFamily(bounds=bounds)  # refuses a bad bound before the logs are read
    exps = read_logdir(d)  # refuses malformed logs with the problem named
    linear = [e.name for e in exps if e.meta["rig"] != "rotary"]
    if linear:
        raise LogFormatError(f"{d}: {', '.join(linear)} come from the linear rig; the replay family covers "
                             "the rotary rig (diagnose linear-rig logs in a directory of their own once it does)")
    # the sensors' conventions (which chamber is which, the torque's and the angle's signs), read off
    # physics the rig cannot escape; a clear reversal is undone before anything is fitted, and said
    conv = read_conventions(family, exps)
    # a channel the rig may lack that reads one value in every log measures nothing: fitted as a
    # constant it bends the baseline (a torque read as 0 throughout hid a vane leak that closes 0.97
    # of the gap without it), so it leaves the diagnosis and the report says so
    flats = [flat_channels(e) for e in exps]
    unmeasured = {c: flats[0][c] for c in family.optional_channels if all(c in f for f in flats)}
    if unmeasured:
        family.channels = tuple(c for c in family.channels if c not in unmeasured)
    atmosphere = vented_atmosphere(exps)  # read in the format's wiring, which read_conventions restored
    calib, held, why = _split_station(exps, held_out)
    report = diagnose(family, calib, held, candidates, protocol=PROTOCOL, stop=stop, with_traces=traces,
                      progress=progress)
    report["experiments"]["unmeasured_channels"] = unmeasured
    report["experiments"]["atmosphere"] = atmosphere
    report["experiments"] |= conv.report()
    report["baseline"]["bounds"] = {p.name: [p.lo, p.hi] for p in family.baseline()}
    report["experiments"]["split"] = why
    # what each log gave the fit to learn from (the regimes the split weighs)
    # (a single log is split in time: its two parts are logs of their own here)
    sig = {id(e): excites(e) for e in (*exps, *calib, *held)}
    report["experiments"]["excites"] = {e.name: sorted(sig[id(e)]) for e in exps}
    ran = {str(e.meta["experiment"]): (float(e.meta["scale"]) if isinstance(e.meta.get("scale"), int | float)
                                        else None) for e in exps}
    hidden = unshown(set().union(*(sig[id(e)] for e in calib)), set().union(*(sig[id(e)] for e in held)), ran)
    for c, value in unmeasured.items():
        for effect in family.optional_channels[c]:
            hidden[effect] = {"needs": [f"a measured {c}"], "fitted": False, "experiments": [],
                              "why": f"no log measures the {c} (it reads {value:g} in every log), so these logs "
                                     "cannot rule it out"}
    report["experiments"]["unshown"] = hidden
    untested = []
    for c in report["ranking"]:
        u = hidden.get(c["effect"])
        if u is not None and not c["significant"]:
            # a candidate the logs showed significant is tested, whatever the verdict made of it
            c["not_significant_because"] = [*c["not_significant_because"], u["why"]]
            untested.append(c["effect"])
    report["verdict"]["untested"] = [e for e in hidden if e in untested]
    if unmeasured:
        report["verdict"]["summary"] += (f"; {', '.join(unmeasured)} read one value in every log, taken as not "
                                         "measured and left out")
    report["verdict"]["summary"] += conv.summary()
    if atmosphere["note"]:
        report["verdict"]["summary"] += f"; {atmosphere['note']}"
    if report["verdict"]["untested"]:
        report["verdict"]["summary"] += (f"; not shown by the held-out logs, so not ruled out: "
                                         f"{', '.join(report['verdict']['untested'])}")
    return report | {"adapter": "station"}


def _split_station(exps: list[Experiment],
                   held_out: list[str] | None) -> tuple[list[Experiment], list[Experiment], str]:
    """Hold out whole experiments: the last repetition of every kind that was run more than once.

    A protocol run (:func:`~app.engine.diagnosis.protocol.run_protocol`) repeats
    every experiment, so each kind is both fitted and scored; logs of kinds
    run once are only fitted on. Without repetitions, :func:`split_by_coverage`.

    Returns:
        Calibration and held-out experiments, and how they were chosen (for the report).
    """
    if held_out:
        calib, held = _split(exps, held_out)
        return calib, held, "held out as asked"
    kinds: dict[str, list[Experiment]] = {}
    for e in exps:
        kinds.setdefault(str(e.meta["experiment"]), []).append(e)
    held = [v[-1] for v in kinds.values() if len(v) > 1]
    if not held:
        return split_by_coverage(exps)
    return ([e for e in exps if all(e is not h for h in held)], held,
            "the last repetition of every experiment run more than once")


TORQUE_SIGN_AGREEMENT = 0.1
"""Below this share of samples agreeing with the pressures' sign, the torque is taken reversed
(:meth:`~app.engine.diagnosis.rotary.RotaryFamily.torque_sign_agreement`); a right sign agrees in
nearly all of them, the mirror image in nearly none."""
TORQUE_SIGN_MIN_SAMPLES = 100
"""Fewer such samples than this (a protocol that never holds the chambers 1 bar apart) decide nothing."""

PRESSURE_ORDER_AGREEMENT = 0.1
"""Below this share of settled fills whose chamber pressures stand in their commands' order, p_a and p_b are
taken swapped (:meth:`~app.engine.diagnosis.rotary.RotaryFamily.pressure_order_agreement`; right: all of them)."""
ANGLE_SIGN_DISSIPATION = -0.5
"""Below this net share of power lost to the motion, the angle and speed are taken reversed
(:meth:`~app.engine.diagnosis.rotary.RotaryFamily.dissipation`; right: 0.99–1.0 on every rig tried, reversed: −1)."""
DCV_WIRING_AGREEMENT = 0.1
"""Below this share of settled, fully open samples whose chamber stands where the format's wiring puts it, that
DCV's command is taken mirrored about 5 V (:meth:`~app.engine.diagnosis.rotary.RotaryFamily.dcv_wiring_agreement`;
right: all of them, on every rig and protocol tried)."""
CONVENTION_MIN_SAMPLES = 100
"""Fewer samples than this decide nothing about a valve's wiring, the pressures' order or the angle's sign."""

VENT_HELD_S = 0.3
"""A chamber its DCV has held fully open to exhaust this long [s] stands at the atmosphere (0.001–0.003 bar
above it, the 5th–95th percentiles within −0.003 … +0.007, on the protocol's fill_shut logs)."""
VENT_MIN_SAMPLES = 50
"""Fewer vented samples of a chamber than this say nothing about its reading of the atmosphere."""
ATMOSPHERE_TOL_BAR = 0.02
"""A vented chamber reading further than this from the logs' ``p_atm_bar`` [bar] is said (3 × the venting's
own spread): the atmosphere written in the logs, or that sensor's zero, is off."""

MOVING_RAD_S = rotary.MOVING_RAD_S
"""Speed above which a sample counts as motion for :func:`excites` [rad/s]."""
DCV_OPEN_V = rotary.DCV_OPEN_V
"""A DCV command this far from 5 V [V] or further counts as fully open for :func:`excites`."""


class Conventions(NamedTuple):
    """What :func:`read_conventions` found about how the logs' sensors were written, and undid."""

    pressure_swapped: bool
    pressure_agreement: float
    pressure_samples: int
    torque_reversed: bool
    torque_agreement: float
    torque_samples: int
    angle_reversed: bool
    dissipation: float
    moving_samples: int
    dcv_mirrored: tuple[str, ...] = ()
    dcv_agreement: tuple[float, float] = (1.0, 1.0)
    dcv_samples: tuple[int, int] = (0, 0)

    def report(self) -> dict[str, dict[str, Any]]:
        """The report's ``experiments.dcv_wiring``, ``pressure_order``, ``torque_sign`` and ``angle_sign``."""
        return {"dcv_wiring": {s: {"mirrored": s in self.dcv_mirrored, "agreement": a, "samples": n}
                               for s, a, n in zip("ab", self.dcv_agreement, self.dcv_samples, strict=True)},
                "pressure_order": {"swapped": self.pressure_swapped, "agreement": self.pressure_agreement,
                                   "samples": self.pressure_samples},
                "torque_sign": {"reversed": self.torque_reversed, "agreement": self.torque_agreement,
                                "samples": self.torque_samples},
                "angle_sign": {"reversed": self.angle_reversed, "dissipation": self.dissipation,
                               "samples": self.moving_samples}}

    def summary(self) -> str:
        """Clauses for the verdict line, one per convention undone ("" when none was)."""
        out = ""
        for side, agreement, n in zip("ab", self.dcv_agreement, self.dcv_samples, strict=True):
            if side in self.dcv_mirrored:
                out += (f"; DCV-{side}'s command was read mirrored about 5 V (fully open, chamber {side} stood near "
                        "the atmosphere where the format's wiring fills it and near its regulator's pressure where "
                        f"it exhausts it, in {100 * (1 - agreement):.0f} % of {n} settled samples)")
        order_known = self.pressure_samples >= CONVENTION_MIN_SAMPLES
        if self.pressure_swapped:
            out += (f"; p_a and p_b were read swapped (with both chambers filling from regulators set ≥ 0.5 V "
                    f"apart, their pressures stood in the other order in {100 * (1 - self.pressure_agreement):.0f} "
                    f"% of {self.pressure_samples} settled samples)")
        if self.torque_reversed:
            out += (f"; the torque was read with its sign reversed (it opposed the sign the chamber pressures give "
                    f"it in {100 * (1 - self.torque_agreement):.0f} % of {self.torque_samples} samples where they "
                    "alone set it" + ("" if order_known else "; if the torque's sign is right, p_a and p_b are "
                                      "swapped") + ")")
        if self.angle_reversed:
            out += (f"; the angle and speed were read with their signs reversed (as written, the chambers' and "
                    f"the measured torque fed the vane's motion power back instead of losing it to friction: net "
                    f"{self.dissipation:.2f} of the power over {self.moving_samples} samples in motion"
                    + ("; with the torque reversed too, this is also what p_a and p_b written in each other's "
                       "columns look like, which no settled fill at two pressures in these logs can tell"
                       if self.torque_reversed and not order_known else "") + ")")
        return out


def vented_atmosphere(exps: list[Experiment]) -> dict[str, Any]:
    """What the chamber sensors read where a DCV has vented their chamber, against the logs' ``p_atm_bar``.

    The replay regulates and exhausts in each log's ``p_atm_bar`` (Eq 3.7); a
    wrong one reads as an offset of both chamber sensors, which
    ``sensor_bias`` would take. Where a DCV has held its chamber fully open
    to exhaust (:data:`DCV_OPEN_V` from 5 V, in the format's wiring) for
    :data:`VENT_HELD_S`, the chamber stands at the atmosphere.

    Returns:
        ``{"p_a": {"offset_bar", "samples"}, "p_b": {…}, "p_atm_bar", "note"}``:
        per chamber the median of (pressure − the log's ``p_atm_bar``) [bar]
        over its vented samples in every log (NaN without any), the logs'
        median ``p_atm_bar`` and a sentence for the verdict ("" when both
        chambers read the atmosphere within :data:`ATMOSPHERE_TOL_BAR`, or
        too few samples say).
    """
    out: dict[str, Any] = {}
    for ch, u in (("p_a", "u_a"), ("p_b", "u_b")):
        parts = []
        for e in exps:
            if u not in e.inputs or ch not in e.channels:
                continue
            cmd = e.inputs[u]
            vents = (cmd - 5.0 if ch == "p_a" else 5.0 - cmd) >= DCV_OPEN_V
            # held: the last n samples all vent (n or more since the last that did not)
            held = rotary.samples_since(~vents) >= max(1, int(round(VENT_HELD_S / e.dt)))
            parts.append(e.channels[ch][held] - float(e.meta["p_atm_bar"]))
        d = np.concatenate(parts) if parts else np.zeros(0)
        out[ch] = {"offset_bar": float(np.median(d)) if d.size else float("nan"), "samples": int(d.size)}
    atm = float(np.median([float(e.meta["p_atm_bar"]) for e in exps]))
    out["p_atm_bar"] = atm
    off = {c: out[c]["offset_bar"] for c in ("p_a", "p_b")
           if out[c]["samples"] >= VENT_MIN_SAMPLES and abs(out[c]["offset_bar"]) > ATMOSPHERE_TOL_BAR}
    note = ""
    if len(off) == 2 and abs(off["p_a"] - off["p_b"]) <= ATMOSPHERE_TOL_BAR:
        note = (f"where a DCV vented its chamber, p_a and p_b read {off['p_a']:+.3f} / {off['p_b']:+.3f} bar from "
                f"the logs' p_atm_bar ({atm:.3f}): the atmosphere written in the logs looks wrong (or both sensors' "
                "zero is off), and sensor_bias takes such an offset either way")
    elif off:
        note = "; ".join(f"where its DCV vented it, {c} reads {v:+.3f} bar from the logs' p_atm_bar ({atm:.3f}): "
                         f"that sensor's zero looks off" for c, v in off.items())
    out["note"] = note
    return out


def read_conventions(family: RotaryFamily, exps: list[Experiment]) -> Conventions:
    """Check how the logs' sensors and valves were written, and undo a clear reversal in place.

    A log written with another convention is fitted against a mirror image
    of itself, and its gap blamed on some effect. Each check reads physics
    the rig cannot escape, in the order each needs the one before it:

    1. each DCV's wiring: fully open, a valve fills or exhausts its chamber
       (:meth:`~app.engine.diagnosis.rotary.RotaryFamily.dcv_wiring_agreement`);
       one wired the other way round has its command read mirrored about 5 V.
       Read as written, a large vane leak's logs with DCV-b mirrored passed
       for swapped pressures and a reversed torque: "no significant effect",
       E 283 × the floor;
    2. which chamber is which: a settled fill stands at its own regulator's
       pressure (:meth:`~app.engine.diagnosis.rotary.RotaryFamily.pressure_order_agreement`).
       Read swapped, a large vane leak's logs gave "no significant effect"
       (E 219 × the floor); undone, the same verdict and E as written right.
       Each valve's wiring, read against the other chamber, is read again;
    3. the torque's sign: where the pressures alone set it
       (:meth:`~app.engine.diagnosis.rotary.RotaryFamily.torque_sign_agreement`;
       the torque on the user rather than the user's on the handle). Read
       reversed, presliding friction was named beside a vane leak;
    4. the angle's sign: the torques on the vane lose power to friction as it
       moves (:meth:`~app.engine.diagnosis.rotary.RotaryFamily.dissipation`;
       only logs with nobody at the handle when the torque reads one value in
       every log). Read reversed, the leak was still named, but the
       baseline's friction went past 2 × nominal and E after it stayed 9 ×
       the right reading's.

    Each decides only on :data:`CONVENTION_MIN_SAMPLES` (the torque:
    :data:`TORQUE_SIGN_MIN_SAMPLES`) samples or more. A reversed torque and
    angle with the pressures' order unknown are what swapped pressures look
    like when a mirrored valve hides the fills (the independent rig's other
    protocol): the checks are then run again with the pressures swapped from
    the start, and that reading is kept if its fills stand in their
    commands' order and the torque and the angle need no reversing.
    """

    raw = _snapshot(exps)
    conv = _read_in_order(family, exps, swap_first=False)
    if conv.torque_reversed and conv.angle_reversed and conv.pressure_samples < CONVENTION_MIN_SAMPLES:
        # what swapped pressures look like when no settled fill showed their order (a valve wired the
        # other way round hides the fills): read them swapped from the start, and keep that reading if
        # its fills then stand in their commands' order and the torque and the angle need no reversing
        read = _snapshot(exps)
        _restore(exps, raw)
        alt = _read_in_order(family, exps, swap_first=True)
        if (alt.pressure_samples >= CONVENTION_MIN_SAMPLES and alt.pressure_agreement <= PRESSURE_ORDER_AGREEMENT
                and not alt.torque_reversed and not alt.angle_reversed):
            return alt
        _restore(exps, read)
    return conv


_Snapshot = list[tuple[dict[str, np.ndarray], dict[str, np.ndarray]]]


def _snapshot(exps: list[Experiment]) -> _Snapshot:
    """Each log's inputs and channels as they stand (the checks replace arrays, never write into them)."""
    return [(dict(e.inputs), dict(e.channels)) for e in exps]


def _restore(exps: list[Experiment], state: _Snapshot) -> None:
    for e, (inputs, channels) in zip(exps, state, strict=True):
        e.inputs, e.channels = dict(inputs), dict(channels)


def _read_in_order(family: RotaryFamily, exps: list[Experiment], swap_first: bool) -> Conventions:
    """:func:`read_conventions`'s four checks in their order; ``swap_first`` takes p_a and p_b swapped before
    any (the pressure order then reported is the one as written)."""

    def mirror(sides: tuple[str, ...]) -> None:
        for side in sides:
            for e in exps:
                e.inputs[f"u_{side}"] = 10.0 - e.inputs[f"u_{side}"]

    def read_wiring() -> tuple[list[tuple[float, int]], tuple[str, ...]]:
        dcv = [family.dcv_wiring_agreement(exps, side) for side in "ab"]
        mirrored = tuple(side for side, (a, n) in zip("ab", dcv, strict=True)
                         if n >= CONVENTION_MIN_SAMPLES and a < DCV_WIRING_AGREEMENT)
        mirror(mirrored)
        return dcv, mirrored

    def swap() -> None:
        for e in exps:
            e.channels["p_a"], e.channels["p_b"] = e.channels["p_b"], e.channels["p_a"]

    if swap_first:
        swap()
    dcv, mirrored = read_wiring()
    p_agree, p_n = family.pressure_order_agreement(exps)
    if swap_first:
        p_agree = 1.0 - p_agree if p_n else p_agree  # as written
    swapped = swap_first or (p_n >= CONVENTION_MIN_SAMPLES and p_agree < PRESSURE_ORDER_AGREEMENT)
    if swapped and not swap_first:
        swap()
        # each valve's wiring was read against the other chamber: read it again against its own
        mirror(mirrored)
        dcv, mirrored = read_wiring()
    t_agree, t_n = family.torque_sign_agreement(exps)
    torque_reversed = t_n >= TORQUE_SIGN_MIN_SAMPLES and t_agree < TORQUE_SIGN_AGREEMENT
    if torque_reversed:
        for e in exps:
            e.channels["torque"] = -e.channels["torque"]
    torque_measured = not all("torque" in flat_channels(e) for e in exps)
    dissipated, moving = family.dissipation(exps, torque_measured=torque_measured)
    angle_reversed = moving >= CONVENTION_MIN_SAMPLES and dissipated < ANGLE_SIGN_DISSIPATION
    if angle_reversed:
        for e in exps:
            e.channels["theta"], e.channels["omega"] = -e.channels["theta"], -e.channels["omega"]
    return Conventions(swapped, p_agree, p_n, torque_reversed, t_agree, t_n, angle_reversed, dissipated, moving,
                       mirrored, (dcv[0][0], dcv[1][0]), (dcv[0][1], dcv[1][1]))


def excites(e: Experiment) -> frozenset[str]:
    """What a rotary-rig log gives a fit to learn from, read off its commands and measurements.

    ``motion`` and ``fast motion`` (the vane turns for a fifth of the log,
    or at ≥ 1 rad/s for a twentieth: friction, inertia, pre-sliding), ``shut``
    (both DCVs held near 5 V: leaks), ``shut after a fast fill or vent`` (a
    shut of ≥ 2 s after a chamber's pressure moved ≥ 1 bar in 1 s: heat
    exchange), ``prv steps`` and
    ``dcv steps`` (pressure transients: valve and line dynamics, supply
    droop), ``dcv partly open`` (a DCV command more than ``DCV_STEP_V``
    from 5 V but short of full opening, :data:`DCV_OPEN_V`, for a twentieth
    of the log: the valve's curve, not only its capacity), ``pressure ≤ 3
    bar`` / ``> 3 bar`` (the level regimes of the report's "where"). The
    command-step sizes, the 1 rad/s band and the 3 bar level are the
    replay's regimes' own (``rotary.PRV_STEP_V``, ``DCV_STEP_V``,
    ``FAST_RAD_S``, ``LEVEL_BAR``); the shares of the log and the shut's
    thresholds are this rule's.
    """
    out = set()
    speed = np.abs(speed_of(e))  # a flat omega (not measured): the angle's rate of change
    # a fifth of the log in motion: a handle held at neutral also twitches when the pressures step
    if np.mean(speed > MOVING_RAD_S) >= 0.2:
        out.add("motion")
    if np.mean(speed > rotary.FAST_RAD_S) >= 0.05:
        out.add("fast motion")
    ua, ub = e.inputs["u_a"], e.inputs["u_b"]
    shut = (np.abs(ua - 5.0) < 0.1) & (np.abs(ub - 5.0) < 0.1)
    if np.mean(shut) >= 0.2:
        out.add("shut")
    # a shut that follows a fast fill or vent: the gas is off the wall's temperature, so the
    # pressure relaxes at constant volume (heat exchange); after a slow fill it has settled
    n1, n2 = (max(1, int(round(s / e.dt))) for s in (1.0, 2.0))
    ends = np.flatnonzero(np.diff(np.r_[shut, False].astype(np.int8)) < 0)
    for i in np.flatnonzero(np.diff(np.r_[False, shut].astype(np.int8)) > 0):
        held_for = ends[np.searchsorted(ends, i)] - i + 1
        if i >= n1 and held_for >= n2 and any(abs(e.channels[c][i] - e.channels[c][i - n1]) >= 1.0
                                              for c in ("p_a", "p_b")):
            out.add("shut after a fast fill or vent")
            break
    z = np.column_stack([e.inputs["z_a"], e.inputs["z_b"]])
    if (rotary.command_changes(z, e.dt) > rotary.PRV_STEP_V).any():
        out.add("prv steps")
    if (rotary.command_changes(np.column_stack([ua, ub]), e.dt) > rotary.DCV_STEP_V).any():
        out.add("dcv steps")
    # the flow at a partial opening is the valve model's shape, not only its capacity
    off = np.abs(np.column_stack([ua, ub]) - 5.0)
    if np.mean(((off > rotary.DCV_STEP_V) & (off < DCV_OPEN_V)).any(axis=1)) >= 0.05:
        out.add("dcv partly open")
    pmax = np.maximum(e.channels["p_a"], e.channels["p_b"])
    for name, share in (("pressure ≤ 3 bar", np.mean(pmax <= rotary.LEVEL_BAR)),
                        ("pressure > 3 bar", np.mean(pmax > rotary.LEVEL_BAR))):
        if share >= 0.1:
            out.add(name)
    return frozenset(out)


class Shows(NamedTuple):
    """What shows an effect best: any one of ``regimes`` (of :func:`excites`; none: every log), which the
    rotary protocol's ``experiments`` have."""

    regimes: tuple[str, ...]
    experiments: tuple[str, ...]


SHOWN_BY: dict[str, Shows] = {
    "inertia": Shows(("fast motion",), ("friction_sweep", "sine_sweep")),
    "presliding_friction": Shows(("motion",), ("friction_sweep", "sine_sweep")),
    "vane_leakage": Shows(("shut",), ("hold_closed", "fill_shut")),
    "external_leakage": Shows(("shut",), ("hold_closed", "fill_shut")),
    "heat_transfer": Shows(("shut after a fast fill or vent",), ("fill_shut",)),
    "tube_dynamics": Shows(("prv steps", "dcv steps"), ("prv_steps", "dcv_steps")),
    "valve_dynamics": Shows(("prv steps", "dcv steps"), ("prv_steps", "dcv_steps")),
    "supply_droop": Shows(("prv steps", "dcv steps"), ("prv_steps", "dcv_steps")),
    "sensor_bias": Shows((), ()),
}
"""Effect → what shows it best: the protocol table (:data:`~app.engine.diagnosis.protocol.VISIBLE`) read
as regimes, so that logs from another protocol are weighed too."""


def unshown(fitted: set[str], scored: set[str],
            ran: dict[str, float | None] | None = None) -> dict[str, dict[str, Any]]:
    """The candidates the held-out logs lack the regimes to show.

    A candidate scored on held-out logs with none of its regimes
    (:data:`SHOWN_BY`) can come out "not significant" although the rig has
    it: a leak is clearest in a shut chamber, heat exchange after a fast
    fill or vent. The report says so beside its verdict, with the protocol
    experiments that would show it.

    Args:
        fitted: The regimes the calibration logs excite (:func:`excites`).
        scored: The regimes the held-out logs excite.
        ran: The protocol experiments the logs hold (their ``experiment``), each with the duration
            factor it ran at where its logs say (``scale``): one that ran and still lacks the regime
            is named as such, not recommended as if it had not run.

    Returns:
        Per such effect: ``needs`` (its regimes), ``fitted`` (whether a
        calibration log has one), ``experiments`` (the protocol's that have
        them) and ``why`` (one sentence).
    """
    ran = ran or {}
    out: dict[str, dict[str, Any]] = {}
    for effect, (needs, exps) in SHOWN_BY.items():
        if not needs or scored.intersection(needs):
            continue
        fit = bool(fitted.intersection(needs))
        done = [x for x in exps if x in ran]
        if done:
            # run at a small duration factor, fill_shut's shut is under the 2 s heat exchange needs
            short = [f for x in done if (f := ran[x]) is not None and f < 1.0]
            hint = (f"the {' and '.join(done)} logs here lack it" +
                    (f" (run at {min(short):g} × the protocol's length; at full length it shows it)"
                     if short else ""))
        else:
            hint = f"the protocol's {' or '.join(exps)} would"
        out[effect] = {"needs": list(needs), "fitted": fit, "experiments": list(exps),
                       "why": f"{'no held-out log' if fit else 'no log'} has what shows it best "
                              f"({' or '.join(needs)}), so these logs cannot rule it out; {hint}"}
    return out


def split_by_coverage(exps: list[Experiment]) -> tuple[list[Experiment], list[Experiment], str]:
    """Hold out a third of the experiments (whole ones), each only if what it excites stays fitted.

    Logs run once each leave no repetition to score on. Holding out the
    last third blindly can take every log with motion away from the fit: on
    the protocol run once (seed 100) the smaller inertia was then not
    found, and the smaller supply droop and valve dynamics closed 0.13 /
    0.04 of the gap. Going
    from the last log back, one is held out when every regime it
    :func:`excites` is still excited by a log left to fit on.

    Returns:
        Calibration and held-out experiments, and how they were chosen.
    """
    if len(exps) == 1:
        a, b = split_time(exps[0])
        return [a], [b], "one log: fitted on its first 60 %, scored on the rest"
    want = max(1, math.ceil(len(exps) / 3))
    sig = {id(e): excites(e) for e in exps}
    held: list[Experiment] = []
    for e in reversed(exps):
        if len(held) == want:
            break
        out = {id(e), *map(id, held)}
        rest = [c for c in exps if id(c) not in out]
        covered = set().union(*(sig[id(c)] for c in rest))
        if sig[id(e)] <= covered:
            held.append(e)
    if not held:
        # every log is alone in something it excites: score on the last, and say so
        held = [exps[-1]]
        why = ("every log excites something no other does; the last is held out, and what only it "
               "excites is scored without having been fitted")
    else:
        why = ("run once each: held out, from the last back, logs whose regimes "
               f"({', '.join(sorted(set().union(*(sig[id(e)] for e in held))))}) other logs also excite")
    held.reverse()
    return [e for e in exps if all(e is not h for h in held)], held, why
