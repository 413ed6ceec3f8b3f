"""One writer per output folder: `FOLDER/.nerfpipe.lock`, held with flock(2) for as long as a stage writes there.

The file holds the holder's pid (and command line) for the refusal message. The kernel drops a flock when its
process dies, however it dies (kill -9 included), so a lock file left by a dead process is taken over without any
pid guessing; a live holder makes a second process refuse with one line naming its pid. flock is per open file
description, so two acquisitions in one process also exclude each other (what the tests use).

The lock file is opened without following a symlink (O_NOFOLLOW) and used only when it is a regular file of this
user with one link: a `.nerfpipe.lock` planted as a symlink or hard link to another file would otherwise have that
file truncated and overwritten with "pid cmdline". Such a lock is refused with one line (UserError).

Taking the lock sweeps what dead writers left in the folder (`sweep_stale`): poses' build folders
(`.colmap.tmp-*`, made only while poses holds this lock, so none is live) and `data.atomic`'s temporaries
(`.NAME.XXXXXXXX.SUFFIX`) untouched for STALE_SECONDS (eval, render and mesh write a file into a folder they do
not lock, so a fresh temporary may be a live writer's).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import re
import shutil
import stat
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from nerfpipe.data.errors import WRITE_ERRNOS, UserError, WriteFailed

__all__ = ["LOCK_NAME", "STALE_SECONDS", "FolderBusy", "folder_lock", "sweep_stale"]

LOCK_NAME = ".nerfpipe.lock"
STALE_SECONDS = 600.0
"""A `data.atomic` temporary not modified for this long belongs to no live writer (a live one writes it within
seconds: checkpoints, JSON, images; a video is written frame by frame)."""
COLMAP_BUILD = ".colmap.tmp-"
"""poses' build folder prefix (`stages.poses`: tempfile.mkdtemp in the scene folder, under this lock)."""
_ATOMIC_TMP = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}(?P<suffix>\.[A-Za-z0-9]+)$")
"""`data.atomic.atomic_path`'s temporary: tempfile.mkstemp(prefix=f".{name}.", suffix=...) (8 random characters)."""
_CUSTOM_SUFFIXES = frozenset({".tmp", ".png", ".npy", ".npz", ".ply"})
"""The suffixes atomic_path's callers pass (or its default for a target without one)."""


class FolderBusy(UserError):
    """Another live process holds the folder's lock."""


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Create `folder` if needed and hold its lock until the block ends; FolderBusy when another process holds it,
    UserError when the lock file is not a regular file of this user (module doc). Sweeps stale temporaries."""
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
        sweep_stale(folder)
        yield path
    finally:
        with contextlib.suppress(OSError):
            path.unlink()  # before the unlock: a process that opens the path from now on makes a new file
        os.close(fd)


def sweep_stale(folder: Path, now: float | None = None) -> list[str]:
    """Remove what dead writers left in `folder` (module doc); the names removed. Call it holding the lock."""
    now = time.time() if now is None else now
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        try:
            if entry.name.startswith(COLMAP_BUILD) and entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            elif _is_atomic_tmp(entry.name) and entry.is_file(follow_symlinks=False):
                if now - entry.stat(follow_symlinks=False).st_mtime < STALE_SECONDS:
                    continue
                os.unlink(entry.path)
            else:
                continue
        except OSError:
            continue  # gone already, or not ours to remove: leave it
        removed.append(entry.name)
    return removed


def _is_atomic_tmp(name: str) -> bool:
    m = _ATOMIC_TMP.match(name)
    return m is not None and m["suffix"] in {Path(m["name"]).suffix, *_CUSTOM_SUFFIXES}


def _open_lock(path: Path) -> int:
    """The lock file's descriptor, not following a symlink; UserError when it is not a regular file of ours."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.EISDIR, errno.ENXIO):
            what = "a symbolic link" if exc.errno == errno.ELOOP else "not a regular file"
            raise UserError(
                f"{path}: the lock file is {what}; expected a regular file (remove it if no nerfpipe "
                f"process writes {path.parent})"
            ) from None
        raise
    st = os.fstat(fd)
    why = (
        "not a regular file"
        if not stat.S_ISREG(st.st_mode)
        else f"owned by uid {st.st_uid}, not this user"
        if st.st_uid != os.geteuid()
        else f"a hard link ({st.st_nlink} names)"
        if st.st_nlink > 1
        else ""
    )
    if why:
        os.close(fd)
        raise UserError(
            f"{path}: the lock file is {why}; expected a regular file of this user (remove it if no "
            f"nerfpipe process writes {path.parent})"
        )
    return fd


def _acquire(path: Path) -> int:
    while True:
        fd = _open_lock(path)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 200).decode(errors="replace").split()
            os.close(fd)
            pid = holder[0] if holder else "unknown"
            raise FolderBusy(
                f"{path.parent} is being written by another nerfpipe process (pid {pid}); "
                f"wait for it to finish or stop it"
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path, follow_symlinks=False).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # the holder removed the file between our open and flock: lock the new one
