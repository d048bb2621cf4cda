"""The withheld-effect suite: logs from a simulated rig with one effect the diagnosed model lacks.

Each case runs the diagnosis protocol (:mod:`.protocol`) on a rig that has
one of the nine effects at one of two magnitudes, nominal parameters off by
up to ±20 % (PRV and DCV flow capacities, dead volumes, pressure-sensor
gains, friction levels — what the baseline recalibrates — by group, or
parameter by parameter: :data:`ERRORS`) and sensor noise.
The diagnosed model (:class:`~app.engine.diagnosis.rotary.RotaryFamily` on
the *unperturbed* nominal rig) lacks the effect. The first repetition of
every experiment calibrates, the second is held out. Effect-free cases
measure the false-positive rate.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, replace
from typing import Any

import numpy as np

from app.engine.diagnosis.core import channel_spread, diagnose
from app.engine.diagnosis.logs import Experiment
from app.engine.diagnosis.protocol import run_protocol
from app.engine.diagnosis.rotary import DCV_FORM_NOMINAL, RotaryFamily
from app.engine.diagnosis.run import PROTOCOL, split_by_coverage, split_last_third
from app.engine.params import (
    HeatTransferEffect,
    InertiaEffect,
    LeakageEffect,
    PlantParams,
    PreslidingEffect,
    SensorBiasEffect,
    SupplyDroopEffect,
    TubeEffect,
    ValveDynamicsEffect,
)

MAGNITUDES: dict[str, tuple[Any, Any]] = {
    "inertia": (InertiaEffect(5e-3), InertiaEffect(1.5e-2)),
    "vane_leakage": (LeakageEffect(0.02), LeakageEffect(0.06)),
    "external_leakage": (LeakageEffect(0.02), LeakageEffect(0.06)),
    "heat_transfer": (HeatTransferEffect(0.3), HeatTransferEffect(0.05)),
    "tube_dynamics": (TubeEffect(2.0, 0.004), TubeEffect(5.0, 0.004)),
    "presliding_friction": (PreslidingEffect(150.0, 0.5), PreslidingEffect(50.0, 0.5)),
    "sensor_bias": (SensorBiasEffect(0.05, -0.05, 0.1), SensorBiasEffect(0.15, 0.1, -0.3)),
    "supply_droop": (SupplyDroopEffect(0.3, 0.05), SupplyDroopEffect(1.0, 0.1)),
    "valve_dynamics": (ValveDynamicsEffect(0.01, 0.03), ValveDynamicsEffect(0.03, 0.1)),
}
"""Two magnitudes per effect (smaller, larger)."""


def friction_per_direction(p: PlantParams, asymmetry: float) -> PlantParams:
    """``p`` with its CCW static and Coulomb levels × (1 + ``asymmetry``) and its CW ones × (1 − ``asymmetry``)."""
    fr = p.friction

    def times(v: tuple[float, ...], f: float) -> tuple[float, ...]:
        return tuple(x * f for x in v)

    up, down = 1.0 + asymmetry, 1.0 - asymmetry
    return replace(p, friction=replace(fr, ts_ccw=times(fr.ts_ccw, up), tc_ccw=times(fr.tc_ccw, up),
                                       ts_cw=times(fr.ts_cw, down), tc_cw=times(fr.tc_cw, down)))


STRUCTURAL: dict[str, tuple[str, Callable[[PlantParams], PlantParams]]] = {
    "dcv_b_0.40": ("the DCV's critical pressure ratio 0.40 (the model's: 0.26, Table 3.3)",
                   lambda p: replace(p, dcv=replace(p.dcv, b=0.40))),
    "prv_b_0.45": ("the PRV's critical pressure ratios 0.45 (the model's: 0.30)",
                   lambda p: replace(p, prv=replace(p.prv, b_supply=0.45, b_exhaust=0.45))),
    "prv_deadband_half": ("the PRV regulator wakes at 0.015 bar and rests at 0.005 (the model's: 0.03 / 0.01); "
                          "a form the recalibration can take",
                          lambda p: replace(p, prv=replace(p.prv, deadband_on_bar=0.015, deadband_off_bar=0.005))),
    "prv_dead_zone": ("the PRV regulator wakes and rests at 0.02 bar and opens its spool in proportion to the "
                      "error past that (the model's: wakes at 0.03, rests at 0.01, opens in proportion to the "
                      "whole error); a form the recalibration can take",
                      lambda p: replace(p, prv=replace(p.prv, deadband_on_bar=0.02, deadband_off_bar=0.02,
                                                       dead_zone=1.0))),
    "stribeck_j_1": ("a Stribeck shape exponent of 1 (the model's: 2, thesis Eq 3.14)",
                     lambda p: replace(p, friction=replace(p.friction, shape_j=1.0))),
    "dcv_null_leak_x2": ("twice the DCV's clearance leak at 5 V",
                         lambda p: replace(p, dcv=replace(p.dcv, null_leak_fraction=2 * p.dcv.null_leak_fraction))),
    "prv_tau_spool_x3": ("a PRV spool three times slower (12 ms)",
                         lambda p: replace(p, prv=replace(p.prv, tau_spool=3 * p.prv.tau_spool))),
    "dcv_closed_centre": ("a DCV shut at 5 V that opens past a 0.2 V dead band with no null zone (the model's: "
                          "underlaps 0.7 / 0.3 V, a 1.6 V null zone); a form the recalibration can take",
                          lambda p: replace(p, dcv=replace(p.dcv, underlap_fill_v=-0.2, underlap_exh_v=-0.2,
                                                           null_width_v=0.0))),
    "friction_per_direction": ("static and Coulomb friction 15 % higher CCW and 15 % lower CW than the rest of "
                               "the friction's error (the model scales both directions by one factor)",
                               lambda p: friction_per_direction(p, 0.15)),
}
"""Rigs that differ from the diagnosed model in form, not in a recalibratable scale nor by a candidate
effect: what a rig model written by someone else looks like to the tool. The baseline cannot fit
these exactly; the tool must leave the rest as unexplained gap, not blame a candidate for it."""

STRUCTURAL_PAIRS: dict[str, tuple[str, int]] = {
    "stribeck_j_1": ("inertia", 1), "dcv_null_leak_x2": ("vane_leakage", 0), "prv_b_0.45": ("supply_droop", 1),
    "prv_deadband_half": ("valve_dynamics", 1), "dcv_b_0.40": ("heat_transfer", 1),
    "prv_tau_spool_x3": ("sensor_bias", 0), "friction_per_direction": ("sensor_bias", 0),
    # a chamber venting to atmosphere where the model's valve leaks at its centre: can the leak be told apart?
    "dcv_closed_centre": ("external_leakage", 0),
    # a regulator resting where the model's would not, beside a slower one: can the lag be told apart?
    "prv_dead_zone": ("valve_dynamics", 0),
}
"""A withheld effect (and magnitude) on each form-mismatched rig: is it still found beside the mismatch?"""


def perturbed(seed: int, spread: float = 0.2) -> PlantParams:
    """The nominal rig with its recalibratable parameters off by up to ±``spread`` (uniform)."""
    rng = np.random.default_rng(seed)

    def f() -> float:
        return float(1.0 + rng.uniform(-spread, spread))

    p = PlantParams()
    fr = p.friction
    s_c, s_v = f(), f()
    friction = replace(fr, ts_ccw=tuple(v * s_c for v in fr.ts_ccw), tc_ccw=tuple(v * s_c for v in fr.tc_ccw),
                       ts_cw=tuple(v * s_c for v in fr.ts_cw), tc_cw=tuple(v * s_c for v in fr.tc_cw),
                       b_ccw=tuple(v * s_v for v in fr.b_ccw), b_cw=tuple(v * s_v for v in fr.b_cw))
    s_prv, s_dcv, s_dv = f(), f(), f()
    g_a, g_b = 1.0 + 0.1 * (f() - 1.0), 1.0 + 0.1 * (f() - 1.0)  # gains: ±2 % (a calibrated sensor)
    return replace(
        p, friction=friction,
        prv=replace(p.prv, c_supply=p.prv.c_supply * s_prv, c_exhaust=p.prv.c_exhaust * s_prv),
        dcv=replace(p.dcv, c=p.dcv.c * s_dcv),
        vane=replace(p.vane, dead_volume_a=p.vane.dead_volume_a * s_dv, dead_volume_b=p.vane.dead_volume_b * s_dv),
        sensors=replace(p.sensors, pressure_gain_a=g_a, pressure_gain_b=g_b),
    )


def perturbed_each(seed: int, spread: float = 0.2) -> PlantParams:
    """The nominal rig with *every* recalibratable parameter off by an error of its own (uniform, ±``spread``).

    :func:`perturbed` scales each group by one factor, the way the baseline
    recalibrates it. A rig model written by someone else need not: here each
    friction table entry (static, Coulomb, Stribeck speed and viscous
    coefficient, per direction and working pressure), the PRV's supply and
    exhaust capacities and each chamber's dead volume has its own error, and
    the Coulomb level stays at most the static one. The baseline can only
    approximate such a rig (:func:`true_params` gives its group averages).
    """
    rng = np.random.default_rng(seed)

    def f() -> float:
        return float(1.0 + rng.uniform(-spread, spread))

    p = PlantParams()
    fr = p.friction
    keys = ("ts_ccw", "tc_ccw", "ws_ccw", "b_ccw", "ts_cw", "tc_cw", "ws_cw", "b_cw")
    each: dict[str, Any] = {k: tuple(v * f() for v in getattr(fr, k)) for k in keys}
    for d in ("ccw", "cw"):  # |T_c| ≤ |T_s| (the CW entries are negative)
        each[f"tc_{d}"] = tuple(math.copysign(min(abs(c), abs(t)), c)
                                for c, t in zip(each[f"tc_{d}"], each[f"ts_{d}"], strict=True))
    g_a, g_b = 1.0 + 0.1 * (f() - 1.0), 1.0 + 0.1 * (f() - 1.0)
    return replace(
        p, friction=replace(fr, **each),
        prv=replace(p.prv, c_supply=p.prv.c_supply * f(), c_exhaust=p.prv.c_exhaust * f()),
        dcv=replace(p.dcv, c=p.dcv.c * f()),
        vane=replace(p.vane, dead_volume_a=p.vane.dead_volume_a * f(), dead_volume_b=p.vane.dead_volume_b * f()),
        sensors=replace(p.sensors, pressure_gain_a=g_a, pressure_gain_b=g_b),
    )


ERRORS: dict[str, Callable[[int, float], PlantParams]] = {"grouped": perturbed, "each": perturbed_each}
"""How a case's rig is off nominal: by group (what the baseline recalibrates) or parameter by parameter."""


