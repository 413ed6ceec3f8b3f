"""User-facing errors: one line, no traceback (cli.py prints them as `error: ...` and exits 2, or `exit_code`)."""

from __future__ import annotations

import errno
import os

__all__ = ["UserError", "WriteFailed", "Interrupted", "WRITE_ERRNOS"]

# Write failures that are the machine's state, not a bug: the user can act on them (free space, fix permissions).
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EACCES, errno.EPERM, errno.EROFS, errno.EFBIG})


class UserError(Exception):
    """Bad input from the user: the message is one line that names the file/field and what was expected."""

    exit_code = 2


class WriteFailed(UserError):
    """A write failed for a reason outside the program (full disk, I/O error, permissions): names file and cause."""

    def __init__(self, path: str | os.PathLike, exc: OSError):
        cause = os.strerror(exc.errno).lower() if exc.errno else str(exc)
        super().__init__(f"{cause} writing {path}")
        self.path, self.errno = path, exc.errno


class Interrupted(UserError):
    """SIGINT/SIGTERM stopped a stage cleanly (after saving what can be resumed); exits 130 or 143 (128 + signal)."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.exit_code = 128 + signum
