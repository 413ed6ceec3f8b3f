"""GNT across scenes: the step `pretrain-gnt` runs on the one training loop (`model.loop.TrainingLoop`).

Each step draws a scene, one of its photos as the target and `batch` of its pixels, and a source count K uniform
in [k_min, k_max] (so one model serves 3 source views as well as 10); the target's own photo is never a source.
The photos' colours are composited on a random colour per ray where they are transparent (as `train` does for
photos with alpha), the network's coverage puts that colour behind what it renders, and the loss is the mean
squared error. A scene's rays are sampled as `train --method gnt` samples it (`ray_range`: through the box of
objects with alpha, in inverse depth otherwise), and its photos are the sources at `source_side` pixels at most.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import Scene, read_scene
from nerfpipe.model.loop import NetStepper
from nerfpipe.model.methods.gnt.model import GntModel, RayRange, ray_range
from nerfpipe.model.methods.gnt.net import GntNet
from nerfpipe.model.methods.gnt.sources import Sources, sources_from_views
from nerfpipe.model.spaces import choose_space
from nerfpipe.model.views import Views, load_views
from nerfpipe.radiance.compositing import over_background
from nerfpipe.radiance.space import Box

__all__ = ["SceneSet", "TrainingScene", "CrossScene", "scene_folders", "load_scene_set", "scene_range"]


@dataclass
class TrainingScene:
    """One generated scene as the cross-scene step reads it."""

    name: str
    views: Views  # every photo of the scene (targets and sources)
    sources: Sources
    range: RayRange


SceneSet = list[TrainingScene]


def scene_folders(root: Path) -> list[Path]:
    """The scene folders under `root` (each holds a transforms.json), sorted; UserError when there are none."""
    if not root.is_dir():
        raise UserError(f"{root}: not a folder of scenes (expected folders that each hold a transforms.json)")
    found = sorted(p.parent for p in root.glob("**/transforms.json"))
    if not found:
        raise UserError(f"{root}: no scene folders (expected .../<scene>/transforms.json: the scene stage, count > 1)")
    return found


def scene_range(scene: Scene) -> RayRange:
    """Where `train --method gnt` samples this scene's rays (`model.methods.gnt.model.ray_range`)."""
    kind, _ = choose_space("auto", scene, plain_background=scene.has_alpha)
    return ray_range(scene, kind is Box)[0]


def load_scene_set(root: Path, source_side: int, device: torch.device) -> SceneSet:
    """Every scene under `root`: all its photos (split files ignored: every photo is a target and a source)."""
    out = []
    for folder in scene_folders(root):
        scene = read_scene(folder)
        views = load_views(scene, tuple(range(len(scene.frames))))
        if len(views.shapes) < 2:
            raise UserError(f"{folder}: a scene needs >= 2 photos to pretrain on, got {len(views.shapes)}")
        sources = sources_from_views(views, source_side).to(device)
        out.append(TrainingScene(name=folder.name, views=views, sources=sources, range=scene_range(scene)))
    return out


@dataclass(eq=False, kw_only=True)
class CrossScene(NetStepper):
    """The cross-scene step (module doc): a `model.loop.Stepper`."""

    net: GntNet
    scenes: SceneSet
    gen: torch.Generator
    device: torch.device
    batch: int
    samples: int
    k_range: tuple[int, int]
    on_log: Any  # (step, mse, k, lr) -> None, after each good step
    last_mse: float = float("nan")
    last_k: int = 0

    def train_step(self, lr: float) -> bool:
        g = self.gen
        scene = self.scenes[int(torch.randint(len(self.scenes), (1,), generator=g))]
        n_views = len(scene.views.shapes)
        target = int(torch.randint(n_views, (1,), generator=g))
        k = int(torch.randint(self.k_range[0], self.k_range[1] + 1, (1,), generator=g))
        k = max(1, min(k, n_views - 1))
        pixels = scene.views.pixels_of(target)
        idx = pixels[torch.randint(pixels.numel(), (self.batch,), generator=g)]
        o, d, rgb, alpha = scene.views.batch(idx, self.device)
        bg = torch.rand(self.batch, 3, generator=g).to(self.device)
        goal = over_background(rgb, alpha[:, None], bg)
        model = GntModel(net=self.net, sources=scene.sources, range=scene.range, samples=self.samples, k=k)
        view = torch.full((self.batch,), target, dtype=torch.long, device=self.device)
        out = model.render(o, d, bg, train=True, view=view)
        loss = torch.mean((out["rgb"] - goal) ** 2)
        if not torch.isfinite(loss):
            return False
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.last_mse, self.last_k = float(loss.detach()), k
        return True

    def log(self, lr: float) -> None:
        self.on_log(self.step, self.last_mse, self.last_k, lr)
