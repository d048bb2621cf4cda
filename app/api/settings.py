"""Server configuration (environment variables prefixed ``CWRR_``)."""

from __future__ import annotations

import ipaddress
from typing import Annotated
from urllib.parse import urlsplit

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from app.storage import database_dialect

MIN_TOKEN_CHARS = 16


class Settings(BaseSettings):
    """Station settings.

    Attributes:
        host: Bind address.
        port: HTTP port.
        viser_port: Port of the viser live-plot server (0: no viser).
        viser_public_url: Where browsers reach the live plots, ``http[s]://host[:port]``,
            when that is not this host's ``viser_port`` (a container's port
            mapping, a reverse proxy); empty: the dashboard's own host name
            and ``viser_port``.
        rate_hz: Control rate [Hz].
        data_dir: Where run logs and the SQLite store live.
        database_url: Run store; default ``sqlite:///<data_dir>/cwrr.sqlite3``.
        auto_connect: Connect to the backend (the simulator) at start-up.
        start_engine: Whether the lifespan touches the engine at all (tests of
            the API surface alone may say no).
        realtime: Run the control loop at SCHED_FIFO priority where allowed
            (root or CAP_SYS_NICE); ``/api/health`` reports whether it took.
        admin_token: Bearer token of the admin role (identification, tuning,
            parameter sets, diagnoses, and all a therapist may do).
        therapist_token: Bearer token of the therapist role (exercises, sessions).
        cors_origins: Browser origins allowed to call the API from other pages
            (none by default: the dashboard is served by this server).
        max_body_bytes: Largest request body [bytes]; larger ones get 413.
        max_upload_bytes: Largest run-log upload (``POST /api/runs``)
            [bytes]; 64 MiB holds ≈ 50 minutes of a 200 Hz log.
        watchdog_s: The engine watchdog's stall time [s] (see ``Engine``).
        hardware: Path of the YAML hardware configuration (backend, channels,
            scaling, calibration); empty: the embedded simulator.
    """

    # hide_input_in_errors: a refused setting must not echo the environment (tokens) into a log
    model_config = SettingsConfigDict(env_prefix="CWRR_", hide_input_in_errors=True)

    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 8000
    viser_port: Annotated[int, Field(ge=0, le=65535)] = 8080
    viser_public_url: str = ""
    rate_hz: Annotated[float, Field(ge=10.0, le=2000.0)] = 200.0
    data_dir: str = "data"
    database_url: str = ""
    auto_connect: bool = True
    start_engine: bool = True
    realtime: bool = True
    admin_token: SecretStr | None = None
    therapist_token: SecretStr | None = None
    cors_origins: list[str] = []
    max_body_bytes: Annotated[int, Field(ge=1024, le=1 << 30)] = 1 << 20
    max_upload_bytes: Annotated[int, Field(ge=1024, le=1 << 30)] = 64 << 20
    watchdog_s: Annotated[float, Field(gt=0.0, le=60.0)] = 1.0
    hardware: str = ""

    @model_validator(mode="after")
    def _access_rules(self) -> Settings:
        tokens = {name: t.get_secret_value() for name, t in
                  (("admin_token", self.admin_token), ("therapist_token", self.therapist_token)) if t is not None}
        for name, value in tokens.items():
            if len(value) < MIN_TOKEN_CHARS or value != value.strip():
                # the value itself is never echoed: error messages end up in logs
                raise ValueError(f"{name} must be at least {MIN_TOKEN_CHARS} characters with no surrounding spaces "
                                 f"(e.g. python -c 'import secrets; print(secrets.token_urlsafe(24))')")
        if len(tokens) == 2 and len(set(tokens.values())) == 1:
            raise ValueError("admin_token and therapist_token must differ (a role is known by its token)")
        if not tokens and not is_loopback(self.host):
            raise ValueError(f"host = {self.host!r} would open the rig to the network without authentication: "
                             f"set CWRR_ADMIN_TOKEN (and optionally CWRR_THERAPIST_TOKEN), or bind to 127.0.0.1")
        if self.database_url:
            # said before the server compiles for a minute (the store had refused it only at start-up)
            database_dialect(self.database_url)
        if self.viser_public_url:
            check_public_url(self.viser_public_url)
        if "*" in self.cors_origins:
            raise ValueError("cors_origins: '*' would let any web page drive the rig; list the origins")
        return self

    @property
    def auth_enabled(self) -> bool:
        """Whether requests must carry a token."""
        return self.admin_token is not None or self.therapist_token is not None

    @property
    def db_url(self) -> str:
        """The effective database URL."""
        return self.database_url or f"sqlite:///{self.data_dir}/cwrr.sqlite3"


def check_public_url(url: str) -> None:
    """Refuse a live-plot address that is not ``http[s]://host[:port]``.

    The gate always sends a signed-in browser to the root of that address, so
    a path, query or fragment could not be honoured; say so instead of
    producing links that do not work.

    Raises:
        ValueError: Naming what is wrong.
    """
    # a URL with credentials in it is never echoed: these messages end up in logs
    shown = "(the URL given)" if "@" in url else repr(url)
    try:
        u = urlsplit(url)
        port = u.port  # raises on a port that is not a number in 0–65535
    except ValueError as exc:
        raise ValueError(f"viser_public_url = {shown}: not a URL ({exc})") from None
    if port == 0:
        raise ValueError(f"viser_public_url = {shown}: port 0 cannot be reached")
    if u.scheme not in ("http", "https") or not u.hostname:
        raise ValueError(f"viser_public_url = {shown} must look like http://host:port or https://host")
    if u.username is not None or u.password is not None:
        raise ValueError("viser_public_url must not carry a user name or password")
    if u.path not in ("", "/") or u.query or u.fragment:
        raise ValueError(f"viser_public_url = {shown}: the live plots are served at the root of their "
                         "address; give scheme, host and port only")


def is_loopback(host: str) -> bool:
    """Whether a bind address is this machine only (``localhost`` counts)."""
    if host == "localhost":
        return True
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return False
    mapped = getattr(ip, "ipv4_mapped", None)  # ::ffff:127.0.0.1 is loopback too
    return bool(ip.is_loopback or (mapped is not None and mapped.is_loopback))
