"""The method interface (model.methods, issue 47): a method written in this file alone and registered from here (an
analytic sphere that learns one colour) goes through `train`, `render`, `eval`, `depth`, `mesh` and the viewer's
render path, touching no product file; the registry's plugin path (entry points) finds it too; a stage refuses
in one line what a run cannot do."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import trimesh

from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import Frame, Scene, write_scene
from nerfpipe.data.video import to_uint8, write_png
from nerfpipe.model.checkpoint import read_checkpoint
from nerfpipe.model.methods import Method, Prepared, RunFiles, TrainContext, registry
from nerfpipe.model.trained import read_run_scene
from nerfpipe.radiance import paths
from nerfpipe.radiance.camera import Intrinsics, generate_rays
from nerfpipe.stages import depth as depth_stage
from nerfpipe.stages import eval as eval_stage
from nerfpipe.stages import mesh as mesh_stage
from nerfpipe.stages import render as render_stage
from nerfpipe.stages import train
from nerfpipe.stages.view.run_view import render_camera

CENTRE, RADIUS = np.array([0.1, -0.05, 0.2]), 0.6
TRUE_COLOUR = (0.8, 0.3, 0.15)


# ---------------------------------------------------------------------------------------------- the toy method
def _hits(o: torch.Tensor, d: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit rays o, d [R, 3] against the sphere: hit [R] bool and the first t [R] (0 where missed)."""
    oc = o - torch.as_tensor(CENTRE, dtype=o.dtype, device=o.device)
    b = (oc * d).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - radius**2)
    hit = disc > 0
    t = torch.where(hit, -b - torch.sqrt(disc.clamp_min(0)), torch.zeros_like(b))
    return hit & (t > 0), t


