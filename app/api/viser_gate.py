"""The viser live plots behind the station's tokens.

viser serves its page and its websocket on one port and has no sign-in of its
own, so on a station with tokens anyone who could reach that port would watch
a person's live torque and pressures. There, viser listens on loopback only
(on a port the OS picks) and this gate holds the public viser port:

* ``GET /api/viser`` (any signed-in role) hands out a link carrying a
  *ticket*: single use, valid for :data:`TICKET_S`.
* Opening that link answers ``303`` to the same page without the ticket and
  sets an ``HttpOnly``, ``SameSite=Strict`` cookie holding a *viewer pass*
  valid for :data:`PASS_S`. The ticket never stays in the address bar or the
  browser's history long enough to be reused.
* Every other connection must bring a valid pass; it is then spliced byte for
  byte to viser (its page and its websocket alike). Without one the gate
  answers ``401`` with a page saying where to open the plots from.

Tickets and passes are HMAC-signed with a key drawn when the server starts,
so a restart signs every viewer out. The API never reads this cookie: it is
not a way to call the API, only to watch.

Hand-written rather than taken from a library: what is needed is a header
check in front of a raw TCP splice — no HTTP or websocket framing is parsed
after the head, so a viewer costs the interpreter one read and one write per
chunk — and the station stays one process with no reverse proxy to set up.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import secrets
import threading
import time
from collections.abc import Callable
from http.cookies import CookieError, SimpleCookie
from urllib.parse import parse_qsl, urlencode, urlsplit

TICKET_S = 60.0
"""A link from ``GET /api/viser`` must be opened within this time [s]."""
PASS_S = 12 * 3600.0
"""A browser that opened a link may watch for this long [s] (a working day)."""
HEAD_LIMIT = 16 * 1024
"""Largest request head the gate reads [bytes]; larger gets 431."""
HEAD_TIMEOUT_S = 10.0
"""A client that has not sent its request head within this time is dropped [s]."""
CHUNK = 64 * 1024

_REFUSED_PAGE = (
    "<!doctype html><meta charset='utf-8'><title>CWRR live plots: sign in</title>"
    "<body style='font-family:sans-serif;max-width:40rem;margin:3rem auto'>"
    "<h1>Sign in first</h1><p>{why}</p>"
    "<p>Open the live plots from the station's dashboard: sign in there and use "
    "<em>Open the live plots and 3-D view</em>. That link lets this browser watch for "
    "{hours:g} hours.</p></body>"
)


class Signer:
    """Signs and checks tickets and passes: ``kind.expiry.nonce.mac`` with a key of this process.

    Args:
        clock: Wall clock [s] (injected so tests can age a ticket without waiting).
    """

    def __init__(self, clock: Callable[[], float] = time.time) -> None:
        self._key = secrets.token_bytes(32)
        self._clock = clock
        self._spent: dict[str, float] = {}  # single-use tickets already opened → their expiry
        self._lock = threading.Lock()

    def _mac(self, body: str) -> str:
        return hmac.new(self._key, body.encode(), hashlib.sha256).hexdigest()

    def issue(self, kind: str, lifetime_s: float) -> str:
        """A new signed value of ``kind`` that expires ``lifetime_s`` from now."""
        body = f"{kind}.{int(self._clock() + lifetime_s)}.{secrets.token_urlsafe(12)}"
        return f"{body}.{self._mac(body)}"

    def check(self, value: str | None, kind: str, spend: bool = False) -> str | None:
        """None if ``value`` is a valid, unexpired ``kind`` (and, with ``spend``, unused); else why not."""
        if not value:
            return "no pass"
        body, _, mac = value.rpartition(".")
        parts = body.split(".")
        if len(parts) != 3 or not hmac.compare_digest(mac.encode(), self._mac(body).encode()):
            return "this pass was not issued by this station (or the station has restarted since)"
        got_kind, expiry, _nonce = parts
        now = self._clock()
        if got_kind != kind:
            return f"a {got_kind} is not a {kind}"
        if float(expiry) < now:
            return "this link has expired" if kind == "ticket" else "this browser's viewing time is over"
        if spend:
            with self._lock:
                self._spent = {k: e for k, e in self._spent.items() if e >= now}
                if body in self._spent:
                    return "this link has been used already"
                self._spent[body] = float(expiry)
        return None


def _response(status: str, headers: dict[str, str], body: bytes = b"") -> bytes:
    lines = [f"HTTP/1.1 {status}", *(f"{k}: {v}" for k, v in headers.items()),
             f"Content-Length: {len(body)}", "Connection: close", "", ""]
    return "\r\n".join(lines).encode("latin-1") + body


def _refused(status: str, why: str) -> bytes:
    page = _REFUSED_PAGE.format(why=why, hours=PASS_S / 3600.0).encode()
    return _response(status, {"Content-Type": "text/html; charset=utf-8", "Cache-Control": "no-store"}, page)


class ViserGate:
    """The public viser port of a station with tokens: checks the pass, then splices to viser.

    Runs its own event loop on a thread, so viewers never queue behind API requests.

    Args:
        host: Public bind address (the station's ``--host``).
        port: Public port (the station's ``--viser-port``).
        upstream_port: The loopback port viser itself listens on.
        signer: Signs the tickets ``GET /api/viser`` hands out and the passes the gate sets.
    """

    def __init__(self, host: str, port: int, upstream_port: int, signer: Signer,
                 public_url: str | None = None) -> None:
        self.host, self.port, self.upstream_port, self.signer = host, port, upstream_port, signer
        # where browsers reach this gate when a port mapping or a proxy stands in front: links point
        # there, and its host name is the Origin a proxied websocket arrives with
        self.public_root = public_url.rstrip("/") if public_url else None
        self.public_host = urlsplit(public_url).hostname if public_url else None
        self.cookie = f"cwrr_viser_{port}"  # cookies ignore ports: two stations on one host keep theirs apart
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.Server | None = None
        self._thread = threading.Thread(target=self._loop.run_forever, name="cwrr-viser-gate", daemon=True)

    def start(self) -> None:
        """Bind the public port (raises ``OSError`` if it is taken) and start serving."""
        self._thread.start()
        fut = asyncio.run_coroutine_threadsafe(self._bind(), self._loop)
        try:
            fut.result(10.0)
        except BaseException as exc:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(2.0)
            if isinstance(exc, OSError):
                raise OSError(exc.errno, f"the live plots cannot listen on {self.host}:{self.port} "
                                         f"({exc.strerror or exc}); choose another --viser-port, "
                                         "or 0 for no live plots") from exc
            raise

    async def _bind(self) -> None:
        self._server = await asyncio.start_server(self._serve, self.host, self.port, limit=HEAD_LIMIT)
        if self.port == 0:
            self.port = self._server.sockets[0].getsockname()[1]
            self.cookie = f"cwrr_viser_{self.port}"

    def stop(self) -> None:
        """Close the port and every viewer's connection."""
        if not self._thread.is_alive():
            return

        async def close() -> None:
            if self._server is not None:
                self._server.close()
            # each connection's task closes both its ends as it is cancelled (the finally blocks below)
            others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for t in others:
                t.cancel()
            await asyncio.gather(*others, return_exceptions=True)

        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(close(), self._loop).result(5.0)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5.0)
        if not self._thread.is_alive():
            self._loop.close()

    def link(self, host: str) -> str:
        """A fresh single-use link to the plots, at the public address if one was given.

        Args:
            host: The host name the browser reached the dashboard by.
        """
        root = self.public_root or f"http://{host}:{self.port}"
        return f"{root}/?ticket={self.signer.issue('ticket', TICKET_S)}"

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await self._handle(reader, writer)
        except (ConnectionError, OSError, asyncio.IncompleteReadError):
            pass  # a viewer that went away mid-answer
        finally:
            writer.close()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
        except asyncio.LimitOverrunError:
            writer.write(_response("431 Request Header Fields Too Large", {}))
            await writer.drain()
            return
        except (TimeoutError, asyncio.IncompleteReadError):
            return
        request_line, *lines = head.decode("latin-1").split("\r\n")
        parts = request_line.split(" ")
        if len(parts) != 3:
            writer.write(_response("400 Bad Request", {}))
            await writer.drain()
            return
        method, target, _version = parts
        headers = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines if ":" in ln)}
        url = urlsplit(target)
        query = parse_qsl(url.query, keep_blank_values=True)
        ticket = next((v for k, v in query if k == "ticket"), None)
        if ticket is not None:
            why = self.signer.check(ticket, "ticket", spend=True)
            if why is not None or method != "GET":
                writer.write(_refused("401 Unauthorized", why or "a link is opened with GET"))
            else:
                # the page again without the ticket, now with a pass the browser sends on its own
                rest = urlencode([(k, v) for k, v in query if k != "ticket"])
                # always this server's root (viser serves its page there): a path such as
                # "//elsewhere" must not turn the answer into a redirect to another site
                location = "/" + (f"?{rest}" if rest else "")
                cookie = (f"{self.cookie}={self.signer.issue('pass', PASS_S)}; Max-Age={int(PASS_S)}; "
                          "Path=/; HttpOnly; SameSite=Strict")
                writer.write(_response("303 See Other", {"Location": location, "Set-Cookie": cookie,
                                                         "Cache-Control": "no-store"}))
            await writer.drain()
            return
        why = self.signer.check(self._pass_of(headers.get("cookie", "")), "pass")
        if why is None and not self._same_host(headers):
            why = "the page asking comes from another site"
        if why is not None:
            writer.write(_refused("401 Unauthorized", why))
            await writer.drain()
            return
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.upstream_port)
        up_writer.write(head)
        pipes = {asyncio.ensure_future(self._pipe(reader, up_writer)),
                 asyncio.ensure_future(self._pipe(up_reader, writer))}
        try:
            # either side ending ends both: a viewer gone without a word must not hold viser's end open
            await asyncio.wait(pipes, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for p in pipes:
                p.cancel()
            up_writer.close()

    def _pass_of(self, cookie_header: str) -> str | None:
        try:
            morsel = SimpleCookie(cookie_header).get(self.cookie)
        except CookieError:
            return None
        return morsel.value if morsel is not None else None

    def _same_host(self, headers: dict[str, str]) -> bool:
        # SameSite=Strict already keeps the pass off other sites' requests; a websocket's Origin
        # is checked as well, because browsers send it and a pass must not be ridden from elsewhere
        origin = headers.get("origin")
        if origin is None or origin == "null":
            return origin is None
        host = headers.get("host", "")
        seen = urlsplit(origin).hostname
        # behind a proxy the Host header may be the proxy's upstream name; the public one counts too
        return seen == urlsplit(f"//{host}").hostname or (self.public_host is not None and seen == self.public_host)

    @staticmethod
    async def _pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
        try:
            while data := await src.read(CHUNK):
                dst.write(data)
                await dst.drain()
        except (ConnectionError, OSError):
            pass
