"""Issue 7 item 6 for the live plots: on a station with tokens, only a signed-in browser may watch.

viser has no sign-in, so there it listens on loopback and ``app.api.viser_gate``
holds the public viser port. These tests talk to that port over real sockets:
its page and its websocket are refused without a pass, a link from
``GET /api/viser`` gives one exactly once, and with it viser answers as usual.
"""

from __future__ import annotations

import http.client
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr

from app.api.main import create_app
from app.api.settings import Settings
from app.api.viser_gate import PASS_S, TICKET_S, Signer
from tests.conftest import free_port, viser_viewer

THERAPIST = "thr-" + "9a8b7c6d5e4f3a2b1c0d"
ADMIN = "adm-" + "1a2b3c4d5e6f7a8b9c0d"


@pytest.fixture(scope="module")
def gated(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, int]]:
    vport = free_port()
    s = Settings(data_dir=str(tmp_path_factory.mktemp("gate")), viser_port=vport, auto_connect=False,
                 admin_token=ADMIN, therapist_token=THERAPIST)  # type: ignore[arg-type]
    with TestClient(create_app(s)) as c:
        yield c, vport


def _get(port: int, path: str, headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], str]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("GET", path, headers=headers or {})
        r = conn.getresponse()
        return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read().decode("utf-8", "replace")
    finally:
        conn.close()


def _link(c: TestClient) -> str:
    r = c.get("/api/viser", headers={"Authorization": f"Bearer {THERAPIST}"})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["expires_s"] == TICKET_S
    url: str = body["url"]
    return url[url.index("/", len("http://")):]  # the path and query on the viser port


def _open_link(c: TestClient, port: int) -> str:
    """Open a fresh link as a browser would; returns the Cookie header the browser then sends."""
    status, headers, _ = _get(port, _link(c))
    assert status == 303, (status, headers)
    return headers["set-cookie"].split(";", 1)[0]


# ------------------------------------------------------------------ tickets and passes


def test_a_ticket_is_valid_once_and_only_until_it_expires() -> None:
    now = [1000.0]
    s = Signer(clock=lambda: now[0])
    t = s.issue("ticket", 60.0)
    assert s.check(t, "pass") == "a ticket is not a pass"
    assert s.check(t, "ticket", spend=True) is None
    assert s.check(t, "ticket", spend=True) == "this link has been used already"
    late = s.issue("ticket", 60.0)
    now[0] += 61.0
    assert s.check(late, "ticket", spend=True) == "this link has expired"


def test_a_forged_or_foreign_pass_is_refused() -> None:
    s, other = Signer(), Signer()
    p = s.issue("pass", 60.0)
    kind, expiry, nonce, mac = p.split(".")
    assert s.check(p, "pass") is None
    for bad in (other.issue("pass", 60.0),                      # another station (or before a restart)
                f"{kind}.{int(expiry) + 10**6}.{nonce}.{mac}",   # lifetime stretched by hand
                p[:-1] + ("0" if p[-1] != "0" else "1"),         # signature altered
                "pass", "", None):
        assert s.check(bad, "pass") is not None, bad


# ------------------------------------------------------------------ the gate on a running station


def test_viser_itself_listens_on_loopback_only(gated: tuple[TestClient, int]) -> None:
    c, port = gated
    plots = c.app.state.plots  # type: ignore[attr-defined]
    assert plots.server.get_host() == "127.0.0.1"
    assert plots.server.get_port() != port


def test_without_a_pass_the_page_and_the_websocket_are_refused(gated: tuple[TestClient, int]) -> None:
    from websockets.exceptions import InvalidStatus

    c, port = gated
    status, _, page = _get(port, "/")
    assert status == 401 and "Sign in first" in page and "no pass" in page
    with pytest.raises(InvalidStatus) as e:
        viser_viewer(port, {})
    assert e.value.response.status_code == 401
    # the API hands out links to signed-in callers only
    assert c.get("/api/viser").status_code == 401


def test_a_link_signs_the_browser_in_once_and_viser_then_answers(gated: tuple[TestClient, int]) -> None:
    c, port = gated
    link = _link(c)
    status, headers, _ = _get(port, link + "&darkMode")
    assert status == 303
    assert headers["location"] == "/?darkMode="  # the ticket leaves the address, other options stay
    cookie = headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and f"Max-Age={int(PASS_S)}" in cookie
    status, _, page = _get(port, link)
    assert status == 401 and "used already" in page
    # browsers read "/\\host" as "//host": a path copied into the redirect would send them there
    status, headers, _ = _get(port, "/\\elsewhere.example" + _link(c))
    assert status == 303 and headers["location"] == "/"
    status, headers, page = _get(port, "/", {"Cookie": cookie.split(";", 1)[0]})
    assert status == 200 and headers["content-type"].startswith("text/html") and "<title>Viser</title>" in page


def test_with_a_pass_the_websocket_reaches_viser(gated: tuple[TestClient, int]) -> None:
    c, port = gated
    cookie = _open_link(c, port)
    with viser_viewer(port, {"Cookie": cookie, "Origin": f"http://127.0.0.1:{port}"}) as ws:
        first = ws.recv(timeout=10)
    assert isinstance(first, bytes) and len(first) > 0  # viser's msgpack state for a new client