class Colour(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.logit = torch.nn.Parameter(torch.zeros(3))

    def rgb(self) -> torch.Tensor:
        return torch.sigmoid(self.logit)


@dataclass(eq=False)
class SphereModel:
    """The toy's `TrainModel`: a fixed sphere whose one colour is learned."""

    radius: float
    background: Any
    colour: Colour = dataclasses.field(default_factory=Colour)
    appearance: Any = None
    space: Any = None
    chunk: int = 4096
    random_draws_per_ray: int = 0

    def render(self, o, d, background, *, train, view=None, **_):
        hit, t = _hits(o, d, self.radius)
        bg = background.to(o).expand(o.shape[0], 3)
        rgb = torch.where(hit[:, None], self.colour.rgb().to(o).expand(o.shape[0], 3), bg)
        return {"rgb": rgb, "acc": hit.to(o.dtype), "depth": t, "samples": torch.tensor(float(o.shape[0]))}

    def param_groups(self, lr):
        return [{"params": [self.colour.logit], "lr": lr, "lr_scale": 1.0}]

    def train_mode(self, on):
        self.colour.train(on)

    def after_step(self):
        pass

    def learned(self):
        return {"colour": self.colour}

    def snapshot(self):
        return self.colour.logit.detach().clone()

    def restore(self, snapshot):
        with torch.no_grad():
            self.colour.logit.copy_(snapshot)
        return False

    def describe(self):
        return {"sphere": {"centre": CENTRE.tolist(), "radius": self.radius}}


@dataclass
class SphereRun:
    """The toy's run for the stages (`model.run.Run`): rays, a signed distance, colours."""

    scene: Scene
    rgb: torch.Tensor  # [3] the learned colour
    radius: float
    background: torch.Tensor
    device: torch.device = torch.device("cpu")
    downscale: float = 1.0
    pose_refinement: dict | None = None
    appearance: None = None
    method: str = "sphere"
    capabilities: frozenset = frozenset({"rays", "sdf", "color"})
    far: float = math.inf

    @property
    def aabb(self) -> torch.Tensor:
        return torch.as_tensor(np.stack([CENTRE - 1.2 * self.radius, CENTRE + 1.2 * self.radius]), dtype=torch.float32)

    occupancy = None

    def render_rays(self, rays_o, rays_d, *, infer=None, median=True):
        hit, t = _hits(rays_o.float(), rays_d.float(), self.radius)
        rgb = torch.where(hit[:, None], self.rgb.expand(rays_o.shape[0], 3), self.background.expand(rays_o.shape[0], 3))
        out = {"rgb": rgb, "depth": t, "acc": hit.float()}
        return out | ({"depth_median": torch.where(hit, t, torch.full_like(t, math.inf))} if median else {})

    def sdf(self, x):
        return torch.linalg.norm(x - torch.as_tensor(CENTRE, dtype=x.dtype), dim=-1) - self.radius

    def color(self, x, d):
        return self.rgb.expand(x.shape[0], 3)


@dataclass(frozen=True, kw_only=True)
class SphereOptions:
    """The toy's options."""

    radius: float | None = None
    """The sphere's radius (None: 0.6, as the photos were made)."""


class SphereMethod(Method):
    name = "sphere"
    summary = "an analytic sphere that learns one colour (a test's method)"
    Options = SphereOptions

    def validate(self, options):
        if options.radius is not None and not options.radius > 0:
            raise UserError(f"radius: expected > 0, got {options.radius}")

    def prepare(self, ctx: TrainContext, options, reasons):
        radius = RADIUS if options.radius is None else options.radius
        reasons["radius"] = "the photos' sphere" if options.radius is None else "asked for"
        return Prepared(options=SphereOptions(radius=radius), space=None)

    def default_lr(self):
        return 0.1, "0.1 for one colour"

    def build(self, ctx, prepared, state):
        model = SphereModel(radius=prepared.options.radius, background=ctx.background)
        if state is not None:
            model.colour.load_state_dict(state["sphere"]["colour"])
        return model

    def checkpoint(self, model):
        return {"sphere": {"radius": model.radius, "colour": model.colour.state_dict()}}

    def load(self, run: RunFiles, device):
        state = read_checkpoint(run.checkpoint, device)
        colour = Colour()
        colour.load_state_dict(state["sphere"]["colour"])
        bg = torch.tensor([1.0, 1.0, 1.0])
        rgb = colour.rgb().detach()
        return SphereRun(
            scene=read_run_scene(run.run_dir, run.config), rgb=rgb, radius=state["sphere"]["radius"], background=bg
        )


SPHERE = SphereMethod()


@pytest.fixture
def registered():
    registry.register(SPHERE)
    yield SPHERE
    registry.unregister(SPHERE.name)


# ---------------------------------------------------------------------------------------------- its photos
def sphere_scene(root: Path, views: int = 12, size: int = 32) -> Path:
    """Photos of the true sphere on white from an orbit (every third a test view), and their transforms.json."""
    intr = Intrinsics(w=size, h=size, fx=28.0, fy=28.0, cx=size / 2, cy=size / 2)
    orbit = paths.Orbit(centre=CENTRE, up=np.array([0.0, 0, 1]), radius=3.0, elevation_deg=25.0, start_azimuth_deg=0.0)
    poses = paths.turntable(orbit, views)
    frames = tuple(Frame(file_path=f"images/v{i:02d}.png", world_from_cam=p) for i, p in enumerate(poses))
    for frame in frames:
        o, d = generate_rays(intr, torch.as_tensor(frame.world_from_cam))
        hit, _ = _hits(o, d, RADIUS)
        rgb = torch.where(hit[:, None], torch.tensor(TRUE_COLOUR, dtype=o.dtype), torch.ones(3, dtype=o.dtype))
        write_png(root / frame.file_path, to_uint8(rgb.reshape(size, size, 3).numpy()))
    test = tuple(range(0, views, 3))
    scene = Scene(
        root=root,
        frames=frames,
        intrinsics=intr,
        splits={"train": tuple(i for i in range(views) if i not in test), "test": test},
        aabb=np.stack([CENTRE - 1.0, CENTRE + 1.0]),
        near=0.5,
        far=6.0,
    )
    write_scene(scene)
    return root


# ---------------------------------------------------------------------------------------------- the chain
def test_a_method_from_this_file_goes_through_every_stage(registered, tmp_path):
    scene_dir = sphere_scene(tmp_path / "scene")
    run_dir = tmp_path / "run"
    out = train.run(
        train.Config(scene_dir=scene_dir, run_dir=run_dir, method="sphere", max_steps=150, eval_every=50, device="cpu")
    )
    doc = json.loads((run_dir / "config.json").read_text())
    assert doc["method"] == "sphere" and doc["options"] == {"radius": RADIUS} and doc["lr"] == 0.1
    manifest = json.loads(out.manifest.read_text())
    assert manifest["used"]["method"] == "sphere" and manifest["used"]["sphere"]["radius"] == RADIUS
    assert "occupancy_grid" in manifest["left_out"]
    state = torch.load(out.checkpoint, weights_only=True)
    learned = torch.sigmoid(state["sphere"]["colour"]["logit"])
    torch.testing.assert_close(learned, torch.tensor(TRUE_COLOUR), atol=0.02, rtol=0)  # it learned its colour
    assert out.test_psnr > 35  # the toy is its photos' own renderer: 8-bit rounding and edge pixels only

    ev = eval_stage.run(eval_stage.Config(run_dir=run_dir, out=tmp_path / "eval.json", device="cpu"))
    assert ev.result["n_views"] == 4 and ev.result["psnr"] > 35

    video = render_stage.run(
        render_stage.Config(
            run_dir=run_dir,
            out=tmp_path / "turn.mp4",
            path="turntable",
            frames=4,
            device="cpu",
            frames_dir=tmp_path / "f",
        )
    )
    frame = np.asarray(__import__("imageio.v3", fromlist=["imread"]).imread(sorted((tmp_path / "f").glob("*.png"))[0]))
    colours = frame.reshape(-1, frame.shape[-1])[:, :3].astype(float) / 255
    assert video.n_frames == 4 and (np.abs(colours - TRUE_COLOUR).max(axis=1) < 0.06).mean() > 0.05

    dm = depth_stage.run(depth_stage.Config(run_dir=run_dir, out_dir=tmp_path / "depth", device="cpu"))
    assert len(dm.names) == 4

    mesh = mesh_stage.run(
        mesh_stage.Config(run_dir=run_dir, out=tmp_path / "sphere.ply", frame="normalized", resolution=48, device="cpu")
    )
    verts = trimesh.load(mesh.mesh).vertices
    radii = np.linalg.norm(verts - CENTRE, axis=1)  # the zero level set of its signed distance: the sphere
    assert abs(float(np.median(radii)) - RADIUS) < 0.01 and float(np.abs(radii - RADIUS).max()) < 0.05
    report = json.loads(mesh.report.read_text())
    assert report["method"]["name"] == "signed distance"

    from nerfpipe.model import load_trained

    run = load_trained(run_dir, "cpu")
    image = render_camera(run, (1.0, 0.0, 0.0, 0.0), (0.1, -3.0, 0.2), 0.8, 1.0, 24, coarse=True)
    assert image.shape == (24, 24, 3) and image.dtype == np.uint8


def test_a_run_of_the_method_is_refused_where_it_cannot_serve(registered, tmp_path):
    """A stage says in one line what the run cannot do: export-points needs a density or a signed distance (its
    normals); the toy has a signed distance, so its points come out with the distance's normals, and without one
    the stage refuses."""
    from nerfpipe.model import load_trained
    from nerfpipe.stages import export_points

    scene_dir = sphere_scene(tmp_path / "scene", views=6, size=16)
    train.run(train.Config(scene_dir=scene_dir, run_dir=tmp_path / "run", method="sphere", max_steps=2, device="cpu"))
    config = export_points.Config(run_dir=tmp_path / "run", out=tmp_path / "p.ply", frame="normalized", device="cpu")
    out = export_points.run(config)
    report = json.loads(out.report.read_text())
    run = load_trained(tmp_path / "run", "cpu")
    radii = np.linalg.norm(np.asarray(trimesh.load(out.out, process=False).vertices) - CENTRE, axis=1)
    assert out.points > 0 and np.abs(radii / run.radius - 1).max() < 0.05  # on the toy's sphere
    normals = report["normals"]  # +grad f faces every camera that saw its point (-grad f would face none)
    assert normals["rule"].startswith("+grad f") and normals["facing_camera_before_reorienting"] == 1.0
    assert normals["from_view_direction"] == 0 and normals["reoriented"] == 0
    blind = dataclasses.replace(run, capabilities=frozenset({"rays", "color"}))
    with pytest.raises(UserError, match="a sphere run cannot give a signed distance at points or give a density at"):
        export_points.export(blind, dataclasses.replace(config, out=tmp_path / "q.ply"))
    assert not (tmp_path / "q.ply").exists()
    with pytest.raises(UserError, match="radius: expected > 0"):
        train.run(
            train.Config(
                scene_dir=scene_dir, run_dir=tmp_path / "r2", method="sphere", options=SphereOptions(radius=-1.0)
            )
        )


def test_entry_points_plug_methods_in(monkeypatch):
    """A method a package declares in the `nerfpipe.methods` entry-point group is found by name."""

    class EntryPoint:
        name = "sphere"

        def load(self):
            return SphereMethod

    monkeypatch.setattr(registry, "entry_points", lambda group: [EntryPoint()] if group == "nerfpipe.methods" else [])
    monkeypatch.setattr(registry, "_plugins_loaded", False)
    try:
        assert "sphere" in registry.method_names()
        assert isinstance(registry.method_named("sphere"), SphereMethod)
    finally:
        registry.unregister("sphere")
    with pytest.raises(UserError, match="unknown method 'nope': expected one of density, nerf"):
        registry.method_named("nope")


def test_readme_lists_every_built_in_method_with_its_summary():
    """The README's methods table is written by hand: it names each built-in method with the summary `--help` gives."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    for name in registry.BUILTIN:
        method = registry.method_named(name)
        assert f"| `{name}`" in readme and method.summary in readme, f"README's methods table misses {name}"
