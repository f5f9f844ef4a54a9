"""The lab's web server: static pages, a status API, and one websocket (one session) per open page.

Protocol of ``/ws/{page}?seed=S&hz=H``:

* server -> browser, text: ``hello`` (scalar names, parameters, actions, values, notices, world bounds) once, then
  ``state`` after every accepted command, ``error`` (with a message) for every rejected one;
* server -> browser, binary: frames (``slam2d.web.frames``) at ``hz`` per second (default 60, 1..120);
* browser -> server, text JSON, at most ``MAX_COMMAND_BYTES``: ``{"type":"key","key":"ArrowUp","down":true}``,
  ``{"type":"param","name":"sensor_range_m","value":6}``, ``{"type":"action","name":"reset"}``,
  ``{"type":"ping"}``. Anything else is answered with an ``error`` message; the session carries on.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from pathlib import Path
from typing import Any

from fastapi import FastAPI, WebSocket
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.websockets import WebSocketDisconnect, WebSocketState

from slam2d.association import METHODS
from slam2d.io.json_text import dumps
from slam2d.lab.registry import estimator_names
from slam2d.web.chapters import render_chapter
from slam2d.web.fleet import register_fleet
from slam2d.web.frames import TAGS, encode_frame
from slam2d.web.pages import PAGE_BY_SLUG, PAGES
from slam2d.web.params import CommandError
from slam2d.web.sessions import Session
from slam2d.web.worker import SessionWorker

STATIC = Path(__file__).parent / "static"
MAX_COMMAND_BYTES = 4096
#: protocol-level limit handed to uvicorn: larger messages close the connection (code 1009) before parsing
WS_MAX_SIZE = 1 << 20
DEFAULT_HZ = 60
#: pages open at once (each owns a simulation and a worker thread); more are refused with a message, so a script
#: opening sockets in a loop cannot exhaust the machine's memory, threads or CPU
MAX_SESSIONS = 32

log = logging.getLogger("slam2d.web")


def _int_query(ws: WebSocket, name: str, default: int, lo: int, hi: int) -> int:
    raw = ws.query_params.get(name)
    if raw is None:
        return default
    try:
        return min(max(int(raw), lo), hi)
    except ValueError:
        return default


def parse_command(data: str | bytes | None) -> dict[str, Any]:
    """Decode one browser command; CommandError (sent back to the page) for anything that is not a small object."""
    if data is None:
        raise CommandError("empty message")
    if isinstance(data, bytes):
        raise CommandError("commands must be JSON text messages, not binary")
    if len(data.encode("utf-8", "surrogatepass")) > MAX_COMMAND_BYTES:
        raise CommandError(f"command too large ({len(data)} characters; the limit is {MAX_COMMAND_BYTES} bytes)")
    try:
        msg = json.loads(data)
    except (json.JSONDecodeError, RecursionError) as e:
        raise CommandError(f"malformed JSON: {e}") from None
    if not isinstance(msg, dict):
        raise CommandError(f"a command must be a JSON object, got {type(msg).__name__}")
    return msg


#: commands one page may send: bursts of RATE_BURST, RATE_PER_S per second sustained; the rest are dropped with a
#: visible message (a stuck key repeat or a script flooding the socket must not queue minutes of work)
RATE_PER_S, RATE_BURST = 50.0, 100


class RateLimiter:
    """Token bucket: ``allow(now)`` is True while tokens last; ``burst`` tokens, refilled at ``per_s`` per second."""

    def __init__(self, per_s: float = RATE_PER_S, burst: int = RATE_BURST) -> None:
        self.per_s, self.burst = per_s, float(burst)
        self.tokens = float(burst)
        self.last: float | None = None

    def allow(self, now: float) -> bool:
        if self.last is not None:
            self.tokens = min(self.burst, self.tokens + max(0.0, now - self.last) * self.per_s)
        self.last = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


class Connection:
    """One websocket: a receiver task applying commands, a sender loop advancing the session and sending frames."""

    def __init__(self, ws: WebSocket, session: Session, hz: int, worker: SessionWorker) -> None:
        self.ws, self.session, self.hz, self.worker = ws, session, hz, worker
        self.lock = asyncio.Lock()  # one writer at a time on the socket
        # every session call runs in the session's own worker thread (so one slow estimator or JCBB search never
        # stalls the event loop or another tab); commands wait for the step in progress
        self.session_lock = asyncio.Lock()
        self.closed = False
        self.limiter = RateLimiter()
        # commands are rate-limited as they arrive, not as they are applied: a receiver that waited for each command
        # would read a flood only as fast as the session applies it, so a slow machine would never see it as one
        self.commands: asyncio.Queue[str | bytes | None] = asyncio.Queue(maxsize=RATE_BURST)
        self.dropped = 0  # commands dropped since the last rate-limit message
        self.dropped_notice_at = -float("inf")

    async def send_json(self, obj: dict[str, Any]) -> None:
        async with self.lock:
            await self.ws.send_text(dumps(obj))  # numpy values as Python, NaN and inf as null

    async def receiver(self) -> None:
        """Read commands as they arrive; queue what the token bucket (and the bounded queue) allows, drop the rest."""
        while True:
            msg = await self.ws.receive()
            if msg["type"] == "websocket.disconnect":
                self.closed = True
                return
            now = time.monotonic()
            if self.limiter.allow(now):
                with contextlib.suppress(asyncio.QueueFull):  # full: the session is behind by a whole burst
                    self.commands.put_nowait(msg.get("text") if msg.get("text") is not None else msg.get("bytes"))
                    continue
            self.dropped += 1
            if now - self.dropped_notice_at >= 1.0:  # one message per second, not one per dropped command
                self.dropped_notice_at = now
                await self.send_json({"type": "error", "message": (
                    f"too many commands: {self.dropped} dropped (a page may send {RATE_PER_S:g} per second, "
                    f"bursts of {RATE_BURST}); the session carries on")})
                self.dropped = 0

    async def applier(self) -> None:
        """Apply queued commands in order, each in the session's worker; reply to each (a state or a named error)."""
        while True:
            raw = await self.commands.get()
            try:
                cmd = parse_command(raw)
                async with self.session_lock:
                    reply = await self.worker.run(self.session.apply, cmd)
            except CommandError as e:
                await self.send_json({"type": "error", "message": str(e)})
                continue
            except Exception as e:  # a bug in a session must cost one command, not the connection
                log.warning("page %s: command failed: %s: %s", self.session.page, type(e).__name__, e)
                await self.send_json({"type": "error", "message": f"command failed: {type(e).__name__}: {e}"})
                continue
            if reply is not None:
                await self.send_json(reply)

    def _tick(self, dt: float, seq: int) -> tuple[bytes, dict[str, Any] | None]:
        """Advance and draw; plus the state when advancing changed it (a task done, a notice)."""
        self.session.advance(dt)
        state = self.session.state() if self.session.take_state_change() else None
        return encode_frame(seq, self.session.sections()), state

    async def sender(self) -> None:
        period = 1.0 / self.hz
        seq = 0
        last = time.perf_counter()
        nxt = last
        while not self.closed:
            now = time.perf_counter()
            async with self.session_lock:
                frame, state = await self.worker.run(self._tick, min(now - last, 0.5), seq)
            last = now
            async with self.lock:
                await self.ws.send_bytes(frame)
            if state is not None:  # "pushed": not a reply to a command
                await self.send_json({**state, "pushed": True})
            seq += 1
            nxt += period
            delay = nxt - time.perf_counter()
            if delay < -period:  # behind by more than a frame: drop frames rather than burst to catch up
                nxt = time.perf_counter()
                delay = 0.0
            await asyncio.sleep(max(delay, 0.0))


