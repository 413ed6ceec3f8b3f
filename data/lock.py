"""One writer per output folder: `FOLDER/.nerfpipe.lock`, held with flock(2) for as long as a stage writes there.

The file holds the holder's pid (and command line) for the refusal message. The kernel drops a flock when its
process dies, however it dies (kill -9 included), so a lock file left by a dead process is taken over without any
pid guessing; a live holder makes a second process refuse with one line naming its pid. flock is per open file
description, so two acquisitions in one process also exclude each other (what the tests use).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from nerfpipe.data.errors import WRITE_ERRNOS, UserError, WriteFailed

__all__ = ["LOCK_NAME", "FolderBusy", "folder_lock"]

LOCK_NAME = ".nerfpipe.lock"


class FolderBusy(UserError):
    """Another live process holds the folder's lock."""


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Create `folder` if needed and hold its lock until the block ends; FolderBusy when another process holds it."""
    folder = Path(folder)
    path = folder / LOCK_NAME
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = _acquire(path)
    except OSError as exc:
        if exc.errno in WRITE_ERRNOS:
            raise WriteFailed(path, exc) from exc
        raise
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()} {' '.join(sys.argv)[:200]}\n".encode())
        yield path
    finally:
        with contextlib.suppress(OSError):
            path.unlink()  # before the unlock: a process that opens the path from now on makes a new file
        os.close(fd)


def _acquire(path: Path) -> int:
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 200).decode(errors="replace").split()
            os.close(fd)
            pid = holder[0] if holder else "unknown"
            raise FolderBusy(f"{path.parent} is being written by another nerfpipe process (pid {pid}); "
                             f"wait for it to finish or stop it") from None  # fmt: skip
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # the holder removed the file between our open and flock: lock the new one
