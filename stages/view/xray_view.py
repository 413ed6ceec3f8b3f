"""An X-ray run in viser: its DRR or MIP at a chosen gantry angle (the panel's image), the reconstructed volume's
box, and a movable slice plane through the volume (an image in the 3-D scene, along x, y or z).

The volume is evaluated once on the scene's grid (`XrayRun.volume()`, mu in 1/mm); DRR and MIP go through it with
the exact projector (`model.xray`). Grey levels: DRR over [0, its max], MIP and slices over [0, the volume's
99.9th percentile].
"""

from __future__ import annotations

import math

import numpy as np

from nerfpipe.radiance.keyframes import quat_from_matrix
from nerfpipe.stages.view.scene_view import box_edges

__all__ = ["AXES", "slice_image", "projection_image", "XrayView"]

AXES = ("x", "y", "z")


def _grey_u8(img: np.ndarray, hi: float) -> np.ndarray:
    v = np.clip(np.nan_to_num(np.asarray(img, dtype=np.float32)) / max(hi, 1e-12), 0.0, 1.0)
    return np.repeat((v * 255 + 0.5).astype(np.uint8)[..., None], 3, axis=-1)


def slice_image(volume: np.ndarray, axis: str, fraction: float, hi: float) -> tuple[np.ndarray, int]:
    """The slice of `volume` [nx, ny, nz] across `axis` at `fraction` in [0, 1] -> (uint8 [rows, cols, 3], index).
    Rows run along the second remaining axis (upwards), columns along the first."""
    a = AXES.index(axis)
    k = min(volume.shape[a] - 1, max(0, int(fraction * volume.shape[a])))
    plane = np.take(volume, k, axis=a)  # [n_first, n_second]
    return _grey_u8(plane.T[::-1], hi), k


def projection_image(run, kind: str, angle_deg: float, volume) -> np.ndarray:
    """DRR or MIP of the run at a gantry angle (degrees) as uint8 [n_v, n_u, 3]."""
    fn = run.drr if kind == "DRR" else run.mip
    img = fn(math.radians(angle_deg), volume=volume).numpy()
    return _grey_u8(img, float(img.max()) if kind == "DRR" else float(np.percentile(volume.numpy(), 99.9)))


class XrayView:
    def __init__(self, server, run) -> None:
        self.server, self.run = server, run
        self.volume = run.volume()  # [nx, ny, nz] CPU float32
        self.vol_np = self.volume.numpy()
        self.hi = float(np.percentile(self.vol_np, 99.9)) or 1.0
        box = np.asarray(run.grid.box, dtype=np.float64)
        self.box = box
        self.size = float(np.linalg.norm(box[1] - box[0]))
        self.handles: dict = {}
        """The panel's controls (projection, angle, image, axis, where) and the scene's slice image ("slice")."""

    def draw(self) -> None:
        s = self.server
        s.scene.set_up_direction("+z")
        s.scene.add_line_segments("/xray/box", box_edges(self.box), colors=(255, 160, 0), thickness=0.003 * self.size)
        with s.gui.add_folder("X-ray"):
            kind = s.gui.add_dropdown("Projection", ("DRR", "MIP"), initial_value="DRR")
            angle = s.gui.add_slider("Gantry angle (deg)", min=0.0, max=360.0, step=1.0, initial_value=0.0)
            image = s.gui.add_image(projection_image(self.run, "DRR", 0.0, self.volume), label="projection")
            axis = s.gui.add_dropdown("Slice axis", AXES, initial_value="z")
            where = s.gui.add_slider("Slice position", min=0.0, max=1.0, step=0.01, initial_value=0.5)
        self.handles.update(projection=kind, angle=angle, image=image, axis=axis, where=where)

        def update_projection(_=None) -> None:
            image.image = projection_image(self.run, kind.value, float(angle.value), self.volume)

        def update_slice(_=None) -> None:
            self._draw_slice(axis.value, float(where.value))

        kind.on_update(update_projection)
        angle.on_update(update_projection)
        axis.on_update(update_slice)
        where.on_update(update_slice)
        update_slice()
        centre = self.box.mean(axis=0)
        s.initial_camera.position = tuple(centre + np.array([1.2, -1.2, 0.8]) * self.size)
        s.initial_camera.look_at = tuple(centre)

    def _draw_slice(self, axis: str, fraction: float) -> None:
        img, k = slice_image(self.vol_np, axis, fraction, self.hi)
        a = AXES.index(axis)
        lo, hi = self.box
        pos = lo + (hi - lo) * 0.5
        pos[a] = lo[a] + (k + 0.5) * (hi[a] - lo[a]) / self.vol_np.shape[a]
        first, second = [i for i in range(3) if i != a]
        # an image lies in its local x-y plane (x right, y up): rotate so x -> axis `first`, y -> axis `second`
        rot = np.zeros((3, 3))
        rot[first, 0], rot[second, 1] = 1.0, 1.0
        rot[:, 2] = np.cross(rot[:, 0], rot[:, 1])
        self.handles["slice"] = self.server.scene.add_image(
            "/xray/slice",
            img,
            render_width=float(hi[first] - lo[first]),
            render_height=float(hi[second] - lo[second]),
            wxyz=quat_from_matrix(rot),
            position=pos,
        )
