"""User-facing errors: one line, no traceback (cli.py prints them as `error: ...` and exits 2)."""

__all__ = ["UserError"]


class UserError(Exception):
    """Bad input from the user: the message is one line that names the file/field and what was expected."""
