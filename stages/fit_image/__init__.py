"""Stage `fit-image`: fit one image with coordinate networks, the NeRF warm-up (pixel (u, v) -> RGB).

    nerfpipe fit-image IMAGE OUT_DIR [--freqs 10] [--sweep 0,2,5,10] [--encoding fourier|grid|both]

Models (one per entry, trained one after another, each on its own clock):
- fourier L: gamma(u, v) = ((u, v), sin(2^k (u, v)), cos(2^k (u, v)) for k < L) (`radiance.fields.encodings`, the
  vanilla field's encoding; L = 0 is the bare coordinates), then an MLP (`layers` linear layers of `hidden`
  ReLU units) and a sigmoid. One model per L in `sweep` (empty: just `freqs`).
- grid R: the fast field itself (`radiance.fields.TensoRF`, VM planes and lines at R per axis) queried on the
  plane z = 0: its xy plane times its z line is a dense feature plane over (u, v), and the xz / yz planes times
  the y / x lines are rank-`GRID_RANK` products of one-dimensional functions of v and u; the same basis, small
  MLP and sigmoid as in 3-D, the same learning rates (grids at lr, MLP at lr / 20). Bilinear lookups into
  R x R cells instead of a deep MLP: why the fast field converges in seconds, not minutes.
Every step draws `batch` random pixels (all of them when the image has fewer) and takes one Adam step on their
mean squared error, on the loop `train` runs (`model.loop.TrainingLoop`: the step and time budget, the clock, and
a non-finite loss restoring the last good state at half the learning rate). PSNR is measured on the whole image
every `eval_every` steps and at the end; the clock (`seconds`) counts training only, as `train` does.

Conventions: pixel (col i, row j) has its centre at (i + 0.5, j + 0.5) (docs/DESIGN.md); u = 2 (i + 0.5) / W - 1,
v = 2 (j + 0.5) / H - 1, both in (-1, 1). Frequencies are 2^k without pi, as `positional_encoding` writes them.
An RGBA image is composited on white; colours are in [0, 1].

Outputs under OUT_DIR:
  NAME.png           the reconstruction of each model (NAME: fourier_L10, grid_R64, ...)
  montage.png        ground truth and every reconstruction side by side, labelled with PSNR and seconds
  psnr_vs_time.png   PSNR (dB) against training seconds, one line per model
  metrics.csv        step, seconds, model, loss, psnr (blank where not evaluated)
  summary.json       per model: encoding, L or R, parameters, steps, seconds, final PSNR; image size
  config.json, manifest.json (written last)
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor, nn

from nerfpipe.data.atomic import write_json
from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import MetricsLog, output_folder, write_config, write_manifest
from nerfpipe.data.transforms import load_image
from nerfpipe.data.video import to_uint8, write_png
from nerfpipe.model.device import cpu_threads, resolve_device
from nerfpipe.model.loop import Budget, Clock, LoopSettings, Schedule, TrainingLoop
from nerfpipe.radiance.compositing import over_background
from nerfpipe.radiance.metrics import psnr_from_mse
from nerfpipe.stages.fit_image.models import FourierMLP, GridImage, parameters, pixel_coords
from nerfpipe.stages.fit_image.plots import montage, plot

__all__ = ["Config", "Outputs", "ModelResult", "run", "pixel_coords", "FourierMLP", "GridImage", "MAX_FREQS"]

VERSION = "1"
ENCODINGS = ("fourier", "grid", "both")
MAX_FREQS = 20
"""Largest L: 2^19 (u, v) already varies by 2^19 radians across the image; fp32 keeps no more."""
"""Grid model: VM components per axis (3 x 16 features into the basis)."""
EVAL_CHUNK = 1 << 16
METRICS = ["step", "seconds", "model", "loss", "psnr"]


@dataclass(frozen=True, kw_only=True)
class Config:
    image: Path
    """Image to fit (PNG, JPEG, ...; RGBA is composited on white)."""
    out_dir: Path
    """Folder for the reconstructions, montage, plot, metrics and summary (created)."""
    freqs: int = 10
    """Frequencies L of the Fourier encoding (0: bare coordinates) when `sweep` is empty."""
    sweep: tuple[int, ...] = ()
    """Train one Fourier model per L in this list, e.g. 0,2,5,10 (empty: just `freqs`)."""
    encoding: Literal["fourier", "grid", "both"] = "both"
    """fourier: the sinusoidal-encoding MLPs; grid: the fast field's VM grid encoding; both: all side by side."""
    grid_resolution: int | None = None
    """Grid cells per axis of the grid model (None: the image's longer side in pixels, 8 to 512)."""
    hidden: int = 256
    """Fourier MLP: units per hidden layer."""
    layers: int = 4
    """Fourier MLP: linear layers (hidden layers + the output layer)."""
    steps: int = 2000
    """Optimizer steps per model (each model also stops at `max_seconds`)."""
    max_seconds: float = 60.0
    """Training seconds per model (evaluation excluded)."""
    batch: int = 10000
    """Random pixels per step (every pixel when the image has fewer)."""
    lr: float | None = None
    """Adam learning rate (None: 1e-3 for the Fourier MLPs, 0.02 for the grid, its MLP at lr / 20)."""
    eval_every: int = 50
    """Measure the whole-image PSNR every this many steps (0: only at the start and the end)."""
    seed: int = 0
    """Seed for initialisation and pixel batches (each model starts from it)."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:N."""
    threads: int | None = None
    """CPU: torch intra-op threads during the run (None: torch's default). On a busy 2-core machine 1 thread
    ran 150 steps of a small MLP in 0.7 s where 2 threads took 10 s."""
    overwrite: bool = False
    """Replace an earlier output in out_dir (set aside in OUT_DIR.previous/ until this one is written)."""


