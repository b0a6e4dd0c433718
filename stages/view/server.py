"""viser's server with goi's gate in front: only goi's own pages reach it, and nothing leaves
the machine.

viser (1.1, pinned `viser>=1.1,<2` in pyproject.toml) serves its page and its websocket from
one `websockets.asyncio.server.serve(..., process_request=...)` call, and offers no hook to
check a request before it is served, no origin list, no cap on connections, and a Share button
whose handler opens a public tunnel (share.viser.studio) to the server on any page's request.
Two small, documented interventions close that:

1. While `serve()` builds the `ViserServer`, viser's infra module sees a `websockets` whose
   `asyncio.server.serve` is `_guarded_serve`: the real function, called with viser's own
   arguments, its `process_request` wrapped by goi's check (`stages.view.access`: Host, Origin,
   token; the cap on pages), its message size capped, and each accepted connection's `recv`
   wrapped so that a frame that is not a viser message (or a camera report that is not a
   camera, an input update that is not a value, a click or box that is not a point of the
   canvas) is dropped with one log line instead of ending
   the connection with a traceback. Refusals are logged, at most `LOG_LINES` a minute.
   Nothing else in the process sees the wrapper, and it is removed as soon as viser has bound
   its port. If viser stops calling `serve` this way (an upgrade), `serve()` finds its guard
   unused and refuses to start: it never serves unguarded (tests/view/test_access.py).
2. `GoiViserServer` overrides `request_share_url`, the method viser's Share-request handler
   calls: the request is refused and logged, no tunnel is made. The page's theme hides the
   button (`show_share_button=False`).
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import threading
import types
import weakref
from collections.abc import Callable, Iterator
from typing import Any

from stages.core.errors import GoiError
from stages.view.access import NEED_TOKEN, Access
from stages.view.cameras import MIN_FOV

#: The viser versions this wrapper was written against (pyproject.toml pins the same range).
VISER_RANGE = ((1, 1), (2, 0))

_BUILD_LOCK = threading.Lock()  # one ViserServer built at a time: the wrapper is per build
#: Refusals logged a minute at most (a flood of bad requests must not flood the log).
LOG_LINES = 30


class Guard:
    """What `_guarded_serve` enforces for one server, and what it saw."""

    def __init__(
        self,
        access: Access,
        max_pages: int,
        max_message_bytes: int,
        log: Callable[[str], None],
    ):
        self.access = access
        self.max_pages = max_pages
        self.max_message_bytes = max_message_bytes
        self._log = log
        self._logged: list[float] = []  # when the lines of the last minute were logged
        self._quiet_since = 0.0
        self.used = False  # viser called serve() through the guard
        self._pages: weakref.WeakSet[Any] = weakref.WeakSet()  # websockets accepted

    def log(self, line: str) -> None:
        """A refusal's line, unless LOG_LINES were logged in the last minute."""
        import time

        now = time.monotonic()
        self._logged = [t for t in self._logged if now - t < 60]
        if len(self._logged) >= LOG_LINES:
            if now - self._quiet_since >= 60:
                self._quiet_since = now
                self._log(f"more than {LOG_LINES} refusals a minute: the next are not logged")
            return
        self._logged.append(now)
        self._log(line)

    def check(self, connection: Any, request: Any) -> tuple[Any, str | None]:
        """(the refusal to send, or None to go on; the cookie to set on the page)."""
        headers = request.headers
        websocket = "Upgrade" in headers or "Sec-WebSocket-Key" in headers
        port = int(connection.local_address[1])
        d = self.access.check(request.path, headers, port, websocket)
        if not d.ok:
            self.log(f"refused {d.reason} from {_peer(connection)}")
            return connection.respond(d.status, NEED_TOKEN + "\n"), None
        if websocket:
            from websockets.protocol import State

            live = [c for c in self._pages if c.state in (State.CONNECTING, State.OPEN)]
            if len(live) >= self.max_pages:
                self.log(f"refused a page from {_peer(connection)}: {self.max_pages} pages open")
                text = f"goi view: {self.max_pages} pages are open already (--max-pages)\n"
                return connection.respond(503, text), None
            self._pages.add(connection)
            _drop_bad_frames(connection, self.log)
        return None, d.set_cookie

    def process_request(self, inner: Callable[..., Any] | None) -> Callable[..., Any]:
        """viser's process_request (its HTTP server) behind `check`."""

        def process(connection: Any, request: Any) -> Any:
            refusal, cookie = self.check(connection, request)
            if refusal is not None:
                return refusal
            response = inner(connection, request) if inner is not None else None
            if response is not None:  # the page (viser's HTTP server)
                h = response.headers
                h["Cache-Control"] = "no-store"
                h["X-Frame-Options"] = "DENY"
                h["Content-Security-Policy"] = "frame-ancestors 'none'"
                h["Referrer-Policy"] = "no-referrer"
                if cookie:
                    h["Set-Cookie"] = cookie
            return response

        return process


