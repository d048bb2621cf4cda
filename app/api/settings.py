"""Server configuration (environment variables prefixed ``CWRR_``)."""

from __future__ import annotations

from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Station settings.

    Attributes:
        host: Bind address.
        port: HTTP port.
        viser_port: Port of the viser live-plot server.
        rate_hz: Control rate [Hz].
        data_dir: Where run logs and the SQLite store live.
        start_engine: Start the engine thread with the app (tests may not).
    """

    model_config = SettingsConfigDict(env_prefix="CWRR_")

    host: str = "127.0.0.1"
    port: int = 8000
    viser_port: int = 8080
    rate_hz: float = 200.0
    data_dir: str = "data"
    start_engine: bool = True