LOOPBACK_HOSTS = frozenset({"127.0.0.1", "localhost", "::1", "[::1]"})
#: a connection that has not completed a request within this time is closed (slow or stuck clients)
HEADER_TIMEOUT_S = 10.0


def _hostname(authority: str) -> str:
    """``host[:port]`` or ``[v6]:port`` -> the host name, lower case."""
    a = authority.strip().lower()
    if a.startswith("["):
        return a[: a.find("]") + 1] if "]" in a else a
    return a.rsplit(":", 1)[0] if a.count(":") == 1 else a


def origin_allowed(origin: str, allowed: frozenset[str]) -> bool:
    """A browser Origin is allowed when it is exactly one of ``allowed`` or an http(s) origin on a loopback host."""
    o = origin.strip().lower().rstrip("/")
    if o in allowed:
        return True
    scheme, sep, rest = o.partition("://")
    return bool(sep) and scheme in ("http", "https") and "/" not in rest and _hostname(rest) in LOOPBACK_HOSTS


class OriginHostGuard:
    """ASGI middleware: refuse every HTTP request and websocket whose ``Origin`` is not loopback (or explicitly
    allowed) and, when ``hosts`` is given, whose ``Host`` is not one of them (DNS rebinding). A page on another
    site can then neither read the lab nor drive its sessions. Requests without ``Origin`` (curl, scripts, the
    browser's own navigations) pass: Origin is what a foreign page cannot leave out or forge."""

    def __init__(self, app: Any, allow_origins: frozenset[str] = frozenset(),
                 hosts: frozenset[str] | None = None) -> None:
        self.app = app
        self.allow_origins = frozenset(o.strip().lower().rstrip("/") for o in allow_origins)
        self.hosts = hosts

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] in ("http", "websocket"):
            headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
            origin, host = headers.get("origin"), headers.get("host", "")
            bad = None
            if origin is not None and not origin_allowed(origin, self.allow_origins):
                bad = f"origin {origin!r} not allowed (slam2d lab --allow-origin ORIGIN)"
            elif self.hosts is not None and _hostname(host) not in self.hosts:
                bad = f"host {host!r} not allowed"
            if bad is not None:
                log.warning("refused %s %s: %s", scope["type"], scope.get("path"), bad)
                if scope["type"] == "websocket":
                    await send({"type": "websocket.close", "code": 1008})
                else:
                    response = JSONResponse({"error": bad}, status_code=403)
                    await response(scope, receive, send)
                return
        await self.app(scope, receive, send)