def _peer(connection: Any) -> str:
    try:
        host, port = connection.remote_address[:2]
        return f"{host}:{port}"
    except (TypeError, ValueError, AttributeError):
        return "?"


def _drop_bad_frames(connection: Any, log: Callable[[str], None]) -> None:
    """Wrap the connection's recv: frames that are not viser messages are dropped (logged
    once per connection with their count), before viser's consumer would raise on them."""
    from viser import _messages

    inner = connection.recv
    dropped = [0]

    async def recv(*args: Any, **kwargs: Any) -> Any:
        while True:
            raw = await inner(*args, **kwargs)
            why = _not_a_message(raw, _messages)
            if why is None:
                return raw
            dropped[0] += 1
            if dropped[0] == 1:
                log(f"dropped a frame from {_peer(connection)}: {why} (later ones unlogged)")

    connection.recv = recv


def _not_a_message(raw: object, messages: Any) -> str | None:
    if not isinstance(raw, bytes | bytearray):
        return "a text frame (viser's pages send binary)"
    try:
        m = messages.Message.deserialize(bytes(raw))
    except Exception as e:  # any decoding failure: the frame is not a viser message
        return f"not a viser message ({type(e).__name__})"
    if isinstance(m, messages.ViewerCameraMessage):
        return _bad_camera(m)
    if isinstance(m, messages.GuiUpdateMessage):
        return _bad_gui_update(m)
    if isinstance(m, messages.ScenePointerMessage):
        return _bad_pointer(m, messages)
    return None


def _bad_pointer(m: Any, messages: Any) -> str | None:
    """Why a scene click or box is not one viser's page sends (None when it is one): a click
    has one canvas position and a finite ray, a box two positions; the modifier is one of
    viser's key combinations."""
    import typing

    kinds = {"click": 1, "rect-select": 2}
    n = kinds.get(m.event_type) if isinstance(m.event_type, str) else None
    if n is None:
        return "a pointer event of no known kind"
    pos = m.screen_pos
    if not (isinstance(pos, list | tuple) and len(pos) == n and all(_finite(p, 2) for p in pos)):
        return "a pointer event whose position is not a point of the canvas"
    if n == 1 and not (_finite(m.ray_origin, 3) and _finite(m.ray_direction, 3)):
        return "a click whose ray is not finite numbers"
    if m.modifier is not None and m.modifier not in typing.get_args(messages.KeyModifier):
        return "a pointer event with a key modifier viser does not send"
    return None


#: The longest text a page's input may hold (a prompt is capped far below, with a message).
MAX_TEXT_VALUE = 4096


def _bad_gui_update(m: Any) -> str | None:
    """Why an input's new value is not one viser's page sends (None when it is one): the page
    sends {"value": V}, V text, a flag, a number or a short list of numbers (a colour)."""
    if not isinstance(m.updates, dict) or set(m.updates) != {"value"}:
        return "an input update that is not a value"
    v = m.updates["value"]
    if isinstance(v, str):
        return None if len(v) <= MAX_TEXT_VALUE else "an input value of over 4096 characters"
    if isinstance(v, bool) or (isinstance(v, int | float) and math.isfinite(v)):
        return None
    if isinstance(v, list | tuple) and len(v) <= 4 and _finite(v, len(v)):
        return None
    return "an input value that is not text, a flag, a number or a colour"


def _finite(values: object, n: int) -> bool:
    """`values` is a list of `n` finite numbers (not text that reads as one, not flags)."""
    if not isinstance(values, list | tuple) or len(values) != n:
        return False
    return all(
        isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) for x in values
    )


def _bad_camera(m: Any) -> str | None:
    """Why a camera report is not one a browser sends (None when it is one)."""
    if not (_finite(m.wxyz, 4) and _finite(m.position, 3) and _finite(m.look_at, 3)):
        return "a camera report with a pose that is not finite numbers"
    if not _finite(m.up_direction, 3):
        return "a camera report with an up direction that is not finite numbers"
    if not (_finite([m.fov, m.near, m.far], 3) and MIN_FOV <= m.fov <= math.pi - MIN_FOV):
        return "a camera report with a field of view that is not an angle"
    for v in (m.image_width, m.image_height):
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 16384:
            return "a camera report with a canvas size that is not 1..16384 pixels"
    return None


@contextlib.contextmanager
def _websockets_seen_by_viser(guard: Guard) -> Iterator[None]:
    """viser's infra module sees `websockets` with `asyncio.server.serve` guarded, for the
    time of one build (see the module doc)."""
    import websockets
    import websockets.asyncio.server
    from viser.infra import _infra

    real_serve = websockets.asyncio.server.serve

    def _guarded_serve(handler: Any, host: Any, port: Any, **kw: Any) -> Any:
        guard.used = True
        kw["process_request"] = guard.process_request(kw.get("process_request"))
        kw["max_size"] = guard.max_message_bytes
        return real_serve(handler, host, port, **kw)

    server_ns = _Namespace(websockets.asyncio.server, serve=_guarded_serve)
    asyncio_ns = _Namespace(websockets.asyncio, server=server_ns)
    seen = _Namespace(websockets, asyncio=asyncio_ns)
    before = _infra.websockets
    _infra.websockets = seen  # type: ignore[assignment]
    try:
        yield
    finally:
        _infra.websockets = before


