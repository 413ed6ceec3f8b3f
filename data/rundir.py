"""A stage's output folder: `config.json`, `metrics.csv`, `manifest.json` (written last: the Makefile sentinel).

manifest.json schema:
    {stage, nerfpipe_version, started (ISO time), wall_seconds, versions {python, torch, ...},
     inputs {path: sha256}, outputs [paths], used {what: detail}, left_out {what: why}, ...extra}
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import hashlib
import io
import os
import platform
import shutil
import time
from collections.abc import Iterable, Iterator, Mapping
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

from nerfpipe.data.atomic import write_json, write_text
from nerfpipe.data.errors import UserError
from nerfpipe.data.lock import LOCK_NAME, folder_lock

__all__ = [
    "config_to_json",
    "write_config",
    "write_manifest",
    "sha256_file",
    "versions",
    "sidecar",
    "MetricsLog",
    "Stopwatch",
    "output_folder",
    "previous_folder",
    "scene_from_run",
    "find_run_scene",
    "RUN_FILES",
    "refuse_output_inside",
]

_PACKAGES = (
    "nerfpipe",
    "torch",
    "numpy",
    "pycolmap",
    "opencv-contrib-python-headless",
    "scikit-image",
    "trimesh",
    "pymeshlab",
)


def sidecar(out: str | os.PathLike, what: str) -> Path:
    """`dir/name.mp4` -> `dir/name.<what>` (the manifest / metrics files written next to a file output)."""
    out = Path(out)
    return out.with_name(f"{out.stem}.{what}")


def versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def _jsonable(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and (value != value or value in (float("inf"), float("-inf"))):
        return str(value)  # strict JSON has no NaN/inf
    return value


def config_to_json(config: Any) -> dict[str, Any]:
    """A stage config dataclass as a JSON-ready dict (paths as strings, inf as "inf")."""
    return _jsonable(config)


def scene_from_run(run_dir: Path, scene: Path) -> str:
    """The scene folder relative to the run folder (both resolved): config.json's `scene_from_run`, so that a run
    moved together with its scene still finds it (`find_run_scene`)."""
    return os.path.relpath(Path(scene).resolve(), Path(run_dir).resolve())


def find_run_scene(run_dir: Path, doc: Mapping[str, Any], keys: Iterable[str]) -> list[Path]:
    """Where a run's scene may be, in the order to try: config.json's `scene_from_run` against the run folder,
    then each of `keys` that config.json holds (paths as recorded). The first that exists is the scene; the
    list is for messages too. Empty when config.json names none."""
    tried = [Path(run_dir) / doc["scene_from_run"]] if isinstance(doc.get("scene_from_run"), str) else []
    return tried + [Path(doc[k]) for k in keys if isinstance(doc.get(k), str)]


def write_config(folder: str | os.PathLike, config: Any) -> Path:
    return write_json(Path(folder) / "config.json", config_to_json(config))


def write_manifest(
    folder: str | os.PathLike,
    *,
    stage: str,
    started: float,
    inputs: Iterable[str | os.PathLike] = (),
    outputs: Iterable[str | os.PathLike] = (),
    used: Mapping[str, Any] | None = None,
    left_out: Mapping[str, str] | None = None,
    name: str = "manifest.json",
    **extra: Any,
) -> Path:
    """Write the provenance record. Call it LAST: its presence means the folder is complete.

    started: `time.time()` when the stage began; inputs are hashed (files) or listed (folders).
    """
    hashed = {}
    for p in inputs:
        p = Path(p)
        hashed[str(p)] = sha256_file(p) if p.is_file() else ("folder" if p.is_dir() else "missing")
    doc = {
        "stage": stage,
        "nerfpipe_version": versions().get("nerfpipe", "unknown"),
        "started": datetime.fromtimestamp(started, timezone.utc).isoformat(),
        "wall_seconds": round(time.time() - started, 3),
        "versions": versions(),
        "inputs": hashed,
        "outputs": [str(p) for p in outputs],
        "used": _jsonable(dict(used or {})),
        "left_out": dict(left_out or {}),
        **_jsonable(extra),
    }
    return write_json(Path(folder) / name, doc)


class Stopwatch:
    """Wall-clock seconds since construction (time.perf_counter)."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()

    def __call__(self) -> float:
        return time.perf_counter() - self.t0