def create_app(*, allow_origins: frozenset[str] = frozenset(), hosts: frozenset[str] | None = None,
               max_sessions: int = MAX_SESSIONS) -> FastAPI:
    """The lab application (run with uvicorn, ``ws_per_message_deflate=False``); every request passes
    :class:`OriginHostGuard` first. At most ``max_sessions`` pages have a session at once (one being built counts)."""
    app = FastAPI(title="slam2d lab", docs_url=None, redoc_url=None, openapi_url=None)
    for p in PAGES:  # a broken page template fails here, at start, not when someone opens the page
        render_chapter(p.slug)
    app.add_middleware(OriginHostGuard, allow_origins=allow_origins, hosts=hosts)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    register_fleet(app)
    sessions: set[WebSocket] = set()  # the sockets that hold a session (built, or being built)

    @app.get("/")
    async def index() -> FileResponse:
        return FileResponse(STATIC / "index.html")

    @app.get("/favicon.ico")
    async def favicon() -> Response:
        return Response(status_code=204)

    @app.get("/api/status")
    async def api_status() -> JSONResponse:
        pages = [{"slug": p.slug, "number": p.number, "title": p.title, "summary": p.summary} for p in PAGES]
        return JSONResponse({"estimators": estimator_names(), "association_methods": list(METHODS), "pages": pages,
                             "frame_tags": {k: list(v) for k, v in TAGS.items()}})

    @app.get("/lab/{slug}")
    async def page(slug: str) -> Response:
        if slug not in PAGE_BY_SLUG:
            return JSONResponse({"error": f"unknown page {slug!r}; pages: {sorted(PAGE_BY_SLUG)}"}, status_code=404)
        return HTMLResponse(render_chapter(slug))

    @app.websocket("/ws/{slug}")
    async def socket(ws: WebSocket, slug: str) -> None:
        await ws.accept()
        spec = PAGE_BY_SLUG.get(slug)
        if spec is None:
            await ws.send_text(json.dumps({"type": "error", "message": f"unknown page {slug!r}"}))
            await ws.close(code=1008)
            return
        if len(sessions) >= max_sessions:
            await ws.send_text(json.dumps({"type": "error", "message": (
                f"too many pages open on this lab ({max_sessions} at most): close another tab, then reload this "
                "page")}))
            await ws.close(code=1013)  # try again later
            return
        seed = _int_query(ws, "seed", 0, 0, 2**31 - 1)
        hz = _int_query(ws, "hz", DEFAULT_HZ, 1, 120)
        conn: Connection | None = None
        tasks: list[asyncio.Task[None]] = []
        worker = SessionWorker(f"session-{slug}")
        sessions.add(ws)
        try:
            session = await worker.run(spec.make, seed)
            conn = Connection(ws, session, hz, worker)
            await conn.send_json(await worker.run(session.hello))
            tasks = [asyncio.create_task(conn.receiver()), asyncio.create_task(conn.applier()),
                     asyncio.create_task(conn.sender())]
            done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for t in pending:
                t.cancel()
            for t in pending:
                try:
                    await t
                except (asyncio.CancelledError, Exception):
                    pass
            for t in done:
                exc = t.exception()
                if exc is not None and not _is_disconnect(exc):
                    log.warning("session %s ended with %s: %s", slug, type(exc).__name__, exc)
                    with contextlib.suppress(Exception):  # tell the page why it stopped, if it still listens
                        await conn.send_json({"type": "error", "message": f"this page's session stopped: "
                                                                          f"{type(exc).__name__}: {exc}"})
        except asyncio.CancelledError:  # the server is shutting down (Ctrl+C): end this page quietly
            for t in tasks:
                t.cancel()
        except Exception as exc:  # never let one page take the server down
            if not _is_disconnect(exc):
                log.exception("session %s failed", slug)
        finally:
            sessions.discard(ws)
            worker.close()
            if ws.client_state == WebSocketState.CONNECTED and ws.application_state == WebSocketState.CONNECTED:
                try:
                    await ws.close()
                except Exception:
                    pass

    return app


