"""Who may drive `goi view`: only its own pages, opened with the run's token.

A page of goi view can read the scene, every training photo (fly to a camera), every tab's
prompts and answers, ask prompts and write exports. A port on 127.0.0.1 does not keep other
web pages out: any site the user visits can open `ws://127.0.0.1:PORT` from a script
(cross-site websocket hijacking), and a DNS name made to point at 127.0.0.1 (DNS rebinding)
can even serve its page from a name of its own. So every request is checked here before the
server answers it:

- the Host it names is a name of this server (an address literal, `localhost`, the machine's
  own names or `--host`) at the served port: a rebound DNS name is refused;
- a websocket's Origin is the page's own origin (`http://` + that Host): another site's page,
  or another local server's, is refused (a browser always sends Origin with a websocket and a
  page cannot forge it);
- the request carries the run's secret token, as Jupyter's does: `?token=...` in the address
  printed at start, which the page's response turns into a cookie for this port
  (HttpOnly, SameSite=Strict), so the page's websocket and a reload carry it too.
  `--no-token` drops this check on a trusted machine (the two above stay).

Pure functions of the request (path and headers): `stages.view.server` calls them from the
websocket server's handshake hook, and the tests call them directly.
"""

from __future__ import annotations

import hmac
import ipaddress
import secrets
import socket
from collections.abc import Mapping
from dataclasses import dataclass, field
from http.cookies import CookieError, SimpleCookie
from urllib.parse import parse_qs, urlsplit

#: Said to whoever opens the page without the token.
NEED_TOKEN = (
    "goi view: this page needs the address goi view printed when it started (with its "
    "?token=...); ask whoever started it, or start goi view yourself"
)


def new_token() -> str:
    """A per-run secret: 32 random bytes, URL-safe."""
    return secrets.token_urlsafe(32)


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _is_address(name: str) -> bool:
    try:
        ipaddress.ip_address(name.strip("[]"))
        return True
    except ValueError:
        return False


def server_names(host: str) -> frozenset[str]:
    """The names a browser may call this server by (lower case, without the port): the
    address literals are always allowed (a DNS rebinding needs a name), so are `localhost`,
    `--host` and, when serving beyond the loopback, the machine's own names."""
    names = {"localhost", host.lower().strip("[]")}
    if not is_loopback(host):
        names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
    return frozenset(n for n in names if n)


@dataclass(frozen=True)
class Decision:
    """What to do with one request: serve it (`ok`), with a cookie to set, or refuse it with
    `status` and `reason` (the one line the viewer logs)."""

    ok: bool
    status: int = 200
    reason: str = ""
    set_cookie: str | None = None


@dataclass(frozen=True)
class Access:
    """The run's rules: its token (None with --no-token) and the names it is served under."""

    token: str | None
    names: frozenset[str] = field(default_factory=frozenset)

    def cookie_name(self, port: int) -> str:
        # cookies ignore ports: one per port, so two viewers on one machine keep their own
        return f"goi-view-{port}"

    def check(self, path: str, headers: Mapping[str, str], port: int, websocket: bool) -> Decision:
        """The decision for a request to `path` with `headers` on the served `port`."""
        host = headers.get("Host")
        named = _host_port(host) if host else None
        if named is None or named[1] != port or not self._our_name(named[0]):
            return Decision(False, 403, f"a request for another server name (Host {host!r})")
        if websocket:
            origin = headers.get("Origin")
            if origin is None or _origin(origin) != ("http", named[0], port):
                return Decision(False, 403, f"a websocket from another origin ({origin!r})")
        if self.token is None:
            return Decision(True)
        query = parse_qs(urlsplit(path).query).get("token", [])
        cookie = _cookie(headers.get("Cookie", ""), self.cookie_name(port))
        given = [t for t in (*query, cookie) if t]
        if not any(hmac.compare_digest(t.encode(), self.token.encode()) for t in given):
            what = "a websocket" if websocket else "a page"
            return Decision(False, 403, f"{what} without the run's token")
        set_cookie = None
        if not websocket and query:
            set_cookie = f"{self.cookie_name(port)}={self.token}; Path=/; HttpOnly; SameSite=Strict"
        return Decision(True, set_cookie=set_cookie)

    def _our_name(self, name: str) -> bool:
        return name in self.names or _is_address(name)


def _host_port(host: str) -> tuple[str, int] | None:
    """`Host` header -> (name in lower case, port); None when malformed."""
    try:
        parts = urlsplit(f"http://{host}")
        name, port = parts.hostname, parts.port
    except ValueError:
        return None
    if not name or parts.path or parts.query or parts.username is not None:
        return None
    return name.lower(), port if port is not None else 80


def _origin(origin: str) -> tuple[str, str, int] | None:
    try:
        parts = urlsplit(origin)
        name, port = parts.hostname, parts.port
    except ValueError:
        return None
    if not name or parts.path not in ("", "/"):
        return None
    default = {"http": 80, "https": 443}.get(parts.scheme, -1)
    return parts.scheme, name.lower(), port if port is not None else default


def _cookie(header: str, name: str) -> str | None:
    try:
        jar = SimpleCookie()
        jar.load(header)
    except CookieError:
        return None
    morsel = jar.get(name)
    return morsel.value if morsel is not None else None