class MetricsLog:
    """Error-vs-run-time log: rows of {step, seconds, ...}; `save()` rewrites the CSV atomically."""

    def __init__(self, path: str | os.PathLike, columns: Iterable[str]):
        self.path = Path(path)
        self.columns = list(columns)
        if self.columns[:2] != ["step", "seconds"]:
            raise ValueError(f"expected columns to start with step, seconds; got {self.columns[:2]}")
        self.rows: list[dict[str, Any]] = []

    def append(self, **row: Any) -> None:
        unknown = set(row) - set(self.columns)
        if unknown:
            raise ValueError(f"unknown metrics columns {sorted(unknown)}; expected {self.columns}")
        self.rows.append(row)

    def load(self) -> None:
        """Read existing rows (for --resume)."""
        if self.path.is_file():
            with open(self.path, newline="") as f:
                self.rows = [{k: v for k, v in r.items() if v != ""} for r in csv.DictReader(f)]

    def save(self) -> Path:
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=self.columns, restval="", lineterminator="\n")
        w.writeheader()
        w.writerows(self.rows)
        return write_text(self.path, buf.getvalue())


RUN_FILES = frozenset(
    {
        "config.json",
        "checkpoint.pt",
        "metrics.csv",
        "manifest.json",
        "psnr_vs_time.png",
        "per_view.json",
        "per_view_worst.png",
        "transforms.json",
        "volume.npy",
        LOCK_NAME,
    }
)
"""The names a run folder owns (what train and xray-train write there): a consumer's output may not take one."""


def refuse_output_inside(out: str | os.PathLike, run: str | os.PathLike, what: str = "output") -> None:
    """UserError when a consumer stage's output `out` (a file or a folder, as given) would damage the run folder
    `run` it reads: `out` is the run folder, holds it (an output folder's overwrite moves it aside), or is a file
    the run owns (RUN_FILES). A new name inside the run (RUN/eval.json, RUN/depth/) is allowed. Paths compare
    resolved (symlinks followed), so a link does not hide the run."""
    out_r, run_r = Path(out).resolve(), Path(run).resolve()
    if out_r == run_r:
        raise UserError(f"{out}: the {what} would be the run folder {run} itself; expected a path outside it")
    if out_r in run_r.parents:
        raise UserError(
            f"{out}: the {what} folder holds the run {run} (writing it would set the run aside); "
            "expected a path beside the run"
        )
    if out_r.parent == run_r and out_r.name in RUN_FILES:
        raise UserError(f"{out}: the run {run} owns {out_r.name}; expected another name for the {what}")


def previous_folder(folder: str | os.PathLike) -> Path:
    """Where `--overwrite` sets an earlier output aside: `FOLDER.previous/` beside it (as poses does with colmap/)."""
    folder = Path(folder)
    return folder.with_name(folder.name + ".previous")


@contextlib.contextmanager
def output_folder(
    folder: str | os.PathLike, *, overwrite: bool, resume: bool = False, marks: Iterable[str] = ("manifest.json",)
) -> Iterator[Path | None]:
    """Hold `folder`'s lock (`data.lock`) while a stage writes there, and apply the rerun rule.

    An earlier output (any of `marks` in the folder) is refused with one line unless `resume` (the stage continues
    it) or `overwrite`: then every entry is moved to FOLDER.previous/ (an older one there is deleted), which is
    deleted when the block ends without error and kept (with its name in the error) when it fails. Yields that
    folder or None. A folder this call created is removed again when the block fails leaving it empty.
    """
    folder = Path(folder)
    created = not folder.exists()
    try:
        with _claimed(folder, overwrite=overwrite, resume=resume, marks=marks) as previous:
            yield previous
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only when empty: a failed stage leaves no empty output folder behind
        raise


@contextlib.contextmanager
def _claimed(folder: Path, *, overwrite: bool, resume: bool, marks: Iterable[str]) -> Iterator[Path | None]:
    with folder_lock(folder):
        found = sorted(m for m in marks if (folder / m).exists())
        previous = None
        if found and not resume:
            if not overwrite:
                how = "resume=True to continue it or overwrite=True" if "checkpoint.pt" in found else "overwrite=True"
                raise UserError(
                    f"{folder} already holds an earlier output ({', '.join(found)}); set {how} to replace it"
                )
            previous = previous_folder(folder)
            shutil.rmtree(previous, ignore_errors=True)
            previous.mkdir()
            for entry in folder.iterdir():
                if entry.name != LOCK_NAME:
                    os.replace(entry, previous / entry.name)
        try:
            yield previous
        except UserError as exc:
            if previous is not None:
                exc.args = (f"{exc} (the earlier output is kept in {previous})",)
            raise
        if previous is not None:
            shutil.rmtree(previous, ignore_errors=True)
