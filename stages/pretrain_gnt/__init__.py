"""Stage `pretrain-gnt`: train GNT across a folder of scenes, the weights `train --method gnt --init` starts from.

    nerfpipe scene SCENES --subject random --count 200 ...     # a dataset of scenes (make pretrain-gnt)
    nerfpipe pretrain-gnt SCENES OUT_DIR [--max-seconds 1800]

The step is `model.methods.gnt.pretrain.CrossScene` on the one training loop (budget, clock, learning-rate decay,
non-finite recovery, interrupts). Every scene's photos are all targets and sources (their split files are not
read): held-out scenes, not held-out photos, measure what the model learned (`make bench-gnt`).

Outputs under OUT_DIR:
  weights.pt      the network (`model.methods.gnt.weights`: config, parameters, provenance); written at the end
  config.json     the resolved config
  metrics.csv     step, seconds, loss (the step's mean squared error), psnr of it, k (the step's source views), lr
  manifest.json   written last: scenes, steps, seconds, the loss at the start and the end
An interrupted run writes weights.partial.pt (never weights.pt) and says so; a later run starts afresh.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import MetricsLog, output_folder, sha256_file, write_config, write_manifest
from nerfpipe.model.device import cpu_threads, resolve_device
from nerfpipe.model.loop import Budget, Clock, LoopSettings, Schedule, TrainingLoop
from nerfpipe.model.methods.gnt.features import EXTRACTORS
from nerfpipe.model.methods.gnt.net import READOUTS, GntNet
from nerfpipe.model.methods.gnt.pretrain import CrossScene, load_scene_set
from nerfpipe.model.methods.gnt.weights import build_net, read_weights, write_weights
from nerfpipe.radiance.metrics import psnr_from_mse

__all__ = ["Config", "Outputs", "run"]

METRICS = ["step", "seconds", "loss", "psnr", "k", "lr"]
LOG_EVERY = 25


@dataclass(frozen=True, kw_only=True)
class Config:
    scenes: Path
    """Folder of scene folders, each with its transforms.json (`nerfpipe scene --count N` writes one)."""
    out_dir: Path
    """Folder for weights.pt, metrics.csv, config.json and manifest.json (created)."""
    max_seconds: float = 1800.0
    """Stop after this many seconds of training."""
    max_steps: int = 1_000_000
    """Stop after this many steps."""
    extractor: str = "shallow"
    """Image features: shallow or resunet (`model.methods.gnt.features`)."""
    readout: str = "blend"
    """A sample's colour: blend (the source pixels', weighted) or direct (`model.methods.gnt.net`); with --init,
    the weights' own."""
    init: str | None = None
    """Continue from these weights (a weights.pt, a gnt run's checkpoint.pt, or 'pretrained')."""
    source_views: tuple[int, int] = (3, 10)
    """A step's source views are drawn uniformly in this range (one model for few and many views)."""
    gnt_samples: int = 32
    """Samples a ray."""
    source_side: int = 256
    """Longest side of the source images, pixels."""
    batch_rays: int = 512
    """Rays a step, all from one photo of one scene."""
    lr: float = 5e-4
    """Adam's learning rate at the start (exponential decay to lr x lr_decay)."""
    lr_decay: float = 0.1
    """Learning-rate factor reached at the end."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:N."""
    seed: int = 0
    """Seed of the weights and of the draws of scenes, photos and pixels."""
    threads: int | None = None
    """CPU: torch intra-op threads (None: torch's default)."""
    overwrite: bool = False
    """Replace an earlier output in out_dir."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out_dir: Path
    weights: Path
    """weights.pt."""
    manifest: Path
    steps: int
    seconds: float
    loss_start: float
    """Mean loss of the first LOG_EVERY steps."""
    loss_end: float
    """Mean loss of the last LOG_EVERY steps."""


def _check(config: Config) -> None:
    if config.extractor not in EXTRACTORS:
        raise UserError(f"pretrain-gnt: expected --extractor in {sorted(EXTRACTORS)}, got {config.extractor!r}")
    if config.readout not in READOUTS:
        raise UserError(f"pretrain-gnt: expected --readout in {list(READOUTS)}, got {config.readout!r}")
    lo, hi = config.source_views
    if not 1 <= lo <= hi:
        raise UserError(f"pretrain-gnt: expected --source-views LO,HI with 1 <= LO <= HI, got {lo},{hi}")
    if not config.max_seconds > 0 or config.max_steps < 1 or config.batch_rays < 1 or config.gnt_samples < 2:
        raise UserError("pretrain-gnt: expected max_seconds > 0, max_steps >= 1, batch_rays >= 1, gnt_samples >= 2")


def run(config: Config, progress: Progress | None = None) -> Outputs:
    _check(config)
    progress = progress or NO_PROGRESS
    device = resolve_device(config.device)
    started = time.time()
    with cpu_threads(config.threads):  # bad input refused before any write, within the thread cap as before
        scenes = load_scene_set(Path(config.scenes), config.source_side, device)
        init = read_weights(config.init, device) if config.init else None
    with output_folder(config.out_dir, overwrite=config.overwrite), cpu_threads(config.threads):
        out = Path(config.out_dir)
        write_config(out, config)
        torch.manual_seed(config.seed)
        init_provenance: dict = {}
        if init is not None:
            net_cfg, state, init_provenance = init
            net = build_net(net_cfg, state, device)
        else:
            net = GntNet(extractor=config.extractor, readout=config.readout).to(device)
        opt = torch.optim.Adam(net.parameters(), lr=config.lr)
        metrics = MetricsLog(out / "metrics.csv", METRICS)
        losses: list[float] = []
        task = progress.add_task("pretrain-gnt", total=config.max_seconds)
        clock = Clock(0.0)

        def on_log(step: int, mse: float, k: int, lr: float) -> None:
            losses.append(mse)
            if step % LOG_EVERY == 0:
                recent = sum(losses[-LOG_EVERY:]) / len(losses[-LOG_EVERY:])
                psnr = psnr_from_mse(recent)
                metrics.append(
                    step=step, seconds=round(clock(), 3), loss=f"{recent:.6g}", psnr=f"{psnr:.3f}", k=k, lr=lr
                )
                metrics.save()
                progress.update(task, completed=clock(), description=f"pretrain-gnt {psnr_from_mse(recent):.2f} dB")

        def partial(seconds: float) -> None:
            write_weights(out / "weights.partial.pt", net.config(), net.state_dict(), {"partial_at_step": steps.step})

        steps = CrossScene(
            net=net,
            scenes=scenes,
            opt=opt,
            gen=torch.Generator().manual_seed(config.seed),
            device=device,
            batch=config.batch_rays,
            samples=config.gnt_samples,
            k_range=config.source_views,
            on_log=on_log,
            on_checkpoint=partial,
        )
        settings = LoopSettings(
            name="pretrain-gnt",
            budget=Budget(max_steps=config.max_steps, max_seconds=config.max_seconds),
            schedule=Schedule(lr=config.lr, decay=config.lr_decay),
            checkpoint_seconds=300.0,
            checkpoint_path=out / "weights.partial.pt",
        )
        seconds = TrainingLoop(settings, steps, clock).run()
        if not losses:
            raise UserError("pretrain-gnt: no step was taken (every loss was not finite)")
        metrics.save()
        start = sum(losses[:LOG_EVERY]) / len(losses[:LOG_EVERY])
        end = sum(losses[-LOG_EVERY:]) / len(losses[-LOG_EVERY:])
        provenance = {
            "stage": "pretrain-gnt",
            "scenes": str(config.scenes),
            "scene_count": len(scenes),
            "photos": sum(len(s.views.shapes) for s in scenes),
            "steps": steps.step,
            "seconds": round(seconds, 1),
            "device": str(device),
            "loss_start": start,
            "loss_end": end,
            "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(config).items()},
            "init_provenance": init_provenance or None,  # what the weights it continued were made by
        }
        weights = write_weights(out / "weights.pt", net.config(), net.state_dict(), provenance)
        (out / "weights.partial.pt").unlink(missing_ok=True)
        manifest = write_manifest(
            out,
            stage="pretrain-gnt",
            started=started,
            outputs=["weights.pt", "metrics.csv", "config.json"],
            used={
                **{k: v for k, v in provenance.items() if k not in ("config", "init_provenance")},
                "steps_before": (init_provenance or {}).get("steps"),
                "net": net.config(),
                "parameters": sum(p.numel() for p in net.parameters()),
                "weights_sha256": sha256_file(weights),
                "psnr_start": round(psnr_from_mse(start), 3) if math.isfinite(start) else None,
                "psnr_end": round(psnr_from_mse(end), 3) if math.isfinite(end) else None,
            },
        )
        return Outputs(
            out_dir=out,
            weights=weights,
            manifest=manifest,
            steps=steps.step,
            seconds=seconds,
            loss_start=start,
            loss_end=end,
        )
