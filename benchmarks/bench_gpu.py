"""`make bench-gpu`: every GPU figure of issue 51 that exists, measured by one script in under 9 minutes on one GPU,
printed as one table (figure, value, goal, seconds, device, commit).

Rows, each through the commands a user types (`nerfpipe CMD ...`: the CLI's own parsing into the stage's Config, then
its `run`, in this process; `make` is not used because the device machine cannot install the project's venv, and
`poses` is left out because pycolmap is not there: the fox row converts the capture's own poses, as `make POSED=`
would, rather than `PHOTOS=`):
- `lego_800`: `convert lego_800` -> `train --max-seconds 240` (no other option) -> `eval` on its 25 test views.
  Goal >= 36 dB (instant-ngp ~36 dB in 5 min; nerfacc's instant-NGP 35.67 dB in 288 s on a TITAN RTX).
- `fox`: `convert fox` -> `train --max-seconds FOX_SECONDS` -> `render` (its own budget) -> `eval` -> `depth`, end to
  end. Goal <= 3 min, >= 29 dB.
- `splats`: `splat` from the lego_800 run (`--max-seconds SPLAT_SECONDS`; gsplat's backend where it is importable,
  else the torch rasteriser) -> `eval` of the .ply; frames a second at 800x800 (`model.render_view` of the splats,
  timed in this process). Goal: within 1 dB of the field, >= 100 fps.
- `viewer`: the viewer's render path (`model.preview.render_preview`) of the lego_800 run at 800x800, coarse and
  refined, frames a second. Goal >= 30 fps.
- `method:NAME`: every other registered method (`model.methods`) but nerf: `train --method NAME --max-seconds
  METHOD_SECONDS` on lego_800 -> `eval`. Their issues' goals.

Rows run in the order lego, viewer, splats, fox, other methods (the cheap rows on the lego run first), each
skipped when it would end past DEADLINE_SECONDS.

Data: `--data DIR` holds `lego_800/` and `fox/` as `../shared/data` has them; `make bench-gpu-pack` copies them into
the git-ignored `.gpu-data/` (the fox at half size, which is what train reads on CUDA anyway), so that one device call
carries them (64 MiB with the checkout). `--smoke` runs every row at toy sizes on any device (tests/test_bench_gpu.py
runs it; no goal is judged there): generated scenes instead of the data, step budgets instead of seconds. Without CUDA
and without `--smoke` the script stops with one line.

    .venv/bin/python -m benchmarks.bench_gpu --data .gpu-data --out runs/bench/gpu      # on the GPU machine
    .venv/bin/python -m benchmarks.bench_gpu --smoke --out /tmp/smoke                  # anywhere, seconds
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.provenance import commit

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

__all__ = ["Row", "main", "pack"]

LEGO_SECONDS, FOX_SECONDS, SPLAT_SECONDS, METHOD_SECONDS = 240, 100, 60, 120
"""Training budgets (seconds) of the lego_800 field, the fox's chain, the splats and each other method."""
DEADLINE_SECONDS = 550
"""A row whose estimated cost would end past this many seconds from the start is skipped and says so: one device call
runs at most 600 s, so the table must be written before then."""
VIEW_FRAMES, SMOKE_FRAMES = 20, 2
"""Frames timed per viewer / splat speed figure (after one warm-up frame); --smoke times SMOKE_FRAMES."""
SMOKE_STEPS = 12
"""Steps of every smoke training (the script's plumbing, not its figures)."""
SMOKE_FIELD_STEPS = 100
"""Steps of the smoke lego field the splat and viewer rows start from: 12 leave no surface to put Gaussians on."""


@dataclass
class Row:
    figure: str
    value: str
    goal: str
    seconds: float
    met: bool | None = None
    notes: list[str] = field(default_factory=list)


def _importable() -> None:
    """`nerfpipe` importable from this checkout even where it is not installed (the device machine): a folder holding
    a link named nerfpipe to the checkout, first on sys.path."""
    try:
        import nerfpipe  # noqa: F401
    except ImportError:
        link_dir = Path(os.environ.get("TMPDIR", "/tmp")) / "nerfpipe_import"
        link_dir.mkdir(parents=True, exist_ok=True)
        if not (link_dir / "nerfpipe").exists():
            (link_dir / "nerfpipe").symlink_to(ROOT, target_is_directory=True)
        sys.path.insert(0, str(link_dir))


def stage(*args: str | Path) -> float:
    """`nerfpipe ARGS` as a user types it: the CLI's own parsing into the stage's Config (`cli.config_from_args`),
    then the stage's `run`, in this process (no start-up per stage); its wall seconds."""
    import importlib

    from nerfpipe.cli import STAGES, config_from_args

    text = [str(a) for a in args]
    print("$ nerfpipe " + " ".join(text), flush=True)
    t0 = time.perf_counter()
    config = config_from_args(text[0], text[1:])
    importlib.import_module(STAGES[text[0]].module).run(config)
    return time.perf_counter() - t0


