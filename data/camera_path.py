"""Camera-path files: what `nerfpipe view` records and `nerfpipe render --path FILE.json` plays back.

The format is nerfstudio's `camera_path.json` (what `ns-render camera-path` reads and its viewer writes), so a
file made by either tool plays in both; nerfpipe adds its keyframes and a format tag. docs/camera_path.md has the
full description. Read:
- `camera_path` [F]: one entry per video frame, `camera_to_world` (16 numbers, row-major 4x4, or a 4x4 list;
  OpenGL camera axes: x right, y up, looking down -z) in the **scene frame** of the run (transforms.json's
  normalised frame), `fov` (vertical, degrees), `aspect` (width / height, informational);
- `render_width`, `render_height` (pixels), `fps` (or `seconds`: fps = frames / seconds), `camera_type`
  (only `perspective` is rendered).
Written in addition: `format: "nerfpipe-camera-path"`, `version`, `seconds`, `keyframes` (nerfpipe's own list:
`world_from_cam` 4x4, `fov` degrees, `time` seconds) from which `camera_path` was interpolated
(`radiance.keyframes`).

Limits: a frame is at most `MAX_SIDE` pixels on a side and `MAX_PIXELS` in all (a file asking for 200000 x 200000
made torch try to allocate 320 GB); a file nested too deeply for the JSON parser is refused naming the file.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfpipe.data.atomic import write_json
from nerfpipe.data.errors import UserError
from nerfpipe.radiance.keyframes import interpolate_keyframes

__all__ = [
    "FORMAT",
    "VERSION",
    "MAX_SIDE",
    "MAX_PIXELS",
    "CameraPathFile",
    "check_frame_size",
    "read_camera_path",
    "write_camera_path",
]

FORMAT = "nerfpipe-camera-path"
VERSION = 1
MAX_SIDE = 16384
"""The widest or tallest frame nerfpipe renders, in pixels (four 4K frames across)."""
MAX_PIXELS = 8192 * 8192
"""The most pixels in one frame (67 M: 8K UHD is 33 M); its float images alone take about 1 GB."""


@dataclass(frozen=True, kw_only=True)
class CameraPathFile:
    world_from_cams: np.ndarray
    """[F, 4, 4] float64, scene frame, OpenGL axes."""
    fovs_deg: np.ndarray
    """[F] vertical field of view in degrees."""
    width: int
    height: int
    fps: float
    source: str
    """'nerfpipe' (written by view) or 'nerfstudio' (any other camera_path.json)."""


def _matrix(value, where: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where}: expected 16 numbers (a 4x4 camera-to-world matrix)") from None
    if m.size != 16:
        raise UserError(f"{where}: expected 16 numbers (a 4x4 camera-to-world matrix), got {m.size}")
    m = m.reshape(4, 4)
    if not np.all(np.isfinite(m)):
        raise UserError(f"{where}: not finite")
    if abs(np.linalg.det(m[:3, :3])) < 1e-9:
        raise UserError(f"{where}: the rotation part is singular")
    return m


def _positive(doc: dict, key: str, path: Path) -> float:
    value = doc.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise UserError(f"{path}: field {key!r}: expected a number > 0, got {value!r}")
    return float(value)


def check_frame_size(width: int, height: int, where: str, names: tuple[str, str] = ("width", "height")) -> None:
    """UserError `{where}: field ...` when a frame is wider or taller than MAX_SIDE or larger than MAX_PIXELS."""
    for name, value in zip(names, (width, height), strict=True):
        if value > MAX_SIDE:
            raise UserError(f"{where}: field {name!r}: {value} px is more than the {MAX_SIDE} px nerfpipe renders")
    if width * height > MAX_PIXELS:
        raise UserError(
            f"{where}: field '{names[0]} x {names[1]}': {width} x {height} = {width * height} pixels is "
            f"more than the {MAX_PIXELS} nerfpipe renders in one frame"
        )


def read_camera_path(path: str | Path) -> CameraPathFile:
    """Read a nerfpipe or nerfstudio camera path; UserError naming the file, the frame and the field."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{path}: camera path file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: not a JSON camera path ({exc})") from None
    except RecursionError:
        raise UserError(f"{path}: not a camera path: JSON nested too deeply to read") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("camera_path"), list) or not doc["camera_path"]:
        raise UserError(f"{path}: field 'camera_path': expected a non-empty list of cameras (nerfstudio format)")
    kind = doc.get("camera_type", "perspective")
    if kind != "perspective":
        raise UserError(f"{path}: field 'camera_type': only 'perspective' is rendered, got {kind!r}")
    width, height = int(_positive(doc, "render_width", path)), int(_positive(doc, "render_height", path))
    check_frame_size(width, height, str(path), ("render_width", "render_height"))
    frames = doc["camera_path"]
    if "fps" in doc:
        fps = _positive(doc, "fps", path)
    elif "seconds" in doc:
        fps = len(frames) / _positive(doc, "seconds", path)
    else:
        raise UserError(f"{path}: needs 'fps' or 'seconds'")
    poses, fovs = [], []
    for i, cam in enumerate(frames):
        where = f"{path}: camera_path[{i}]"
        if not isinstance(cam, dict) or "camera_to_world" not in cam:
            raise UserError(f"{where}: field 'camera_to_world' missing")
        poses.append(_matrix(cam["camera_to_world"], f"{where}.camera_to_world"))
        fov = cam.get("fov")
        if isinstance(fov, bool) or not isinstance(fov, (int, float)) or not 0 < fov < 180:
            raise UserError(f"{where}.fov: expected a vertical field of view in degrees in (0, 180), got {fov!r}")
        fovs.append(float(fov))
    return CameraPathFile(
        world_from_cams=np.stack(poses),
        fovs_deg=np.array(fovs),
        width=width,
        height=height,
        fps=fps,
        source="nerfpipe" if doc.get("format") == FORMAT else "nerfstudio",
    )


def write_camera_path(
    path: str | Path,
    *,
    keyframes: np.ndarray,  # [K, 4, 4] world_from_cam, scene frame, OpenGL axes
    fovs_deg: np.ndarray,  # [K] vertical
    times: np.ndarray,  # [K] seconds, strictly increasing
    width: int,
    height: int,
    fps: float = 30.0,
) -> Path:
    """Interpolate the keyframes (`radiance.keyframes`) and write the path atomically; returns the path."""
    if width < 1 or height < 1:
        raise UserError(f"camera path: expected a size >= 1 px, got {width}x{height}")
    check_frame_size(width, height, "camera path")
    try:
        poses, fovs = interpolate_keyframes(keyframes, fovs_deg, times, fps)
    except ValueError as exc:
        raise UserError(f"camera path: {exc}") from None
    keyframes = np.asarray(keyframes, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "frame": "scene (transforms.json's normalised frame), OpenGL camera axes",
        "camera_type": "perspective",
        "render_width": int(width),
        "render_height": int(height),
        "fps": float(fps),
        "seconds": float(times[-1] - times[0]),
        "keyframes": [
            {"world_from_cam": k.tolist(), "fov": float(f), "time": float(t)}
            for k, f, t in zip(keyframes, np.asarray(fovs_deg, dtype=np.float64), times, strict=True)
        ],
        "camera_path": [
            {"camera_to_world": p.reshape(-1).tolist(), "fov": float(f), "aspect": width / height}
            for p, f in zip(poses, fovs, strict=True)
        ],
    }
    return write_json(path, doc)
