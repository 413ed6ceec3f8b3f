"""The viser server: loopback by default, a loud warning for any other address, a clean stop.

`start(host, port)` refuses a port outside 1..65535 and a host that is not an address (UserError), prints a
warning on stderr when the host is not a loopback address (anyone who can reach it sees the scene and can use
the viewer), and returns the running `viser.ViserServer`. `serve_forever(server)` sleeps until Ctrl-C (or
`stop` is set) and then stops the server.
"""

from __future__ import annotations

import ipaddress
import socket
import sys
import threading

from data.errors import UserError

__all__ = ["is_loopback", "start", "serve_forever"]


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

    return viser.ViserServer(host=host, port=port, verbose=False)


def serve_forever(server, stop: threading.Event | None = None) -> None:
    """Block until Ctrl-C (KeyboardInterrupt) or `stop` is set; the server is stopped either way."""
    stop = stop or threading.Event()
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
