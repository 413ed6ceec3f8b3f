"""Drawing a scene (transforms.json) in viser: camera frusta with their images, sparse points, the box, the up
axis; clicking a camera shows its image and name, and a toggle draws a few of its rays with their samples.

Everything is in the scene frame (up +z by contract; the arrow shows the training cameras' own up,
`radiance.paths.up_axis`, which `render` orbits around). Rays are sampled as training would before any
occupancy is known: `RAY_SAMPLES` stratified intervals between the ray's entry into and exit from the box.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from nerfpipe.data.transforms import Scene, load_image
from nerfpipe.radiance import paths
from nerfpipe.radiance.aabb import ray_aabb_segment
from nerfpipe.radiance.camera import generate_rays
from nerfpipe.radiance.samplers import stratified_intervals
from nerfpipe.stages.view.cameras import vertical_fov, viser_pose

__all__ = ["THUMBNAIL", "RAY_GRID", "RAY_SAMPLES", "thumbnail", "camera_rays", "box_edges", "SceneView"]

THUMBNAIL = 96
"""Long side, in pixels, of the images drawn in the frusta and shown on click."""
RAY_GRID = 3
"""The ray toggle draws RAY_GRID x RAY_GRID rays of the selected camera, spread over its image."""
RAY_SAMPLES = 24
"""Sample points drawn on each ray."""


def thumbnail(scene: Scene, i: int, long_side: int = THUMBNAIL) -> np.ndarray:
    """Frame i's image as uint8 [h, w, 3], at most `long_side` px (alpha composited on white)."""
    img = load_image(scene.image_path(i))
    if img.shape[2] == 4:
        img = img[..., :3] * img[..., 3:] + (1.0 - img[..., 3:])
    step = max(1, int(np.ceil(max(img.shape[:2]) / long_side)))
    return (np.clip(img[::step, ::step, :3], 0, 1) * 255 + 0.5).astype(np.uint8)


def camera_rays(scene: Scene, i: int, grid: int = RAY_GRID, samples: int = RAY_SAMPLES):
    """A grid x grid fan of frame i's rays -> (segments [R, 2, 3] from the camera to the box's far side,
    sample midpoints [R * samples, 3] inside the box; none for rays that miss it)."""
    intr = scene.frame_intrinsics(i)
    u = (np.arange(grid) + 0.5) / grid
    uv = torch.tensor([(a * intr.w, b * intr.h) for b in u for a in u], dtype=torch.float64)
    o, d = generate_rays(intr, torch.as_tensor(scene.frames[i].world_from_cam), uv)
    aabb = torch.as_tensor(np.asarray(scene.aabb, dtype=np.float64).reshape(2, 3))
    t0, t1 = ray_aabb_segment(o, d, aabb, max(scene.near, 0.0), 1e10)
    hit = t1 > t0
    far = torch.where(hit, t1, torch.full_like(t1, 2.0 * float((aabb[1] - aabb[0]).norm())))
    segments = torch.stack([o, o + d * far[:, None]], dim=1)
    if not bool(hit.any()):
        return segments.numpy(), np.zeros((0, 3))
    s, e = stratified_intervals(t0[hit], t1[hit], samples)
    mid = 0.5 * (s + e)  # [H, S]
    pts = o[hit][:, None] + d[hit][:, None] * mid[..., None]
    return segments.numpy(), pts.reshape(-1, 3).numpy()


def box_edges(aabb: np.ndarray) -> np.ndarray:
    """The 12 edges of an axis-aligned box [2, 3] as segments [12, 2, 3]."""
    lo, hi = np.asarray(aabb, dtype=np.float64).reshape(2, 3)
    corners = np.array([[(hi if (k >> a) & 1 else lo)[a] for a in range(3)] for k in range(8)])
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return np.stack([corners[[a, b]] for a, b in pairs])


