"""Who may use the viewer: every HTTP request and every websocket upgrade passes `Gate.refusal` before viser
sees it; a refused one gets `403 Forbidden` and a one-line reason, and never a websocket.

A request is let in when all of these hold:

- **Host** names this machine: `localhost`, an IP address (127.0.0.1, [::1], a LAN address), this machine's
  host name or the `host` the viewer was bound to; any port (an SSH tunnel's local port). A page of another
  site that re-points its own name at this machine (DNS rebinding) sends its own name, and is refused.
- **Origin**, when the request has one (browsers always send it on a websocket), is the same host and port as
  Host: the viewer's own page. A page of any other site, or another local server's page, is refused. A request
  without Origin is not from a page in a browser (a script): the token decides for it.
- **The token** (`secrets.token_urlsafe`, new for each viewer, in the URL `nerfpipe view` prints: `?token=...`)
  is in the URL's query or in the cookie that the page's first request sets (`HttpOnly`, `SameSite=Strict`;
  viser's page opens its websocket without the query, so the cookie carries the token there). Every bind,
  loopback included: on a shared machine every local user can reach 127.0.0.1.

viser (1.1.1) offers no hook for this: its server calls `websockets.asyncio.server.serve(..., process_request=
viser's file server)` in its own thread while `viser.ViserServer()` starts. `gated(gate)` wraps that one call,
for the time the server starts, so that our check runs before viser's `process_request`; the server refuses to
start (RuntimeError) when viser did not call it, so a viser that changes this can never serve unguarded
(tests/test_view_security.py fails first).
"""

from __future__ import annotations

import contextlib
import hmac
import http
import http.cookies
import ipaddress
import secrets
import socket
import sys
import threading
from dataclasses import dataclass, field
from urllib.parse import parse_qs, urlsplit

__all__ = ["TOKEN_PARAM", "Gate", "new_token", "gated"]

TOKEN_PARAM = "token"
"""The query parameter of the viewer's URL that carries its token."""


def new_token() -> str:
    return secrets.token_urlsafe(24)


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def _host_port(netloc: str, scheme: str = "http") -> tuple[str, int] | None:
    """'name:port' / '[v6]:port' / 'name' -> (lower-case name, port; the scheme's default when none), None when it
    does not parse."""
    try:
        parts = urlsplit("//" + netloc)
        name, port = parts.hostname, parts.port
    except ValueError:
        return None
    if not name or parts.username is not None or parts.password is not None or parts.path or parts.query:
        return None
    return name, port if port is not None else (443 if scheme == "https" else 80)


def _shown(values: list[str]) -> str:
    return ", ".join(v[:80] for v in values) or "(none)"


@dataclass
class Gate:
    """The viewer's check; `port` is the port served (the cookie's name), set once the server is bound."""

    bind_host: str
    port: int
    token: str = field(default_factory=new_token)
    names: frozenset[str] = frozenset()
    """Host names (lower case) that name this machine, besides IP addresses."""
    warned: set[str] = field(default_factory=set)

    def __post_init__(self) -> None:
        if not self.names:
            here = {"localhost", self.bind_host, socket.gethostname()}
            with contextlib.suppress(OSError):
                here.add(socket.getfqdn())
            self.names = frozenset(n.lower().strip("[]") for n in here if n)

    @property
    def cookie(self) -> str:
        return f"nerfpipe_view_{self.port}"

    def refusal(self, request) -> str | None:
        """Why `request` (websockets' Request: path, headers) is refused, or None to let it in."""
        hosts = request.headers.get_all("Host")
        host = _host_port(hosts[0]) if len(hosts) == 1 else None
        if host is None:
            return f"Host {_shown(hosts)} is not one address"
        if not (_is_ip(host[0]) or host[0] in self.names):
            return f"Host {_shown(hosts)} does not name this machine (DNS rebinding?)"
        origins = request.headers.get_all("Origin")
        if origins:
            scheme, _, netloc = origins[0].partition("://") if len(origins) == 1 else ("", "", "")
            if scheme not in ("http", "https") or _host_port(netloc, scheme) != _host_port(hosts[0], scheme):
                return f"Origin {_shown(origins)} is not the viewer's own page (Host {_shown(hosts)})"
        if not self._has_token(request):
            return "no valid token (open the URL that nerfpipe view printed, with its ?token=...)"
        return None

    def _query_token(self, request) -> str | None:
        values = parse_qs(urlsplit(request.path).query).get(TOKEN_PARAM, [])
        return values[0] if len(values) == 1 else None

    def _has_token(self, request) -> bool:
        given = [self._query_token(request)]
        for header in request.headers.get_all("Cookie"):
            jar = http.cookies.SimpleCookie()
            with contextlib.suppress(http.cookies.CookieError):
                jar.load(header)
            if self.cookie in jar:
                given.append(jar[self.cookie].value)
        return any(g is not None and hmac.compare_digest(g.encode(), self.token.encode()) for g in given)

    def process_request(self, connection, request, inner):
        """websockets' `process_request`: a 403 for a refused request; else viser's own answer (`inner`), with
        the token's cookie when the URL carried the token."""
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        why = self.refusal(request)
        if why is not None:
            self._warn(connection, why)
            body = f"nerfpipe view: refused: {why}\n".encode()
            headers = Headers({"Content-Type": "text/plain; charset=utf-8", "Content-Length": str(len(body))})
            return Response(http.HTTPStatus.FORBIDDEN, "Forbidden", headers, body)
        response = inner(connection, request) if inner is not None else None
        if response is not None and self._query_token(request) is not None:
            response.headers["Set-Cookie"] = f"{self.cookie}={self.token}; Path=/; HttpOnly; SameSite=Strict"
        return response

    def _warn(self, connection, why: str) -> None:
        kind = why.split(" ", 1)[0]
        if kind not in self.warned:  # once per kind: a refused page's websocket retries every second
            self.warned.add(kind)
            peer = getattr(connection, "remote_address", None)
            print(f"warning: view: refused a request from {peer[0] if peer else '?'}: {why}", file=sys.stderr)


_GATING = threading.Lock()


def _viser_version() -> str:
    import viser

    return getattr(viser, "__version__", "?")


@contextlib.contextmanager
def gated(gate: Gate):
    """While viser's server starts inside this block, its `websockets.asyncio.server.serve` call gets
    `gate.process_request` in front of viser's own; RuntimeError when viser made no such call."""
    import websockets.asyncio.server as ws_server

    calls = []

    def serve(handler, *args, process_request=None, **kwargs):
        calls.append(process_request)
        check = lambda connection, request: gate.process_request(connection, request, process_request)  # noqa: E731
        return original(handler, *args, process_request=check, **kwargs)

    with _GATING:
        original = ws_server.serve
        ws_server.serve = serve
        try:
            yield
        finally:
            ws_server.serve = original
    if not calls:
        raise RuntimeError(
            f"viser {_viser_version()} did not start its server through websockets.asyncio.server.serve, so the "
            "viewer's access check (stages/view/gate.py) cannot sit in front of it: not serving; install viser 1.1"
        )
