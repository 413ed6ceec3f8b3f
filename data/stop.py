"""Stop requests: SIGINT (Ctrl-C) and SIGTERM turned into a flag that a long loop polls between steps.

A loop that polls the flag can save what it has (a checkpoint) and raise `data.errors.Interrupted` with one line,
instead of dying wherever the signal lands. A second signal while the first is being handled raises
KeyboardInterrupt at once (the user insists; atomic writes keep files whole). Off the main thread (where Python
cannot install handlers) the flag never rises and signals keep their usual effect.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from dataclasses import dataclass

__all__ = ["StopRequest", "stop_on_signals"]


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
            raise KeyboardInterrupt
        request.signum = signum

    previous = {s: signal.signal(s, handler) for s in signums}
    try:
        yield request
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