@dataclass
class SceneView:
    """The scene's drawing and its camera panel (the GUI shows the clicked camera's image and name)."""

    server: object
    scene: Scene
    size: float = 1.0
    selected: int | None = None
    handles: dict = field(default_factory=dict)
    frusta: dict = field(default_factory=dict)
    """Camera index -> its frustum's scene handle."""

    def draw(self, indices: tuple[int, ...] | None = None, *, label: str = "Cameras", images: bool = True) -> None:
        """Draw the scene; `indices`: the cameras drawn (default all); `images=False` draws their frusta empty (a
        run's live render stays visible behind them; a click still shows the camera's image in the panel)."""
        s = self.server
        aabb = np.asarray(self.scene.aabb, dtype=np.float64).reshape(2, 3)
        self.size = float(np.linalg.norm(aabb[1] - aabb[0]))
        s.scene.set_up_direction("+z")
        s.scene.add_line_segments("/scene/box", box_edges(aabb), colors=(255, 160, 0), thickness=0.004 * self.size)
        centre = aabb.mean(axis=0)
        poses = np.stack([f.world_from_cam for f in self.scene.frames])
        up, why = paths.up_axis(poses)
        s.scene.add_line_segments(
            "/scene/up",
            np.array([[centre, centre + 0.35 * self.size * up]]),
            colors=(40, 120, 255),
            thickness=0.008 * self.size,
        )
        s.scene.add_label("/scene/up_label", "up", position=tuple(centre + 0.38 * self.size * up))
        self._draw_points()
        with s.gui.add_folder(label):
            self.handles["name"] = s.gui.add_markdown("Click a camera to see its image.")
            self.handles["image"] = s.gui.add_image(np.full((8, 8, 3), 255, np.uint8), label="image")
            rays = s.gui.add_checkbox("Show its rays and samples", initial_value=False)
            s.gui.add_markdown(f"Box: orange. Up (blue): {why}.")
        rays.on_update(lambda _: self._draw_rays(rays.value))
        self.handles["rays"] = rays
        for i in range(len(self.scene.frames)) if indices is None else indices:
            self._draw_camera(i, images)

    def _draw_points(self) -> None:
        path = self.scene.named_file("sparse_points_path")  # confined to the scene folder (data.confine)
        if path is None or not path.is_file():
            return
        import trimesh

        cloud = trimesh.load(path, process=False)
        pts = np.asarray(cloud.vertices, dtype=np.float32)
        colours = getattr(getattr(cloud, "visual", None), "vertex_colors", None)
        colours = np.asarray(colours)[:, :3] if colours is not None and len(colours) == len(pts) else (200, 200, 200)
        self.server.scene.add_point_cloud("/scene/points", pts, colors=colours, point_size=0.004 * self.size)

    def _draw_camera(self, i: int, image: bool = True) -> None:
        intr = self.scene.frame_intrinsics(i)
        wxyz, pos = viser_pose(self.scene.frames[i].world_from_cam)
        frustum = self.server.scene.add_camera_frustum(
            f"/cameras/{i:04d}",
            fov=vertical_fov(intr),
            aspect=intr.w / intr.h,
            scale=0.05 * self.size,
            image=thumbnail(self.scene, i) if image else None,
            wxyz=wxyz,
            position=pos,
            color=(60, 60, 60),
        )
        frustum.on_click(lambda _event, i=i: self.select(i))
        self.frusta[i] = frustum

    def select(self, i: int) -> None:
        """Show frame i's image and name in the panel (and its rays when the toggle is on)."""
        self.selected = i
        name = self.scene.frames[i].file_path
        split = [k for k, v in self.scene.splits.items() if i in v]
        self.handles["name"].content = f"**{name}** (frame {i}{', ' + '/'.join(split) if split else ''})"
        self.handles["image"].image = thumbnail(self.scene, i, 256)
        self._draw_rays(self.handles["rays"].value)

    def _draw_rays(self, on: bool) -> None:
        for key in ("/scene/rays", "/scene/samples"):
            if key in self.handles:
                self.handles.pop(key).remove()
        if not on or self.selected is None:
            return
        segments, pts = camera_rays(self.scene, self.selected)
        self.handles["/scene/rays"] = self.server.scene.add_line_segments(
            "/scene/rays", segments, colors=(220, 30, 30), thickness=0.002 * self.size
        )
        if len(pts):
            self.handles["/scene/samples"] = self.server.scene.add_point_cloud(
                "/scene/samples", pts.astype(np.float32), colors=(255, 220, 0), point_size=0.006 * self.size
            )
