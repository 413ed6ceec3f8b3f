"""The projection scene (X-ray / CT): geometry, line integrals, splits and an optional ground-truth volume.

A scene is a folder (docs/DESIGN.md "Projection scenes"):
    projections.json   geometry (mode, dso, dsd, detector shape/pitch/offset, per-view angles), units, splits,
                       the reconstruction grid, noise, provenance; written last (the folder is complete)
    projections.npy    float32 [V, n_v, n_u] line integrals p = -log(I / I0) (dimensionless)
    volume.npy         optional ground truth: float32 [nx, ny, nz] mu per length unit on `grid`

Lengths are in `length_unit` (readers convert to mm); the frame and pixel conventions are radiance.xray's.
Readers for what users of the field already have:
- `read_naf_pickle`: NAF / SAX-NeRF `*.pickle` (TIGRE geometry in mm, `train`/`val` dicts with `angles` and
  `projections`, `image` the volume in [x, y, z]). Their projections are line integrals over lengths in
  metres with the volume in 1/m, so lengths stay in mm and the volume is divided by 1000 (1/mm).
  The pickle is read with `data.safe_pickle.load_restricted` (plain data and numpy arrays only; any other
  global is refused, so no code from the file runs); `trust=True` (xray-train's `trust_pickle`) unpickles it
  plainly, for a file the user vouches for.
- `read_r2_gaussian`: R2-Gaussian's `meta_data.json` + `proj_*/*.npy` (+ `vol_gt.npy`); its scanner lengths are
  metres (its own NAF converter multiplies by 1000 for mm): lengths x 1000, the volume / 1000.
TIGRE orders are kept as those projects write them: `nDetector`, `dDetector`, `sDetector` are [v, u];
`offDetector` is [u, v]; `nVoxel`/`dVoxel`/`sVoxel`/`offOrigin` are [x, y, z].

Every reader and `write_projection_scene` validate the whole scene first and raise a one-line
`data.errors.UserError` naming the field (nothing is written on error): detector behind the source (dsd <= 0)
or not beyond the axis (dsd <= dso), projection count != angle count, detector shape mismatch, non-finite
values, negative attenuation, split indices out of range.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from nerfpipe.data.atomic import write_json
from nerfpipe.data.confine import inside, read_json
from nerfpipe.data.errors import UserError
from nerfpipe.data.safe_pickle import load_restricted, load_trusted
from nerfpipe.data.volumes import check_volume, write_npy
from nerfpipe.radiance.xray import VoxelGrid, XrayGeometry

__all__ = [
    "FORMAT",
    "ProjectionScene",
    "validate_geometry",
    "validate_scene",
    "read_projection_scene",
    "write_projection_scene",
    "read_naf_pickle",
    "read_r2_gaussian",
    "read_any",
]

FORMAT = "nerfpipe-projections"
VERSION = 1
JSON_NAME, PROJ_NAME, VOLUME_NAME = "projections.json", "projections.npy", "volume.npy"


@dataclass(frozen=True, kw_only=True)
class ProjectionScene:
    """An X-ray scan: `projections [V, n_v, n_u]` float32 line integrals, one per `geometry.angles` entry."""

    geometry: XrayGeometry
    projections: np.ndarray
    splits: dict[str, tuple[int, ...]]
    grid: VoxelGrid
    """Where the object is (and where reconstructions are sampled): the ground truth's grid when known."""
    volume: np.ndarray | None = None
    """Ground truth mu [nx, ny, nz] on `grid` (1 / length_unit), or None."""
    noise: dict | None = None
    """How the projections were made noisy ({"model": "poisson", "i0": ..., "starved_pixels": ...}) or None."""
    root: Path | None = None
    extra: dict = field(default_factory=dict)
    """Provenance and unknown keys, kept on write."""

    @property
    def length_unit(self) -> str:
        return self.geometry.length_unit

    def split(self, name: str) -> tuple[int, ...]:
        return self.splits.get(name, ())


