"""Cameras over a trained run: camera paths (turntable, arc, trajectory, spiral, a split's cameras) and rendering
one camera.

Cameras are world_from_cam [4, 4] in the scene frame, OpenGL axes (x right, y up, looking down -z); `render_view`
returns z-depth (along the optical axis) in scene units; a run that renders rays (`model.run`) renders the camera's
rays, one that renders whole cameras (splats, `model.splat_run`) rasterises the camera itself. Paths come from
`radiance.paths`: `turntable` orbits the point the training cameras look at, `arc` is the part of that orbit the
training cameras cover, `trajectory` follows the training cameras (capture order, or azimuth order when the capture
order wanders) smoothed and resampled, `spiral` is LLFF's forward-facing path, `test` / `train` replay a split's cameras
with their own intrinsics (distortion included); a `.json` file (`data.camera_path`: recorded by `nerfpipe view`, or
nerfstudio's camera_path.json) is played back frame by frame with its own size and field of view. `auto` picks spiral
for a forward-facing capture, turntable when the training cameras go round the object (largest azimuth gap <=
`MAX_TURNTABLE_GAP_DEG`), trajectory otherwise, and says why in `CameraPath.used`. Synthetic paths use the first
training camera's intrinsics without distortion, scaled by 1/downscale.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nerfpipe.data.camera_path import read_camera_path
from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import Scene, is_forward_facing
from nerfpipe.model.run import can, require
from nerfpipe.radiance import paths
from nerfpipe.radiance.camera import Intrinsics, generate_rays

__all__ = [
    "PATHS",
    "OPAQUE",
    "render_view",
    "training_intrinsics",
    "CameraPath",
    "camera_path",
    "is_path_file",
    "path_from_file",
]

PATHS = ("auto", "turntable", "arc", "trajectory", "spiral", "test", "train")
MAX_TURNTABLE_GAP_DEG = 90.0
"""`auto` orbits all the way round only when no gap between the training cameras' azimuths exceeds this."""
TRAJECTORY_SIGMA = 2.0
"""Gaussian smoothing of the trajectory's keyframes (training camera centres), in keyframes (hand shake)."""
CAPTURE_ORDER_SLACK = 1.5
"""`trajectory` follows the capture (file-name) order unless that path is this much longer than azimuth order."""
OPAQUE = 0.5
"""Pixels with accumulated opacity below this count as background for depth ranges and depth exports."""


@torch.no_grad()
def render_view(
    trained: Any,
    intr: Intrinsics,
    world_from_cam: np.ndarray,
    device: torch.device,
    *,
    depth: bool = True,
    infer: Any = None,
):
    """Render one camera (scene frame, OpenGL axes) of a run (`model.run.Run`). Returns numpy float32 arrays:
    rgb [H, W, 3], depth [H, W] (z-depth of the expected t, scene units), depth_median [H, W] (z-depth of the
    median t), acc [H, W]. Memory: `render_rays` works through the rays in chunks.
    A run that renders whole cameras (capability `cameras`: splats) renders the camera itself; with `depth=False` it
    may leave depth and depth_median out (a second pass for splats). A run that renders rays returns them whatever
    `depth` says. `infer`: how a ray run's grid field stops its rays (`model.field_model.Inference`; None: the run's
    exact default)."""
    if can(trained, "cameras"):
        return trained.render_camera(intr, world_from_cam, depth=depth)
    require(trained, "rays", stage="rendering a camera")
    pose = torch.as_tensor(np.asarray(world_from_cam, dtype=np.float64))
    rays_o, rays_d = generate_rays(intr, pose)  # float64 [R, 3]
    forward = -pose[:3, 2]
    cos = (rays_d @ forward).to(torch.float32)  # t -> z-depth factor
    extra = {} if infer is None else {"infer": infer}
    out = trained.render_rays(rays_o.to(device, torch.float32), rays_d.to(device, torch.float32), **extra)
    h, w = intr.h, intr.w

    def grab(key: str, shape: tuple[int, ...]) -> np.ndarray:
        return out[key].detach().float().cpu().reshape(shape).numpy()

    cos_np = cos.reshape(h, w).numpy()
    return {
        "rgb": grab("rgb", (h, w, 3)),
        "depth": grab("depth", (h, w)) * cos_np,
        "depth_median": grab("depth_median", (h, w)) * cos_np,
        "acc": grab("acc", (h, w)),
    }


def training_intrinsics(scene: Scene) -> Intrinsics:
    """The first training camera's intrinsics (what synthetic paths render with, before downscale)."""
    train = scene.split("train") or tuple(range(len(scene.frames)))
    return scene.frame_intrinsics(train[0])


