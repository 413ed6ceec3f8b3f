"""What stages report progress to: a `rich.progress.Progress`-shaped object the CLI owns, or nothing.

Stages take `progress: Progress | None` and never build a display themselves; `None` means silent
(`NO_PROGRESS`). The CLI creates the one live display (cli.py) and passes it in.
"""

from __future__ import annotations

from typing import Any, Protocol

__all__ = ["Progress", "NO_PROGRESS"]


class Progress(Protocol):
    """The subset of `rich.progress.Progress` stages use."""

    def add_task(self, description: str, total: float | None = None, **fields: Any) -> Any: ...

    def advance(self, task_id: Any, advance: float = 1) -> None: ...

    def update(self, task_id: Any, **fields: Any) -> None: ...


class _Silent:
    """A Progress that shows nothing."""

    def add_task(self, description: str, total: float | None = None, **fields: Any) -> int:
        return 0

    def advance(self, task_id: Any, advance: float = 1) -> None:
        pass

    def update(self, task_id: Any, **fields: Any) -> None:
        pass


NO_PROGRESS: Progress = _Silent()
