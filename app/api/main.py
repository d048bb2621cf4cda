"""Application factory: the lifespan owns the station, the store and the live plots; routers stay thin."""

from __future__ import annotations

import logging
import math
import re
import socket
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fastapi import Depends, FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse, Response
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.api.auth import READ, BodyLimit, Role, presented_role
from app.api.deps import known_query_only
from app.api.jobs import Jobs
from app.api.models import AuthInfo, ViserInfo
from app.api.routers import diagnoses, engine, params, runs, sessions
from app.api.settings import Settings
from app.api.viser_gate import TICKET_S, Signer, ViserGate
from app.engine.hardware.config import load_config
from app.engine.params import ParameterError
from app.engine.station import Station, TransitionError
from app.storage import Store, StoreUnavailable, claim_data_dir, release_data_dir

if TYPE_CHECKING:
    from app.api.liveplots import LivePlots

STATIC = Path(__file__).resolve().parent.parent / "static"
BODY_ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"description": "The body is not readable JSON"},
    413: {"description": "The body is larger than CWRR_MAX_BODY_BYTES (CWRR_MAX_UPLOAD_BYTES for a run-log upload)"}}
"""What any call with a body may answer; the OpenAPI document lists them on those calls only."""
TAGS: list[dict[str, Any]] = [
    {"name": "engine", "description": "The station's state machine (disconnected → idle → running or identifying "
                                      "→ idle, a latched fault), exercises, identification, tuning, the emergency "
                                      "stop, live samples and the health of the control loop."},
    {"name": "runs", "description": "Stored runs (exercises, identifications, protocols, diagnoses): their "
                                    "metrics, results and logs, exports as CSV, Parquet or MATLAB .mat, logs "
                                    "recorded elsewhere, and an exercise beside the other controllers."},
    {"name": "parameters", "description": "Parameter sets checked by the thesis GUIs' rules: friction, "
                                          "controller gains, fuzzy universes, scenario settings."},
    {"name": "sessions", "description": "Therapy sessions: a person's pseudonymous id, notes, and the runs "
                                        "made under them."},
    {"name": "diagnoses", "description": "The sim-to-real gap diagnosis: the protocol, ranges for the "
                                         "recalibration, running one on stored runs, its traces."},
    {"name": "auth", "description": "Whether this station needs a token, and what the one sent may do."},
]
"""The groups of /docs, each with what it holds."""
DOCS_ASSETS = "/static-docs"
"""Where /docs and /redoc load Swagger UI's and ReDoc's scripts from (fastapi-offline's copies)."""
log = logging.getLogger(__name__)


def station_name(data_dir: str | Path) -> str:
    """This station in the store: its folder's lasting id, with the host and folder for a reader.

    The id is made once and kept in ``DATA_DIR/.station-id``: a container
    recreated on the same volume gets a new host name but is the same
    station, and must call its own killed runs interrupted.
    """
    folder = Path(data_dir).resolve()
    path = folder / ".station-id"
    try:
        sid = path.read_text(encoding="utf-8").strip()
    except FileNotFoundError:
        sid = ""
    if not sid:
        from app.engine.runlog import atomic_write_text

        sid = uuid.uuid4().hex
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, sid + "\n")  # the folder is claimed (claim_data_dir): no other station writes it
    return f"{sid} {socket.gethostname()}:{folder}"


def repair_interrupted_logs(store: Store, data_dir: str | Path) -> list[int]:
    """Repair the logs of the runs a crash or kill left running (those in this station's folder).

    Returns:
        The ids of the runs whose log was repaired.
    """
    from app.engine.runlog import repair_log

    folder = Path(data_dir).resolve()
    repaired = []
    for run_id, csv in store.interrupted_at_open:
        path = Path(csv).resolve() if csv else None
        if path is None or not path.is_relative_to(folder):
            continue
        try:
            if repair_log(path) is not None:
                repaired.append(run_id)
        except OSError as exc:  # one unreadable log keeps the station from starting no more than before
            log.warning("run %d: its log %s could not be repaired (%s)", run_id, path, exc)
    return repaired


