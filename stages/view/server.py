"""The viser server: loopback by default, a loud warning for any other address, a token and an Origin/Host check on
every request (`stages.view.gate`), a clean stop.

`start(host, port, gate)` refuses a port outside 1..65535 and a host that is not an address (UserError), prints a
warning on stderr when the host is not a loopback address (anyone who can reach it and has the URL's token can
use the viewer), and returns the running `viser.ViserServer` with `gate` in front of it (viser's own banner and
"Server stopped" lines are kept off stdout: `nerfpipe view` prints its own). `url(host, port, gate)` is the
address to open, token included. `wait(stop, ready)` prints `ready` once Ctrl-C and SIGTERM are caught
and blocks until one comes (returning its number) or `stop` is set.
"""

from __future__ import annotations

import contextlib
import io
import ipaddress
import socket
import sys
import threading
from urllib.parse import quote

from nerfpipe.data.errors import UserError
from nerfpipe.data.stop import stop_on_signals
from nerfpipe.stages.view.gate import TOKEN_PARAM, Gate, gated

__all__ = ["is_loopback", "start", "stop_quietly", "url", "wait"]


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and 'localhost'."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def start(host: str, port: int, gate: Gate):
    """A running viser server on host:port (port 0: a free one) that lets in only what `gate` lets in (its `port`
    is set to the port served)."""
    if not 0 <= port <= 65535:
        raise UserError(f"--port: expected 0..65535, got {port}")
    try:
        socket.getaddrinfo(host, None)
    except socket.gaierror:
        raise UserError(f"--host: {host!r} is not an address of this machine") from None
    if port == 0:
        with socket.socket() as s:
            s.bind((host, 0))
            port = s.getsockname()[1]
    else:
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError as exc:
                raise UserError(f"--port: cannot listen on {host}:{port} ({exc.strerror})") from None
    if not is_loopback(host):
        print(
            f"warning: serving on {host}: anyone who can reach this machine on port {port} and has the URL (its "
            "token) can use the viewer (use the default --host 127.0.0.1 to keep it to this machine)",
            file=sys.stderr,
        )
    import viser

    gate.port, server = port, None
    try:
        with gated(gate), contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner even if not verbose
            server = viser.ViserServer(host=host, port=port, verbose=False)
    except BaseException:
        if server is not None:
            stop_quietly(server)
        raise
    gate.port = server.get_port()  # viser moves on when the port was taken meanwhile
    return server


def url(host: str, port: int, gate: Gate) -> str:
    """http://HOST:PORT/?token=... (a wildcard bind names this machine by its host name)."""
    if host in ("0.0.0.0", "::", ""):
        host = socket.gethostname()
    name = f"[{host}]" if ":" in host else host
    return f"http://{name}:{port}/?{TOKEN_PARAM}={quote(gate.token)}"


def stop_quietly(server) -> None:
    """Stop a viser server (its thread prints "(viser) Server stopped" while stop() joins it: kept off stdout)."""
    with contextlib.redirect_stdout(io.StringIO()):
        server.stop()


def wait(stop: threading.Event, ready: str = "", poll: float = 0.2) -> int | None:
    """Print `ready` (once SIGINT and SIGTERM are caught) and block until one of them comes or `stop` is set ->
    the signal's number, or None for `stop`."""
    with stop_on_signals() as request:
        if ready:
            print(ready, flush=True)
        while request.signum is None and not stop.wait(poll):
            pass
    return request.signum
