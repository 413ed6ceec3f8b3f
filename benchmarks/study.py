"""`make study`: error against samples and run time, training, meshing and stiff inputs, as one Markdown page.

Run: .venv/bin/python -m benchmarks.study --out runs/study [--quick] [--threads 1] [--device cpu]
     [--sections compositing,stability,training,mesh,fit_image]
(`make study` ~ 12 min and `make study-quick` ~ 1.5 min on 2 busy CPU cores.) Writes OUT/README.md (last: the
Makefile's sentinel) with PNG plots and tables next to it, `results.json` (every number) and `work/` (scenes, runs).

Sections (each a function `Context -> Section`, so tests can run one on a tiny `Plan`):
1. compositing: `radiance.compositing.composite` on media with closed-form answers (homogeneous slab, the
   image of a homogeneous sphere, piecewise-constant steps, a smooth Gaussian blob): density taken at each
   interval's midpoint (as a field query is), N uniform intervals on [0, FAR]; mean |error| of opacity and
   expected depth over rays at random offsets against N and against compositing time; the order of convergence
   is the fitted slope of log error against log N.
2. stability: `radiance.stability` (the sweep tests/test_compositing.py asserts on): worst relative error against
   a 40-digit reference and finiteness of values and gradients, per dtype; plus the naive `cumprod(1 - alpha)`
   opacity in fp32 for contrast.
3. training: `scene` -> `convert` -> `train` (fast field at 2-3 grid resolutions, vanilla field), each from the
   Config the CLI builds for the command line shown (`cli.config_from_args`), then `report` on the runs.
4. mesh: `benchmarks.bench_mesh.measure` (in this process: no peak memory) on the analytic stand-in at several
   marching-cubes resolutions, at the exact level and the auto threshold, and on the largest-grid fast run; the
   sampling floor is the Chamfer distance between two independent point samplings of the exact surface.
5. fit_image: `fit-image` on view 0 of the study's scene (Fourier L sweep and the fast field's grid).
Timings are wall-clock on whatever machine runs it: the page records CPU count, threads and load average.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import importlib
import json
import math
import os
import platform
import shlex
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = [
    "Plan",
    "FULL",
    "QUICK",
    "Context",
    "Section",
    "SECTIONS",
    "stage",
    "compositing",
    "stability",
    "training",
    "mesh",
    "fit_image",
    "write_page",
    "main",
]

FAR = 4.0
"""Compositing rays run over t in [0, FAR]."""


@dataclass(frozen=True)
class Plan:
    """How big each section is (`FULL`: make study, `QUICK`: make study-quick)."""

    name: str
    samples: tuple[int, ...]  # compositing: intervals per ray
    rays: int  # compositing: rays per medium (random offsets), and per timing batch
    repeats: int  # compositing: timing repeats (median)
    scene_size: int
    scene_views: int
    train_seconds: float
    fast_resolutions: tuple[tuple[int, int], ...]  # train --resolution START,END per fast run
    vanilla_batch: int
    eval_every: tuple[int, int]  # train --eval-every for the fast runs and the vanilla run (0: at the end only)
    final_eval_views: int
    levels: tuple[float, ...]  # report: time to reach these PSNRs
    mesh_resolutions: tuple[int, ...]
    mesh_auto: bool  # also mesh the stand-in at the auto threshold
    mesh_warm_up: bool  # mesh once before timing (imports and first calls are not meshing time)
    trained_mesh_resolutions: tuple[int, ...]
    fit_sweep: tuple[int, ...]
    fit_seconds: float


FULL = Plan(
    name="full",
    samples=(4, 8, 16, 32, 64, 128, 256, 512, 1024),
    rays=2048,
    repeats=3,
    scene_size=48,
    scene_views=24,
    train_seconds=90.0,
    fast_resolutions=((16, 48), (32, 96), (64, 160)),
    vanilla_batch=64,
    eval_every=(50, 10),
    final_eval_views=3,
    levels=(15.0, 20.0, 25.0),
    mesh_resolutions=(16, 32, 64, 128, 256),
    mesh_auto=True,
    mesh_warm_up=True,
    trained_mesh_resolutions=(64, 128),
    fit_sweep=(0, 2, 5, 10),
    fit_seconds=12.0,
)
QUICK = Plan(
    name="quick",
    samples=(4, 8, 16, 32, 64, 128, 256),
    rays=512,
    repeats=1,
    scene_size=32,
    scene_views=12,
    train_seconds=5.0,
    fast_resolutions=((16, 32), (32, 64)),
    vanilla_batch=64,
    eval_every=(10, 0),
    final_eval_views=1,
    levels=(10.0, 15.0, 20.0),
    mesh_resolutions=(16, 32, 64),
    mesh_auto=False,
    mesh_warm_up=False,
    trained_mesh_resolutions=(),
    fit_sweep=(0, 6),
    fit_seconds=2.0,
)


@dataclass
class Section:
    """One part of the page: its Markdown (images linked relative to OUT) and its numbers for results.json."""

    key: str
    title: str
    markdown: str
    data: dict = field(default_factory=dict)
    seconds: float = 0.0


@dataclass(frozen=True)
class Context:
    out: Path  # the page's folder
    plan: Plan
    threads: int
    device: str


# ---------------------------------------------------------------------------------------------- helpers
def stage(command: str, *args: Any) -> Any:
    """Run `nerfpipe COMMAND ARGS...` in this process: the Config the CLI builds, the stage's `run`."""
    from nerfpipe import cli

    config = cli.config_from_args(command, [str(a) for a in args])
    return importlib.import_module(cli.STAGES[command].module).run(config)