def _video_encoder() -> list[str]:
    """The fox's `render` writes an H.264 mp4 through imageio-ffmpeg, which the device machine lacks (and carrying its
    30 MB wheel passes the 64 MiB a call carries with the data): there, frames are encoded by OpenCV's mp4v writer
    instead, behind the same `write_frames` generator. The rendering timed is the same; the notes say so."""
    try:
        import imageio_ffmpeg  # noqa: F401

        return []
    except ImportError:
        pass
    import types

    import cv2

    def write_frames(path, size, fps=24.0, **_ignored):
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, tuple(size))
        try:
            while True:
                frame = yield
                if frame is None:
                    continue
                writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        finally:
            writer.release()

    sys.modules["imageio_ffmpeg"] = types.SimpleNamespace(write_frames=write_frames)
    return ["video encoded by OpenCV (mp4v): imageio-ffmpeg is not on the device machine"]


def _eval(path: Path) -> dict:
    return json.loads(path.read_text())


SMOKE_DENSITY = ["--resolution", "16,32"]
"""The density method's grid in smoke runs (its default grows to 96^3 at 24 px: 30 s for 100 steps, not 4)."""


def _budget(smoke: bool, seconds: float, steps: int = SMOKE_STEPS) -> list[str]:
    """Stop rule of a training: seconds; in smoke runs `steps`, at 512 rays a step."""
    if not smoke:
        return ["--max-seconds", str(seconds)]
    return ["--max-steps", str(steps), "--max-seconds", "600", "--batch-rays", "512"]


def _smoke_data(out: Path) -> tuple[Path, Path]:
    """Toy stand-ins of lego_800 (a Blender-layout object) and the fox (posed photos of a room)."""
    lego, fox = out / "data" / "lego", out / "data" / "fox"
    if not (lego / "transforms_train.json").is_file():
        stage("scene", lego, "--kind", "blender", "--size", "24", "--views", "12", "--overwrite")
    if not (fox / "transforms.json").is_file():
        stage("scene", fox, "--kind", "posed", "--layout", "room", "--size", "24", "--views", "10", "--overwrite")
    return lego, fox


def lego_row(data: Path, out: Path, smoke: bool) -> tuple[Row, Path]:
    shutil.rmtree(out / "lego", ignore_errors=True)  # measured afresh
    scene, run = out / "lego" / "scene", out / "lego" / "run"
    s = stage("convert", data, scene)
    s += stage(
        "train",
        scene,
        run,
        "--overwrite",
        *_budget(smoke, LEGO_SECONDS, SMOKE_FIELD_STEPS),
        *(SMOKE_DENSITY if smoke else []),
    )
    s += stage("eval", run, out / "lego" / "eval.json")
    ev = _eval(out / "lego" / "eval.json")
    steps = json.loads((run / "manifest.json").read_text())["used"]["steps"]
    value = f"{ev['psnr']:.2f} dB / SSIM {ev['ssim']:.3f}, {steps} steps"
    return Row("lego_800 field, 240 s, no options", value, ">= 36 dB", s, ev["psnr"] >= 36.0), run


def fox_row(data: Path, out: Path, smoke: bool) -> Row:
    shutil.rmtree(out / "fox", ignore_errors=True)
    scene, run, w = out / "fox" / "scene", out / "fox" / "run", out / "fox"
    s = stage("convert", data, scene)
    s += stage("train", scene, run, "--overwrite", *_budget(smoke, FOX_SECONDS), *(SMOKE_DENSITY if smoke else []))
    frames = ["--frames", "8"] if smoke else []
    encoder = _video_encoder()
    s += stage("render", run, w / "video.mp4", "--max-seconds", "20", *frames)
    s += stage("eval", run, w / "eval.json")  # then depth, as make runs them: depth reads eval's renders
    s += stage("depth", run, w / "depth", "--overwrite")
    ev = _eval(w / "eval.json")
    figure, value = "fox, POSED chain (convert, train, render, eval, depth)", f"{ev['psnr']:.2f} dB, {s:.0f} s"
    row = Row(figure, value, "<= 180 s, >= 29 dB", s, s <= 180 and ev["psnr"] >= 29.0)
    row.notes += ["poses left out: pycolmap is not on the device machine (the capture's own poses)", *encoder]
    return row


