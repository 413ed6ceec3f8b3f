"""The viser server: loopback by default, a loud warning for any other address, a clean stop.

`start(host, port)` refuses a port outside 1..65535 and a host that is not an address (UserError), prints a
warning on stderr when the host is not a loopback address (anyone who can reach it sees the scene and can use
the viewer), and returns the running `viser.ViserServer` (viser's own banner and "Server stopped" lines are kept
off stdout: `nerfpipe view` prints its own). `wait(stop, ready)` prints `ready` once Ctrl-C and SIGTERM are caught
and blocks until one comes (returning its number) or `stop` is set.
"""

from __future__ import annotations

import contextlib
import io
import ipaddress
import socket
import sys
import threading

from nerfpipe.data.errors import UserError
from nerfpipe.data.stop import stop_on_signals

__all__ = ["is_loopback", "start", "stop_quietly", "wait"]


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and 'localhost'."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def start(host: str, port: int):
    """A running viser server on host:port (port 0: a free one)."""
    if not 0 <= port <= 65535:
        raise UserError(f"--port: expected 0..65535, got {port}")
    try:
        socket.getaddrinfo(host, None)
    except socket.gaierror:
        raise UserError(f"--host: {host!r} is not an address of this machine") from None
    if not is_loopback(host):
        print(f"warning: serving on {host}: anyone who can reach this machine on port {port} can use the viewer "
              "(use the default --host 127.0.0.1 to keep it to this machine)", file=sys.stderr)  # fmt: skip
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
    import viser

    with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner even with verbose=False
        return viser.ViserServer(host=host, port=port, verbose=False)


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