def simulated_rig(seed: int = 0, param_error: float = 0.0, errors: str = "grouped",
                  effects: Mapping[str, int] | None = None) -> PlantParams:
    """The simulated rig a protocol runs on (``cwrr protocol``, ``POST /api/diagnoses``).

    Args:
        seed: Seed of the parameter errors.
        param_error: Their spread (0.2 = ±20 %; 0: the nominal rig).
        errors: ``grouped`` (:func:`perturbed`) or ``each`` (:func:`perturbed_each`).
        effects: Effect → magnitude, 1 (smaller) or 2 (larger) of :data:`MAGNITUDES`.

    Raises:
        ValueError: An unknown error kind, effect or magnitude, or a spread outside [0, 0.5].
    """
    if errors not in ERRORS:
        raise ValueError(f"errors = {errors!r}: must be one of {', '.join(ERRORS)}")
    if not 0.0 <= param_error <= 0.5:
        raise ValueError(f"param_error = {param_error}: outside its allowed range [0, 0.5]")
    rig = ERRORS[errors](seed, param_error) if param_error > 0 else PlantParams()
    for name, mag in (effects or {}).items():
        if name not in MAGNITUDES:
            raise ValueError(f"unknown effect {name!r}; known: {', '.join(MAGNITUDES)}")
        if mag not in (1, 2):
            raise ValueError(f"effect {name}: magnitude {mag} must be 1 (smaller) or 2 (larger)")
        rig = rig.with_effects(**{name: MAGNITUDES[name][mag - 1]})
    return rig