@dataclass(frozen=True, kw_only=True)
class ModelResult:
    name: str
    """File-name stem: fourier_L10, grid_R64."""
    label: str
    """Plot label: "fourier L=10", "grid R=64"."""
    reconstruction: Path
    parameters: int
    steps: int
    seconds: float
    psnr: float
    """Whole-image PSNR at the end, dB."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out_dir: Path
    models: tuple[ModelResult, ...]
    montage: Path
    plot: Path
    metrics: Path
    summary: Path
    manifest: Path


# ---------------------------------------------------------------------------------------------- models
# ---------------------------------------------------------------------------------------------- checks
def _validate(config: Config) -> None:
    if config.encoding not in ENCODINGS:
        raise UserError(f"--encoding: expected one of {', '.join(ENCODINGS)}, got {config.encoding!r}")
    for name, values in (("--freqs", (config.freqs,)), ("--sweep", config.sweep)):
        bad = [v for v in values if not (isinstance(v, int) and 0 <= v <= MAX_FREQS)]
        if bad:
            raise UserError(f"{name}: expected frequencies in 0..{MAX_FREQS}, got {bad[0]!r}")
    if len(set(config.sweep)) != len(config.sweep):
        raise UserError(f"--sweep: a frequency is listed twice in {','.join(map(str, config.sweep))}")
    if config.grid_resolution is not None and not 2 <= config.grid_resolution <= 4096:
        raise UserError(f"--grid-resolution: expected 2..4096, got {config.grid_resolution}")
    at_least = {
        "--hidden": (config.hidden, 1),
        "--layers": (config.layers, 1),
        "--steps": (config.steps, 1),
        "--batch": (config.batch, 1),
        "--eval-every": (config.eval_every, 0),
    }
    for name, (value, lo) in at_least.items():
        if value < lo:
            raise UserError(f"{name}: expected an integer >= {lo}, got {value}")
    if not config.max_seconds > 0:
        raise UserError(f"--max-seconds: expected > 0, got {config.max_seconds}")
    if config.threads is not None and config.threads < 1:
        raise UserError(f"--threads: expected an integer >= 1, got {config.threads}")
    if config.lr is not None and not (config.lr > 0 and math.isfinite(config.lr)):
        raise UserError(f"--lr: expected a finite number > 0, got {config.lr}")
    if Path(config.out_dir).is_file():
        raise UserError(f"{config.out_dir}: OUT_DIR is a file; expected a folder")


def _load(path: Path) -> np.ndarray:
    """The image as float32 [H, W, 3] in [0, 1] (RGBA over white); UserError naming the file."""
    img = load_image(path)  # UserError: "<path>: image not found" / "cannot decode image"
    if img.shape[-1] == 4:
        img = over_background(img[..., :3], img[..., 3:], np.ones(3, np.float32))
    if min(img.shape[:2]) < 2:
        raise UserError(f"{path}: expected an image of at least 2 x 2 pixels, got {img.shape[1]} x {img.shape[0]}")
    return np.ascontiguousarray(img, dtype=np.float32)


# ---------------------------------------------------------------------------------------------- training
def _specs(config: Config, size: tuple[int, int]) -> list[tuple[str, str, int]]:
    """(name, label, L or R) for every model to train, Fourier ones first."""
    specs = []
    if config.encoding in ("fourier", "both"):
        specs += [(f"fourier_L{L}", f"fourier L={L}", L) for L in (config.sweep or (config.freqs,))]
    if config.encoding in ("grid", "both"):
        r = config.grid_resolution or min(max(8, max(size)), 512)
        specs.append((f"grid_R{r}", f"grid R={r}", r))
    return specs


@torch.no_grad()
def _predict(model: nn.Module, coords: Tensor) -> Tensor:
    return torch.cat([model(c) for c in coords.split(EVAL_CHUNK)])


@dataclass(kw_only=True)
class _Steps:
    """One model's fit: its step on the shared loop (`model.loop.Stepper`; no checkpoints, no schedule)."""

    model: nn.Module
    opt: torch.optim.Optimizer
    coords: Tensor  # [P, 2]
    target: Tensor  # [P, 3]
    config: Config
    gen: torch.Generator
    clock: Clock
    record: Callable[[int, float, float | str], float]  # (step, seconds, loss) -> whole-image PSNR, logged
    progress: Progress
    task: Any
    step: int = 0
    lr_factor: float = 1.0
    loss: float = math.nan

    def prepare(self, fraction: float) -> bool:
        return False

    def train_step(self, lr: float) -> bool:
        n, batch = self.coords.shape[0], self.config.batch
        idx = torch.randint(n, (batch,), generator=self.gen, device=self.coords.device) if n > batch else None
        x, y = (self.coords, self.target) if idx is None else (self.coords[idx], self.target[idx])
        err = torch.mean((self.model(x) - y) ** 2)
        loss = float(err.detach())  # synchronises
        if not math.isfinite(loss):
            return False
        self.opt.zero_grad(set_to_none=True)
        err.backward()
        self.opt.step()
        self.loss = loss
        return True

    def log(self, lr: float) -> None:
        self.progress.advance(self.task)
        every = self.config.eval_every
        if every and self.step % every == 0 and self.step < self.config.steps:
            seconds = self.clock()
            with self.clock.paused():
                self.record(self.step, seconds, round(self.loss, 6))

    def snapshot(self) -> tuple[dict, dict]:
        return copy.deepcopy(self.model.state_dict()), copy.deepcopy(self.opt.state_dict())

    def restore(self, snapshot: tuple[dict, dict]) -> None:
        self.model.load_state_dict(snapshot[0])
        self.opt.load_state_dict(snapshot[1])

    def checkpoint(self, seconds: float) -> None:
        pass  # fit-image keeps no checkpoint: a run is seconds long

    def finish(self, seconds: float) -> None:
        pass


