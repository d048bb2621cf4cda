"""Parameter sets a lab stores and reuses: what each kind holds and how it is checked.

Five kinds, each validated by the same object the engine later builds from it,
so a stored set can never fail at run time:

- ``rotary`` / ``linear``: friction-identification inputs, with the thesis
  GUIs' rules and messages (Figures 3.19 and 3.27, SPEC §6);
- ``workout``: the scenario shape (:class:`~app.engine.scenarios.ScenarioSettings`);
- ``gains``: Cascade PID gains of PRV-a and PRV-b (Eq 3.26's form);
- ``fuzzy``: the fuzzy scheduler's input universes and defuzzifier (thesis 3.6.3).

Every refusal is a :class:`~app.engine.params.ParameterError` whose text starts
with ``"<field>: "`` so the API can name the field.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal

from app.engine.params import ParameterError

Kind = Literal["rotary", "linear", "workout", "gains", "fuzzy"]
KINDS: tuple[str, ...] = ("rotary", "linear", "workout", "gains", "fuzzy")

GAIN_FIELDS: tuple[str, ...] = ("kp_a", "ki_a", "kd_a", "kp_b", "ki_b", "kd_b")
"""Cascade PID gains [-, 1/s, s] of PRV-a then PRV-b."""

FUZZY_FIELDS: tuple[str, ...] = ("e_range", "de_range", "defuzz")
WORKOUT_FIELDS: tuple[str, ...] = ("speed", "amplitude_deg", "t_engage", "t_dist_after", "dist_speed",
                                   "dist_duration", "dp_b_bar", "conv_band", "conv_timeout")
"""The scenario shape a therapist may change; P_w and the target belong to the run itself."""


def fields_of(kind: str) -> tuple[str, ...]:
    """The field names of a kind, in entry order."""
    from app.engine.ident.gui_rules import LinearInputs, RotaryInputs

    if kind == "rotary":
        return tuple(f.name for f in dataclasses.fields(RotaryInputs))
    if kind == "linear":
        return tuple(f.name for f in dataclasses.fields(LinearInputs))
    if kind == "workout":
        return WORKOUT_FIELDS
    if kind == "gains":
        return GAIN_FIELDS
    if kind == "fuzzy":
        return FUZZY_FIELDS
    raise ParameterError(f"kind: {kind!r} must be one of {', '.join(KINDS)}")


def _number(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ParameterError(f"{name}: must be a number, got {v!r}")
    if not math.isfinite(float(v)):
        raise ParameterError(f"{name}: must be a finite number")
    return float(v)


def _named(exc: ParameterError, fields: tuple[str, ...]) -> ParameterError:
    """Prefix a check's message with its field when it does not name one already."""
    msg = str(exc)
    head = msg.split(" ", 1)[0]
    if head.endswith(":") and head[:-1] in fields:
        return exc
    return ParameterError(f"{head if head in fields else fields[0]}: {msg}")


def validate(kind: str, values: dict[str, Any], *, partial: bool = False) -> dict[str, Any]:
    """Check a parameter set and return it normalised (counts as ints, numbers as floats).

    Args:
        kind: One of :data:`KINDS`.
        values: Field → value in the GUI's units.
        partial: Allow missing fields (defaults fill them) — workout and
            fuzzy sets only; identification inputs (the thesis GUIs require
            every field) and gains (all six or none) are always complete.

    Raises:
        ParameterError: ``"<field>: <message>"`` for the first problem found.
    """
    fields = fields_of(kind)
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ParameterError(f"{unknown[0]}: unknown field; fields of {kind}: {', '.join(fields)}")
    if not partial or kind in ("rotary", "linear", "gains"):
        missing = [f for f in fields if f not in values]
        if missing:
            raise ParameterError(f"{missing[0]}: missing value")
    out: dict[str, Any] = {}
    for f in fields:
        if f not in values:
            continue
        v = values[f]
        if kind == "fuzzy" and f == "defuzz":
            if v not in ("wavg", "centroid"):
                raise ParameterError(f"defuzz: {v!r} must be 'wavg' (Eq 3.27) or 'centroid'")
            out[f] = v
            continue
        x = _number(f, v)
        out[f] = int(x) if f in ("ns", "nd") and x.is_integer() else x
    build(kind, out)
    return out


def build(kind: str, values: dict[str, Any]) -> Any:
    """The engine object a (validated) set stands for.

    Returns:
        ``RotaryInputs``, ``LinearInputs``, ``ScenarioSettings``, the gains as
        ``((K_p, K_i, K_d) of a, of b)``, or a ``FuzzyConfig``.
    """
    if kind in ("rotary", "linear"):
        from app.engine.ident.gui_rules import LinearInputs, RotaryInputs

        return (RotaryInputs if kind == "rotary" else LinearInputs)(**values)
    try:
        if kind == "workout":
            from app.engine.scenarios import ScenarioSettings

            return ScenarioSettings(**values)
        if kind == "gains":
            from app.engine.params import check_range

            g = {**dict.fromkeys(GAIN_FIELDS, math.nan), **values}
            for f in GAIN_FIELDS:
                if math.isnan(g[f]):
                    raise ParameterError(f"{f}: missing value")
                check_range(f, g[f], 0.0, 100.0)
            return ((g["kp_a"], g["ki_a"], g["kd_a"]), (g["kp_b"], g["ki_b"], g["kd_b"]))
        if kind == "fuzzy":
            from app.engine.control.fuzzy import FuzzyConfig

            return FuzzyConfig(**values)
    except ParameterError as exc:
        raise _named(exc, fields_of(kind)) from None
    raise ParameterError(f"kind: {kind!r} must be one of {', '.join(KINDS)}")
