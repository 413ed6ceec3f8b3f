"""The trained-run library: load a run, render any camera from it, build and checkpoint field models.

Layering: `radiance/` (maths) <- `data/` (file formats) <- `model/` (this) <- `stages/` <- `cli.py`.
Every stage, the viewer and the X-ray mode render trained runs through this API:

    run = load_trained(run_dir, device="auto")               # model.run: the run's method opens it (model.methods)
    view = render_view(run, intrinsics, world_from_cam)      # model.cameras: rgb, depth, depth_median, acc
    cams = camera_path(trained.scene, "turntable", frames=120)
"""

from nerfpipe.model.cameras import OPAQUE, PATHS, CameraPath, camera_path, render_view, training_intrinsics
from nerfpipe.model.device import resolve_device
from nerfpipe.model.run import CAPABILITIES, Run, can, load_trained, require, require_any
from nerfpipe.model.trained import WHITE, Trained

__all__ = [
    "CAPABILITIES",
    "OPAQUE",
    "PATHS",
    "WHITE",
    "CameraPath",
    "Run",
    "Trained",
    "camera_path",
    "can",
    "load_trained",
    "render_view",
    "require",
    "require_any",
    "resolve_device",
    "training_intrinsics",
]
