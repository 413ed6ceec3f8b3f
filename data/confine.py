"""Reading a dataset someone else made: what its files name stays inside its folder, and its JSON cannot
exhaust the stack.

A dataset names files relative to its folder (transforms.json's `file_path`, `mask_path`, `depth_file_path`,
`sparse_points_path`, a COLMAP model's image names, LLFF's image folder). `inside` resolves such a name
(symlinks followed) and refuses it, with one line naming the field and the path, when it is absolute, leads out
with `..`, or reaches outside the folder through a symlink: a downloaded dataset must not make `convert` copy
`~/.ssh/id_rsa` into images/ or `view` send it to a browser. `read_json` reads a JSON file and turns every way
it can fail (not UTF-8, not JSON, nested too deeply for the parser) into one line naming the file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from nerfpipe.data.errors import UserError

__all__ = ["inside", "read_json"]


def _resolve(path: Path, file: str | os.PathLike, what: str, rel: object) -> Path:
    try:
        return path.resolve()
    except RuntimeError:  # Python < 3.13: "Symlink loop from ..."
        raise UserError(f"{file}: {what} '{rel}' cannot be resolved: symlink loop") from None
    except (OSError, ValueError) as e:  # ELOOP, ENAMETOOLONG, an embedded NUL byte
        reason = os.strerror(e.errno).lower() if isinstance(e, OSError) and e.errno else str(e)
        raise UserError(f"{file}: {what} '{rel}' cannot be resolved: {reason}") from None


def inside(
    root: str | os.PathLike, relative: str | os.PathLike, what: str, *, file: str | os.PathLike | None = None
) -> Path:
    """`root / relative` resolved (symlinks followed; it need not exist). UserError naming `file` (default
    `root`), the field `what` and the path when `relative` is absolute or the result is not inside `root`."""
    root = Path(root)
    file = root if file is None else file
    if not isinstance(relative, str | os.PathLike) or not str(relative):
        raise UserError(f"{file}: {what}: expected a non-empty path relative to the dataset folder {root}")
    root_resolved = _resolve(root, file, "the dataset folder", root)
    path = _resolve(root / relative, file, what, relative)
    if path != root_resolved and root_resolved not in path.parents:
        raise UserError(f"{file}: {what} '{relative}' resolves outside the dataset folder {root}")
    if Path(relative).is_absolute():
        raise UserError(
            f"{file}: {what} '{relative}' is an absolute path; expected one relative to the dataset folder {root}"
        )
    return path


def read_json(path: str | os.PathLike) -> Any:
    """The JSON document in `path`; UserError naming the file when it cannot be read or parsed."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise UserError(f"{path}: not valid JSON ({e})") from None
    except RecursionError:
        raise UserError(f"{path}: not valid JSON (nested too deeply)") from None
    except OSError as e:
        reason = os.strerror(e.errno).lower() if e.errno else str(e)
        raise UserError(f"{path}: cannot read ({reason})") from None