def _json_safe(v: Any) -> Any:
    """``v`` with every non-finite float written as text (``"nan"``, ``"inf"``): JSON has no such number."""
    if isinstance(v, float) and not math.isfinite(v):
        return repr(v)
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_safe(x) for x in v]
    return v


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app; the engine, store and viser server start and stop with the lifespan."""
    settings = settings or Settings()

    # read here, not in the lifespan: a wrong file is refused with the field named before a server starts
    hardware = load_config(settings.hardware) if settings.hardware else None

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        claim_data_dir(settings.data_dir)  # one station per data folder (cwrr serve claimed it already)
        try:
            async with _station_lifespan(app):
                yield
        finally:
            release_data_dir(settings.data_dir)

    @asynccontextmanager
    async def _station_lifespan(app: FastAPI) -> AsyncIterator[None]:
        store = Store(settings.db_url, station=station_name(settings.data_dir))
        repair_interrupted_logs(store, settings.data_dir)
        station = Station(data_dir=settings.data_dir, sink=store,
                          rate_hz=hardware.rate_hz if hardware is not None else settings.rate_hz,
                          realtime=settings.realtime, stall_s=settings.watchdog_s,
                          hardware=hardware, hardware_path=settings.hardware or None)
        app.state.store, app.state.station = store, station
        app.state.jobs = jobs = Jobs()
        plots: LivePlots | None = None
        gate: ViserGate | None = None
        if settings.start_engine:
            # the live plots first: what viser and the radar charts import and build is then in
            # the heap that connect collects and freezes before the loop runs (Station.connect)
            if settings.viser_port:
                from app.api.liveplots import LivePlots

                if settings.auth_enabled:
                    # viser has no sign-in: it listens on loopback and the gate holds the public port
                    plots = LivePlots(station, "127.0.0.1", 0, store)
                    gate = ViserGate(settings.host, settings.viser_port, plots.server.get_port(), Signer(),
                                     settings.viser_public_url or None)
                    try:
                        gate.start()
                    except BaseException:
                        plots.stop()
                        raise
                else:
                    plots = LivePlots(station, settings.host, settings.viser_port, store)
                plots.start()
            if settings.auto_connect:
                station.connect()
        app.state.plots, app.state.viser_gate = plots, gate
        try:
            yield
        finally:
            if gate is not None:
                gate.stop()
            if plots is not None:
                plots.stop()
            jobs.shutdown()  # before the store closes: a stopped job records itself as cancelled
            station.close()
            store.close()

    # FastAPI's /docs and /redoc load Swagger UI and ReDoc from a CDN (and fonts from Google): a station
    # beside a rig is often offline, and their pages stayed blank. FastAPIOffline serves the same
    # scripts from the installed package (DOCS_ASSETS)
    app = FastAPIOffline(title="CWRR Lab Station", version="0.2.0", lifespan=lifespan,
                         dependencies=[Depends(known_query_only)], favicon_url="/static/favicon.svg",
                         generate_unique_id_function=operation_id, openapi_tags=TAGS,
                         static_url=DOCS_ASSETS,
                         description="Control station of the pneumatic wrist/forearm rehabilitation robot (CWRR).",
                         responses={**BODY_ERRORS,
                                    503: {"description": "The run store cannot be used now (a full disk, a locked "
                                                         "or unreachable database); the detail says which"}},
                         )
    app.state.settings = settings
    too_large = (f"request body too large: the limit is {settings.max_body_bytes} bytes "
                 f"(CWRR_MAX_BODY_BYTES)")

    upload_too_large = (f"run log too large: the upload limit is {settings.max_upload_bytes} bytes "
                        f"(CWRR_MAX_UPLOAD_BYTES); split the log into experiments")
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes, detail=too_large,
                       routes={"/api/runs": (settings.max_upload_bytes, upload_too_large)})

    if settings.cors_origins:  # closed unless a lab names the pages that may call the API
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins, allow_credentials=False,
                           allow_methods=["GET", "POST"], allow_headers=["Authorization", "Content-Type"])

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        headers = dict(exc.headers or {})
        if exc.status_code == 413:  # BodyLimit raised it with the limit of the route
            return JSONResponse(status_code=413, content={"detail": exc.detail})
        if exc.status_code == 405:
            # Starlette names only the first matching route's methods; a path served by
            # several routes (GET and POST /api/params) must list them all
            path = request.url.path
            methods = {m for r in request.app.router.routes
                       if getattr(r, "methods", None) and r.path_regex.match(path)  # type: ignore[attr-defined]
                       for m in r.methods}  # type: ignore[attr-defined]
            headers["Allow"] = ", ".join(sorted(methods))
        return await http_exception_handler(request, StarletteHTTPException(exc.status_code, exc.detail, headers))

    @app.exception_handler(RequestValidationError)
    async def unprocessable(request: Request, exc: RequestValidationError) -> JSONResponse:
        # FastAPI's own handler echoes each refused input, and a NaN or Infinity sent by a script
        # (Python's json writes them) made that answer itself fail: a 500 instead of the 422
        return JSONResponse(status_code=422, content={"detail": _json_safe(jsonable_encoder(exc.errors()))})

    @app.exception_handler(StoreUnavailable)
    async def store_unavailable(request: Request, exc: StoreUnavailable) -> JSONResponse:
        return JSONResponse(status_code=503, content={"detail": str(exc)})

    @app.exception_handler(TransitionError)
    async def conflict(request: Request, exc: TransitionError) -> JSONResponse:
        return JSONResponse(status_code=409, content={"detail": str(exc), "state": exc.state.value})

    @app.exception_handler(ParameterError)
    async def invalid(request: Request, exc: ParameterError) -> JSONResponse:
        # "field: message" names the field; "field = value: why" keeps the value in the message
        head, _sep, msg = str(exc).partition(": ")
        m = re.fullmatch(r"([A-Za-z_]\w*)( = .*)?", head)
        if not msg or m is None:
            field, msg = "body", str(exc)
        else:
            field = m.group(1)
            msg = str(exc) if m.group(2) else msg
        return JSONResponse(status_code=422, content={"detail": [{"loc": ["body", field], "msg": msg,
                                                                  "type": "value_error"}]})

    app.include_router(engine.router)
    app.include_router(runs.router)
    app.include_router(runs.exercises_router)
    app.include_router(params.router)
    app.include_router(sessions.router)
    app.include_router(diagnoses.router)

    @app.get("/api/viser", tags=["engine"], response_model=ViserInfo, summary="Where the live plots are served",
             dependencies=[READ])
    def viser_url(request: Request) -> ViserInfo:
        """The live plots' address for this browser (null when viser is off); on a station with tokens a
        signed link that expires (`expires_s`)."""
        if getattr(request.app.state, "plots", None) is None:
            return ViserInfo(url=None, expires_s=None)
        host = request.url.hostname or settings.host
        gate: ViserGate | None = request.app.state.viser_gate
        if gate is not None:
            return ViserInfo(url=gate.link(host), expires_s=TICKET_S)
        if settings.viser_public_url:
            return ViserInfo(url=settings.viser_public_url.rstrip("/"), expires_s=None)
        # the port viser bound: it takes the next free one when the asked one is in use
        return ViserInfo(url=f"http://{host}:{request.app.state.plots.server.get_port()}", expires_s=None)

    @app.get("/api/auth", tags=["auth"], response_model=AuthInfo,
             summary="Whether a token is needed, and the role of the one sent (needs none itself)")
    def auth_info(request: Request) -> AuthInfo:
        """Whether this station needs tokens (once they are configured; a bind address other than loopback
        requires them), and the role of the `Authorization: Bearer` token sent, if any."""
        role = presented_role(request)
        return AuthInfo(required=settings.auth_enabled,
                        role="admin" if role == Role.ADMIN else "therapist" if role == Role.THERAPIST else None)

    static = RevalidatedStaticFiles(directory=STATIC)

    @app.api_route("/", methods=["GET", "HEAD"], include_in_schema=False)  # HEAD: a monitor's "is it up"
    async def index(request: Request) -> Response:
        return await static.get_response("index.html", request.scope)

    app.mount("/static", static, name="static")
    base_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            spec = base_openapi()
            integral_bounds(spec)  # FastAPI's schema models hold every bound as a float
            for ops in spec["paths"].values():
                for op in ops.values():
                    if "requestBody" not in op:  # a call without a body cannot send unreadable or large ones
                        for code in BODY_ERRORS:
                            op["responses"].pop(str(code), None)
            if not settings.auth_enabled:
                without_tokens(spec)
        return app.openapi_schema  # type: ignore[return-value]

    app.openapi = openapi  # type: ignore[method-assign]
    return app


class RevalidatedStaticFiles(StaticFiles):
    """The pages, their scripts and their stylesheet, each revalidated at every load (its ETag answers
    304 while it is unchanged). Without a Cache-Control a browser keeps a file for a share of its age
    as it sees fit: after an update of the station a page could run with a script of the version before."""

    def file_response(self, *args: Any, **kwargs: Any) -> Response:
        response = super().file_response(*args, **kwargs)
        response.headers["Cache-Control"] = "no-cache"
        return response


def operation_id(route: APIRoute) -> str:
    """An operation's id in the OpenAPI document: its tag and handler, ``runs-list_runs``.

    What a generated client names its methods by (FastAPI's own default,
    ``list_runs_api_runs_get``, repeats the path and the method).
    """
    return f"{route.tags[0]}-{route.name}" if route.tags else route.name


def without_tokens(spec: dict[str, Any]) -> None:
    """Take the bearer scheme out of an OpenAPI document, in place: this station has no tokens.

    It then serves its own machine and ignores an ``Authorization`` header
    (:mod:`app.api.auth`), so a document declaring one would promise refusals
    that never come: a client would be told to send a token nobody checks.
    """
    for ops in spec.get("paths", {}).values():
        for op in ops.values():
            op.pop("security", None)
    spec.get("components", {}).pop("securitySchemes", None)


_BOUNDS = ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum", "multipleOf")


def integral_bounds(node: Any) -> None:
    """Give an integer's bounds back as integers, in place, throughout a schema.

    FastAPI's OpenAPI models type them as floats, so an id's ``le=2**62`` reached ``/openapi.json``
    as ``4.611686018427388e+18`` and a magnitude's ``le=2`` as ``2.0``: a typed client generated from it
    gets float bounds on integer fields, and schema checkers report the mismatch. A bound beside an
    ``anyOf`` (an optional query parameter's) counts when every typed branch is an integer or null.
    """
    if isinstance(node, list):
        for item in node:
            integral_bounds(item)
        return
    if not isinstance(node, dict):
        return
    # "type" is a schema keyword here, or the name of a property (a dict) in a properties mapping
    branches = [node, *(b for b in node.get("anyOf", []) if isinstance(b, dict))]
    types = {t if isinstance(t, str) else "" for t in (b.get("type") for b in branches)}
    if "integer" in types and types <= {"integer", "null", None}:
        for key in _BOUNDS:
            v = node.get(key)
            if isinstance(v, float) and v.is_integer():
                node[key] = int(v)
    for value in node.values():
        integral_bounds(value)