def splat_rows(run: Path, out: Path, smoke: bool, field_psnr: float) -> list[Row]:
    shutil.rmtree(out / "splats", ignore_errors=True)
    ply = out / "splats" / "splats.ply"
    budget = ["--max-steps", str(SMOKE_STEPS), "--max-seconds", "600", "--gaussians", "2000"] if smoke else []
    s = stage("splat", run, ply, *(budget or ["--max-seconds", str(SPLAT_SECONDS)]))
    s += stage("eval", ply, out / "splats" / "eval.json")
    ev = _eval(out / "splats" / "eval.json")
    gap = field_psnr - ev["psnr"]
    value = f"{ev['psnr']:.2f} dB ({gap:+.2f} under the field)"
    quality = Row(f"lego splats, {SPLAT_SECONDS} s", value, "within 1 dB of the field", s, gap <= 1.0)
    size, frames = (64, SMOKE_FRAMES) if smoke else (800, VIEW_FRAMES)
    fps = _fps_splats(ply, size, frames)
    speed = Row(f"splats at {size}x{size}", f"{fps:.1f} fps", ">= 100 fps", frames / max(fps, 1e-9), fps >= 100)
    return [quality, speed]


def _fps_splats(ply: Path, size: int, frames: int) -> float:
    import torch

    from nerfpipe.model import render_view
    from nerfpipe.model.splat_run import load_splats

    run = load_splats(ply)
    return _fps(lambda intr, pose: render_view(run, intr, pose, run.device, depth=False), run, size, frames, torch)


def viewer_row(run: Path, smoke: bool) -> list[Row]:
    import torch

    from nerfpipe.model import load_trained
    from nerfpipe.model.preview import render_preview

    trained = load_trained(run)
    (size, frames), rows = ((64, SMOKE_FRAMES) if smoke else (800, VIEW_FRAMES)), []
    for coarse in (True, False):
        fps = _fps(lambda i, p, c=coarse: render_preview(trained, i, p, coarse=c), trained, size, frames, torch)
        label = "coarse (moving)" if coarse else "refined (still)"
        rows.append(Row(f"viewer at {size}x{size}, {label}", f"{fps:.1f} fps", ">= 30 fps", frames / max(fps, 1e-9)))
        rows[-1].met = fps >= 30
    return rows


FPS_SECONDS = 10.0
"""A frames-a-second figure stops timing after this many seconds (at least one frame): the first H200 run drew the
viewer at 0.8 fps, and 20 frames of each mode took the time another row needed."""


def _fps(render, run, size: int, frames: int, torch) -> float:
    """Frames a second of `render(intr, pose)` over up to `frames` cameras along the run's turntable at size x
    size, timing stopped after FPS_SECONDS."""
    from nerfpipe.model import camera_path
    from nerfpipe.radiance.camera import Intrinsics

    cams = camera_path(run.scene, "turntable", frames=frames + 1)
    base = cams.intrinsics[0]
    f = base.fx * size / max(base.w, base.h)
    intr = Intrinsics(w=size, h=size, fx=f, fy=f, cx=size / 2, cy=size / 2)
    render(intr, cams.world_from_cams[0])  # warm-up (kernels, caches)
    sync = torch.cuda.synchronize if torch.cuda.is_available() else (lambda: None)
    sync()
    t0, done = time.perf_counter(), 0
    for pose in cams.world_from_cams[1:]:
        render(intr, pose)
        done += 1
        if time.perf_counter() - t0 > FPS_SECONDS:
            break
    sync()
    return done / max(time.perf_counter() - t0, 1e-9)


def method_rows(lego_scene: Path, out: Path, smoke: bool) -> list[Row]:
    from nerfpipe.model.methods import method_names

    rows = []
    for name in method_names():
        if name in ("density", "nerf"):  # density: the lego row; nerf: the paper's model, hours on any GPU
            continue
        run = out / f"method_{name}" / "run"
        s = stage("train", lego_scene, run, "--method", name, "--overwrite", *_budget(smoke, METHOD_SECONDS))
        s += stage("eval", run, run.parent / "eval.json")
        ev = _eval(run.parent / "eval.json")
        rows.append(Row(f"method {name}, lego_800, {METHOD_SECONDS} s", f"{ev['psnr']:.2f} dB", "its issue's", s))
    return rows