def _scaled(intr: Intrinsics, downscale: float, keep_distortion: bool) -> Intrinsics:
    out = intr.scaled(1.0 / downscale) if downscale != 1 else intr
    if not keep_distortion and out.has_distortion:
        out = Intrinsics(w=out.w, h=out.h, fx=out.fx, fy=out.fy, cx=out.cx, cy=out.cy)
    return out


@dataclass(frozen=True, kw_only=True)
class CameraPath:
    world_from_cams: np.ndarray
    """[N, 4, 4] scene frame, OpenGL axes."""
    intrinsics: tuple[Intrinsics, ...]
    """One per camera."""
    names: tuple[str, ...]
    """A file-name stem per camera."""
    frame_indices: tuple[int, ...] | None
    """Dataset frame index per camera for test/train replays (None for synthetic paths)."""
    used: dict[str, Any]
    """How the path was derived (for the manifest)."""


def _natural_key(name: str) -> list:
    """'img10.jpg' after 'img9.jpg': digit runs compare as numbers."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def _auto_kind(scene: Scene, train_poses: np.ndarray) -> tuple[str, str, paths.Coverage | None]:
    """(kind, reason, coverage) for `--path auto`."""
    if is_forward_facing(scene):
        return "spiral", "forward-facing capture (the cameras saw the scene from one side)", None
    cover = paths.azimuth_coverage(train_poses, paths.orbit_from_cameras(train_poses))
    span = f"the training cameras cover {cover.covered_deg:.0f} degrees of azimuth about the orbit axis"
    gap = f"largest gap {cover.largest_gap_deg:.0f} degrees"
    if cover.largest_gap_deg <= MAX_TURNTABLE_GAP_DEG + 1e-6:
        return "turntable", f"{span} ({gap} <= {MAX_TURNTABLE_GAP_DEG:.0f}): they go round the object", cover
    reason = f"{span} ({gap} > {MAX_TURNTABLE_GAP_DEG:.0f}): following the captured trajectory"
    return "trajectory", reason, cover


def _path_order(scene: Scene, train_idx: tuple[int, ...], train_poses: np.ndarray, cover: paths.Coverage):
    """Order of the training cameras along a trajectory -> (indices into train_idx, reason)."""
    by_name = np.array(sorted(range(len(train_idx)), key=lambda k: _natural_key(scene.frames[train_idx[k]].file_path)))
    by_azimuth = paths.azimuth_order(cover)
    centres = paths.camera_centres(train_poses)
    named, swept = paths.path_length(centres[by_name]), paths.path_length(centres[by_azimuth])
    if named <= CAPTURE_ORDER_SLACK * swept:
        return by_name, f"capture order (file names; path {named:.3g} vs {swept:.3g} scene units in azimuth order)"
    why = f"the file-name order wanders: path {named:.3g} vs {swept:.3g} scene units"
    return by_azimuth, f"azimuth order ({why})"


def is_path_file(kind: str) -> bool:
    """True when a `--path` value names a camera-path file (`*.json`) rather than a built-in path."""
    return str(kind).lower().endswith(".json")


def path_from_file(file: str | Path, downscale: float = 1.0) -> CameraPath:
    """A recorded camera path (`data.camera_path`): one camera per entry, pinhole intrinsics from the file's
    render size and vertical field of view (fx = fy, centred), scaled by 1/downscale."""
    if not downscale > 0:
        raise UserError(f"downscale: expected > 0, got {downscale}")
    doc = read_camera_path(file)
    intr = []
    for fov in doc.fovs_deg:
        f = 0.5 * doc.height / np.tan(np.radians(fov) / 2)
        base = Intrinsics(w=doc.width, h=doc.height, fx=f, fy=f, cx=doc.width / 2, cy=doc.height / 2)
        intr.append(_scaled(base, downscale, keep_distortion=False))
    names = tuple(f"frame_{k:05d}" for k in range(len(intr)))
    used = {
        "path": "file",
        "file": str(file),
        "format": doc.source,
        "fps_in_file": doc.fps,
        "size_in_file_wh": [doc.width, doc.height],
    }
    return CameraPath(
        world_from_cams=doc.world_from_cams, intrinsics=tuple(intr), names=names, frame_indices=None, used=used
    )


def camera_path(
    scene: Scene,
    kind: str,
    *,
    frames: int = 120,
    downscale: float = 1.0,
    elevation: float | None = None,
    radius: float | None = None,
) -> CameraPath:
    """Cameras of a path over a trained run's scene. radius in the user's units (scaled into the scene frame);
    radius and elevation shape the turntable and the arc (a trajectory keeps the cameras' own). A `kind` ending in
    .json is a camera-path file (`path_from_file`; frames, radius and elevation do not apply)."""
    if is_path_file(kind):
        return path_from_file(kind, downscale)
    if kind not in PATHS:
        raise UserError(f"path: unknown path {kind!r}; expected one of {', '.join(PATHS)} or a FILE.json")
    if not downscale > 0:
        raise UserError(f"downscale: expected > 0, got {downscale}")
    if kind in ("test", "train"):
        idx = scene.split(kind) or (scene.split("val") if kind == "test" else ())
        if not idx:
            raise UserError(f"path={kind}: the run's scene ({scene.root}) has no {kind} split")
        poses = np.stack([scene.frames[i].world_from_cam for i in idx])
        intr = tuple(_scaled(scene.frame_intrinsics(i), downscale, keep_distortion=True) for i in idx)
        names = tuple(Path(scene.frames[i].file_path).stem for i in idx)
        split = kind if scene.split(kind) else "val"
        return CameraPath(
            world_from_cams=poses,
            intrinsics=intr,
            names=names,
            frame_indices=tuple(idx),
            used={"path": kind, "split": split},
        )
    if frames < 1:
        raise UserError(f"frames: expected >= 1, got {frames}")
    if radius is not None and not radius > 0:
        raise UserError(f"radius: expected > 0, got {radius}")
    if elevation is not None and not -90 < elevation < 90:
        raise UserError(f"elevation: expected degrees in (-90, 90), got {elevation}")
    train_idx = scene.split("train") or tuple(range(len(scene.frames)))
    train_poses = np.stack([scene.frames[i].world_from_cam for i in train_idx])
    intr = _scaled(training_intrinsics(scene), downscale, keep_distortion=False)
    used: dict[str, Any] = {}
    cover = None
    if kind == "auto":
        kind, reason, cover = _auto_kind(scene, train_poses)
        used["auto"] = {"chose": kind, "reason": reason}
    used.update(path=kind, intrinsics="first training camera, no distortion")
    if kind in ("turntable", "arc", "trajectory"):
        orbit = paths.orbit_from_cameras(train_poses)
        if cover is None:
            cover = paths.azimuth_coverage(train_poses, orbit)
        used["coverage"] = {
            "covered_deg": round(cover.covered_deg, 1),
            "largest_gap_deg": round(cover.largest_gap_deg, 1),
            "cameras": len(train_idx),
            "of": "training camera azimuths about the orbit axis through the centre",
        }
        used.update(centre_scene=orbit.centre.tolist(), up=orbit.up.tolist(), up_reason=paths.up_axis(train_poses)[1])
    if kind in ("turntable", "arc"):
        if radius is not None:
            orbit = dataclasses.replace(orbit, radius=radius * scene.applied_scale)
        if elevation is not None:
            orbit = dataclasses.replace(orbit, elevation_deg=float(elevation))
        if kind == "arc":
            orbit = dataclasses.replace(orbit, start_azimuth_deg=cover.start_deg)
            used.update(start_azimuth_deg=cover.start_deg, sweep_deg=cover.covered_deg)
        poses = paths.turntable(orbit, frames, sweep_deg=360.0 if kind == "turntable" else cover.covered_deg)
        defaults = [name for name, value in (("radius", radius), ("elevation", elevation)) if value is None]
        used.update(
            radius_scene=orbit.radius,
            radius_user=orbit.radius / scene.applied_scale,
            elevation_deg=orbit.elevation_deg,
            from_training_cameras=defaults,
        )
    elif kind == "trajectory":
        order, why = _path_order(scene, train_idx, train_poses, cover)
        sigma = TRAJECTORY_SIGMA if len(order) > 2 else 0.0
        try:
            poses = paths.trajectory(train_poses[order], frames, centre=orbit.centre, up=orbit.up, sigma=sigma)
        except ValueError as exc:  # a path through the point it looks at
            raise UserError(f"path=trajectory: {exc}; use path=turntable") from None
        used.update(
            order=why,
            keyframes=len(order),
            smoothing_sigma_keyframes=sigma,
            length_scene=round(paths.path_length(poses[:, :3, 3]), 4),
            orientation="looks at the centre, image up towards `up`",
            spline="centripetal Catmull-Rom through the smoothed keyframes, resampled at equal arc length",
        )
        ignored = [name for name, value in (("radius", radius), ("elevation", elevation)) if value is not None]
        if ignored:
            used["ignored"] = {
                name: "a trajectory keeps the training cameras' distances and heights" for name in ignored
            }
    else:
        try:
            poses = paths.spiral(train_poses, frames)
        except ValueError as exc:
            raise UserError(f"path=spiral: {exc}; use path=turntable") from None
        used.update(focus_scene=paths.focus_point(train_poses).tolist(), rotations=2, radii_percentile=90)
    names = tuple(f"frame_{k:05d}" for k in range(len(poses)))
    return CameraPath(
        world_from_cams=poses, intrinsics=(intr,) * len(poses), names=names, frame_indices=None, used=used
    )