def _command_line(command: str, *args: Any) -> str:
    """What to type in a shell for `stage(command, *args)`."""
    return shlex.join(["nerfpipe", command, *(str(a) for a in args)])


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> str:
    from nerfpipe.data.atomic import atomic_path

    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    _pyplot().close(fig)
    return path.name


def _table(header: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows])


def _g(x: float | None, digits: int = 2) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{x:.{digits}g}"


def _slope(xs: list[float], ys: list[float], floor: float = 1e-13) -> float | None:
    """Least-squares slope of log y against log x over the points with y above `floor` (None: < 2 points)."""
    pts = [(math.log(x), math.log(y)) for x, y in zip(xs, ys, strict=True) if y > floor and x > 0]
    if len(pts) < 2:
        return None
    a = np.array(pts)
    return float(np.polyfit(a[:, 0], a[:, 1], 1)[0])


# ---------------------------------------------------------------------------------------------- 1. compositing
@dataclass(frozen=True)
class Medium:
    """A density along rays with exact opacity and expected depth; every ray is shifted by its own offset."""

    name: str
    formula: str
    sigma: Callable[[np.ndarray, np.ndarray], np.ndarray]  # (t [R, N], offset [R, 1]) -> sigma [R, N]
    exact: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # offset [R] -> (acc [R], depth [R])


