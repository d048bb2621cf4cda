"""Therapy sessions: a pseudonymous person id, notes, and the runs recorded in them."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query

from app.api.auth import AUTH_RESPONSES, READ, THERAPIST
from app.api.deps import IdPath, StoreDep
from app.api.models import NotesIn, PersonFilter, Session, SessionIn

router = APIRouter(prefix="/api/sessions", tags=["sessions"], dependencies=[READ], responses=AUTH_RESPONSES)


def _sessions(store: StoreDep, rows: list[dict[str, Any]]) -> list[Session]:
    runs = store.session_run_ids([r["id"] for r in rows])
    return [Session(**r, runs=runs[r["id"]]) for r in rows]


def _session(store: StoreDep, row: dict[str, Any]) -> Session:
    return _sessions(store, [row])[0]


@router.post("", dependencies=[THERAPIST], response_model=Session, status_code=201, summary="Open a session")
def open_session(body: SessionIn, store: StoreDep) -> Session:
    """A therapy session groups the runs of one person (a pseudonymous id, never a name) under a
    therapist's notes; a start request takes its `session_id`."""
    row = store.session(store.add_session(body.person, body.notes))
    assert row is not None
    return _session(store, row)


@router.get("", response_model=list[Session], summary="Sessions, newest first")
def list_sessions(store: StoreDep, person: PersonFilter = None,
        limit: Annotated[int, Query(ge=1, le=1000, description="At most this many sessions")] = 100,
        offset: Annotated[int, Query(ge=0, le=10**9, description="Skip this many of the newest first")] = 0,
        ) -> list[Session]:
    """Each session with its person, notes and the ids of its runs; `person` narrows them to one person."""
    return _sessions(store, store.sessions(person, limit, offset))


@router.get("/{session_id}", response_model=Session, responses={404: {"description": "No such session"}},
            summary="One session with its runs")
def get_session(session_id: IdPath, store: StoreDep) -> Session:
    """The session, its notes and the ids of its runs."""
    row = store.session(session_id)
    if row is None:
        raise HTTPException(404, f"session {session_id} does not exist")
    return _session(store, row)


@router.patch("/{session_id}", dependencies=[THERAPIST], response_model=Session,
              responses={404: {"description": "No such session"}}, summary="Replace a session's notes")
def edit_notes(session_id: IdPath, body: NotesIn, store: StoreDep) -> Session:
    """The session's notes are replaced as a whole; each run keeps its own (`PATCH /api/runs/{id}`)."""
    if not store.set_session_notes(session_id, body.notes):
        raise HTTPException(404, f"session {session_id} does not exist")
    row = store.session(session_id)
    assert row is not None
    return _session(store, row)