def _form(rig: PlantParams) -> dict[str, float]:
    """The model's form (RotaryFamily.dcv_centre and prv_regulator) that ``rig`` has.

    The DCV centre's closure and dead band: exact for a shut centre with equal
    overlaps and no null zone; the thesis's centre (nominal) otherwise, exact
    for that rig. The PRV regulator's band, hysteresis and dead zone: exact
    (its gain and lag are the nominal's on every rig of the suite).
    """
    dcv = dict(DCV_FORM_NOMINAL)
    if rig.dcv.underlap_fill_v == rig.dcv.underlap_exh_v <= 0.0 and rig.dcv.null_width_v == 0.0:
        dcv = {"dcv_centre_closure": 1.0, "dcv_dead_band_v": -rig.dcv.underlap_fill_v}
    r, n = rig.prv, PlantParams().prv
    band = (r.deadband_on_bar + r.deadband_off_bar) / (n.deadband_on_bar + n.deadband_off_bar)
    hyst = (r.deadband_on_bar - r.deadband_off_bar) / (n.deadband_on_bar - n.deadband_off_bar) / band
    return dcv | {"prv_band_scale": band, "prv_hysteresis_scale": hyst, "prv_dead_zone": r.dead_zone}


def true_params(rig: PlantParams, effect: str | None) -> dict[str, float]:
    """The diagnosed model's parameters that reproduce ``rig`` (the suite's answer key).

    Exact for :func:`perturbed`'s rigs; for :func:`perturbed_each`'s, group
    averages (the model's form cannot reproduce them exactly).
    """
    n = PlantParams()
    fr, nf = rig.friction, n.friction

    def ratio(a: tuple[float, ...], b: tuple[float, ...]) -> float:
        return float(np.mean(np.asarray(a) / np.asarray(b)))

    x = {"prv_c_scale": 0.5 * (rig.prv.c_supply / n.prv.c_supply + rig.prv.c_exhaust / n.prv.c_exhaust),
         "dcv_c_scale": rig.dcv.c / n.dcv.c,
         "dead_volume_scale": 0.5 * (rig.vane.dead_volume_a / n.vane.dead_volume_a
                                     + rig.vane.dead_volume_b / n.vane.dead_volume_b),
         **_form(rig),
         "gain_a": rig.sensors.pressure_gain_a, "gain_b": rig.sensors.pressure_gain_b,
         "friction_scale": ratio(fr.ts_ccw + fr.tc_ccw + fr.ts_cw + fr.tc_cw,
                                 nf.ts_ccw + nf.tc_ccw + nf.ts_cw + nf.tc_cw),
         "viscous_scale": ratio(fr.b_ccw + fr.b_cw, nf.b_ccw + nf.b_cw),
         "friction_pressure_weight": 1.0}  # the simulator reads Table 4.2 at the lower chamber pressure
    if effect is not None:
        names = {p.name for p in RotaryFamily().effect(effect)}
        x |= {f"{effect}.{k}": float(v) for k, v in asdict(getattr(rig.effects, effect)).items()
              if f"{effect}.{k}" in names}
    return x