class _Namespace(types.SimpleNamespace):
    """A module with some attributes replaced; every other one is the module's."""

    def __init__(self, module: Any, **replaced: Any):
        super().__init__(**replaced)
        self._module = module

    def __getattr__(self, name: str) -> Any:
        return getattr(self.__dict__["_module"], name)


def check_viser_version() -> None:
    import viser

    try:
        version = tuple(int(x) for x in viser.__version__.split(".")[:2])
    except ValueError:
        version = (0, 0)
    lo, hi = VISER_RANGE
    if not lo <= version < hi:
        raise GoiError(
            f"goi view was written for viser >={lo[0]}.{lo[1]},<{hi[0]}.{hi[1]} (its page and "
            f"websocket are guarded through viser's internals); found viser {viser.__version__}: "
            f"pip install 'viser>={lo[0]}.{lo[1]},<{hi[0]}.{hi[1]}'"
        )


def serve(host: str, port: int, guard: Guard, on_share: Callable[[], None]) -> Any:
    """A `GoiViserServer` on (host, port), every request through `guard`."""
    import viser

    check_viser_version()

    class GoiViserServer(viser.ViserServer):
        """viser's server with its Share request refused (see the module doc)."""

        def request_share_url(self, verbose: bool = True) -> str | None:
            on_share()
            return None

        def disconnect_share_url(self) -> None:
            return None

    with _BUILD_LOCK, _websockets_seen_by_viser(guard):
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: goi prints its own
            server = GoiViserServer(host=host, port=port, verbose=False)
    if not guard.used:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
        raise GoiError(
            f"viser {viser.__version__} no longer serves through the call goi view guards "
            "(stages/view/server.py); goi view refuses to serve a page anyone could drive: "
            f"install viser>={VISER_RANGE[0][0]}.{VISER_RANGE[0][1]},<{VISER_RANGE[1][0]}"
        )
    return server


#: A busy --port is skipped for the next free one, up to this many ports.
PORT_TRIES = 100


def servable_port(host: str, port: int) -> int:
    """The port goi view will serve on: `port` or the next free one (0: any), once `host`
    is known to resolve to an address of this machine. Refused here, before any work, what
    viser would otherwise retry a thousand times and then wait for forever."""
    import errno
    import socket

    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as e:
        why = e.strerror if isinstance(e, OSError) else str(e)
        raise GoiError(f"--host: {host} does not resolve to an address ({why})") from None
    last = port if port == 0 else min(port + PORT_TRIES - 1, 65535)
    for p in range(port, last + 1):
        try:
            for family, kind, proto, _, addr in infos:
                with socket.socket(family, kind, proto) as s:
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio binds
                    s.bind((addr[0], p, *addr[2:]))
        except OSError as e:
            if e.errno == errno.EADDRINUSE and p != 0:
                continue
            if e.errno == errno.EADDRNOTAVAIL:
                raise GoiError(f"--host: {host} is not an address of this machine") from None
            if e.errno == errno.EACCES:
                raise GoiError(f"--port: {p} needs privileges this user lacks") from None
            raise GoiError(f"--host/--port: cannot serve on {host}:{p} ({e.strerror})") from None
        return p
    raise GoiError(f"--port: ports {port} to {last} are all in use; give another --port")


class _OneLine(logging.Handler):
    """A library's log record as one line of goi's log, without its traceback."""

    def __init__(self, log: Callable[[str], None]):
        super().__init__(logging.WARNING)
        self._log = log

    def emit(self, record: logging.LogRecord) -> None:
        try:
            line = f"{record.name}: {record.getMessage()}"
            if record.exc_info and record.exc_info[1] is not None:
                e = record.exc_info[1]
                line += f" ({type(e).__name__}: {str(e)[:200]})"
            self._log(" ".join(line.split())[:500])
        except Exception:  # a log line must never take the server down
            pass


def quiet_libraries(log: Callable[[str], None]) -> Callable[[], None]:
    """The server's libraries (asyncio's loop, websockets) log into goi's log, one line a
    record and no traceback, while goi view serves: what a client that is not viser's page
    sends ends as one line, never a traceback. Returns the function that undoes it."""
    undo = []
    for name in ("asyncio", "websockets"):
        logger = logging.getLogger(name)
        handler = _OneLine(log)
        before = logger.propagate
        logger.addHandler(handler)
        logger.propagate = False
        undo.append((logger, handler, before))

    def restore() -> None:
        for logger, handler, before in undo:
            logger.removeHandler(handler)
            logger.propagate = before

    return restore
