"""Parameter sets and the thesis GUIs' guided forms (Appendix 1–2 rules and messages)."""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter

from app.api.deps import StoreDep
from app.api.models import FieldState, FormCheckIn, FormState, ParamSet, ParamSetIn
from app.engine.ident.gui_rules import GuidedForm, LinearInputs, RotaryInputs
from app.engine.params import ParameterError

router = APIRouter(prefix="/api", tags=["parameters"])


@router.post("/forms/{rig}", response_model=FormState, summary="Replay typed values through a thesis GUI form")
def check_form(rig: Literal["rotary", "linear"], body: FormCheckIn) -> FormState:
    form = GuidedForm(rig)
    refused: str | None = None
    message = form.message
    for name, value in body.values.items():
        res = form.enter(name, value)  # unknown field → ParameterError → 422
        message = res.message
        if not res.ok:
            refused = name
            break
    editable = form.editable
    fields = [FieldState(name=r.name, label=r.label, valid=bool(form.valid.get(r.name)), editable=r.name == editable)
              for r in form.rules]
    return FormState(fields=fields, message=message, ready=form.phase == "ready", refused=refused)


@router.post("/params", response_model=ParamSet, status_code=201, summary="Validate and store a parameter set")
def save_params(body: ParamSetIn, store: StoreDep) -> ParamSet:
    v = body.values
    cls = RotaryInputs if body.kind == "rotary" else LinearInputs
    fields = [f for f in cls.__dataclass_fields__]
    unknown = sorted(set(v) - set(fields))
    if unknown:
        raise ParameterError(f"{unknown[0]}: unknown field; fields: {', '.join(fields)}")
    missing = [f for f in fields if f not in v]
    if missing:
        raise ParameterError(f"{missing[0]}: missing value")
    kwargs: dict[str, Any] = {f: (int(v[f]) if f in ("ns", "nd") and float(v[f]).is_integer() else v[f])
                              for f in fields}
    cls(**kwargs)
    row = store.param_set(store.save_params(body.kind, body.name, dict(v)))
    assert row is not None
    return ParamSet(**row)


@router.get("/params", response_model=list[ParamSet], summary="Stored parameter sets, newest first")
def list_params(store: StoreDep, kind: Literal["rotary", "linear"] | None = None) -> list[ParamSet]:
    return [ParamSet(**p) for p in store.param_sets(kind)]
