"""Stop requests: SIGINT (Ctrl-C) and SIGTERM turned into a flag that a long loop polls between steps.

A loop that polls the flag can save what it has (a checkpoint) and raise `data.errors.Interrupted` with one line,
instead of dying wherever the signal lands. A second signal while the first is being handled raises
KeyboardInterrupt at once (the user insists; atomic writes keep files whole). Off the main thread (where Python
cannot install handlers) the flag never rises and signals keep their usual effect.

Every other stage stops where it is: `sigterm_raises` (installed by `cli.main` for the whole command) makes
SIGTERM raise `Terminated`, a KeyboardInterrupt, wherever the program is, so that a stage killed by a scheduler
unwinds as on Ctrl-C (atomic writes delete their temporaries, render removes its frames) and the CLI prints one
line and exits 143 instead of dying silently. `stop_on_signals` inside that block replaces the handler for its
own block and puts it back after. Importing pycolmap installs glog's failure-signal handler at the C level, behind
Python's back (it answers SIGTERM with a 35-line stack trace); `reclaim_sigterm`, called by the CLI once the stage
is imported, puts Python's handler back.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from dataclasses import dataclass

__all__ = ["StopRequest", "Terminated", "reclaim_sigterm", "sigterm_raises", "stop_on_signals"]


@dataclass
class StopRequest:
    signum: int | None = None
    """The signal that asked to stop (signal.SIGINT or signal.SIGTERM), None while none has."""

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else ""


@contextlib.contextmanager
def stop_on_signals(signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[StopRequest]:
    """Within the block, the signals set `request.signum` instead of interrupting; handlers restored after."""
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return

    def handler(signum: int, frame: object) -> None:
        if request.signum is not None:
            raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt
        request.signum = signum

    previous = {s: signal.signal(s, handler) for s in signums}
    try:
        yield request
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program was (see `sigterm_raises`). A KeyboardInterrupt, so that everything that
    cleans up after Ctrl-C cleans up after it, and `except Exception` does not swallow it."""

    signum = signal.SIGTERM


@contextlib.contextmanager
def sigterm_raises() -> Iterator[None]:
    """Within the block, SIGTERM raises `Terminated`; a second SIGTERM (while the first unwinds) kills at once, as
    SIGTERM does by default. The previous handler is restored after. A SIGTERM that the parent set to be ignored
    stays ignored, and off the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: object) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        raise Terminated

    previous = signal.getsignal(signal.SIGTERM)
    if previous == signal.SIG_IGN:
        yield
        return
    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def reclaim_sigterm() -> None:
    """Install again the SIGTERM handler Python believes is current (`signal.getsignal`): a C extension's import
    may have replaced it at the C level (pycolmap: glog's stack-trace handler). Off the main thread: nothing."""
    if threading.current_thread() is threading.main_thread():
        current = signal.getsignal(signal.SIGTERM)
        if current is not None:
            signal.signal(signal.SIGTERM, current)
