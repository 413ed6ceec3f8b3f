"""A synthetic scene's `ground_truth/` folder (written by `stages.scene`): the one reader of its cameras.

Layout (see `stages.scene`):
  ground_truth/cameras.json     {"frames": {image stem: {"file_path": "images/<name>", "world_from_cam": 4x4,
                                intrinsics...}}, ...}; a frame may also be a bare 4x4 or use "transform_matrix"
  ground_truth/depth/<stem>.npy float32 [H, W] z-depth in metres, 0 = background
  ground_truth/mesh.ply         the rendered surface, metres

Cameras are `world_from_cam` 4x4 in OpenGL axes (x right, y up, looking down -z), metres, in the ground-truth
frame. They are keyed by image stem (what depth files are named by); `by_file_name()` keys them by image file
name instead (what COLMAP models and transforms.json frames are keyed by).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nerfpipe.data.confine import inside, read_json
from nerfpipe.data.errors import UserError

__all__ = ["GroundTruth", "read_ground_truth"]


@dataclass(frozen=True, kw_only=True)
class GroundTruth:
    folder: Path
    """The ground_truth/ folder (holds cameras.json, depth/)."""
    world_from_cam: dict[str, np.ndarray]
    """Image stem (file name without extension) -> [4, 4] OpenGL camera, ground-truth frame."""
    file_names: dict[str, str] = field(default_factory=dict)
    """Image stem -> image file name (from the frame's file_path; the frame's key when it has none)."""

    @property
    def cameras(self) -> Path:
        """The cameras.json file."""
        return self.folder / "cameras.json"

    def depth_path(self, name: str) -> Path:
        """depth/<stem>.npy for an image file name or stem (it may not exist), resolved inside the ground_truth
        folder (UserError when a symlink leads out)."""
        return inside(self.folder, f"depth/{Path(name).stem}.npy", f"the depth map of {name}")

    def by_file_name(self) -> dict[str, np.ndarray]:
        """Image file name -> [4, 4] OpenGL world_from_cam."""
        return {self.file_names.get(stem, stem): m for stem, m in self.world_from_cam.items()}


def read_ground_truth(path: str | Path) -> GroundTruth:
    """Read the cameras of a ground_truth/ folder, the scene folder holding it, or its cameras.json itself.

    UserError (one line, naming the file) when there is no cameras.json or a frame is not a finite 4x4 matrix.
    """
    path = Path(path)
    if path.is_file() and path.name == "cameras.json":
        path = path.parent
    folder = path / "ground_truth" if (path / "ground_truth" / "cameras.json").is_file() else path
    cams = folder / "cameras.json"
    if not cams.is_file():
        raise UserError(f"ground truth: {path} has no cameras.json (nor ground_truth/cameras.json)")
    frames: dict[str, np.ndarray] = {}
    names: dict[str, str] = {}
    doc = read_json(cams)
    try:
        for key, value in doc["frames"].items():
            name = Path(str(key)).name
            if isinstance(value, dict):  # {file_path, world_from_cam (or transform_matrix), intrinsics...}
                name = Path(value["file_path"]).name if "file_path" in value else name
                value = value.get("world_from_cam", value.get("transform_matrix"))
            stem = Path(str(key)).stem
            frames[stem], names[stem] = np.asarray(value, dtype=np.float64), name
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise UserError(f"{cams}: expected {{'frames': {{image name: 4x4 matrix}}}} ({type(exc).__name__})") from None
    bad = [k for k, m in frames.items() if m.shape != (4, 4) or not np.isfinite(m).all()]
    if bad:
        raise UserError(f"{cams}: frames[{bad[0]!r}] is not a finite 4x4 matrix")
    return GroundTruth(folder=folder, world_from_cam=frames, file_names=names)
