"""Who may drive the station: bearer tokens with two roles, the bind rule, a body-size limit.

The station has two kinds of users (brief, issue 7 item 6): a *therapist* runs
exercises (connect, start, stop, clear a fault, open sessions) and an *admin*
also changes what the controllers use (identification, PID tuning, parameter
sets, gap diagnoses). Reading is open to both roles.

Rules:

* No token configured and the server bound to loopback (the default,
  ``127.0.0.1``): one trusted local user, no sign-in — but a request that
  arrives from a non-loopback address is still refused, so starting uvicorn by
  hand on ``0.0.0.0`` cannot open the rig to the network by accident.
* Any other bind address needs at least one token (``Settings`` refuses to
  start otherwise); once tokens exist they are required on every ``/api``
  endpoint except the two below, whatever the bind address.
* ``GET /api/health`` (the container's health check) and
  ``POST /api/engine/estop`` need no token: stopping the machine must never
  wait for a password, and it only ever makes the rig safer.

Tokens are compared in constant time and live in ``SecretStr`` fields, so
they are never printed by the settings' ``repr`` nor written to a log.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
from enum import IntEnum
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.api.settings import Settings, is_loopback


class Role(IntEnum):
    """Roles, ordered: a higher role may do all a lower one may."""

    THERAPIST = 1
    ADMIN = 2


def _client_is_remote(request: Request) -> bool:
    client = request.client
    if client is None:  # a Unix socket: local by construction
        return False
    try:
        ipaddress.ip_address(client.host)
    except ValueError:  # not an IP at all (an in-process test client)
        return False
    return not is_loopback(client.host)


def _role_of(settings: Settings, request: Request) -> Role | None:
    """The caller's role from ``Authorization: Bearer …``, or None."""
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    if scheme.lower() != "bearer" or not token:
        return None
    given = token.strip().encode()
    # both compared every time, so the time taken says nothing about which one matched
    role: Role | None = None
    for r, secret in ((Role.ADMIN, settings.admin_token), (Role.THERAPIST, settings.therapist_token)):
        if secret is not None and hmac.compare_digest(given, secret.get_secret_value().encode()) and role is None:
            role = r
    return role


def presented_role(request: Request) -> Role | None:
    """The caller's role, or None where a protected endpoint would refuse it (never raises)."""
    settings: Settings = request.app.state.settings
    if not settings.auth_enabled:
        return None if _client_is_remote(request) else Role.ADMIN
    return _role_of(settings, request)


BEARER = HTTPBearer(auto_error=False, scheme_name="token", description=(
    "A therapist or admin token (CWRR_THERAPIST_TOKEN / CWRR_ADMIN_TOKEN), sent as `Authorization: Bearer "
    "<token>`. A station without tokens serves its own machine and needs none."))
"""The tokens as the OpenAPI document declares them: /docs gets its Authorize button, a generated client
its bearer parameter. Declaration only (``auto_error=False``): :func:`caller_role` decides, and says why."""


def caller_role(request: Request,
                _token: Annotated[HTTPAuthorizationCredentials | None, Security(BEARER)] = None) -> Role:
    """The role of the caller, or an HTTP 401/403 that says what is missing."""
    role = presented_role(request)
    if role is not None:
        return role
    if not request.app.state.settings.auth_enabled:  # no tokens, so refused only for being remote
        raise HTTPException(403, "this station has no access tokens configured, so it serves this machine "
                                 "only; set CWRR_ADMIN_TOKEN / CWRR_THERAPIST_TOKEN to admit remote clients")
    raise HTTPException(401, "sign in: send 'Authorization: Bearer <token>' (a therapist or admin token)",
                        headers={"WWW-Authenticate": "Bearer"})


def require(needed: Role) -> Any:
    """A dependency that admits callers of role ``needed`` or higher."""

    def check(role: Annotated[Role, Depends(caller_role)]) -> Role:
        if role < needed:
            raise HTTPException(403, f"this action needs the {needed.name.lower()} role; "
                                     f"your token is a {role.name.lower()} token")
        return role

    return Depends(check)


AUTH_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"description": "No valid token (on a station with tokens): send 'Authorization: Bearer <token>'"},
    403: {"description": "The token's role may not do this, or a remote caller on a station without tokens"},
}
"""What the protected endpoints may answer, for the OpenAPI document."""

READ = Depends(caller_role)
"""Any signed-in role (or the local user)."""
THERAPIST = require(Role.THERAPIST)
"""Exercises: connect, start, stop, clear, sessions."""
ADMIN = require(Role.ADMIN)
"""Identification, tuning, parameter sets, diagnoses."""


class BodyLimit:
    """ASGI middleware: request bodies over ``max_bytes`` get 413 with the API's JSON error.

    A declared ``Content-Length`` is refused before the app runs; a chunked body
    is counted as it arrives and refused with an ``HTTPException`` (which FastAPI
    passes to the app's handler as it is). Hand-written rather than FastAPI's own
    ``max_body_size`` because that one answers a declared oversize in plain text,
    past the app's exception handlers.

    Args:
        app: The wrapped application.
        max_bytes: Largest accepted body [bytes].
        detail: The error message.
        routes: Other limits for some paths: path → (largest body [bytes], message)
            (a run-log upload is larger than any other request).
    """

    def __init__(self, app: ASGIApp, max_bytes: int, detail: str,
                 routes: dict[str, tuple[int, str]] | None = None) -> None:
        self.app, self.max_bytes, self.detail = app, max_bytes, detail
        self.routes = routes or {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        max_bytes, detail = self.routes.get(scope["path"].rstrip("/"), (self.max_bytes, self.detail))
        declared = dict(scope["headers"]).get(b"content-length", b"")
        if declared.isdigit() and int(declared) > max_bytes:
            body = json.dumps({"detail": detail}).encode()
            await send({"type": "http.response.start", "status": 413,
                        "headers": [(b"content-type", b"application/json"),
                                    (b"content-length", str(len(body)).encode())]})
            await send({"type": "http.response.body", "body": body})
            return
        seen = 0

        async def counted() -> Message:
            nonlocal seen
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > max_bytes:
                    raise HTTPException(413, detail)
            return msg

        await self.app(scope, counted, send)
