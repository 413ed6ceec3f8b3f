"""Stage `pretrain-voxels`: train the single-view voxel network on a shapes dataset (the weights `voxels` uses).

    nerfpipe shapes SHAPES_DIR --count 400 --views 6          # the data (make pretrain-voxels)
    nerfpipe pretrain-voxels SHAPES_DIR OUT_DIR [--max-seconds 2400]

The step is `model.voxels.pretrain.VoxelStep` on the one training loop (budget, clock, learning-rate decay,
non-finite recovery, interrupts). Held-out objects and the held-out family, not held-out photos of the trained
objects, measure what it learned (`make bench-voxels`).

Outputs under OUT_DIR:
  weights.pt      the network (`model.voxels.weights`); written at the end
  config.json     the resolved config
  metrics.csv     step, seconds, loss (binary cross-entropy, mean of the last LOG_EVERY steps), iou (the same
                  steps' batches at 0.5), lr
  manifest.json   written last: examples, steps, seconds, loss and IoU at the start and the end, parameters
An interrupted run writes weights.partial.pt (never weights.pt) and says so; a later run starts afresh.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import MetricsLog, output_folder, sha256_file, write_config, write_manifest
from nerfpipe.model.device import cpu_threads, resolve_device
from nerfpipe.model.loop import Budget, Clock, LoopSettings, Schedule, TrainingLoop
from nerfpipe.model.voxels.net import VoxelNet
from nerfpipe.model.voxels.pretrain import ShapeSet, VoxelStep
from nerfpipe.model.voxels.weights import load_net, write_weights

__all__ = ["Config", "Outputs", "run", "load_shapes"]

METRICS = ["step", "seconds", "loss", "iou", "lr"]
LOG_EVERY = 25


@dataclass(frozen=True, kw_only=True)
class Config:
    shapes: Path
    """A shapes dataset: the folder `nerfpipe shapes` wrote, or its shapes.npz."""
    out_dir: Path
    """Folder for weights.pt, metrics.csv, config.json and manifest.json (created)."""
    max_seconds: float = 2400.0
    """Stop after this many seconds of training."""
    max_steps: int = 1_000_000
    """Stop after this many steps."""
    batch: int = 32
    """Photos a step."""
    lr: float = 1e-3
    """Adam's learning rate at the start (exponential decay to lr x lr_decay)."""
    lr_decay: float = 0.05
    """Learning-rate factor reached at the end."""
    init: str | None = None
    """Continue from these weights (a weights.pt, or 'pretrained')."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:N."""
    seed: int = 0
    """Seed of the weights and of the draws of photos."""
    threads: int | None = None
    """CPU: torch intra-op threads (None: torch's default)."""
    overwrite: bool = False
    """Replace an earlier output in out_dir."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out_dir: Path
    weights: Path
    manifest: Path
    steps: int
    seconds: float
    loss_start: float
    loss_end: float


def load_shapes(path: Path) -> tuple[ShapeSet, dict]:
    """A shapes dataset (folder or npz) -> (the set, its arrays other than inputs and bits); UserError when it is
    not one."""
    path = Path(path)
    npz = path / "shapes.npz" if path.is_dir() else path
    if not npz.is_file():
        raise UserError(f"{path}: not a shapes dataset (expected shapes.npz, which `nerfpipe shapes` writes)")
    try:
        with np.load(npz) as data:
            arrays = {k: data[k] for k in data.files}
    except Exception as exc:
        raise UserError(f"{npz}: not a shapes dataset (unreadable: {type(exc).__name__})") from None
    if "inputs" not in arrays or "bits" not in arrays or "res" not in arrays:
        raise UserError(f"{npz}: not a shapes dataset (expected inputs, bits and res)")
    res = int(arrays["res"])
    if arrays["bits"].shape[-1] * 8 != res**3 or len(arrays["bits"]) != len(arrays["inputs"]):
        raise UserError(f"{npz}: inputs {arrays['inputs'].shape} and bits {arrays['bits'].shape} disagree")
    data = ShapeSet(inputs=torch.from_numpy(arrays.pop("inputs")), bits=torch.from_numpy(arrays.pop("bits")), res=res)
    return data, arrays


def run(config: Config, progress: Progress | None = None) -> Outputs:
    if not config.max_seconds > 0 or config.max_steps < 1 or config.batch < 2 or not config.lr > 0:
        raise UserError("pretrain-voxels: expected max_seconds > 0, max_steps >= 1, batch >= 2 and lr > 0")
    progress = progress or NO_PROGRESS
    device = resolve_device(config.device)
    started = time.time()
    data, meta = load_shapes(config.shapes)
    side = data.inputs.shape[-1]
    init = load_net(config.init, device) if config.init else None  # bad input refused before any write
    if init is not None and (init[0].side, init[0].res) != (side, data.res):
        took = f"{init[0].side} px -> {init[0].res}^3"
        raise UserError(f"pretrain-voxels: the weights take {took}, the data is {side} -> {data.res}^3")
    with output_folder(config.out_dir, overwrite=config.overwrite), cpu_threads(config.threads):
        out = Path(config.out_dir)
        write_config(out, config)
        torch.manual_seed(config.seed)
        init_provenance: dict = {}
        if init is not None:
            net, init_provenance = init  # VoxelStep puts it in training mode
        else:
            net = VoxelNet(side=side, res=data.res).to(device)
        opt = torch.optim.Adam(net.parameters(), lr=config.lr)
        metrics = MetricsLog(out / "metrics.csv", METRICS)
        losses: list[float] = []
        ious: list[float] = []
        task = progress.add_task("pretrain-voxels", total=config.max_seconds)
        clock = Clock(0.0)

        def on_log(step: int, loss: float, iou: float, lr: float) -> None:
            losses.append(loss)
            ious.append(iou)
            if step % LOG_EVERY == 0:
                recent = float(np.mean(losses[-LOG_EVERY:]))
                recent_iou = float(np.nanmean(ious[-LOG_EVERY:]))
                metrics.append(
                    step=step, seconds=round(clock(), 3), loss=f"{recent:.5g}", iou=f"{recent_iou:.4f}", lr=lr
                )
                metrics.save()
                progress.update(task, completed=clock(), description=f"pretrain-voxels IoU {recent_iou:.3f}")

        def partial(seconds: float) -> None:
            write_weights(out / "weights.partial.pt", net.config(), net.state_dict(), {"partial_at_step": steps.step})

        steps = VoxelStep(
            net=net,
            data=data,
            opt=opt,
            gen=torch.Generator().manual_seed(config.seed),
            device=device,
            batch=config.batch,
            on_log=on_log,
            on_checkpoint=partial,
        )
        settings = LoopSettings(
            name="pretrain-voxels",
            budget=Budget(max_steps=config.max_steps, max_seconds=config.max_seconds),
            schedule=Schedule(lr=config.lr, decay=config.lr_decay),
            checkpoint_seconds=300.0,
            checkpoint_path=out / "weights.partial.pt",
        )
        seconds = TrainingLoop(settings, steps, clock).run()
        if not losses:
            raise UserError("pretrain-voxels: no step was taken (every loss was not finite)")
        metrics.save()
        n = min(LOG_EVERY, len(losses))
        start, end = float(np.mean(losses[:n])), float(np.mean(losses[-n:]))
        provenance = {
            "stage": "pretrain-voxels",
            "shapes": str(config.shapes),
            "families": [str(f) for f in meta.get("families", [])],
            "examples": len(data.inputs),
            "objects": int(len(np.unique(np.stack([meta["family"], meta["seed"]]), axis=1).T))
            if "seed" in meta
            else None,
            "steps": steps.step,
            "seconds": round(seconds, 1),
            "device": str(device),
            "loss_start": start,
            "loss_end": end,
            "iou_start": float(np.nanmean(ious[:n])),
            "iou_end": float(np.nanmean(ious[-n:])),
            "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(config).items()},
            "init_provenance": init_provenance or None,  # what the weights it continued were made by
        }
        weights = write_weights(out / "weights.pt", net.config(), net.state_dict(), provenance)
        (out / "weights.partial.pt").unlink(missing_ok=True)
        manifest = write_manifest(
            out,
            stage="pretrain-voxels",
            inputs=[Path(config.shapes)],
            started=started,
            outputs=["weights.pt", "metrics.csv", "config.json"],
            used={
                **{k: v for k, v in provenance.items() if k not in ("config", "init_provenance")},
                "steps_before": (init_provenance or {}).get("steps"),
                "net": net.config(),
                "parameters": sum(p.numel() for p in net.parameters()),
                "weights_sha256": sha256_file(weights),
                "weights_bytes": weights.stat().st_size,
            },
        )
        return Outputs(
            out_dir=out,
            weights=weights,
            manifest=manifest,
            steps=steps.step,
            seconds=seconds if math.isfinite(seconds) else 0.0,
            loss_start=start,
            loss_end=end,
        )
