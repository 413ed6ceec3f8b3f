"""CT volumes on disk: `.npy`, MATLAB `.mat` (v4-v7, scipy), raw binary with a given shape and dtype, NIfTI
(`.nii`, `.nii.gz`, nibabel). Every reader returns a `Volume`: attenuation mu >= 0 per length unit, float32
[nx, ny, nz] (index (i, j, k) -> x, y, z; radiance.xray's voxel convention), its voxel size and units.

- Voxel size: NIfTI's header (`pixdim`, in the file's spatial unit, converted to mm); the other formats carry
  none, so the caller gives `spacing` (the stages' `--voxel-size`).
- NIfTI: the array axes are taken as x, y, z as stored; the affine's rotation and origin are recorded in
  `Volume.note` but not applied (the reconstruction lives on the same index grid).
- DICOM is not read: a series is a folder of slices that must be sorted, rescaled (RescaleSlope/Intercept)
  and converted from Hounsfield units to attenuation with a spectrum-dependent factor; convert it to NIfTI
  first (e.g. dcm2niix) and state the attenuation scale.
- Bad input raises `data.errors.UserError` with one line naming the file and what is wrong (non-finite or
  negative attenuation, wrong dimensionality, missing shape/dtype for raw).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.errors import UserError

__all__ = ["Volume", "read_volume", "check_volume", "write_npy", "iso_surface", "VOLUME_SUFFIXES"]

VOLUME_SUFFIXES = (".npy", ".mat", ".raw", ".nii", ".nii.gz")
_NIFTI_TO_MM = {"mm": 1.0, "meter": 1000.0, "micron": 1e-3, "unknown": 1.0}


@dataclass(frozen=True, kw_only=True)
class Volume:
    """A CT volume: `data` float32 [nx, ny, nz], mu per `length_unit`, voxels of `spacing` (same unit)."""

    data: np.ndarray
    spacing: tuple[float, float, float]
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    length_unit: str = "mm"
    note: dict = field(default_factory=dict)


def check_volume(data: np.ndarray, name: str) -> np.ndarray:
    """float32 [nx, ny, nz], finite, >= 0 (UserError naming `name` otherwise)."""
    data = np.asarray(data)
    if data.ndim != 3 or min(data.shape) < 1:
        raise UserError(f"{name}: expected a 3-D volume [nx, ny, nz], got shape {tuple(data.shape)}")
    if not np.issubdtype(data.dtype, np.number) or np.issubdtype(data.dtype, np.complexfloating):
        raise UserError(f"{name}: expected real numbers, got dtype {data.dtype}")
    data = data.astype(np.float32)
    bad = ~np.isfinite(data)
    if bad.any():
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        raise UserError(f"{name}: {int(bad.sum())} non-finite attenuation values (first at voxel {first})")
    if (data < 0).any():
        first = tuple(int(i) for i in np.argwhere(data < 0)[0])
        raise UserError(
            f"{name}: negative attenuation ({int((data < 0).sum())} voxels, min {float(data.min()):.4g} at voxel "
            f"{first}); expected mu >= 0 (convert Hounsfield units to attenuation first)"
        )
    return data


def _check_spacing(spacing, name: str) -> tuple[float, float, float]:
    if spacing is None:
        raise UserError(f"{name}: this format has no voxel size: give one (voxel_size, in mm)")
    s = np.broadcast_to(np.asarray(spacing, dtype=np.float64), (3,))
    if not (np.isfinite(s).all() and (s > 0).all()):
        raise UserError(f"{name}: voxel size must be > 0 and finite, got {tuple(s.tolist())}")
    return tuple(float(v) for v in s)


def _read_mat(path: Path, key: str | None) -> np.ndarray:
    import scipy.io

    try:
        mat = scipy.io.loadmat(path)
    except NotImplementedError:
        raise UserError(f"{path}: MATLAB v7.3 (HDF5) files are not read: save with -v7 or as .npy") from None
    except (ValueError, OSError) as exc:
        raise UserError(f"{path}: cannot read MATLAB file ({exc})") from None
    arrays = {k: v for k, v in mat.items() if not k.startswith("__") and isinstance(v, np.ndarray) and v.ndim == 3}
    if key is not None:
        if key not in mat:
            raise UserError(f"{path}: no variable {key!r} (3-D variables: {sorted(arrays)})")
        return np.asarray(mat[key])
    if len(arrays) != 1:
        raise UserError(f"{path}: expected exactly one 3-D variable, found {sorted(arrays)}: name one (key=NAME)")
    return next(iter(arrays.values()))


def _read_raw(path: Path, shape, dtype: str | None) -> np.ndarray:
    if shape is None or dtype is None:
        raise UserError(f"{path}: a raw volume needs its shape and dtype (shape=(NX, NY, NZ), dtype=float32)")
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise UserError(f"{path}: unknown dtype {dtype!r}") from None
    shape = tuple(int(n) for n in shape)
    expected = int(np.prod(shape)) * dt.itemsize
    size = path.stat().st_size
    if size != expected:
        raise UserError(f"{path}: {size} bytes, but shape {shape} of {dt} needs {expected}")
    # Raw files are stored with x fastest (Fortran order), as TIGRE, MATLAB and most scanners write them.
    return np.fromfile(path, dtype=dt).reshape(shape, order="F")


def _read_nifti(path: Path) -> tuple[np.ndarray, tuple[float, float, float], dict]:
    try:
        import nibabel
    except ImportError:
        raise UserError(f"{path}: reading NIfTI needs the nibabel package (pip install nibabel)") from None
    try:
        img = nibabel.load(str(path))
        data = np.asarray(img.dataobj)
    except Exception as exc:  # nibabel raises many types for corrupt files
        raise UserError(f"{path}: cannot read NIfTI ({type(exc).__name__}: {exc})") from None
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    unit = img.header.get_xyzt_units()[0] or "unknown"
    scale = _NIFTI_TO_MM.get(unit, 1.0)
    zooms = tuple(float(z) * scale for z in img.header.get_zooms()[:3])
    return data, zooms, {"nifti_affine": np.asarray(img.affine).tolist(), "nifti_unit": unit}


def _suffix(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def read_volume(
    path: str | os.PathLike,
    *,
    spacing: float | tuple[float, float, float] | None = None,
    key: str | None = None,
    shape: tuple[int, int, int] | None = None,
    dtype: str | None = None,
) -> Volume:
    """Read a CT volume (see the module docstring); `spacing` (mm) is used where the file has no voxel size."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such volume file")
    suffix = _suffix(path)
    note: dict = {"source": str(path), "format": suffix}
    if suffix == ".npy":
        try:
            data = np.load(path, allow_pickle=False)
        except ValueError as exc:
            raise UserError(f"{path}: cannot read .npy ({exc})") from None
    elif suffix == ".mat":
        data = _read_mat(path, key)
    elif suffix == ".raw":
        data = _read_raw(path, shape, dtype)
    elif suffix in (".nii", ".nii.gz"):
        data, zooms, extra = _read_nifti(path)
        note.update(extra)
        spacing = zooms
    elif suffix in (".dcm", ".ima") or path.is_dir():
        raise UserError(f"{path}: DICOM is not read; convert the series to NIfTI (e.g. dcm2niix) first")
    else:
        raise UserError(f"{path}: unknown volume format {suffix!r}; expected one of {', '.join(VOLUME_SUFFIXES)}")
    data = check_volume(data, str(path))
    return Volume(data=data, spacing=_check_spacing(spacing, str(path)), note=note)


def write_npy(path: str | os.PathLike, array: np.ndarray) -> Path:
    """np.save, atomically."""
    path = Path(path)
    with atomic_path(path, suffix=".npy") as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.ascontiguousarray(array))
    return path


def iso_surface(
    values: np.ndarray, level: float, first_centre: np.ndarray, spacing: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of values [nx, ny, nz] (index (i, j, k) -> x, y, z) at `level`, padded with zeros by one
    cell so the surface closes where the object meets the grid's edge. Vertices float64 [V, 3] at first_centre
    [3] + index * spacing [3] (cell centres), faces int64 [F, 3] wound counter-clockwise seen from outside for
    values that grow into the object (skimage's "ascent"; degenerate triangles left out)."""
    from skimage.measure import marching_cubes

    verts, faces, _, _ = marching_cubes(
        np.pad(values, 1), level=level, gradient_direction="ascent", allow_degenerate=False
    )
    verts = np.asarray(first_centre, np.float64) + (verts.astype(np.float64) - 1.0) * np.asarray(spacing, np.float64)
    return verts, faces.astype(np.int64)
