"""Atomic file writes: write to a temporary name in the same folder, flush it to disk, then os.replace.

A failed or interrupted stage therefore never leaves a file that looks complete. A write that fails for a
reason outside the program (full disk, I/O error, permissions: `data.errors.WRITE_ERRNOS`) raises
`data.errors.WriteFailed` naming the target file and the cause (`no space left on device writing run/x.pt`);
the previous file of that name, if any, is left as it was. The data is fsync'ed before the rename, so a full disk
that the file system reports only on flush (delayed allocation) is caught here too, not after the rename.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from nerfpipe.data.errors import WRITE_ERRNOS, WriteFailed

__all__ = ["atomic_path", "write_bytes", "write_text", "write_json"]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success flush and rename it to `path`, on error delete it.

    `suffix` defaults to the target's suffix so libraries that pick a format by extension still work.
    OSErrors in WRITE_ERRNOS (raised by the caller's writes or here) become WriteFailed naming `path`.
    """
    path = Path(path)
    tmp_path = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix or ".tmp", dir=path.parent)
        os.close(fd)
        tmp_path = Path(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp makes 0600; a finished file gets the usual permissions
        yield tmp_path
        _fsync(tmp_path)
        os.replace(tmp_path, path)
    except BaseException as exc:
        if tmp_path is not None:
            tmp_path.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS:
            raise WriteFailed(path, exc) from exc
        raise


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write(f: Any, data: bytes | memoryview) -> None:
    """The one place `write_bytes` writes (tests patch it to inject faults)."""
    f.write(data)


def write_bytes(path: str | os.PathLike, data: bytes | memoryview) -> Path:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        _write(f, data)
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Strict JSON (NaN/inf refused), indented, newline-terminated."""
    return write_text(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")