def _segments_exact(segments: list[tuple[np.ndarray, np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous pieces (a [R], b [R], sigma) in order along the ray -> (opacity, expected depth), exactly:
    each piece adds T_a (a + 1/s - (b + 1/s) e^{-s (b - a)}) to the integral of t sigma T."""
    trans, num = np.ones_like(segments[0][0]), np.zeros_like(segments[0][0])
    for a, b, s in segments:
        if s > 0:
            e = np.exp(-s * (b - a))
            num += trans * ((a + 1 / s) - (b + 1 / s) * e)
            trans = trans * e
    acc = 1 - trans
    return acc, num / acc


def _pieces(bounds: tuple[float, ...], dens: tuple[float, ...]) -> tuple[Callable, Callable]:
    """(sigma, exact) of piecewise-constant density `dens[i]` on [bounds[i], bounds[i + 1]) (+ the ray's offset)."""

    def sigma(t, off):
        out = np.zeros_like(t)
        for a, b, s in zip(bounds[:-1], bounds[1:], dens, strict=True):
            out = np.where((t >= a + off) & (t < b + off), s, out)
        return out

    def exact(off):
        return _segments_exact([(a + off, b + off, s) for a, b, s in zip(bounds[:-1], bounds[1:], dens, strict=True)])

    return sigma, exact


def _sphere_half_chord(n: int) -> np.ndarray:
    """Half chord lengths of n parallel rays through a unit sphere, impact parameters evenly in [0, 0.97]."""
    b = np.linspace(0.0, 0.97, n)
    return np.sqrt(1 - b * b)


GAUSS = (3.0, 2.0, 0.35)  # peak density A, centre mu, width s


def _gauss_tau(t: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Optical depth from 0 to t of A exp(-(t - mu)^2 / 2 s^2)."""
    from scipy.special import erf

    a, _, s = GAUSS
    k = s * math.sqrt(2)
    return a * s * math.sqrt(math.pi / 2) * (erf((t - mu) / k) + erf(mu / k))


def _gauss_exact(off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Opacity from erf; expected depth by composite 10-point Gauss-Legendre on 400 panels (error < 1e-14)."""
    a, mu0, s = GAUSS
    mu = mu0 + off[:, None]
    x, w = np.polynomial.legendre.leggauss(10)
    edges = np.linspace(0, FAR, 401)
    h = np.diff(edges)[:, None] / 2
    t = ((edges[:-1, None] + edges[1:, None]) / 2 + h * x[None]).reshape(-1)  # [400 * 10]
    wt = (h * w[None]).reshape(-1)
    integrand = t * a * np.exp(-((t - mu) ** 2) / (2 * s * s)) * np.exp(-_gauss_tau(t, mu))  # [R, T]
    acc = 1 - np.exp(-_gauss_tau(np.full_like(off, FAR), mu0 + off))
    return acc, (integrand * wt).sum(-1) / acc


def media(rays: int) -> list[Medium]:
    """The four media, for `rays` rays (the sphere's rays cross its disc at evenly spaced impact parameters)."""
    slab_sigma, slab_exact = _pieces((0.9, 2.5), (1.5,))
    steps_sigma, steps_exact = _pieces((0.3, 1.1, 1.9, 2.6, 3.3), (0.4, 2.5, 0.0, 1.2))
    half = _sphere_half_chord(rays)

    def sphere_sigma(t, off):
        c = 2.0 + off
        return np.where(np.abs(t - c) < half[:, None], 1.2, 0.0)

    def sphere_exact(off):
        return _segments_exact([(2.0 + off - half, 2.0 + off + half, 1.2)])

    a, mu, s = GAUSS
    return [
        Medium("slab", "σ = 1.5 on [0.9, 2.5)", slab_sigma, slab_exact),
        Medium("sphere", "σ = 1.2 in a unit sphere, rays at impact 0..0.97", sphere_sigma, sphere_exact),
        Medium("steps", "σ = 0.4, 2.5, 0, 1.2 on [0.3, 1.1, 1.9, 2.6, 3.3)", steps_sigma, steps_exact),
        Medium(
            "gaussian",
            f"σ = {a:g} exp(-(t - {mu:g})² / 2·{s:g}²)",
            lambda t, off: a * np.exp(-((t - mu - off) ** 2) / (2 * s * s)),
            _gauss_exact,
        ),
    ]


def _composite_rays(sigma: np.ndarray, n: int, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    from nerfpipe.radiance.compositing import composite

    edges = torch.linspace(0.0, FAR, n + 1, dtype=dtype)
    r = sigma.shape[0]
    t0, t1 = edges[:-1].expand(r, n), edges[1:].expand(r, n)
    s = torch.as_tensor(sigma, dtype=dtype)
    return composite(s, torch.ones(r, n, 3, dtype=dtype), t0, t1)


def _time_composite(rays: int, n: int, repeats: int) -> float:
    """Best-of-`repeats` seconds of one float32 `composite` of `rays` rays x n samples (after a warm-up call; the
    minimum, as load from other processes only ever adds time)."""
    sigma = np.random.default_rng(0).random((rays, n)) * 3
    _composite_rays(sigma, n, torch.float32)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        _composite_rays(sigma, n, torch.float32)
        times.append(time.perf_counter() - t)
    return float(min(times))


def compositing(ctx: Context) -> Section:
    plan = ctx.plan
    offsets = np.random.default_rng(0).random(plan.rays) * 0.5  # [R]
    rows, curves = [], {}
    seconds = [_time_composite(plan.rays, n, plan.repeats) for n in plan.samples]
    for m in media(plan.rays):
        acc_x, depth_x = m.exact(offsets)
        errs = {"opacity": [], "depth": []}
        for n in plan.samples:
            t_mid = (np.arange(n) + 0.5) * (FAR / n)
            out = _composite_rays(m.sigma(np.broadcast_to(t_mid, (plan.rays, n)), offsets[:, None]), n, torch.float64)
            errs["opacity"].append(float(np.mean(np.abs(out["acc"].numpy() - acc_x))))
            errs["depth"].append(float(np.mean(np.abs(out["depth"].numpy() - depth_x))))
        asymptotic = [i for i, n in enumerate(plan.samples) if n >= 16]
        order = {k: _slope([plan.samples[i] for i in asymptotic], [v[i] for i in asymptotic]) for k, v in errs.items()}
        curves[m.name] = {"errors": errs, "order": order, "exact_opacity_mean": float(acc_x.mean())}
        pick = [n for n in (16, 64, 256, 1024) if n in plan.samples]
        rows.append(
            [
                m.name,
                m.formula,
                f"{acc_x.mean():.3f}",
                *(_g(errs["opacity"][plan.samples.index(n)]) for n in pick),
                *(_g(None if order[k] is None else -order[k], 3) for k in ("opacity", "depth")),
            ]
        )
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=110)
    for i, (name, c) in enumerate(curves.items()):
        color = f"C{i}"
        for key, style in (("opacity", "o-"), ("depth", "s--")):
            ys = c["errors"][key]
            axes[0].loglog(plan.samples, ys, style, color=color, ms=3, label=f"{name} {key}")
            axes[1].loglog([s * 1e3 for s in seconds], ys, style, color=color, ms=3, label=f"{name} {key}")
    for ax, xlabel in ((axes[0], "samples per ray N"), (axes[1], f"composite time for {plan.rays} rays (ms, fp32)")):
        ax.set_xlabel(xlabel)
        ax.set_ylabel("mean |error| over rays")
        ax.grid(alpha=0.3, which="both")
    n0 = plan.samples[0]
    for p, label in ((1, "N⁻¹"), (2, "N⁻²")):
        axes[0].loglog(plan.samples, [0.3 * (n0 / n) ** p for n in plan.samples], ":", color="grey", lw=1)
        axes[0].annotate(label, (plan.samples[-1], 0.3 * (n0 / plan.samples[-1]) ** p), fontsize=8, color="grey")
    axes[0].legend(fontsize=7, ncol=2)
    axes[0].set_title("compositing error vs samples per ray")
    axes[1].set_title("compositing error vs time")
    fig.tight_layout()
    plot = _save(fig, ctx.out / "compositing.png")
    pick = [n for n in (16, 64, 256, 1024) if n in plan.samples]
    table = _table(
        [
            "medium",
            "density on t ∈ [0, 4] (+ offset U[0, 0.5) per ray)",
            "opacity",
            *(f"opacity error, N={n}" for n in pick),
            "order (opacity)",
            "order (depth)",
        ],
        rows,
    )
    timing = _table(["N", *map(str, plan.samples)], [["ms", *(f"{s * 1e3:.2f}" for s in seconds)]])
    md = f"""Each ray is cut into N equal intervals on [0, {FAR:g}]; the density is taken at each interval's midpoint
(as a field query is) and `radiance.compositing.composite` gives opacity and expected depth, compared with the exact
values (closed forms; the Gaussian's depth by 4000-point Gauss-Legendre). Errors are the mean over {plan.rays} rays,
each shifted by its own random offset (so boundaries fall anywhere inside an interval), computed in float64 so that
only the quadrature error shows; the time axis is one float32 `composite` call for {plan.rays} rays (best of
{plan.repeats}). The order is minus the fitted slope of log error against log N for N ≥ 16.

![compositing error against samples and time]({plot})

{table}

A density with jumps (slab, sphere, steps) converges at first order: the interval holding a boundary is wrong by a
fraction of its length. The smooth blob converges at second order (the midpoint rule); its opacity error first falls
much faster (the midpoint rule is spectrally accurate for a function that vanishes smoothly at both ends) until the
blob's tails cut off at t = 0 and {FAR:g} leave the N⁻² term. Compositing time grows linearly in N once the call
overhead is paid, so error against time has the same slopes: halving a jump's error costs twice the time.

Composite time (float32, {plan.rays} rays):

{timing}
"""
    return Section(
        "compositing",
        "Compositing: error against samples per ray and against time",
        md,
        {"samples": list(plan.samples), "seconds": seconds, "media": curves},
    )


# ---------------------------------------------------------------------------------------------- 2. stability
def _naive_acc(sigmas: torch.Tensor, t0: torch.Tensor, t1: torch.Tensor) -> torch.Tensor:
    """Opacity by the textbook recipe STYLE.md warns against: alpha = 1 - exp(-sigma delta), T = cumprod(1 - alpha)."""
    delta = t1 - t0
    tau = torch.where((sigmas == 0) | (delta == 0), torch.zeros_like(sigmas), sigmas * delta)
    alpha = 1 - torch.exp(-tau)
    trans = torch.cumprod(torch.nn.functional.pad(1 - alpha, (1, 0), value=1.0), dim=-1)[..., :-1]
    return (trans * alpha).sum(-1)


def stability(ctx: Context) -> Section:
    from nerfpipe.radiance.stability import QUANTITIES, TAUS, closed_form, relative_error, run_sweep, summarize

    dtypes = (torch.float16, torch.bfloat16, torch.float32, torch.float64)
    summaries, per_tau = [], {}
    n = len(TAUS)
    for dtype in dtypes:
        sweep = run_sweep(dtype)
        summaries.append(summarize(sweep))
        ref = closed_form(sweep.sigmas, sweep.t_starts, sweep.t_ends, sweep.rgbs, sweep.background, 1.0)  # opacity only
        err = relative_error(sweep.outputs["acc"], ref["acc"], dtype)[n : 2 * n]  # the finite-far rays
        per_tau[str(dtype).removeprefix("torch.")] = err.tolist()
        if dtype == torch.float32:
            naive = relative_error(_naive_acc(sweep.sigmas, sweep.t_starts, sweep.t_ends), ref["acc"], dtype)
            per_tau["float32, cumprod(1 - alpha)"] = naive[n : 2 * n].tolist()
    rows = []
    for s in summaries:
        worst = s["worst_rel_error"]
        k = max(worst, key=worst.get)
        flags = [("yes" if s[f] else "**no**") for f in ("values_finite", "gradients_finite", "weights_sum_le_one")]
        where = f"{_g(worst[k] / s['eps'])} ({k}, {s['worst_at'][k]})"
        rows.append([s["dtype"], f"{s['eps']:.2g}", *(_g(worst[q]) for q in QUANTITIES), where, *flags])
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.2), dpi=110)
    for name, errs in per_tau.items():
        ax.loglog(TAUS, [max(e, 1e-18) for e in errs], "o-" if "cumprod" not in name else "x:", ms=3, label=name)
    ax.set_xlabel("optical depth σδ of the first interval (finite-far rays)")
    ax.set_ylabel("relative error of opacity (floored at 1e-18)")
    ax.set_title("stiff sweep: opacity error against σδ")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    plot = _save(fig, ctx.out / "stability.png")
    table = _table(
        [
            "dtype",
            "eps",
            *(f"worst rel. error: {q}" for q in QUANTITIES),
            "worst / eps (where)",
            "values finite",
            "gradients finite",
            "Σw ≤ 1 + eps",
        ],
        rows,
    )
    md = f"""`radiance.stability.run_sweep(dtype)`, the sweep `tests/test_compositing.py` asserts on: 52 rays, one per
decade of σδ from 1e-12 to 1e12 in four intervals `[0, 1)`, a zero-length `[1, 1)`, `[1, 2)` and an infinite
`[2, ∞)`, the same rays with a finite far `[2, 3)`, an empty ray and a ray opening with σ = ∞; composited in each
dtype (fp16 and bf16 inputs are computed in float32 and returned in their dtype), then backpropagated. The reference
is 40-digit decimal arithmetic on the inputs as rounded to the dtype, so the errors are the compositing's, not the
inputs' rounding.
Relative error is `|x - ref| / max(|ref|, tiny(dtype))`.

{table}

![opacity relative error against σδ]({plot})

Reading it: every dtype keeps values and gradients finite across 24 decades, with infinite far planes and zero-length
intervals. The errors are a few units of the dtype's own eps, i.e. the rounding of the output, with one exception:
fp16 expected depth of rays whose opacity is below eps(fp16) (depth = Σ w t / eps, from subnormal fp16 weights).
The dotted line is the textbook `T = cumprod(1 - α)` with `α = 1 - exp(-σδ)` in fp32: below σδ ≈ 1e-8, `exp(-σδ)`
rounds to 1 and the opacity to 0 (relative error 1), and up to σδ ≈ 1 it loses digits, where `-expm1` keeps full
precision. In the plot, an error of 0 is drawn at 1e-18: from σδ ≈ 30 on the opacity is exactly 1 in every dtype,
and fp16 densities below its smallest subnormal (6e-8) round to 0 before compositing (so does the reference).
"""
    title = "Stiff and extreme inputs: σδ from 1e-12 to 1e12, infinite far, zero-length, four dtypes"
    data = {"summaries": summaries, "opacity_error_per_tau": {"taus": list(TAUS), **per_tau}}
    return Section("stability", title, md, data)


# ---------------------------------------------------------------------------------------------- 3. training
def _scene(ctx: Context) -> tuple[Path, Path, list[str]]:
    """The study's synthetic scene (source folder, converted scene folder) and the commands that made it."""
    plan, work = ctx.plan, ctx.out / "work"
    src, scene_dir = work / "scene_src", work / "scene"
    scene_args = (src, "--kind", "posed", "--size", plan.scene_size, "--views", plan.scene_views, "--seed", 0)
    commands = [_command_line("scene", *scene_args), _command_line("convert", src, scene_dir)]
    if not (src / "manifest.json").is_file():
        stage("scene", *scene_args)
    if not (scene_dir / "transforms.json").is_file():
        stage("convert", src, scene_dir)
    return src, scene_dir, commands


def _curve(metrics: Path) -> list[tuple[float, float]]:
    with open(metrics, newline="") as f:
        return [(float(r["seconds"]), float(r["test_psnr"])) for r in csv.DictReader(f) if r.get("test_psnr")]


def training(ctx: Context) -> Section:
    plan, work = ctx.plan, ctx.out / "work"
    src, scene_dir, commands = _scene(ctx)
    common = (
        "--max-seconds",
        plan.train_seconds,
        "--max-steps",
        10**9,
        "--threads",
        ctx.threads,
        "--device",
        ctx.device,
    )
    # Periodic held-out PSNR on 1024 pixels (fast) or 512 (vanilla: 192 samples per ray through an 8x256 MLP cost
    # seconds per evaluation on a CPU, so it also renders only one full test view at the end); evaluation time is
    # not training time (train excludes it).
    fast_eval, vanilla_eval = plan.eval_every
    runs = [
        (
            f"fast {a}-{b}",
            (
                "--method",
                "density",
                "--resolution",
                f"{a},{b}",
                "--eval-every",
                fast_eval,
                "--eval-pixels",
                1024,
                "--final-eval-views",
                plan.final_eval_views,
            ),
        )
        for a, b in plan.fast_resolutions
    ]
    runs.append(
        (
            "vanilla",
            (
                "--method",
                "nerf",
                "--batch-rays",
                plan.vanilla_batch,
                "--eval-every",
                vanilla_eval,
                "--eval-pixels",
                512,
                "--final-eval-views",
                1,
            ),
        )
    )
    results, run_dirs = {}, []
    for label, extra in runs:
        run_dir = work / "runs" / label.replace(" ", "_")
        if run_dir.exists():
            shutil.rmtree(run_dir)  # a fresh run: the curve must not continue an old one
        args = (scene_dir, run_dir, *extra, *common)
        commands.append(_command_line("train", *args))
        t = time.perf_counter()
        out = stage("train", *args)
        results[label] = {
            "steps": out.steps,
            "seconds": round(out.seconds, 1),
            "test_psnr": out.test_psnr,
            "wall_seconds": round(time.perf_counter() - t, 1),
            "curve": _curve(out.metrics),
        }
        run_dirs.append(run_dir)
    report_dir = ctx.out / "training"
    labels = [label for label, _ in runs]
    levels = ",".join(f"{v:g}" for v in plan.levels)
    report_args = (*run_dirs, report_dir, "--labels", ",".join(labels), "--levels", levels, "--overwrite")
    commands.append(_command_line("report", *report_args))
    report = stage("report", *report_args)
    rel = report_dir.relative_to(ctx.out)
    summary = report.markdown.read_text(encoding="utf-8").strip()
    rate = {k: f"{v['steps'] / max(v['seconds'], 1e-9):.1f}" for k, v in results.items()}
    rows = [[k, v["steps"], v["seconds"], rate[k], v["wall_seconds"]] for k, v in results.items()]
    steps_per_s = _table(["run", "steps", "training s", "steps / s", "wall s (with evaluation)"], rows)
    cmd_block = "\n".join(commands)
    scored = {k: v["test_psnr"] for k, v in results.items() if v["test_psnr"] is not None}
    best = max(scored, key=scored.get) if scored else None
    best_note = ""
    if best is not None:
        best_note = (
            f" Best final held-out PSNR here: {best} ({scored[best]:.2f} dB). A finer grid has more to fit and"
            " takes longer per step, so in a short budget on small images a coarser grid can come out ahead."
        )
    md = f"""The procedural `posed` scene ({plan.scene_size} px, {plan.scene_views} views, every 8th held out), trained
{plan.train_seconds:g} s per run on {ctx.device} with {ctx.threads} thread(s). Each stage ran in this process from
the Config the CLI builds for these command lines (`cli.config_from_args`), in order:

```bash
{cmd_block}
```

![held-out PSNR against training seconds]({rel}/psnr_vs_time.png)

{summary}

{steps_per_s}

The fast field's grid resolution is `--resolution START,END` (coarse-to-fine upsampling to END³). Peak RSS is the
study process's so far (every stage runs in it), not the run's own. The vanilla field
(the NeRF paper's 8×256 MLP, 64 + 128 samples per ray) takes seconds per step on a CPU: in the same budget it is still
near its starting PSNR, which is why `fast` is the default.{best_note}
"""
    data = {"runs": results, "commands": commands, "scene_src": str(src), "default_run": str(run_dirs[-2])}
    return Section("training", "Training: held-out PSNR against seconds", md, data)


# ---------------------------------------------------------------------------------------------- 4. mesh
def _sampling_floor() -> float:
    """Chamfer between two independent samplings (200k points, bench_mesh.POINTS) of the stand-in's exact surface."""
    from benchmarks.bench_mesh import POINTS
    from benchmarks.mesh_metrics import chamfer_distance
    from benchmarks.standin import StandIn

    s = StandIn(".")
    a, b = s.scene_to_source(s.surface_points(POINTS, seed=0)), s.scene_to_source(s.surface_points(POINTS, seed=1))
    return chamfer_distance(a, b)


def _vertex_error(mesh_path: Path) -> float:
    """Stand-in meshes: mean |signed distance| of the vertices to the exact surface, in source units. One-sided
    (accuracy, not completeness) but free of the sampling floor: vertices are where marching cubes put them."""
    import trimesh

    from benchmarks.standin import StandIn

    standin = StandIn(".")
    m = trimesh.load(mesh_path, force="mesh", process=False)
    scene_from_source = standin.scene.scene_from_source()
    p = np.asarray(m.vertices, np.float64) @ scene_from_source[:3, :3].T + scene_from_source[:3, 3]
    return float(np.abs(standin.sdf(torch.as_tensor(p)).numpy()).mean() / standin.scene.applied_scale)


def mesh(ctx: Context, trained: tuple[Path, Path] | None = None) -> Section:
    """Stand-in at every resolution (exact level; auto too in the full plan); `trained` = (run_dir, scene_src)."""
    from benchmarks.bench_mesh import POINTS, measure

    plan, work = ctx.plan, ctx.out / "work" / "mesh"
    if plan.mesh_warm_up:  # imports and first-call costs, not reported
        measure({"kind": "standin", "resolution": 8, "threshold": 50.0, "out": str(work / "warm_up" / "mesh.ply")})
    rows = []
    for res in plan.mesh_resolutions:
        for threshold in (50.0, "auto") if plan.mesh_auto else (50.0,):
            out = work / f"standin_{res}_{threshold}" / "mesh.ply"
            row = measure({"kind": "standin", "resolution": res, "threshold": threshold, "out": str(out)})
            rows.append(row | {"vertex_error": _vertex_error(out)})
    trained_res = plan.trained_mesh_resolutions if trained is not None else ()
    for res in trained_res:
        spec = {
            "kind": "trained",
            "resolution": res,
            "run_dir": str(trained[0]),
            "scene_src": str(trained[1]),
            "out": str(work / f"trained_{res}" / "mesh.ply"),
        }
        rows.append(measure(spec) | {"vertex_error": None})
    floor = _sampling_floor()
    groups: dict[str, list[dict]] = {}
    for r in rows:
        level = "auto" if r["threshold_rule"] == "auto" else "exact"
        groups.setdefault("trained" if r["kind"] == "trained" else f"stand-in, {level} level", []).append(r)
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=110)
    for i, (key, rs) in enumerate(groups.items()):
        for ax, x in ((axes[0], "resolution"), (axes[1], "seconds")):
            ax.loglog(
                [r[x] for r in rs], [r["chamfer"] for r in rs], "o-", color=f"C{i}", ms=4, label=f"{key}: Chamfer"
            )
            if rs[0]["vertex_error"] is not None:
                ax.loglog(
                    [r[x] for r in rs],
                    [r["vertex_error"] for r in rs],
                    "s--",
                    color=f"C{i}",
                    ms=3,
                    label=f"{key}: vertex distance",
                )
    for ax, xlabel in (
        (axes[0], "marching-cubes resolution (voxels along the longest side)"),
        (axes[1], "meshing seconds (stages.mesh, incl. cleanup and colours)"),
    ):
        ax.axhline(floor, color="grey", ls=":", lw=1, label="Chamfer sampling floor")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("distance (source units)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    res_ticks = sorted({r["resolution"] for r in rows})
    axes[0].set_xticks(res_ticks, [str(v) for v in res_ticks])
    axes[0].minorticks_off()
    axes[0].set_title("mesh error vs resolution")
    axes[1].set_title("mesh error vs time")
    fig.tight_layout()
    plot = _save(fig, ctx.out / "mesh.png")
    body = []
    for r in rows:
        level = f"{r['threshold']:.3g} ({'auto' if r['threshold_rule'] == 'auto' else 'given'})"
        body.append(
            [
                r["kind"],
                level,
                r["resolution"],
                f"{r['chamfer']:.5f}",
                f"{r['chamfer_pct_diag']:.3f}",
                "—" if r["vertex_error"] is None else f"{r['vertex_error']:.5f}",
                r["seconds"],
                r["faces"],
                r["watertight"],
            ]
        )
    header = [
        "field",
        "level",
        "resolution",
        "Chamfer",
        "Chamfer % of diagonal",
        "vertex distance to surface",
        "seconds",
        "faces",
        "watertight",
    ]
    table = _table(header, body)
    orders = {
        key: _slope([r["resolution"] for r in rs], [r["vertex_error"] for r in rs])
        for key, rs in groups.items()
        if rs[0]["vertex_error"] is not None
    }
    order_text = ", ".join(f"{k}: {_g(-v, 3)}" for k, v in orders.items() if v is not None) or "—"
    trained_text = ", and on the last fast run of the training section (visible surface only)" if trained_res else ""
    auto_text = " and at the auto threshold" if plan.mesh_auto else ""
    auto_levels = [r["threshold"] for r in rows if r["kind"] == "standin" and r["threshold_rule"] == "auto"]
    auto_note = ""
    if auto_levels:
        auto_note = (
            f" The auto threshold chose σ = {auto_levels[-1]:.3g} where the exact level is 50: a fixed offset"
            " of the surface that no resolution removes, so its error stops falling once the grid resolves it."
        )
    md = f"""`benchmarks.bench_mesh.measure` (the code behind `make bench-mesh`), run in this process: `stages.mesh` on
the analytic stand-in (a sphere ∪ box, `benchmarks.standin`, in a rotated and scaled source frame) at the exact
iso-level σ_max / 2{auto_text}{trained_text}. Chamfer is the symmetric mean nearest-neighbour distance in the source
frame, {POINTS:,} points per side; its sampling floor ({floor:.5f}), the Chamfer distance between two independent
samplings of the exact surface, is as low as it can show. The stand-in's meshes are also scored by the mean |signed
distance| of their vertices to the exact surface, which has no floor (one-sided: accuracy, not completeness).
Seconds are the whole `mesh` stage (sampling, marching cubes, cleanup, colours, export); peak memory is not
reported (in one process it is cumulative: `make bench-mesh` measures it per resolution).

![mesh error against resolution and time]({plot})

{table}

Order of convergence of the vertex error (minus the slope of log error against log resolution): {order_text}.
Chamfer flattens at the sampling floor once the mesh is finer than the point samples.{auto_note}
"""
    data = {"rows": rows, "sampling_floor": floor, "orders": orders}
    return Section("mesh", "Mesh: Chamfer distance against marching-cubes resolution and time", md, data)


# ---------------------------------------------------------------------------------------------- 5. fit-image
def fit_image(ctx: Context) -> Section:
    plan = ctx.plan
    src, _, _ = _scene(ctx)
    image = sorted((src / "images").glob("*.png"))[0]
    out_dir = ctx.out / "fit_image"
    args = (
        image,
        out_dir,
        "--sweep",
        ",".join(map(str, plan.fit_sweep)),
        "--encoding",
        "both",
        "--steps",
        10**9,
        "--max-seconds",
        plan.fit_seconds,
        "--threads",
        ctx.threads,
        "--device",
        ctx.device,
        "--overwrite",
    )
    out = stage("fit-image", *args)
    rel = out_dir.relative_to(ctx.out)
    rows = [[m.label, f"{m.parameters:,}", m.steps, f"{m.seconds:.1f}", f"{m.psnr:.2f}"] for m in out.models]
    table = _table(["model", "parameters", "steps", "seconds", "PSNR (dB)"], rows)
    md = f"""The NeRF warm-up on one {plan.scene_size} px view of the study's scene: an MLP from pixel coordinates to
RGB with L Fourier frequencies, and the fast field's VM grid on the plane z = 0; {plan.fit_seconds:g} s each:

```bash
{_command_line("fit-image", *args)}
```

![ground truth and reconstructions]({rel}/montage.png)

![PSNR against seconds]({rel}/psnr_vs_time.png)

{table}
"""
    models = [dataclasses.asdict(m) | {"reconstruction": str(m.reconstruction)} for m in out.models]
    title = "Fitting one image: Fourier features against the fast field's grid"
    return Section("fit_image", title, md, {"models": models})


# ---------------------------------------------------------------------------------------------- the page
SECTIONS = ("compositing", "stability", "training", "mesh", "fit_image")


def _machine(ctx: Context) -> dict:
    load = os.getloadavg() if hasattr(os, "getloadavg") else (math.nan,) * 3
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "threads": ctx.threads,
        "device": ctx.device,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "load_average_at_start": [round(v, 2) for v in load],
    }


def write_page(ctx: Context, sections: list[Section], machine: dict, wall: float) -> Path:
    """OUT/results.json, then OUT/README.md (last)."""
    from nerfpipe.data.atomic import write_json, write_text

    doc = {
        "plan": dataclasses.asdict(ctx.plan),
        "machine": machine,
        "wall_seconds": round(wall, 1),
        "written": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "sections": {s.key: {"seconds": round(s.seconds, 1), **s.data} for s in sections},
    }
    write_json(ctx.out / "results.json", json.loads(json.dumps(doc, default=str), parse_constant=lambda c: None))
    rebuild = "make study" if ctx.plan.name == "full" else "make study-quick"
    toc = "\n".join(f"{i}. [{s.title}](#{i}-{_anchor(s.title)}) ({s.seconds:.0f} s)" for i, s in enumerate(sections, 1))
    body = "\n\n".join(f"## {i}. {s.title}\n\n{s.markdown.strip()}" for i, s in enumerate(sections, 1))
    load = ", ".join(map(str, machine["load_average_at_start"]))
    quick = " --quick" if ctx.plan.name == "quick" else ""
    text = f"""# nerfpipe study: error against samples and time, training, meshing, stiff inputs

Rebuilt by `{rebuild}` (`.venv/bin/python -m benchmarks.study --out {ctx.out}{quick}`)
on {doc["written"]}, in {wall:.0f} s: {machine["cpu_count"]} CPUs, {ctx.threads} torch thread(s), device {ctx.device},
torch {machine["torch"]}, load average {load} at the start (timings are wall-clock on a machine that may be
shared). Plan `{ctx.plan.name}`; every number is also in [results.json](results.json).

{toc}

{body}
"""
    return write_text(ctx.out / "README.md", text)


def _anchor(title: str) -> str:
    keep = "".join(c for c in title.lower() if c.isalnum() or c in " -")
    return keep.replace(" ", "-")


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/study"))
    p.add_argument("--quick", action="store_true", help="smaller everything (make study-quick)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1: fastest on a shared machine)")
    p.add_argument("--device", default="cpu", help="torch device for training and fitting (the study: cpu)")
    p.add_argument("--sections", default=",".join(SECTIONS), help="comma-separated subset of " + ",".join(SECTIONS))
    args = p.parse_args(argv)
    wanted = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = sorted(set(wanted) - set(SECTIONS))
    if unknown:
        p.error(f"unknown section(s) {unknown}; expected a subset of {','.join(SECTIONS)}")
    torch.set_num_threads(args.threads)
    ctx = Context(out=args.out, plan=QUICK if args.quick else FULL, threads=args.threads, device=args.device)
    ctx.out.mkdir(parents=True, exist_ok=True)
    (ctx.out / "README.md").unlink(missing_ok=True)  # the sentinel goes until the new page is complete
    machine, t_all = _machine(ctx), time.perf_counter()
    sections: list[Section] = []
    trained = None
    for key in SECTIONS:
        if key not in wanted:
            continue
        t = time.perf_counter()
        if key == "mesh":
            section = mesh(ctx, trained)
        else:
            section = {
                "compositing": compositing,
                "stability": stability,
                "training": training,
                "fit_image": fit_image,
            }[key](ctx)
        if key == "training":
            trained = (Path(section.data["default_run"]), Path(section.data["scene_src"]))
        section.seconds = time.perf_counter() - t
        sections.append(section)
        print(f"study: {key} done in {section.seconds:.0f} s", flush=True)
    page = write_page(ctx, sections, machine, time.perf_counter() - t_all)
    print(f"study: {page} ({time.perf_counter() - t_all:.0f} s)")
    return page


if __name__ == "__main__":
    main()
