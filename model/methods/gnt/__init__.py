"""`train --method gnt`: a generalizable NeRF transformer (GNT, Wang et al. ICLR 2023). Each ray reads the features
of its nearest training photos at its samples (a view transformer over the photos, a ray transformer over the
samples, an attention read-out in place of the volume-rendering sum), so one network renders scenes it was never
trained on from their photos.

Three ways to run it, all `train`:
- per scene (as the source document): `--method gnt`, random weights, the scene's photos as sources;
- zero-shot: `--method gnt --init pretrained --max-steps 0`: the shipped weights (trained on generated scenes by
  `make pretrain-gnt`) plus the scene, no step taken; `render`, `eval`, `depth` and `view` take the run;
- fine-tuned: `--init pretrained` (or a weights file, or another gnt run's checkpoint.pt) with steps.

Modules: `options`, `features` (image feature extractors), `net` (the transformers), `sources` (the photos, their
choice per ray, the bilinear gather), `model` (the `TrainModel`), `hooks` (a step's rays from a few photos), `run`
(the run for the stages), `weights` (weights files), `pretrain` (the cross-scene training on generated scenes).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch

from nerfpipe.data.errors import UserError
from nerfpipe.model.checkpoint import read_checkpoint, restore_appearance, restore_background
from nerfpipe.model.methods.base import Method, Prepared, RunFiles, TrainContext
from nerfpipe.model.methods.gnt.hooks import GntBatches
from nerfpipe.model.methods.gnt.model import GntModel, RayRange, ray_range
from nerfpipe.model.methods.gnt.options import (
    SAMPLES,
    SOURCE_SIDE,
    SOURCE_VIEWS,
    GntOptions,
    validate_options,
)
from nerfpipe.model.methods.gnt.run import GntRun
from nerfpipe.model.methods.gnt.sources import sources_from_views
from nerfpipe.model.methods.gnt.weights import build_net, read_weights
from nerfpipe.model.trained import read_run_scene
from nerfpipe.model.views import load_views
from nerfpipe.radiance.space import Box

__all__ = ["GNT", "GntMethod", "GntOptions"]

LR = 5e-4
"""Adam's learning rate (GNT's)."""
BATCH = (512, 4096)
"""Rays a step by default: CPU, CUDA (a step reads every source's features of its few photos: `hooks.GntBatches`)."""


@dataclass(frozen=True, kw_only=True)
class GntPrepared(Prepared):
    options: GntOptions
    range: RayRange
    init: tuple[dict, dict, dict] | None
    """The initial weights (net config, state, provenance), or None."""


class GntMethod(Method):
    name = "gnt"
    summary = "generalizable NeRF transformer: features of the nearest photos, view and ray transformers"
    Options = GntOptions

    def validate(self, options: GntOptions) -> None:
        validate_options(options)

    def prepare(self, ctx: TrainContext, options: GntOptions, reasons: dict[str, str]) -> GntPrepared:
        n = len(ctx.train_idx)
        if n < 2:
            raise UserError(f"the gnt method renders from other photos: expected >= 2 training photos, got {n}")
        if ctx.refine_poses:
            raise UserError("the gnt method does not refine poses (refine_poses): use method=density")
        init = read_weights(options.init, ctx.device) if options.init else None
        extractor = options.extractor or (init[0]["extractor"] if init else "shallow")
        if init and extractor != init[0]["extractor"]:
            raise UserError(f"extractor: the initial weights use {init[0]['extractor']!r}, not {extractor!r}")
        side = max(max(h, w) for h, w in ctx.train.shapes)
        cap = SOURCE_SIDE[1] if ctx.cuda else SOURCE_SIDE[0]
        readout = options.readout or (init[0]["readout"] if init else "blend")
        if init and readout != init[0]["readout"]:
            raise UserError(f"readout: the initial weights use {init[0]['readout']!r}, not {readout!r}")
        resolved = replace(
            options,
            extractor=extractor,
            readout=readout,
            source_views=min(options.source_views or SOURCE_VIEWS, n),
            gnt_samples=options.gnt_samples or (2 * SAMPLES if ctx.cuda else SAMPLES),
            source_side=options.source_side or min(side, cap),
        )
        rng, why = ray_range(ctx.scene, ctx.space_kind is Box)
        reasons["scene_model"] = f"{ctx.space_kind.name}: {ctx.space_why}; rays {why}"
        for name, default in (
            ("extractor", "shallow" if not init else "the initial weights'"),
            ("readout", "blend" if not init else "the initial weights'"),
            ("source_views", f"{SOURCE_VIEWS}, at most the training photos (a training ray: but its own)"),
            ("gnt_samples", f"{SAMPLES} a ray on CPU, {2 * SAMPLES} on CUDA"),
            ("source_side", f"{cap} px on this device, or the photos' size when smaller"),
        ):
            reasons[name] = "asked for" if getattr(options, name) is not None else default
        return GntPrepared(options=resolved, space=None, range=rng, init=init)

    def default_lr(self) -> tuple[float, str]:
        return LR, f"{LR} (GNT's Adam learning rate)"

    def default_batch(self, cuda: bool) -> tuple[int, str]:
        batch = BATCH[1] if cuda else BATCH[0]
        return batch, f"{BATCH[0]} on CPU (GNT's 512 rays a step), {BATCH[1]} on CUDA"

    def build(self, ctx: TrainContext, prepared: GntPrepared, state: dict | None) -> GntModel:
        o = prepared.options
        if state is not None:
            net = build_net(state["gnt_net_config"], state["gnt_net"], ctx.device)
        elif prepared.init is not None:
            net = build_net(prepared.init[0], prepared.init[1], ctx.device)
        else:
            net = build_net({"extractor": o.extractor, "readout": o.readout}, None, ctx.device)
        model = GntModel(
            net=net,
            sources=sources_from_views(ctx.train, o.source_side).to(ctx.device),
            range=prepared.range,
            samples=o.gnt_samples,
            k=o.source_views,
        )
        model.background = ctx.background if state is None else restore_background(state, ctx.device)
        return model

    def hooks(self, ctx: TrainContext, prepared: GntPrepared, model: GntModel) -> list:
        return [GntBatches(ctx.train.offsets, prepared.options.views_per_step)]

    def checkpoint(self, model: GntModel) -> dict[str, Any]:
        return {
            "gnt_net_config": model.net.config(),
            "gnt_net": model.net.state_dict(),
            "gnt_range": model.range.to_dict(),
            "gnt_samples": model.samples,
            "gnt_source_views": model.k,
            "gnt_source_side": max(model.sources.size),
        }

    def load(self, run: RunFiles, device: torch.device) -> GntRun:
        state = read_checkpoint(run.checkpoint, device)
        scene = read_run_scene(run.run_dir, run.config)
        try:
            net = build_net(state["gnt_net_config"], state["gnt_net"], device)
            rng = RayRange.from_dict(state["gnt_range"])
            samples, k, side = int(state["gnt_samples"]), int(state["gnt_source_views"]), int(state["gnt_source_side"])
        except (KeyError, TypeError, ValueError) as exc:
            raise UserError(f"{run.checkpoint}: not a gnt checkpoint this version reads ({exc})") from None
        background = restore_background(state, device)
        views = load_views(scene, scene.split("train"), run.downscale)
        if background.mode == "plain":  # the sources as training read them (stages.train.setup clears them so)
            views.mask_colour(tuple(float(v) for v in background.eval_colour()))
        model = GntModel(
            net=net,
            sources=sources_from_views(views, side).to(device),
            range=rng,
            samples=samples,
            k=k,
            background=background,
        )
        model.appearance = restore_appearance(state, device)
        model.train_mode(False)
        return GntRun(
            scene=scene,
            model=model,
            device=device,
            background=model.background.eval_colour().detach(),
            downscale=run.downscale,
        )


GNT = GntMethod()