def _fit(
    model: nn.Module,
    lr: float,
    coords: Tensor,
    target: Tensor,
    config: Config,
    log: MetricsLog,
    name: str,
    progress: Progress,
) -> tuple[Tensor, int, float, float]:
    """Train one model on the shared loop (`model.loop`: budget, clock, non-finite recovery); returns
    (prediction [P, 3], steps, seconds, final PSNR)."""

    def record(step: int, seconds: float, loss: float | str) -> float:
        model.eval()
        pred = _predict(model, coords)
        value = psnr_from_mse(float(torch.mean((pred - target) ** 2)))
        model.train()
        log.append(step=step, seconds=round(seconds, 4), model=name, loss=loss, psnr=round(value, 4))
        return value

    gen = torch.Generator(device=coords.device).manual_seed(config.seed)
    opt = torch.optim.Adam(model.param_groups(lr))
    task = progress.add_task(f"fit {name}", total=config.steps)
    record(0, 0.0, "")
    clock = Clock()
    steps = _Steps(
        model=model,
        opt=opt,
        coords=coords,
        target=target,
        config=config,
        gen=gen,
        clock=clock,
        record=record,
        progress=progress,
        task=task,
    )
    settings = LoopSettings(
        name=f"fit-image {name}",
        budget=Budget(max_steps=config.steps, max_seconds=config.max_seconds),
        schedule=Schedule(lr=lr),
    )
    seconds = TrainingLoop(settings, steps, clock).run()
    final = record(steps.step, seconds, round(steps.loss, 6))
    return _predict(model, coords), steps.step, seconds, final


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """Fit config.image with every model the config asks for (see the module doc)."""
    with output_folder(config.out_dir, overwrite=config.overwrite):
        _validate(config)
        with cpu_threads(config.threads):
            return _run(config, progress or NO_PROGRESS)