def test_a_pass_cannot_be_ridden_from_another_site(gated: tuple[TestClient, int]) -> None:
    from websockets.exceptions import InvalidStatus

    c, port = gated
    cookie = _open_link(c, port)
    with pytest.raises(InvalidStatus) as e:
        viser_viewer(port, {"Cookie": cookie, "Origin": "http://evil.example"})
    assert e.value.response.status_code == 401
    assert b"another site" in e.value.response.body


def test_without_tokens_the_link_goes_straight_to_viser(tmp_path: Path) -> None:
    s = Settings(data_dir=str(tmp_path), viser_port=free_port(), auto_connect=False)
    with TestClient(create_app(s)) as c:
        body = c.get("/api/viser").json()
        assert c.app.state.viser_gate is None  # type: ignore[attr-defined]
        assert body == {"url": f"http://testserver:{c.app.state.plots.server.get_port()}",  # type: ignore[attr-defined]
                        "expires_s": None}


def test_behind_a_port_mapping_or_a_proxy_the_link_names_the_public_address(tmp_path: Path) -> None:
    """``viser_public_url``: the link points there, and a proxy's forwarded websocket (Host the
    upstream name, Origin the public one) is let through while other sites stay refused."""
    from websockets.exceptions import InvalidStatus

    vport = free_port()
    s = Settings(data_dir=str(tmp_path), viser_port=vport, auto_connect=False,
                 admin_token=SecretStr(ADMIN), therapist_token=SecretStr(THERAPIST),
                 viser_public_url="https://plots.lab.example:9443/")
    with TestClient(create_app(s)) as c:
        url = c.get("/api/viser", headers={"Authorization": f"Bearer {THERAPIST}"}).json()["url"]
        assert url.startswith("https://plots.lab.example:9443/?ticket="), url
        status, headers, _ = _get(vport, url[url.index("/?"):])  # what the proxy forwards
        assert status == 303 and headers["location"] == "/"
        cookie = headers["set-cookie"].split(";", 1)[0]
        with viser_viewer(vport, {"Cookie": cookie, "Origin": "https://plots.lab.example:9443"}) as ws:
            assert isinstance(ws.recv(timeout=10), bytes)
        with pytest.raises(InvalidStatus) as e:
            viser_viewer(vport, {"Cookie": cookie, "Origin": "https://evil.example"})
        assert e.value.response.status_code == 401
    s = Settings(data_dir=str(tmp_path), viser_port=free_port(), auto_connect=False,
                 viser_public_url="http://station.lab.example:9080")
    with TestClient(create_app(s)) as c:
        assert c.get("/api/viser").json() == {"url": "http://station.lab.example:9080", "expires_s": None}


@pytest.mark.parametrize(("url", "words"), [
    ("ftp://station:21", "must look like http://host:port"),
    ("station:9080", "must look like http://host:port"),
    ("http://station:9080/plots", "served at the root"),
    ("http://station:9080/?x=1", "served at the root"),
    ("http://user:secret@station:9080", "user name or password"),
    ("http://station:99999", "not a URL"),
])
def test_a_public_address_that_cannot_work_is_refused(tmp_path: Path, url: str, words: str) -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match=words) as e:
        Settings(data_dir=str(tmp_path), viser_public_url=url)
    assert "secret" not in str(e.value)


def test_a_taken_viser_port_stops_the_start_with_the_reason(tmp_path: Path) -> None:
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        s = Settings(data_dir=str(tmp_path), viser_port=taken.getsockname()[1], auto_connect=False,
                     admin_token=ADMIN)  # type: ignore[arg-type]
        with pytest.raises(OSError, match="choose another --viser-port"), TestClient(create_app(s)):
            pass


def test_shutting_down_closes_the_viewers_connections(tmp_path: Path) -> None:
    import time

    from websockets.exceptions import ConnectionClosed

    vport = free_port()
    s = Settings(data_dir=str(tmp_path), viser_port=vport, auto_connect=False,
                 admin_token=ADMIN, therapist_token=THERAPIST)  # type: ignore[arg-type]
    with TestClient(create_app(s)) as c:
        ws = viser_viewer(vport, {"Cookie": _open_link(c, vport)})
        ws.recv(timeout=10)
        t0 = time.monotonic()
    assert time.monotonic() - t0 < 10.0
    with pytest.raises(ConnectionClosed):
        while True:  # what viser had sent before the end may still be buffered
            ws.recv(timeout=5)
    ws.close()


def _raw(port: int, data: bytes) -> bytes:
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(data)
        s.shutdown(socket.SHUT_WR)  # all sent: the gate sees the end of the request
        chunks = []
        while chunk := s.recv(65536):
            chunks.append(chunk)
    return b"".join(chunks)


def test_malformed_requests_get_a_clear_answer_and_the_gate_keeps_serving(gated: tuple[TestClient, int]) -> None:
    c, port = gated
    assert _raw(port, b"HELLO\r\n\r\n").startswith(b"HTTP/1.1 400 ")
    big = b"GET / HTTP/1.1\r\nHost: x\r\nX-Pad: " + b"a" * 40_000 + b"\r\n\r\n"
    assert _raw(port, big).startswith(b"HTTP/1.1 431 ")
    assert _raw(port, b"GET / HTTP/1.1\r\n") == b""  # a client that hangs up mid-head gets nothing
    forged = b"GET /?ticket=ticket.99999999999.x.deadbeef HTTP/1.1\r\nHost: x\r\n\r\n"
    assert b"not issued by this station" in _raw(port, forged)
    status, _, _ = _get(port, "/", {"Cookie": _open_link(c, port)})
    assert status == 200