# ---------------------------------------------------------------------------------------------- validation
def _positive(value: Any, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise UserError(f"{name}: expected a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise UserError(f"{name}: expected a finite number > 0, got {value!r}")
    return v


def _pair(value: Any, name: str, kind=float) -> tuple:
    try:
        items = [kind(v) for v in value]
    except (TypeError, ValueError):
        raise UserError(f"{name}: expected two numbers [v, u], got {value!r}") from None
    if len(items) != 2:
        raise UserError(f"{name}: expected two numbers [v, u], got {value!r}")
    return tuple(items)


def validate_geometry(g: XrayGeometry, where: str = "geometry") -> XrayGeometry:
    """Refuse impossible geometries with one line naming the field."""
    if g.mode not in ("cone", "parallel"):
        raise UserError(f"{where}.mode: expected 'cone' or 'parallel', got {g.mode!r}")
    dso = _positive(g.dso, f"{where}.dso")
    try:
        dsd = float(g.dsd)
    except (TypeError, ValueError):
        raise UserError(f"{where}.dsd: expected a number, got {g.dsd!r}") from None
    if not math.isfinite(dsd) or dsd <= 0:
        raise UserError(f"{where}.dsd: the detector is behind the source (dsd = {g.dsd} <= 0); expected dsd > dso")
    if dsd <= dso:
        raise UserError(
            f"{where}.dsd: the detector must lie beyond the rotation axis: expected dsd > dso = {dso:g}, got {dsd:g}"
        )
    shape = _pair(g.detector_shape, f"{where}.detector_shape", int)
    if min(shape) < 1:
        raise UserError(f"{where}.detector_shape: expected positive pixel counts [n_v, n_u], got {list(shape)}")
    pitch = tuple(_positive(p, f"{where}.detector_pitch") for p in _pair(g.detector_pitch, f"{where}.detector_pitch"))
    offset = _pair(g.detector_offset, f"{where}.detector_offset")
    if not all(math.isfinite(o) for o in offset):
        raise UserError(f"{where}.detector_offset: expected finite numbers, got {list(offset)}")
    angles = np.asarray(g.angles, dtype=np.float64).reshape(-1)
    if not np.isfinite(angles).all():
        raise UserError(f"{where}.angles: {int((~np.isfinite(angles)).sum())} non-finite angles")
    return replace(
        g,
        dso=dso,
        dsd=dsd,
        detector_shape=shape,
        detector_pitch=pitch,
        detector_offset=offset,
        angles=tuple(angles.tolist()),
    )


def _validate_grid(grid: VoxelGrid) -> VoxelGrid:
    shape = tuple(int(n) for n in grid.shape)
    if len(shape) != 3 or min(shape) < 1:
        raise UserError(f"grid.shape: expected three positive voxel counts, got {list(grid.shape)}")
    if len(grid.spacing) != 3:
        raise UserError(f"grid.spacing: expected three voxel sizes, got {list(grid.spacing)}")
    spacing = tuple(_positive(s, "grid.spacing") for s in grid.spacing)
    center = tuple(float(c) for c in grid.center)
    if len(center) != 3 or not all(math.isfinite(c) for c in center):
        raise UserError(f"grid.center: expected three finite numbers, got {list(grid.center)}")
    return VoxelGrid(shape=shape, spacing=spacing, center=center)


def validate_scene(scene: ProjectionScene) -> ProjectionScene:
    """The whole scene, checked; returns it with normalised types (float32 arrays, tuples)."""
    g = validate_geometry(scene.geometry)
    proj = np.asarray(scene.projections)
    if proj.ndim != 3:
        raise UserError(f"projections: expected [views, n_v, n_u], got shape {tuple(proj.shape)}")
    if proj.shape[0] != g.n_views:
        raise UserError(f"projections: {proj.shape[0]} projections but {g.n_views} angles in geometry.angles")
    if tuple(proj.shape[1:]) != tuple(g.detector_shape):
        raise UserError(
            f"projections: images are {list(proj.shape[1:])} but geometry.detector_shape is "
            f"{list(g.detector_shape)} [n_v, n_u]"
        )
    if not np.issubdtype(proj.dtype, np.number):
        raise UserError(f"projections: expected numbers, got dtype {proj.dtype}")
    proj = proj.astype(np.float32)
    bad = ~np.isfinite(proj)
    if bad.any():
        v, j, i = (int(x) for x in np.argwhere(bad)[0])
        raise UserError(
            f"projections: {int(bad.sum())} non-finite line integrals (first: view {v}, row {j}, "
            f"column {i}); expected finite -log(I/I0)"
        )
    splits = {}
    for name, idx in scene.splits.items():
        try:
            ids = tuple(int(i) for i in idx)
        except (TypeError, ValueError):
            raise UserError(f"splits.{name}: expected view indices, got {idx!r}") from None
        out = [i for i in ids if not 0 <= i < g.n_views]
        if out:
            raise UserError(f"splits.{name}: view index {out[0]} out of range [0, {g.n_views})")
        splits[name] = ids
    if not splits.get("train"):
        raise UserError("splits.train: expected at least one training view")
    grid = _validate_grid(scene.grid)
    volume = None
    if scene.volume is not None:
        volume = check_volume(scene.volume, "volume")
        if tuple(volume.shape) != grid.shape:
            raise UserError(f"volume: shape {list(volume.shape)} differs from grid.shape {list(grid.shape)}")
    return replace(scene, geometry=g, projections=proj, splits=splits, grid=grid, volume=volume)


# ---------------------------------------------------------------------------------------------- our format
def _scene_json(scene: ProjectionScene) -> dict:
    g = scene.geometry
    return {
        "format": FORMAT,
        "version": VERSION,
        "length_unit": g.length_unit,
        "attenuation_unit": f"1/{g.length_unit}",
        "geometry": {
            "mode": g.mode,
            "dso": g.dso,
            "dsd": g.dsd,
            "detector_shape": list(g.detector_shape),
            "detector_pitch": list(g.detector_pitch),
            "detector_offset": list(g.detector_offset),
            "angles": list(g.angles),
        },
        "projections": {
            "file": PROJ_NAME,
            "quantity": "line_integral",
            "dtype": "float32",
            "shape": [g.n_views, *g.detector_shape],
        },
        "splits": {k: list(v) for k, v in scene.splits.items()},
        "grid": {
            "shape": list(scene.grid.shape),
            "spacing": list(scene.grid.spacing),
            "center": list(scene.grid.center),
        },
        "volume": None if scene.volume is None else {"file": VOLUME_NAME, "dtype": "float32"},
        "noise": scene.noise,
        **scene.extra,
    }


def write_projection_scene(scene: ProjectionScene, folder: str | os.PathLike) -> Path:
    """Validate, then write the arrays and projections.json (last), each atomically. Returns the JSON path."""
    scene = validate_scene(scene)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_npy(folder / PROJ_NAME, scene.projections)
    if scene.volume is not None:
        write_npy(folder / VOLUME_NAME, scene.volume)
    return write_json(folder / JSON_NAME, _scene_json(scene))


def _get(doc: Mapping, key: str, where: str) -> Any:
    if not isinstance(doc, Mapping) or key not in doc:
        raise UserError(f"{where}: missing field {key!r}")
    return doc[key]


def _load_array(path: Path, name: str) -> np.ndarray:
    if not path.is_file():
        raise UserError(f"{name}: missing file {path}")
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise UserError(f"{name}: cannot read {path} ({exc})") from None


def read_projection_scene(path: str | os.PathLike) -> ProjectionScene:
    """Read a scene folder (or its projections.json); UserError naming the file and field when invalid."""
    path = Path(path)
    if path.is_dir():
        path = path / JSON_NAME
    if not path.is_file():
        raise UserError(f"{path}: no projection scene here (expected {JSON_NAME})")
    doc = read_json(path)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise UserError(f"{path}: not a nerfpipe projection scene (format {FORMAT!r})")
    root = path.parent
    where = str(path)
    gd = _get(doc, "geometry", where)
    geometry = XrayGeometry(
        mode=_get(gd, "mode", f"{where}: geometry"),
        dso=_get(gd, "dso", f"{where}: geometry"),
        dsd=_get(gd, "dsd", f"{where}: geometry"),
        detector_shape=tuple(_get(gd, "detector_shape", f"{where}: geometry")),
        detector_pitch=tuple(_get(gd, "detector_pitch", f"{where}: geometry")),
        detector_offset=tuple(gd.get("detector_offset", (0.0, 0.0))),
        angles=tuple(_get(gd, "angles", f"{where}: geometry")),
        length_unit=str(doc.get("length_unit", "mm")),
    )
    pd = _get(doc, "projections", where)
    projections = _load_array(
        inside(root, str(_get(pd, "file", f"{where}: projections")), "projections.file", file=path), "projections"
    )
    gr = _get(doc, "grid", where)
    grid = VoxelGrid(shape=tuple(gr["shape"]), spacing=tuple(gr["spacing"]), center=tuple(gr.get("center", (0, 0, 0))))
    vd = doc.get("volume")
    volume = (
        _load_array(inside(root, str(_get(vd, "file", f"{where}: volume")), "volume.file", file=path), "volume")
        if vd
        else None
    )
    known = {
        "format",
        "version",
        "length_unit",
        "attenuation_unit",
        "geometry",
        "projections",
        "splits",
        "grid",
        "volume",
        "noise",
    }
    scene = ProjectionScene(
        geometry=geometry,
        projections=projections,
        splits=dict(_get(doc, "splits", where)),
        grid=grid,
        volume=volume,
        noise=doc.get("noise"),
        root=root,
        extra={k: v for k, v in doc.items() if k not in known},
    )
    try:
        return validate_scene(scene)
    except UserError as exc:
        raise UserError(f"{path}: {exc}") from None


# ---------------------------------------------------------------------------------------------- NAF / R2-Gaussian
def _tigre_geometry(d: Mapping, scale: float, angles: np.ndarray, where: str) -> XrayGeometry:
    """TIGRE-style keys (lengths x `scale` -> mm) -> XrayGeometry."""
    n_det = _get(d, "nDetector", where)
    if "dDetector" in d:
        pitch = np.asarray(d["dDetector"], np.float64) * scale
    else:
        pitch = np.asarray(_get(d, "sDetector", where), np.float64) * scale / np.asarray(n_det, np.float64)
    off_uv = np.asarray(d.get("offDetector", (0.0, 0.0)), np.float64).reshape(-1)[:2] * scale
    return XrayGeometry(
        mode=str(d.get("mode", "cone")),
        dso=float(_get(d, "DSO", where)) * scale,
        dsd=float(_get(d, "DSD", where)) * scale,
        detector_shape=tuple(int(n) for n in n_det),
        detector_pitch=tuple(float(p) for p in pitch),
        detector_offset=(float(off_uv[1]), float(off_uv[0])),
        angles=tuple(float(a) for a in np.asarray(angles, np.float64).reshape(-1)),
        length_unit="mm",
    )


def _tigre_grid(d: Mapping, shape: Sequence[int], scale: float) -> VoxelGrid:
    n = np.asarray(d.get("nVoxel", shape), np.float64)
    if "dVoxel" in d:
        spacing = np.asarray(d["dVoxel"], np.float64) * scale
    elif "sVoxel" in d:
        spacing = np.asarray(d["sVoxel"], np.float64) * scale / n
    else:
        raise UserError("dVoxel: the scan gives no voxel size (dVoxel or sVoxel)")
    center = np.asarray(d.get("offOrigin", (0.0, 0.0, 0.0)), np.float64).reshape(-1)[:3] * scale
    return VoxelGrid(shape=tuple(int(v) for v in n), spacing=tuple(spacing.tolist()), center=tuple(center.tolist()))


def _stack_splits(parts: Sequence[tuple[str, np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, dict]:
    projs, angles, splits, start = [], [], {}, 0
    for name, p, a in parts:
        p = np.asarray(p)
        a = np.asarray(a, np.float64).reshape(-1)
        if p.ndim != 3:
            raise UserError(f"{name}.projections: expected [views, n_v, n_u], got shape {tuple(p.shape)}")
        if p.shape[0] != a.shape[0]:
            raise UserError(f"{name}.projections: {p.shape[0]} projections but {a.shape[0]} angles")
        projs.append(p)
        angles.append(a)
        splits[name] = tuple(range(start, start + a.shape[0]))
        start += a.shape[0]
    return np.concatenate(projs), np.concatenate(angles), splits


def read_naf_pickle(path: str | os.PathLike, *, trust: bool = False) -> ProjectionScene:
    """A NAF / SAX-NeRF `*.pickle` scan -> ProjectionScene (mm; volume / 1000 -> 1/mm). `val` becomes `test`.

    Read with the restricted unpickler (`data.safe_pickle.PickleRefused` for a file naming any global beyond
    numpy's array helpers); `trust=True` runs the plain `pickle.load`, which runs code the file names.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    d = load_trusted(path) if trust else load_restricted(path)
    where = str(path)
    if not isinstance(d, dict):
        raise UserError(f"{path}: expected a NAF dict, got {type(d).__name__}")
    parts = []
    for name, key in (("train", "train"), ("test", "val"), ("test", "test")):
        if key in d and not any(p[0] == name for p in parts):
            sub = d[key]
            parts.append((name, _get(sub, "projections", f"{where}: {key}"), _get(sub, "angles", f"{where}: {key}")))
    if not parts:
        raise UserError(f"{path}: missing field 'train'")
    projs, angles, splits = _stack_splits(parts)
    image = d.get("image")
    volume = None if image is None else np.asarray(image, np.float64) / 1000.0  # 1/m -> 1/mm
    shape = image.shape if image is not None else tuple(_get(d, "nVoxel", where))
    try:
        scene = ProjectionScene(
            geometry=_tigre_geometry(d, 1.0, angles, where),
            projections=projs,
            splits=splits,
            grid=_tigre_grid(d, shape, 1.0),
            volume=volume,
            root=path.parent,
            extra={"source": {"format": "naf-pickle", "path": str(path)}},
        )
        return validate_scene(scene)
    except UserError as exc:
        raise UserError(f"{path}: {exc}") from None


def read_r2_gaussian(folder: str | os.PathLike) -> ProjectionScene:
    """R2-Gaussian's `meta_data.json` + `proj_train`/`proj_test` `.npy` files (+ `vol`): metres -> mm."""
    folder = Path(folder)
    meta_path = folder / "meta_data.json" if folder.is_dir() else folder
    folder = meta_path.parent
    if not meta_path.is_file():
        raise UserError(f"{meta_path}: no such file")
    meta = read_json(meta_path)
    where = str(meta_path)
    scanner = _get(meta, "scanner", where)
    parts = []
    for name in ("train", "test"):
        entries = meta.get(f"proj_{name}") or []
        if not entries and name == "train":
            raise UserError(f"{meta_path}: missing field 'proj_train'")
        if not entries:
            continue
        try:
            files = [inside(folder, str(e["file_path"]), f"proj_{name} file_path", file=meta_path) for e in entries]
            angles = np.array([float(e["angle"]) for e in entries])
        except (KeyError, TypeError, ValueError):
            raise UserError(f"{meta_path}: proj_{name}: expected entries {{file_path, angle}}") from None
        projs = np.stack([_load_array(f, f"proj_{name}") for f in files])
        parts.append((name, projs, angles))
    projs, angles, splits = _stack_splits(parts)
    volume = None
    if meta.get("vol"):
        volume = (
            _load_array(inside(folder, str(meta["vol"]), "vol", file=meta_path), "vol").astype(np.float64) / 1000.0
        )  # 1/m -> 1/mm
    shape = volume.shape if volume is not None else tuple(_get(scanner, "nVoxel", where))
    try:
        scene = ProjectionScene(
            geometry=_tigre_geometry(scanner, 1000.0, angles, where),
            projections=projs,
            splits=splits,
            grid=_tigre_grid(scanner, shape, 1000.0),
            volume=volume,
            root=folder,
            extra={"source": {"format": "r2-gaussian", "path": str(meta_path)}},
        )
        return validate_scene(scene)
    except UserError as exc:
        raise UserError(f"{meta_path}: {exc}") from None


def read_any(path: str | os.PathLike, *, trust_pickle: bool = False) -> ProjectionScene:
    """Our folder / projections.json, a NAF `*.pickle`, or an R2-Gaussian folder / meta_data.json.

    `trust_pickle`: unpickle a `*.pickle` plainly (see read_naf_pickle); never set it for a path read from a run."""
    path = Path(path)
    if path.suffix in (".pickle", ".pkl"):
        return read_naf_pickle(path, trust=trust_pickle)
    if path.name == "meta_data.json" or (path.is_dir() and (path / "meta_data.json").is_file()):
        return read_r2_gaussian(path)
    return read_projection_scene(path)
