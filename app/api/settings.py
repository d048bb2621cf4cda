"""Server configuration (environment variables prefixed ``CWRR_``)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Station settings.

    Attributes:
        host: Bind address.
        port: HTTP port.
        viser_port: Port of the viser live-plot server (0: no viser).
        rate_hz: Control rate [Hz].
        data_dir: Where run logs and the SQLite store live.
        database_url: Run store; default ``sqlite:///<data_dir>/cwrr.sqlite3``.
        auto_connect: Connect to the backend (the simulator) at start-up.
        start_engine: Whether the lifespan touches the engine at all (tests of
            the API surface alone may say no).
        realtime: Run the control loop at SCHED_FIFO priority where allowed
            (root or CAP_SYS_NICE); ``/api/health`` reports whether it took.
    """

    model_config = SettingsConfigDict(env_prefix="CWRR_")

    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 8000
    viser_port: Annotated[int, Field(ge=0, le=65535)] = 8080
    rate_hz: Annotated[float, Field(ge=10.0, le=2000.0)] = 200.0
    data_dir: str = "data"
    database_url: str = ""
    auto_connect: bool = True
    start_engine: bool = True
    realtime: bool = True

    @property
    def db_url(self) -> str:
        """The effective database URL."""
        return self.database_url or f"sqlite:///{self.data_dir}/cwrr.sqlite3"
