"""The trained-run library: load a run, render any camera from it, build and checkpoint field models.

Layering: `radiance/` (maths) <- `data/` (file formats) <- `model/` (this) <- `stages/` <- `cli.py`.
Every stage, the viewer and the X-ray mode render trained runs through this API:

    trained = load_trained(run_dir, device="auto")          # model.trained
    view = render_view(trained, intrinsics, world_from_cam)  # model.cameras: rgb, depth, depth_median, acc
    cams = camera_path(trained.scene, "turntable", frames=120)
"""

from nerfpipe.model.cameras import OPAQUE, PATHS, CameraPath, Renderable, camera_path, render_view, training_intrinsics
from nerfpipe.model.device import resolve_device
from nerfpipe.model.trained import WHITE, Trained, load_trained

__all__ = [
    "OPAQUE",
    "PATHS",
    "WHITE",
    "CameraPath",
    "Renderable",
    "Trained",
    "camera_path",
    "load_trained",
    "render_view",
    "resolve_device",
    "training_intrinsics",
]
