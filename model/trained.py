"""A field method's run (density, nerf), ready for rendering and queries: `load_field_run` -> `Trained`.

Everything outside works in the scene frame (transforms.json's normalised frame): `render_rays` returns world
distances, `density(x)` takes scene points, `aabb` is the scene's box. The run's scene space (`radiance.space`)
maps to and from the field's coordinates inside; `occupancy` is None unless the grid lives in the scene frame.
`Trained` is a `model.run.Run` with the capabilities rays, density, colour (a field with colour) and pose_opt.

A run folder works from anywhere: config.json records the scene folder both as given (resolved when the run was
trained) and relative to the run folder, and the relative one is tried first, so a run moved together with its
scene (OUT/run and OUT/scene) still finds it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from nerfpipe.data.errors import UserError
from nerfpipe.data.rundir import find_run_scene
from nerfpipe.data.transforms import Scene, read_scene
from nerfpipe.model.appearance import Appearance
from nerfpipe.model.camera_opt import TEST_POSE_RULE, refined_scene
from nerfpipe.model.checkpoint import read_checkpoint, restore_appearance
from nerfpipe.model.device import rays_per_chunk
from nerfpipe.model.field_model import EXACT, FieldModel, Inference
from nerfpipe.model.methods.base import RunFiles
from nerfpipe.radiance.fields import Field
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.space import Space

__all__ = ["WHITE", "Trained", "load_field_run", "read_run_scene"]

WHITE = (1.0, 1.0, 1.0)
"""Evaluation background of runs trained on images with alpha."""


@dataclass
class Trained:
    """A field method's run, ready for rendering and queries (no grad, chunked)."""

    method: str
    scene: Scene
    model: FieldModel
    device: torch.device
    background: Tensor  # [3] evaluation background
    downscale: float = 1.0
    """The image downscale the run trained at."""
    pose_refinement: dict | None = None
    """Runs trained with --refine-poses: what `model.camera_opt.refined_scene` did to `scene` (whose cameras
    are then the refined ones, test views mapped into the refined frame); None otherwise."""

    @property
    def capabilities(self) -> frozenset[str]:
        caps = {"rays", "density", "pose_opt"}
        return frozenset(caps | {"color"} if self.field.has_color else caps)

    @property
    def field(self) -> Field:
        return self.model.field

    @property
    def space(self) -> Space:
        """The run's scene space (where its field lives)."""
        return self.model.space

    @property
    def far(self) -> float:
        """How far along its rays the run renders (scene units; inf: unbounded, contracted or NDC)."""
        return float(self.space.far)

    @property
    def occupancy(self) -> OccupancyGrid | None:
        """The run's occupancy grid where it lives in the scene frame (None otherwise, or without one)."""
        return getattr(self.model, "grid", None) if self.space.scene_frame else None

    @property
    def aabb(self) -> Tensor:
        """[2, 3] scene frame (NDC and contracted runs: the scene's aabb, not the field's box)."""
        if self.space.scene_frame:
            return self.space.field_box.to(self.device)
        return torch.as_tensor(self.scene.aabb, dtype=torch.float32, device=self.device).reshape(2, 3)

    @property
    def chunk(self) -> int:
        return rays_per_chunk(self.model.chunk, self.device)

    @property
    def appearance(self) -> Appearance | None:
        """The run's per-image appearance codes (train --appearance), None without."""
        return self.model.appearance

    @contextmanager
    def appearance_off(self) -> Iterator[None]:
        """Render without the appearance codes inside the block (eval's half rule fits a code to a plain render)."""
        kept, self.model.appearance = self.model.appearance, None
        try:
            yield
        finally:
            self.model.appearance = kept

    @torch.no_grad()
    def render_rays(
        self, rays_o: Tensor, rays_d: Tensor, *, infer: Inference = EXACT, median: bool = True
    ) -> dict[str, Tensor]:
        """rays_o, rays_d [R, 3] (unit) -> dict(rgb [R, 3], depth [R] (expected t), acc [R], and with `median`
        depth_median [R]).

        depth is sum(w t) / acc; depth_median the t where the accumulated weight reaches 0.5 (inf when the
        ray never reaches it). Missing colour (density-only field) gives rgb = background. `infer`: how a grid
        field stops its rays (`model.field_model.Inference`; the default is exact to float32's epsilon).
        """
        if rays_o.shape != rays_d.shape or rays_o.ndim != 2 or rays_o.shape[-1] != 3:
            raise ValueError(f"expected rays_o, rays_d [R, 3], got {tuple(rays_o.shape)}, {tuple(rays_d.shape)}")
        keys = ("rgb", "depth", "depth_median", "acc") if median else ("rgb", "depth", "acc")
        parts: dict[str, list[Tensor]] = {k: [] for k in keys}
        for i in range(0, rays_o.shape[0], self.chunk):
            o = rays_o[i : i + self.chunk].to(self.device, torch.float32)
            d = rays_d[i : i + self.chunk].to(self.device, torch.float32)
            out = self.model.render(o, d, self.background, train=False, median=median, infer=infer)
            if "rgb" not in out:
                out["rgb"] = self.background.to(o).expand(o.shape[0], 3)
            for k in parts:
                parts[k].append(out[k])
        return {k: torch.cat(v) if v else torch.zeros(0, device=self.device) for k, v in parts.items()}

    def render_differentiable(self, o: Tensor, d: Tensor, background: Tensor) -> dict[str, Tensor]:
        """o, d [R, 3] -> dict(rgb [R, 3], ...) with gradients to the rays (the plain march at the inference step)."""
        return self.model.render(o, d, background, train=False, infer=None)

    def parameters(self) -> Iterator[torch.nn.Parameter]:
        """The field's parameters (frozen by eval's test-pose optimisation)."""
        return self.field.parameters()

    @torch.no_grad()
    def density(self, x: Tensor) -> Tensor:
        """x [N, 3] scene frame -> sigma [N] >= 0 per scene unit (`Space.density_query`: NDC runs, the NDC density
        times NDC length per scene length along the mean camera's ray through x, 0 before the near plane;
        contracted runs, the contracted-space density times contracted length per scene length)."""
        out = []
        for i in range(0, x.shape[0], self.chunk):
            p, scale = self.space.density_query(x[i : i + self.chunk].to(self.device, torch.float32))
            sigma = self.field.density(p)
            out.append(sigma if scale is None else sigma * scale)
        return torch.cat(out) if out else x.new_zeros(0)

    def density_function(self) -> Callable[[Tensor], Tensor]:
        """The fastest density query for large batches of scene points: the field's own where it lives in the scene
        frame (`density` splits queries into render-sized chunks, several times slower on a CPU), else `density`."""
        return self.field.density if self.space.scene_frame else self.density

    @torch.no_grad()
    def color(self, x: Tensor, d: Tensor | None) -> Tensor:
        """x [N, 3], d [N, 3] unit or None -> rgb [N, 3] in [0, 1].

        A view-dependent field given d = None is asked along (0, 0, -1) (looking straight down the up axis).
        """
        if not self.field.has_color:
            raise ValueError("this run's field is density-only: no colour")
        out = []
        for i in range(0, x.shape[0], self.chunk):
            xi = x[i : i + self.chunk].to(self.device, torch.float32)
            di = None
            if self.field.view_dependent:
                di = (
                    d[i : i + self.chunk].to(xi)
                    if d is not None
                    else torch.tensor([0.0, 0.0, -1.0]).to(xi).expand_as(xi)
                )
            if di is not None:
                di = self.space.field_directions(xi, di)
            out.append(self.field.color(self.space.field_points(xi), di))
        return torch.cat(out) if out else x.new_zeros(0, 3)


