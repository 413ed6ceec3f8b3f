"""Gaussian splat files: INRIA's PLY layout (read, write) and antimatter15's 32-byte `.splat` layout (write).

PLY (what graphdeco-inria/gaussian-splatting's `save_ply` writes, and nerfstudio's `ns-export gaussian-splat`,
SuperSplat, gsplat.js and viser read): `format binary_little_endian 1.0`, one `vertex` element, every property
`float` (float32), in this order:
    x y z                  position
    nx ny nz               normals (zeros: unused)
    f_dc_0 f_dc_1 f_dc_2   SH degree-0 coefficient per channel (colour = 0.5 + SH_C0 * f_dc)
    f_rest_0 ..            the higher SH coefficients, channel-major: all of red's (K - 1), then green's, then
                           blue's (INRIA stores [N, K - 1, 3] transposed to [N, 3, K - 1]); 0, 9, 24 or 45 of them
    opacity                logit (opacity = sigmoid)
    scale_0 scale_1 scale_2  log of the standard deviations
    rot_0 rot_1 rot_2 rot_3  quaternion w, x, y, z (not necessarily normalised)
The reader takes the properties by name in any order and any scalar type, other elements after the vertices and
comment / obj_info lines; it refuses ASCII and big-endian files, list properties and files shorter than declared.

.splat (antimatter15/splat `convert.py`; gsplat.js, the three.js viewers): no header, 32 bytes per Gaussian,
little endian, sorted by exp(scale_0 + scale_1 + scale_2) * sigmoid(opacity) descending (a stable sort: ties
keep the PLY order):
    position float32 x3, scale float32 x3 (exp of the log scales),
    rgba uint8 x4 = clip((0.5 + SH_C0 * f_dc, sigmoid(opacity)) * 255, 0, 255) truncated,
    rotation uint8 x4 = clip(q / |q| * 128 + 128, 0, 255) truncated (w, x, y, z).
The higher SH coefficients are dropped there. Arithmetic in float32, on the PLY's float32 values.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.errors import UserError

__all__ = ["SH_C0", "SplatData", "ply_properties", "write_ply", "read_ply", "splat_bytes", "write_splat", "SPLAT_DTYPE"]

SH_C0 = 0.28209479177387814
SPLAT_DTYPE = np.dtype(
    [("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rotation", "u1", (4,))]
)
"""One `.splat` record, 32 bytes."""
_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "<i2",
    "int16": "<i2",
    "ushort": "<u2",
    "uint16": "<u2",
    "int": "<i4",
    "int32": "<i4",
    "uint": "<u4",
    "uint32": "<u4",
    "float": "<f4",
    "float32": "<f4",
    "double": "<f8",
    "float64": "<f8",
}
_MAX_HEADER = 1 << 16


@dataclass
class SplatData:
    """Gaussians as the files store them (numpy float32; module doc)."""

    means: np.ndarray  # [N, 3]
    f_dc: np.ndarray  # [N, 3]
    f_rest: np.ndarray  # [N, 3, K - 1] channel-major, K = (degree + 1)^2
    opacity: np.ndarray  # [N] logit
    scales: np.ndarray  # [N, 3] log
    quats: np.ndarray  # [N, 4] wxyz

    def __post_init__(self) -> None:
        for name in ("means", "f_dc", "f_rest", "opacity", "scales", "quats"):
            setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float32))
        n = self.means.shape[0]
        want = {"means": (n, 3), "f_dc": (n, 3), "opacity": (n,), "scales": (n, 3), "quats": (n, 4)}
        for name, shape in want.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"expected {name} {list(shape)}, got {list(getattr(self, name).shape)}")
        if self.f_rest.ndim != 3 or self.f_rest.shape[:2] != (n, 3) or self.f_rest.shape[2] not in (0, 3, 8, 15):
            raise ValueError(
                f"expected f_rest [{n}, 3, K - 1] with K - 1 in 0, 3, 8, 15, got {list(self.f_rest.shape)}"
            )

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return {0: 0, 3: 1, 8: 2, 15: 3}[self.f_rest.shape[2]]


def ply_properties(sh_degree: int) -> list[str]:
    """INRIA's property names in INRIA's order for SH `sh_degree` (0..3)."""
    if sh_degree not in (0, 1, 2, 3):
        raise ValueError(f"expected an SH degree 0..3, got {sh_degree}")
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def _columns(data: SplatData) -> np.ndarray:
    """[N, P] float32 in `ply_properties` order."""
    n = len(data)
    return np.concatenate(
        [
            data.means,
            np.zeros((n, 3), np.float32),
            data.f_dc,
            data.f_rest.reshape(n, -1),
            data.opacity[:, None],
            data.scales,
            data.quats,
        ],
        axis=1,
    )


def write_ply(path: str | os.PathLike, data: SplatData) -> Path:
    """Write INRIA's layout (module doc), atomically."""
    names = ply_properties(data.sh_degree)
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(data)}\n"
    header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
    body = np.ascontiguousarray(_columns(data), dtype="<f4")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(body.tobytes())
    return Path(path)


