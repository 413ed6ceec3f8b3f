"""The camera-path recorder: keyframes taken from the browser's camera, saved as a camera-path JSON that
`nerfpipe render RUN_DIR OUT.mp4 --path FILE.json` plays back (format: docs/camera_path.md, `data.camera_path`).

Keyframes are spaced evenly over the path's duration (`seconds`); the saved file holds them and the frames
interpolated between them at `fps` (Catmull-Rom positions, slerp rotations, linear field of view). The render
size is `height` pixels high with the browser's aspect ratio at the last keyframe.

The recorder writes only into its `paths_dir`, only new files, only `NAME.json` with NAME of letters, digits,
'.', '_', '-' (no folder, no '..', no leading dot): a name typed in the page (or sent by any client) cannot reach
the run's or the scene's own files (`manifest.json`, `transforms.json`, `config.json` live outside `paths_dir`)
nor replace an earlier path (`new_path_file`).
"""

from __future__ import annotations

import math
import os
import re
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nerfpipe.data.camera_path import write_camera_path
from nerfpipe.data.errors import UserError
from nerfpipe.stages.view.cameras import viser_pose, world_from_cam_gl

__all__ = ["NAME", "Keyframe", "PathRecorder", "add_recorder_gui", "new_path_file"]

NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,95}\.json")
"""A camera path's file name: no separator, no leading dot, at most 101 characters."""


def new_path_file(paths_dir: Path, name: str) -> Path:
    """paths_dir / NAME.json for a new camera path ('.json' added when missing); UserError for any other name or
    for a file that exists."""
    name = name.strip()
    name = name if name.endswith(".json") else name + ".json"
    if not NAME.fullmatch(name) or ".." in name:
        raise UserError(
            f"camera path name {name[:120]!r}: expected a file name of letters, digits, '.', '_', '-' "
            "ending in .json (no folder, no '..')"
        )
    path = Path(paths_dir) / name
    if os.path.lexists(path):
        raise UserError(f"{path} already exists: choose another name (the recorder never replaces a file)")
    return path


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
    paths_dir: Path
    """The only folder it writes to (made on the first save)."""
    keyframes: list[Keyframe] = field(default_factory=list)
    _saving: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def add_browser_camera(self, wxyz, position, fov: float, aspect: float) -> Keyframe:
        """Append the browser's camera (viser pose, vertical fov in radians)."""
        key = Keyframe(world_from_cam_gl(wxyz, position), math.degrees(fov), float(aspect))
        self.keyframes.append(key)
        return key

    def save(self, name: str, *, seconds: float, fps: float, height: int) -> Path:
        """Write the path to a new file `paths_dir/NAME.json` (UserError for another name, an existing file, fewer
        than two keyframes or non-positive numbers)."""
        if len(self.keyframes) < 2:
            raise UserError(f"camera path: record at least two keyframes, have {len(self.keyframes)}")
        if not (seconds > 0 and fps > 0 and height >= 1):
            raise UserError(f"camera path: expected seconds > 0, fps > 0, height >= 1, got {seconds}, {fps}, {height}")
        width = max(1, round(height * self.keyframes[-1].aspect))
        with self._saving:  # two browsers saving one name: the second finds the first's file
            return write_camera_path(
                new_path_file(self.paths_dir, name),
                keyframes=np.stack([k.world_from_cam for k in self.keyframes]),
                fovs_deg=np.array([k.fov_deg for k in self.keyframes]),
                times=np.linspace(0.0, seconds, len(self.keyframes)),
                width=width,
                height=int(height),
                fps=fps,
            )


def add_recorder_gui(server, out_dir: Path, *, size: float) -> PathRecorder:
    """The recorder's panel: add / clear keyframes, duration, fps, height, file name, save."""
    rec = PathRecorder(paths_dir=Path(out_dir))
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
        handles.append(
            server.scene.add_camera_frustum(
                f"/path/key_{len(rec.keyframes):03d}",
                fov=cam.fov,
                aspect=cam.aspect,
                scale=0.04 * size,
                wxyz=wxyz,
                position=pos,
                color=(230, 40, 160),
            )
        )
        status.content = f"{len(rec.keyframes)} keyframes; saved under {out_dir}"

    @clear.on_click
    def _(_event) -> None:
        rec.keyframes.clear()
        while handles:
            handles.pop().remove()
        status.content = f"0 keyframes; saved under {out_dir}"

    @save.on_click
    def _(event) -> None:
        try:
            out = rec.save(name.value, seconds=float(seconds.value), fps=float(fps.value), height=int(height.value))
        except UserError as exc:
            event.client.add_notification("Not saved", str(exc), auto_close_seconds=6.0, color="red")
            return
        status.content = f"{len(rec.keyframes)} keyframes; saved {out}: `nerfpipe render RUN_DIR out.mp4 --path {out}`"
        event.client.add_notification("Camera path saved", str(out), auto_close_seconds=6.0)

    return rec