ModelLoader = Callable[[dict, dict, Scene, torch.device], FieldModel]
"""(config.json, checkpoint, scene, device) -> the method's model with its weights (a field method's own)."""


def load_field_run(files: RunFiles, device: torch.device, method: str, load_model: ModelLoader) -> Trained:
    """A field method's run: the checkpoint, the scene, the model (`load_model`), appearance codes and refined
    cameras; UserError when it is not a finished run."""
    state = read_checkpoint(files.checkpoint, device)
    scene = read_run_scene(files.run_dir, files.config)
    model = load_model(files.config, state, scene, device)
    model.appearance = restore_appearance(state, device)
    refinement = None  # built from the input scene as in training; below, consumers get the refined cameras
    if state.get("camera_opt") is not None:
        scene, refinement = refined_scene(scene, state["camera_opt"], scene.split("train"))
        refinement["test_poses"] = {"rule": TEST_POSE_RULE, **refinement.get("test_poses", {})}
    model.train_mode(False)
    return Trained(
        method=method,
        scene=scene,
        model=model,
        device=device,
        background=model.background.eval_colour().detach(),
        downscale=files.downscale,
        pose_refinement=refinement,
    )


def read_run_scene(run_dir: Path, doc: dict) -> Scene:
    """The run's scene: config.json's `scene_from_run` (relative to the run folder) when it is there, else its
    `scene_dir` (as recorded: absolute for runs trained since it was resolved, else relative to where train ran)."""
    tried = find_run_scene(run_dir, doc, ("scene_dir",))
    if not tried:
        raise UserError(f"{run_dir}: config.json names no scene folder (scene_dir)")
    found = next((p for p in tried if p.is_dir() or p.is_file()), tried[-1])
    try:
        return read_scene(found)
    except UserError as exc:
        raise UserError(
            f"{run_dir}: the run's scene cannot be read (looked in {', '.join(map(str, tried))}): {exc}"
        ) from None
