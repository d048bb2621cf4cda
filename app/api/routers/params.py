"""Parameter sets and the thesis GUIs' guided forms (Appendix 1–2 rules and messages)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Path, Query

from app.api.auth import ADMIN, AUTH_RESPONSES, READ
from app.api.deps import IdPath, StoreDep
from app.api.models import FieldState, FormCheckIn, FormState, ParamSet, ParamSetIn
from app.engine import paramsets
from app.engine.ident.gui_rules import GuidedForm, suggested_values

router = APIRouter(prefix="/api", tags=["parameters"], dependencies=[READ], responses=AUTH_RESPONSES)


@router.post("/forms/{rig}", response_model=FormState, summary="Replay typed values through a thesis GUI form")
def check_form(rig: Annotated[Literal["rotary", "linear"], Path(description=(
        "Which GUI: rotary (thesis Figure 3.19) or linear (Figure 3.27) friction identification"))],
               body: FormCheckIn) -> FormState:
    """Enters the values in order, as a person types them into the GUI: each field unlocks when the one
    before is valid, and the first refused one stops the entry with the GUI's own message. Nothing is
    stored. Each field says what it suggests: on the linear form, the catalogue geometry of `cylinder`."""
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
    suggested = suggested_values(rig, body.cylinder)
    fields = [FieldState(name=r.name, label=r.label, valid=bool(form.valid.get(r.name)), editable=r.name == editable,
                         suggested=suggested[r.name]) for r in form.rules]
    return FormState(fields=fields, message=message, ready=form.phase == "ready", refused=refused)


@router.post("/params", dependencies=[ADMIN], response_model=ParamSet, status_code=201,
             summary="Validate and store a parameter set")
def save_params(body: ParamSetIn, store: StoreDep) -> ParamSet:
    """Checked by the object the engine builds from it, so a stored set never fails when used: the GUIs'
    rules for identification inputs; the ranges of an exercise shape, gains or fuzzy universes. A workout
    or fuzzy set may give some fields (the rest keep their defaults); a 422 names the first refused one."""
    values = paramsets.validate(body.kind, dict(body.values), partial=True)  # ParameterError → 422
    row = store.param_set(store.save_params(body.kind, body.name, values))
    assert row is not None
    return ParamSet(**row)


@router.get("/params/fields", response_model=dict[str, list[str]], summary="The fields of each parameter-set kind")
def param_fields() -> dict[str, list[str]]:
    """Field names per kind (rotary, linear, workout, gains, fuzzy), in entry order."""
    return {k: list(paramsets.fields_of(k)) for k in paramsets.KINDS}


@router.get("/params", response_model=list[ParamSet], summary="Stored parameter sets, newest first")
def list_params(store: StoreDep, kind: Annotated[Literal["rotary", "linear", "workout", "gains", "fuzzy"] | None,
                                                 Query(description="Only sets of this kind")] = None
                ) -> list[ParamSet]:
    """A start request takes a stored set by its id (`workout_id`, `gains_id`, `fuzzy_id`)."""
    return [ParamSet(**p) for p in store.param_sets(kind)]


@router.get("/params/{set_id}", response_model=ParamSet, responses={404: {"description": "No such set"}},
            summary="One stored parameter set")
def get_params(set_id: IdPath, store: StoreDep) -> ParamSet:
    """The set as validated when stored (counts as integers, numbers as floats)."""
    row = store.param_set(set_id)
    if row is None:
        raise HTTPException(404, f"parameter set {set_id} does not exist")
    return ParamSet(**row)
