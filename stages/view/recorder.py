"""The camera-path recorder: keyframes taken from the browser's camera, saved as a camera-path JSON that
`nerfpipe render RUN_DIR OUT.mp4 --path FILE.json` plays back (format: docs/camera_path.md, `data.camera_path`).

Keyframes are spaced evenly over the path's duration (`seconds`); the saved file holds them and the frames
interpolated between them at `fps` (Catmull-Rom positions, slerp rotations, linear field of view). The render
size is `height` pixels high with the browser's aspect ratio at the last keyframe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nerfpipe.data.camera_path import write_camera_path
from nerfpipe.data.errors import UserError
from nerfpipe.stages.view.cameras import viser_pose, world_from_cam_gl

__all__ = ["Keyframe", "PathRecorder", "add_recorder_gui"]


@dataclass(frozen=True)
class Keyframe:
    world_from_cam: np.ndarray
    """[4, 4] scene frame, OpenGL axes."""
    fov_deg: float
    """Vertical field of view."""
    aspect: float
    """Width / height of the browser's view."""


@dataclass
class PathRecorder:
    keyframes: list[Keyframe] = field(default_factory=list)

    def add_browser_camera(self, wxyz, position, fov: float, aspect: float) -> Keyframe:
        """Append the browser's camera (viser pose, vertical fov in radians)."""
        key = Keyframe(world_from_cam_gl(wxyz, position), math.degrees(fov), float(aspect))
        self.keyframes.append(key)
        return key

    def save(self, path: str | Path, *, seconds: float, fps: float, height: int) -> Path:
        """Write the path (UserError with fewer than two keyframes or non-positive numbers)."""
        if len(self.keyframes) < 2:
            raise UserError(f"camera path: record at least two keyframes, have {len(self.keyframes)}")
        if not (seconds > 0 and fps > 0 and height >= 1):
            raise UserError(f"camera path: expected seconds > 0, fps > 0, height >= 1, got {seconds}, {fps}, {height}")
        width = max(1, round(height * self.keyframes[-1].aspect))
        return write_camera_path(
            path, keyframes=np.stack([k.world_from_cam for k in self.keyframes]),
            fovs_deg=np.array([k.fov_deg for k in self.keyframes]),
            times=np.linspace(0.0, seconds, len(self.keyframes)), width=width, height=int(height), fps=fps,
        )  # fmt: skip


def add_recorder_gui(server, out_dir: Path, *, size: float) -> PathRecorder:
    """The recorder's panel: add / clear keyframes, duration, fps, height, file name, save."""
    rec = PathRecorder()
    handles: list = []
    with server.gui.add_folder("Camera path"):
        add = server.gui.add_button("Add keyframe (this view)")
        clear = server.gui.add_button("Clear keyframes")
        seconds = server.gui.add_number("Seconds", initial_value=4.0, min=0.1, step=0.5)
        fps = server.gui.add_number("FPS", initial_value=30.0, min=1.0, step=1.0)
        height = server.gui.add_number("Height (px)", initial_value=480, min=16, step=16)
        name = server.gui.add_text("File", initial_value="camera_path.json")
        save = server.gui.add_button("Save path")
        status = server.gui.add_markdown(f"0 keyframes; saved under {out_dir}")

    @add.on_click
    def _(event) -> None:
        cam = event.client.camera
        key = rec.add_browser_camera(cam.wxyz, cam.position, cam.fov, cam.aspect)
        wxyz, pos = viser_pose(key.world_from_cam)
        handles.append(server.scene.add_camera_frustum(
            f"/path/key_{len(rec.keyframes):03d}", fov=cam.fov, aspect=cam.aspect, scale=0.04 * size,
            wxyz=wxyz, position=pos, color=(230, 40, 160)))  # fmt: skip
        status.content = f"{len(rec.keyframes)} keyframes; saved under {out_dir}"

    @clear.on_click
    def _(_event) -> None:
        rec.keyframes.clear()
        while handles:
            handles.pop().remove()
        status.content = f"0 keyframes; saved under {out_dir}"

    @save.on_click
    def _(event) -> None:
        file = Path(name.value).name or "camera_path.json"
        file = file if file.endswith(".json") else file + ".json"
        try:
            out = rec.save(out_dir / file, seconds=float(seconds.value), fps=float(fps.value), height=int(height.value))
        except UserError as exc:
            event.client.add_notification("Not saved", str(exc), auto_close_seconds=6.0, color="red")
            return
        status.content = f"{len(rec.keyframes)} keyframes; saved {out}: `nerfpipe render RUN_DIR out.mp4 --path {out}`"
        event.client.add_notification("Camera path saved", str(out), auto_close_seconds=6.0)

    return rec