def _header(path: Path, raw: bytes) -> tuple[list[tuple[str, int, list[tuple[str, str]]]], int]:
    """[(element, count, [(property, numpy type)])], offset of the data."""
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise UserError(f"{path}: not a PLY file (expected 'ply' ... 'end_header' in the first {_MAX_HEADER} bytes)")
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    fmt = None
    for line in raw[4:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else ""
        elif words[0] == "element" and len(words) == 3 and re.fullmatch(r"\d{1,12}", words[2]):
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in _TYPES:
            elements[-1][2].append((words[2], _TYPES[words[1]]))
        elif words[0] == "property" and elements:
            raise UserError(
                f"{path}: unsupported PLY property {line.strip()!r}; expected scalar properties "
                "(splat files have no lists)"
            )
        else:
            raise UserError(f"{path}: unreadable PLY header line {line.strip()!r}")
    if fmt != "binary_little_endian":
        raise UserError(f"{path}: PLY format {fmt!r}; expected binary_little_endian (INRIA's splat layout)")
    return elements, end + len(b"end_header\n")


def _check_names(path: Path, names: list[str]) -> None:
    """UserError unless the vertex properties hold INRIA's Gaussian attributes."""
    need = [
        "x",
        "y",
        "z",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    missing = [k for k in need if k not in names]
    if missing:
        raise UserError(
            f"{path}: not a Gaussian splat PLY: no {', '.join(missing)} property "
            "(expected INRIA's layout: x y z, f_dc_*, opacity, scale_*, rot_*)"
        )
    rest = sorted(int(k[7:]) for k in names if re.fullmatch(r"f_rest_\d+", k))
    if rest != list(range(len(rest))) or len(rest) not in (0, 9, 24, 45):
        raise UserError(
            f"{path}: {len(rest)} f_rest_* properties; expected f_rest_0.. with 0, 9, 24 or 45 of them (SH degree 0..3)"
        )
    if len(set(names)) != len(names):
        raise UserError(f"{path}: a vertex property is declared twice")


def read_ply(path: str | os.PathLike) -> SplatData:
    """Read a splat PLY (module doc); UserError naming the file and what is missing or wrong."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            raw = f.read(_MAX_HEADER)
            size = os.fstat(f.fileno()).st_size
            elements, offset = _header(path, raw)
            if not elements or elements[0][0] != "vertex":
                raise UserError(
                    f"{path}: the first PLY element is {elements[0][0] if elements else 'missing'}; "
                    "expected 'vertex' (the Gaussians)"
                )
            _, n, props = elements[0]
            _check_names(path, [name for name, _ in props])
            dtype = np.dtype([(name, t) for name, t in props])
            if offset + n * dtype.itemsize > size:
                raise UserError(
                    f"{path}: the header declares {n} vertices of {dtype.itemsize} bytes, the file holds "
                    f"{max(0, size - offset)} bytes of data (truncated?)"
                )
            f.seek(offset)
            rows = np.fromfile(f, dtype=dtype, count=n)
    except OSError as exc:
        raise UserError(f"{path}: cannot read the splat file ({exc.strerror or exc})") from None
    names = [name for name, _ in props]
    rest = sorted((int(k[7:]), k) for k in names if re.fullmatch(r"f_rest_\d+", k))

    def cols(keys: list[str]) -> np.ndarray:
        return np.stack([rows[k].astype(np.float32) for k in keys], axis=-1) if keys else np.zeros((n, 0), np.float32)

    return SplatData(
        means=cols(["x", "y", "z"]),
        f_dc=cols(["f_dc_0", "f_dc_1", "f_dc_2"]),
        f_rest=cols([k for _, k in rest]).reshape(n, 3, len(rest) // 3),
        opacity=rows["opacity"].astype(np.float32),
        scales=cols(["scale_0", "scale_1", "scale_2"]),
        quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]),
    )


def splat_bytes(data: SplatData) -> bytes:
    """The `.splat` records (module doc), most important first."""
    scales = np.exp(data.scales)  # float32 throughout, as the converter's numpy arithmetic on PLY floats
    alpha = np.float32(1) / (np.float32(1) + np.exp(-data.opacity))
    size = np.exp(data.scales[:, 0] + data.scales[:, 1] + data.scales[:, 2])
    order = np.argsort(-size / (np.float32(1) + np.exp(-data.opacity)), kind="stable")  # the converter's key
    out = np.zeros(len(data), SPLAT_DTYPE)
    out["position"] = data.means[order]
    out["scale"] = scales[order]
    rgba = np.concatenate([np.float32(0.5) + np.float32(SH_C0) * data.f_dc, alpha[:, None]], axis=1)[order]
    out["rgba"] = np.clip(rgba * np.float32(255), 0, 255).astype(np.uint8)
    q = data.quats[order]
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    out["rotation"] = np.clip(q / np.where(norm > 0, norm, 1) * np.float32(128) + np.float32(128), 0, 255).astype(
        np.uint8
    )
    return out.tobytes()


def write_splat(path: str | os.PathLike, data: SplatData) -> Path:
    """Write the `.splat` layout (module doc), atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(splat_bytes(data))
    return Path(path)
