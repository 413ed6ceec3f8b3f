"""Read a pickle without running code from it: the restricted unpickler for NAF / SAX-NeRF scans.

`pickle.load` calls whatever callable the file names (`os.system`, `exec`, ...), so a downloaded `*.pickle` can
run anything. NAF's data files hold only plain data: dicts, lists, tuples, numbers, strings, bools, None and
numpy arrays / scalars / dtypes. Those need no global at all except numpy's own pickling helpers, so
`load_restricted` answers `find_class` from a fixed table and refuses every other global with one line naming the
file and the global (`UserError`). Nothing named in the file is imported: the table maps each name to an object
this process already holds.

The globals numpy's pickling references (listed from numpy 2.4 at pickle protocols 0-5; numpy 1.x writes the same
helpers under `numpy.core`, which maps to the same objects):
- `numpy.core.multiarray._reconstruct` (numpy 2: `numpy._core.multiarray._reconstruct`) with `numpy.ndarray`:
  arrays, protocols 0-4; the data comes back through `ndarray.__setstate__`, which takes an object array (or a
  structured one holding objects) only from a list, whose items go through this same unpickler ("object pickle
  not returning list" for raw bytes: no pointer is read from the file).
- `numpy.core.numeric._frombuffer` (numpy 2: `numpy._core.numeric._frombuffer`): arrays, protocol 5
  (`np.frombuffer`, which refuses object dtypes).
- `numpy.dtype`: every array's and scalar's dtype.
- `numpy.core.multiarray.scalar` (numpy 2: `numpy._core.multiarray.scalar`): numpy scalars (`np.float64(1.5)`);
  it refuses the object dtype.
- `_codecs.encode`: how protocols 0-2 write `bytes` (the array's raw data); allowed only with the latin-1 codec
  those pickles use (a wrapper checks the codec name).

`load_trusted` is the plain `pickle.load`, for a file the user vouches for (xray-train's `trust_pickle`); no
reader that follows a path stored in a run calls it.
"""

from __future__ import annotations

import codecs
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from nerfpipe.data.errors import UserError

__all__ = ["ALLOWED_GLOBALS", "PickleRefused", "load_restricted", "load_trusted"]

try:  # numpy >= 2
    from numpy._core.multiarray import _reconstruct, scalar
    from numpy._core.numeric import _frombuffer
except ImportError:  # numpy 1.x
    from numpy.core.multiarray import _reconstruct, scalar  # type: ignore[no-redef]
    from numpy.core.numeric import _frombuffer  # type: ignore[no-redef]


def _latin1_encode(obj: str, encoding: str = "utf-8", errors: str = "strict") -> bytes:
    """`_codecs.encode` as pickle protocols 0-2 use it for bytes (`encode(text, 'latin1')`), and nothing else
    (no codec is looked up by a name from the file)."""
    if encoding not in ("latin1", "latin-1") or not isinstance(obj, str) or errors != "strict":
        raise pickle.UnpicklingError(f"_codecs.encode with codec {encoding!r}: only latin-1 (bytes) is allowed")
    return codecs.encode(obj, "latin-1")


ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    **{(mod, "_reconstruct"): _reconstruct for mod in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{(mod, "scalar"): scalar for mod in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{(mod, "_frombuffer"): _frombuffer for mod in ("numpy.core.numeric", "numpy._core.numeric")},
    ("_codecs", "encode"): _latin1_encode,
}
"""(module, name) -> the object it stands for; everything a NAF pickle's arrays need, nothing else."""


class PickleRefused(UserError):
    """The file names a global outside ALLOWED_GLOBALS (callers add how to go on: a trust setting, or none)."""

    def __init__(self, path: Path, global_name: str) -> None:
        super().__init__(
            f"{path}: refused to unpickle global '{global_name}': a scan pickle may hold only dicts, lists, "
            "numbers, strings and numpy arrays, and unpickling anything else could run code from the file"
        )
        self.path, self.global_name = path, global_name


class _Refused(pickle.UnpicklingError):
    def __init__(self, module: str, name: str) -> None:
        super().__init__(f"{module}.{name}")
        self.global_name = f"{module}.{name}"


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        try:
            return ALLOWED_GLOBALS[module, name]
        except KeyError:
            raise _Refused(module, name) from None

    def persistent_load(self, pid: Any) -> Any:
        raise pickle.UnpicklingError("persistent ids are not allowed")


def load_restricted(path: str | os.PathLike) -> Any:
    """Unpickle `path` allowing only plain data and numpy arrays: PickleRefused (a UserError) naming the file and
    the first global outside ALLOWED_GLOBALS, UserError when the file is damaged or unreadable."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return _RestrictedUnpickler(f).load()
    except _Refused as exc:
        raise PickleRefused(path, exc.global_name) from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except Exception as exc:  # a damaged pickle raises many types
        raise UserError(f"{path}: cannot read pickle ({type(exc).__name__}: {exc})") from None


def load_trusted(path: str | os.PathLike) -> Any:
    """Plain `pickle.load`: runs whatever the file names. Only for a file the user has said they trust."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return pickle.load(f)  # noqa: S301 -- the user trusts this file (trust_pickle)
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except Exception as exc:  # unpickling raises many types
        raise UserError(f"{path}: cannot read pickle ({type(exc).__name__}: {exc})") from None