def _is_disconnect(exc: BaseException) -> bool:
    name = type(exc).__name__
    return isinstance(exc, WebSocketDisconnect | ConnectionError) or name in (
        "ClientDisconnected", "ConnectionClosed", "ConnectionClosedError", "ConnectionClosedOK") or (
        isinstance(exc, RuntimeError) and ("close" in str(exc).lower() or "disconnect" in str(exc).lower()))


def serve(host: str = "127.0.0.1", port: int = 8000, log_level: str = "warning", *,
          allow_origins: frozenset[str] = frozenset(), announce: Any = None) -> None:
    """Run the lab with uvicorn (blocking). The socket is bound here first, so a busy port is an ``OSError`` before
    anything is printed; ``announce(url)`` is called once the bind succeeded. Per-message compression is off (it
    costs more CPU than it saves here); connections that do not complete a request in ``HEADER_TIMEOUT_S`` close."""
    import socket

    import uvicorn

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(128)
        sock.set_inheritable(True)
    except OSError as e:
        sock.close()
        raise OSError(e.errno, e.strerror, f"{host}:{port}") from None
    wildcard = host in ("0.0.0.0", "::", "")
    hosts = None if wildcard else LOOPBACK_HOSTS | {host.lower(), f"[{host.lower()}]"} | {
        _hostname(o.partition("://")[2]) for o in allow_origins}
    config = uvicorn.Config(create_app(allow_origins=allow_origins, hosts=hosts), log_level=log_level,
                            ws_per_message_deflate=False, ws_max_size=WS_MAX_SIZE, http=_timed_h11(),
                            timeout_keep_alive=5, h11_max_incomplete_event_size=16 * 1024,
                            timeout_graceful_shutdown=0.3)  # type: ignore[arg-type]  # Ctrl+C: 0.3 s
    if announce is not None:
        shown = f"[{host}]" if ":" in host else host
        announce(f"http://{shown}:{sock.getsockname()[1]}/")
    uvicorn.Server(config).run(sockets=[sock])


def _timed_h11() -> Any:
    """uvicorn's h11 protocol with a timer: a connection that has not completed a request within
    ``HEADER_TIMEOUT_S`` of connecting (or of its last completed response) is closed. uvicorn itself waits forever
    for the headers of a slow client."""
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class TimedH11Protocol(H11Protocol):  # type: ignore[misc]
        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            self._header_timer = self.loop.call_later(HEADER_TIMEOUT_S, self._header_check)

        def _header_check(self) -> None:
            if self.transport.is_closing() or self.transport.get_protocol() is not self:
                return  # closed, or upgraded to a websocket
            busy = self.cycle is not None and not self.cycle.response_complete
            if not busy and self.conn.their_state in (h11.IDLE, h11.SEND_BODY):
                self.transport.close()
                return
            self._header_timer = self.loop.call_later(HEADER_TIMEOUT_S, self._header_check)

        def connection_lost(self, exc: Exception | None) -> None:
            self._header_timer.cancel()
            super().connection_lost(exc)

    return TimedH11Protocol