def oracle_gap_closure(report: dict[str, Any], held: list[Experiment], x: dict[str, float],
                       effects: tuple[str, ...]) -> float:
    """GC of the model with the *true* parameters on the held-out logs.

    The most any fit can reach with this replay: what it leaves is the
    replay's own floor (the PRV regulators' rest-band wander, which no
    deterministic replay reproduces sample by sample), not a missing effect.
    """
    fam = RotaryFamily()
    preps = [fam.prepare(e) for e in held]
    meas = [fam.measured(p) for p in preps]
    nr = []
    for c, spread in zip(fam.channels, channel_spread(fam, meas), strict=True):
        res = [fam.predict(p, x, effects)[c] - m[c] for p, m in zip(preps, meas, strict=True)]
        sse = sum(float(np.nansum(r**2)) for r in res)
        cnt = sum(int(np.isfinite(r).sum()) for r in res)
        nr.append(math.sqrt(sse / cnt) / spread)
    hf = report["how_far"]
    e_or = float(np.mean(nr))
    return (hf["e_before"] - e_or) / (hf["e_before"] - hf["e_floor"]) if hf["e_before"] - hf["e_floor"] > 1e-12 \
        else 0.0


def run_case(effect: str | None, magnitude: int = 0, seed: int = 0, scale: float = 1.0,
             structural: str | None = None, errors: str = "grouped",
             friction_asymmetry: float = 0.0, once: str | None = None) -> dict[str, Any]:
    """Generate one case's logs and diagnose them.

    Args:
        effect: The withheld effect, or ``None`` for an effect-free rig.
        magnitude: 0 (smaller) or 1 (larger).
        seed: Seed of the parameter errors and the sensor noise.
        scale: Protocol duration factor.
        structural: A key of :data:`STRUCTURAL`: the rig also differs from
            the model in form (the oracle GC then still uses the model's form).
        errors: A key of :data:`ERRORS`: how the nominal parameters are off.
        friction_asymmetry: The rig's static and Coulomb friction also off per
            direction by this much (:func:`friction_per_direction`; 0: not) [-].
        once: Diagnose the first repetition alone, split as ``cwrr diagnose``
            splits logs run once (``"coverage"``,
            :func:`~app.engine.diagnosis.run.split_by_coverage`) or by the rule
            it replaced (``"last_third"``); None: fit the first repetition,
            score the second.

    Returns:
        ``effect``, ``magnitude``, ``rank`` of the true effect in the ranking
        (1 = first; ``None`` for effect-free), ``verdict``, the true
        effect's held-out ``gap_closure``, ``seconds`` and the report.
    """
    if errors not in ERRORS:
        raise ValueError(f"no parameter-error kind {errors!r}; known: {', '.join(ERRORS)}")
    rig = ERRORS[errors](seed, 0.2)  # the issue's ±20 %
    if structural is not None:
        if structural not in STRUCTURAL:
            raise ValueError(f"no structural variant {structural!r}; known: {', '.join(STRUCTURAL)}")
        rig = STRUCTURAL[structural][1](rig)
    if not -0.5 <= friction_asymmetry <= 0.5:
        raise ValueError(f"friction_asymmetry = {friction_asymmetry}: outside its allowed range [-0.5, 0.5]")
    if friction_asymmetry:
        rig = friction_per_direction(rig, friction_asymmetry)
    if effect is not None:
        rig = rig.with_effects(**{effect: MAGNITUDES[effect][magnitude]})
    if once not in (None, "coverage", "last_third"):
        raise ValueError(f"once = {once!r}: must be 'coverage' or 'last_third'")
    exps = run_protocol(rig, seed=seed, scale=scale, repetitions=1 if once else 2)
    if once == "coverage":
        calib, held, _ = split_by_coverage(exps)
    elif once == "last_third":
        calib, held = split_last_third(exps)
    else:
        calib = [e for e in exps if e.meta["repetition"] == 1]
        held = [e for e in exps if e.meta["repetition"] == 2]
    t0 = time.perf_counter()
    rep = diagnose(RotaryFamily(), calib, held, protocol=PROTOCOL)
    secs = time.perf_counter() - t0
    names = [r["effect"] for r in rep["ranking"]]
    found = rep["verdict"]["effects"]
    first = found[0] if found else None
    rank = (names.index(effect) + 1) if effect is not None else None
    gc = next((r["gap_closure"] for r in rep["ranking"] if r["effect"] == effect), None)
    oracle = oracle_gap_closure(rep, held, true_params(rig, effect), (effect,) if effect else ())
    return {"effect": effect, "magnitude": magnitude, "seed": seed, "structural": structural, "errors": errors,
            "friction_asymmetry": friction_asymmetry, "once": once, "held_out": [e.name for e in held],
            "rank": rank, "first": first, "verdict": found,
            "confusable_with": rep["verdict"]["confusable_with"], "alternatives": rep["verdict"]["alternatives"],
            "gap_closure": gc, "oracle_gap_closure": oracle, "seconds": secs,
            "baseline_beaten": rep["verdict"]["baseline_beaten"], "report": rep}