def table(rows: list[Row], device: str, commit: str) -> str:
    lines = [
        f"bench-gpu at {commit} on {device}",
        "",
        "| figure | value | goal | met | seconds | notes |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        met = "-" if r.met is None else ("yes" if r.met else "**no**")
        lines.append(f"| {r.figure} | {r.value} | {r.goal} | {met} | {r.seconds:.1f} | {'; '.join(r.notes)} |")
    return "\n".join(lines) + "\n"


def pack(data: Path, dest: Path) -> Path:
    """`make bench-gpu-pack`: lego_800 as it is and the fox at half size into `dest` (git-ignored), for one device
    call's carry; refuses in one line when the checkout and the pack pass 64 MiB."""
    import cv2

    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(data / "lego_800", dest / "lego_800")
    fox = dest / "fox"
    (fox / "images").mkdir(parents=True)
    doc = json.loads((data / "fox" / "transforms.json").read_text())
    for frame in doc["frames"]:
        src = data / "fox" / frame["file_path"]
        if src.is_file():
            img = cv2.imread(str(src))
            small = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(fox / frame["file_path"]), small, [cv2.IMWRITE_JPEG_QUALITY, 95])
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        if key in doc:
            doc[key] = doc[key] / 2
    (fox / "transforms.json").write_text(json.dumps(doc, indent=1))
    size = sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())
    tracked = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z"], capture_output=True).stdout.split(b"\0")
    repo = sum((ROOT / t.decode()).stat().st_size for t in tracked if t and (ROOT / t.decode()).is_file())
    print(f"{dest}: {size / 2**20:.1f} MiB; the checkout {repo / 2**20:.1f} MiB")
    if size + repo > 64 * 2**20:
        raise SystemExit(
            f"bench-gpu-pack: {(size + repo) / 2**20:.1f} MiB with the checkout, over the 64 MiB a call carries"
        )
    return dest


def main(argv: list[str] | None = None) -> list[Row]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench" / "gpu")
    p.add_argument("--smoke", action="store_true", help="toy sizes on any device, in seconds (CI)")
    p.add_argument("--pack", type=Path, default=None, help="only copy the data to carry into this folder")
    p.add_argument("--table", type=Path, default=None, help="also write the table (md, json) into this folder")
    args = p.parse_args(argv)
    if args.pack is not None:
        pack(args.data, args.pack)
        return []
    import torch

    if not args.smoke and not torch.cuda.is_available():
        raise SystemExit(
            "bench-gpu: no CUDA device here (torch.cuda.is_available() is False); run it on the GPU "
            "machine, or --smoke to check the script"
        )
    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    _importable()
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    if args.smoke:
        lego, fox = _smoke_data(args.out)
    else:
        lego, fox = args.data / "lego_800", args.data / "fox"
    rows: list[Row] = []

    def attempt(figure: str, cost: float, make) -> None:
        """Rows of one step, or one row saying why there are none (skipped for the deadline, or failed: on the GPU a
        failure is a finding, and the rows after it still run); the table so far is written after each step."""
        left = DEADLINE_SECONDS - (time.perf_counter() - started)
        if not args.smoke and cost > left:
            rows.append(Row(figure, f"skipped: needs ~{cost:.0f} s, {left:.0f} s left of {DEADLINE_SECONDS}", "-", 0.0))
        else:
            t0 = time.perf_counter()
            try:
                made = make()
                rows.extend(made if isinstance(made, list) else [made])
            except Exception as e:  # noqa: BLE001 - recorded in the table, the rest still measured
                if args.smoke:
                    raise
                traceback.print_exc()
                rows.append(Row(figure, f"failed: {type(e).__name__}: {e}"[:300], "-", time.perf_counter() - t0, False))
        _write(args, rows, device, started)

    lego_out: dict = {}

    def lego_step() -> Row:
        row, lego_out["run"] = lego_row(lego, args.out, args.smoke)
        lego_out["psnr"] = _eval(args.out / "lego" / "eval.json")["psnr"]
        return row

    # the cheap rows on the lego run first: the first H200 run spent its 550 s on lego and the fox alone
    attempt("lego_800 field, 240 s, no options", LEGO_SECONDS + 60, lego_step)
    if "run" in lego_out:
        run = lego_out["run"]
        attempt("viewer", 2 * FPS_SECONDS + 10, lambda: viewer_row(run, args.smoke))
        attempt("lego splats", SPLAT_SECONDS + 40, lambda: splat_rows(run, args.out, args.smoke, lego_out["psnr"]))
    attempt("fox, POSED chain", FOX_SECONDS + 60, lambda: fox_row(fox, args.out, args.smoke))
    lego_scene = args.out / "lego" / "scene"
    attempt("other methods", METHOD_SECONDS + 30, lambda: method_rows(lego_scene, args.out, args.smoke))
    text = _write(args, rows, device, started)
    print(text)
    return rows


def _write(args, rows: list[Row], device: str, started: float) -> str:
    """The table so far into OUT (and --table): written after every step, so a run stopped at its limit keeps it."""
    if args.smoke:  # toy sizes check the plumbing; no goal is judged on them
        for r in rows:
            if "smoke: toy size" not in r.notes:  # each row once, though the table is written after every step
                r.met, r.notes = None, [*r.notes, "smoke: toy size"]
        device = device + " (smoke)"
    text = table(rows, device, commit()) + f"\nwall {time.perf_counter() - started:.0f} s\n"
    for folder in {args.out, *([args.table] if args.table else [])}:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "bench_gpu.md").write_text(text)
        (folder / "bench_gpu.json").write_text(json.dumps([r.__dict__ for r in rows], indent=1))
    return text


if __name__ == "__main__":
    main()
