"""A minimal client of the station's REST API for scripts: one JSON request at a time, refusals in the
station's own words. Standard library only; the examples beside it use it."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from typing import Any


class Refused(Exception):
    """The station answered with an error; the message is its own."""


class Station:
    """The station's REST API, one JSON request at a time.

    Args:
        url: The station's address, e.g. ``http://127.0.0.1:8000``.
        token: An API token, or "" on a station without tokens (bound to loopback).
    """

    def __init__(self, url: str, token: str = "") -> None:
        self.url = url.rstrip("/")
        self.headers = {"Content-Type": "application/json"}
        if token:
            self.headers["Authorization"] = f"Bearer {token}"

    def raw(self, method: str, path: str, body: dict[str, Any] | None = None) -> bytes:
        """One request; the answer's bytes. Raises :class:`Refused` with the station's reason."""
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.url + path, data=data, method=method, headers=self.headers)
        try:
            with urllib.request.urlopen(req, timeout=30) as r:
                return bytes(r.read())
        except urllib.error.HTTPError as e:
            try:
                detail = json.loads(e.read()).get("detail")
            except ValueError:
                detail = e.reason
            if isinstance(detail, list):  # a 422: each refused field with its message
                detail = "; ".join(f"{'.'.join(str(x) for x in d.get('loc', [])[1:])}: {d.get('msg')}"
                                   for d in detail)
            raise Refused(f"{method} {path} → {e.code}: {detail}") from None
        except urllib.error.URLError as e:
            raise Refused(f"the station at {self.url} did not answer ({e.reason})") from None

    def call(self, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
        """One request; the answer's JSON."""
        return json.loads(self.raw(method, path, body))