def summarise(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Rates over the cases.

    ``rank1_rate``: the verdict's first effect is the true one (significant);
    ``ranked_first_rate``: the true effect heads the ranking, significant or
    not; ``median_gc``/``median_oracle_gc``: held-out gap closure of the
    fitted and of the true model; ``false_positive_rate``: effect-free rigs
    with any effect in the verdict.
    """
    eff = [r for r in results if r["effect"] is not None]
    null = [r for r in results if r["effect"] is None]
    rank1 = [r for r in eff if r["verdict"][:1] == [r["effect"]]]
    return {
        "cases": len(eff), "rank1_rate": len(rank1) / len(eff) if eff else None,
        "ranked_first_rate": sum(1 for r in eff if r["rank"] == 1) / len(eff) if eff else None,
        "median_gc": float(np.median([r["gap_closure"] for r in eff])) if eff else None,
        "gc_ge_0.7_rate": (sum(1 for r in eff if (r["gap_closure"] or 0) >= 0.7) / len(eff)) if eff else None,
        "null_cases": len(null),
        "false_positive_rate": (sum(1 for r in null if r["verdict"]) / len(null)) if null else None,
        "median_oracle_gc": float(np.median([r["oracle_gap_closure"] for r in eff])) if eff else None,
        "rows": [{k: r.get(k) for k in ("effect", "magnitude", "seed", "structural", "errors", "friction_asymmetry",
                                        "rank", "verdict", "confusable_with", "alternatives", "gap_closure",
                                        "oracle_gap_closure", "baseline_beaten", "seconds")}
                 for r in results],
    }