def _run(config: Config, progress: Progress) -> Outputs:
    started = time.time()
    image = _load(Path(config.image))
    device = resolve_device(config.device)
    h, w = image.shape[:2]
    out_dir = Path(config.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_config(out_dir, config)
    coords = pixel_coords(h, w).to(device)  # [P, 2]
    target = torch.from_numpy(image.reshape(-1, 3)).to(device)  # [P, 3]
    log = MetricsLog(out_dir / "metrics.csv", METRICS)
    results, recons = [], []
    for name, label, value in _specs(config, (h, w)):
        torch.manual_seed(config.seed)
        fourier = name.startswith("fourier")
        model = (FourierMLP(value, config.hidden, config.layers) if fourier else GridImage(value)).to(device)
        lr = config.lr or (1e-3 if fourier else 0.02)
        pred, steps, seconds, final = _fit(model, lr, coords, target, config, log, name, progress)
        log.save()
        recon = pred.reshape(h, w, 3).cpu().numpy()
        path = write_png(out_dir / f"{name}.png", to_uint8(recon))
        recons.append(recon)
        results.append(
            ModelResult(
                name=name,
                label=label,
                reconstruction=path,
                parameters=parameters(model),
                steps=steps,
                seconds=seconds,
                psnr=final,
            )
        )
    montage_path = montage(out_dir / "montage.png", image, recons, results)
    plot_path = plot(out_dir / "psnr_vs_time.png", log.rows, results, Path(config.image).name)
    summary = write_json(
        out_dir / "summary.json",
        {
            "image": str(config.image),
            "width": w,
            "height": h,
            "device": str(device),
            "models": [
                {
                    "name": r.name,
                    "label": r.label,
                    "encoding": r.name.split("_")[0],
                    "parameters": r.parameters,
                    "steps": r.steps,
                    "seconds": round(r.seconds, 3),
                    "psnr": round(r.psnr, 3),
                }
                for r in results
            ],
        },
    )
    outputs = [out_dir / "config.json", log.path, montage_path, plot_path, summary]
    outputs += [r.reconstruction for r in results]
    manifest = write_manifest(
        out_dir,
        stage="fit-image",
        started=started,
        inputs=[config.image],
        outputs=outputs,
        used={
            "device": str(device),
            "models": [r.name for r in results],
            "pixels": h * w,
            "batch": min(config.batch, h * w),
            "threads": torch.get_num_threads(),
        },
        version=VERSION,
    )
    return Outputs(
        out_dir=out_dir,
        models=tuple(results),
        montage=montage_path,
        plot=plot_path,
        metrics=log.path,
        summary=summary,
        manifest=manifest,
    )


# ---------------------------------------------------------------------------------------------- figures
