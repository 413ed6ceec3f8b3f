"""What a `make PHOTOS=... OUT=...` run will do, said once before its first stage; and render's default budget.

    python pipelines/plan.py show STAGE --token T --out OUT --make MAKE --makefile FILE --goals GOALS
        [--photos P] [--posed D] [--poses-args A] [--train-args A] [--render-args A] [--depth-args A] [--mesh-args A]
    python pipelines/plan.py render-seconds RUN_DIR

`show` is the first line of every stage recipe (`show_plan` in pipelines/common.mk). It prints only the first time
in one make invocation (`--token`, kept in OUT/plan.txt next to the plan it printed), so a make with nothing to do
prints nothing, and `make -n` lists the line without running it. The stages that will run are the ones `make -n`
lists for the same goals (make hands its command-line variables on in MAKEFLAGS); if that fails, STAGE and every
stage after it. Figures (rough, for a laptop-class CPU; a CUDA GPU makes every stage but poses much faster):
- poses: COLMAP at about 0.5 s a photo plus 0.01 s a matched pair (exhaustive matching for photos, about 10 pairs
  a frame for sequential video matching): the fox's 50 phone photos took 45 s on an idle 2-core machine;
- convert: about 0.3 s a photo (copies and the downscaled copies);
- train: its `--max-seconds`, 900 unless TRAIN_ARGS says otherwise (it may stop sooner at `--max-steps`);
- render: its `--max-seconds`, which the Makefile sets to half the training run's time (`render-seconds`:
  `RENDER_SHARE` of the run's `used.train_seconds`, at least `MIN_RENDER_SECONDS`) unless RENDER_ARGS says otherwise;
- eval: the test views (every 8th photo) at the size train works at (its default downscale: the long side
  brought to <= 800 px by a power of two) at `CPU_RAYS_PER_S` (render speed measured on the fox on CPU);
- depth: after eval, the test views' depth from eval's renders (the run's render cache): seconds; other views
  (DEPTH_ARGS --views train|turntable, another --downscale) rendered as eval's are;
- mesh: `resolution`^3 density queries at `CPU_POINTS_PER_S` plus colours, or about a minute.
Stdlib only (Pillow for photo sizes when it is there). Never fails the build: a problem prints one line.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import math
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

__all__ = ["main", "option", "render_seconds", "estimate", "Facts"]

CHAIN = ("poses", "convert", "train", "render", "depth", "eval", "mesh")
TRAIN_SECONDS = 900.0
"""train's default --max-seconds."""
MIN_RENDER_SECONDS = 60.0
RENDER_SHARE = 0.5
"""render's default budget as a share of the training time: the video, eval, depth (from eval's renders) and mesh
together within the training's time (issue 54); the other half is eval's and mesh's."""
CPU_RAYS_PER_S = 13_000.0
CPU_POINTS_PER_S = 1_000_000.0
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"}


def option(args: str, name: str, default: str | None = None) -> str | None:
    """The value of `--name V` or `--name=V` in a shell-quoted argument string (the last one wins, as in click)."""
    try:
        words = shlex.split(args)
    except ValueError:
        words = args.split()
    value = default
    for i, word in enumerate(words):
        if word == name and i + 1 < len(words):
            value = words[i + 1]
        elif word.startswith(name + "="):
            value = word[len(name) + 1 :]
    return value


def _number(args: str, name: str, default: float) -> float:
    try:
        return float(option(args, name) or default)
    except ValueError:
        return default


def render_seconds(run_dir: Path) -> float:
    """Render's default budget: `RENDER_SHARE` of the training run's wall time (manifest `used.train_seconds`), at
    least `MIN_RENDER_SECONDS`; of train's default budget when the manifest cannot be read."""
    try:
        doc = json.loads((Path(run_dir) / "manifest.json").read_text())
        seconds = float(doc.get("used", {}).get("train_seconds") or doc["wall_seconds"])
    except (OSError, ValueError, KeyError, TypeError):
        seconds = TRAIN_SECONDS
    return float(max(MIN_RENDER_SECONDS, math.ceil(RENDER_SHARE * seconds)))


@dataclass(frozen=True)
class Facts:
    """What the inputs say about the work: photos, their size, the test views."""

    photos: int | None
    size_wh: tuple[int, int] | None
    test_views: int | None
    video: bool = False
    source: str = ""


def _image_size(path: Path) -> tuple[int, int] | None:
    try:
        from PIL import Image

        with Image.open(path) as img:
            return img.size
    except Exception:  # any unreadable image only loses an estimate
        return None


def _video_facts(path: Path, frames: int) -> Facts:
    size = None
    try:
        import imageio_ffmpeg

        reader = imageio_ffmpeg.read_frames(str(path))
        size = tuple(next(reader)["size"])
        reader.close()
    except Exception:  # no size: no estimate
        pass
    return Facts(photos=frames, size_wh=size, test_views=math.ceil(frames / 8), video=True, source=f"video {path}")


def _transforms_facts(path: Path, test_file: Path | None = None) -> Facts | None:
    try:
        doc = json.loads(path.read_text())
        frames = doc["frames"]
        first = frames[0] if frames else {}
        w, h = doc.get("w", first.get("w")), doc.get("h", first.get("h"))
        size = (int(w), int(h)) if w and h else None
        if size is None and first.get("file_path"):
            size = _image_size(path.parent / first["file_path"])
        n = len(frames)
        tests = len(doc.get("test_filenames", ())) or None
        if tests is None and test_file is not None and test_file.is_file():
            tests = len(json.loads(test_file.read_text())["frames"])
            n += tests
        return Facts(photos=n, size_wh=size, test_views=tests or math.ceil(n / 8), source=str(path))
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None


def facts(out: Path, photos: str, posed: str, poses_args: str) -> Facts:
    """From OUT/scene/transforms.json when an earlier run made it, else from the photos or the posed dataset."""
    scene = _transforms_facts(out / "scene" / "transforms.json")
    if photos:
        p = Path(photos)
        if not p.is_dir():
            return scene or _video_facts(p, int(_number(poses_args, "--video-frames", 150)))
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        size = scene.size_wh if scene else (_image_size(files[0]) if files else None)
        tests = scene.test_views if scene else math.ceil(len(files) / 8)
        return Facts(photos=len(files), size_wh=size, test_views=tests, source=f"{len(files)} photos in {p}")
    if scene:
        return scene
    p = Path(posed)
    for name in ("transforms.json", "transforms_train.json"):
        found = _transforms_facts(p / name, p / "transforms_test.json") if p.is_dir() else None
        if found:
            return found
    return Facts(photos=None, size_wh=None, test_views=None, source=str(p))


def _minutes(seconds: float) -> str:
    if seconds < 90:
        return f"{max(seconds, 1):.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def estimate(stage: str, f: Facts, args: dict[str, str]) -> tuple[float | None, str, str]:
    """(seconds or None when unknown, how sure: '~' estimate | '' budget | '<=' at most, what it is based on)."""
    n = f.photos
    pixels = f.size_wh[0] * f.size_wh[1] if f.size_wh else None
    if stage == "poses":
        if n is None:
            return None, "~", "COLMAP; depends on the photos"
        matcher = option(args["poses"], "--matcher", "auto")
        sequential = matcher == "sequential" or (matcher == "auto" and f.video)
        pairs = n * 10 if sequential else n * (n - 1) / 2
        how = "sequential" if sequential else "exhaustive"
        return 0.5 * n + 0.01 * pairs, "~", f"COLMAP on {n} {'frames' if f.video else 'photos'}, {how} matching"
    if stage == "convert":
        return max(5.0, 0.3 * (n or 0)), "~", "normalise poses, copy and downscale the images"
    train = _number(args["train"], "--max-seconds", TRAIN_SECONDS)
    if stage == "train":
        steps = option(args["train"], "--max-steps")
        why = (
            "TRAIN_ARGS" if option(args["train"], "--max-seconds") else "train's default; TRAIN_ARGS='--max-seconds S'"
        )
        return train, "", f"--max-seconds {train:g} ({why})" + (f", or {steps} steps if sooner" if steps else "")
    if stage == "render":
        mine = option(args["render"], "--max-seconds")
        if mine:
            return _number(args["render"], "--max-seconds", train), "<=", "--max-seconds from RENDER_ARGS"
        why = f"--max-seconds = {RENDER_SHARE:g} x the training run's time (RENDER_ARGS for more)"
        return max(RENDER_SHARE * train, MIN_RENDER_SECONDS), "<=", why
    if stage in ("depth", "eval"):
        views, down = f.test_views, _train_downscale(f.size_wh)
        if stage == "depth":
            kind = option(args["depth"], "--views", "test")
            if kind == "test" and option(args["depth"], "--downscale") is None:
                return 5.0, "~", "the test views' depth from eval's renders (the run's render cache)"
            down = _number(args["depth"], "--downscale", down)
            if kind == "train" and n and views:
                views = n - views
            elif kind == "turntable":
                views = int(_number(args["depth"], "--frames", 120))
        if views is None or pixels is None:
            return None, "~", "renders the test views at full size"
        rays = views * pixels / (down * down)
        size = f"{f.size_wh[0]}x{f.size_wh[1]}" + (f" / {down:g}" if down != 1 else "")
        why = f"{views} views of {size} at ~{CPU_RAYS_PER_S / 1000:.0f}k rays/s on CPU"
        if stage == "depth" and down == 1 and rays / CPU_RAYS_PER_S > 600:
            why += " (DEPTH_ARGS='--downscale 2': a quarter)"
        return rays / CPU_RAYS_PER_S, "~", why
    if stage == "mesh":
        res = int(_number(args["mesh"], "--resolution", 256))
        return max(60.0, res**3 / CPU_POINTS_PER_S), "~", f"{res}^3 density grid, cleanup, colours"
    return None, "~", ""


def _train_downscale(size_wh) -> float:
    """train's default downscale on CPU (model.views.auto_downscale with 800 px)."""
    if not size_wh:
        return 1.0
    factor, side = 1, max(size_wh)
    while side / factor > 800:
        factor *= 2
    return float(factor)


def _will_run(stage: str, make: str, makefile: str, goals: str) -> list[str]:
    """The stages `make -n` lists for these goals (the command-line variables come along in MAKEFLAGS)."""
    env = dict(os.environ)
    env["MAKEFLAGS"] = re.sub(r"--jobserver-(auth|fds)=\S+|(?<!\S)-j\d*", "", env.get("MAKEFLAGS", ""))
    try:
        res = subprocess.run(
            [make, "-n", "--no-print-directory", "-f", makefile, *goals.split()],
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        found = [m.group(1) for m in re.finditer(r"(?:^|/)nerfpipe (\w+)", res.stdout, flags=re.M)]
    except (OSError, subprocess.SubprocessError):
        found = []
    stages = [s for s in CHAIN if s in found]
    return stages if stage in stages else list(CHAIN[CHAIN.index(stage) :])


def plan_text(stages: list[str], f: Facts, args: dict[str, str], out: str) -> str:
    size = f" ({f.size_wh[0]}x{f.size_wh[1]})" if f.size_wh else ""
    lines = [f"nerfpipe plan: {f.source}{size} -> {out}: {', '.join(stages)}"]
    total, unknown = 0.0, []
    for stage in stages:
        seconds, sure, why = estimate(stage, f, args)
        shown = "?" if seconds is None else f"{sure}{_minutes(seconds)}"
        lines.append(f"  {stage:<8} {shown:>9}   {why}")
        if seconds is None:
            unknown.append(stage)
        else:
            total += seconds
    rest = f" + {', '.join(unknown)}" if unknown else ""
    lines.append(f"  {'total':<8} {'~' + _minutes(total):>9}{rest}   (CPU figures)")
    if Path("/proc/driver/nvidia/version").exists():
        lines.append("  a CUDA GPU is present: everything but poses should be much faster than these CPU figures")
    return "\n".join(lines)


def show(a: argparse.Namespace) -> None:
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    record = out / "plan.txt"
    with open(record, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # parallel makes: one recipe prints, the others wait and see its token
        fh.seek(0)
        if fh.readline().strip() == f"# make {a.token}":
            return
        args = {
            "poses": a.poses_args,
            "train": a.train_args,
            "render": a.render_args,
            "depth": a.depth_args,
            "mesh": a.mesh_args,
        }
        text = plan_text(
            _will_run(a.stage, a.make, a.makefile, a.goals), facts(out, a.photos, a.posed, a.poses_args), args, a.out
        )
        print(text, flush=True)
        fh.seek(0)
        fh.truncate()
        fh.write(f"# make {a.token}\n{text}\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pipelines/plan.py")
    sub = parser.add_subparsers(dest="command", required=True)
    s = sub.add_parser("show")
    s.add_argument("stage", choices=CHAIN)
    for name in ("token", "out", "make", "makefile", "goals"):
        s.add_argument(f"--{name}", required=True)
    for name in ("photos", "posed", "poses-args", "train-args", "render-args", "depth-args", "mesh-args"):
        s.add_argument(f"--{name}", default="")
    r = sub.add_parser("render-seconds")
    r.add_argument("run_dir", type=Path)
    a = parser.parse_args(argv)
    if a.command == "render-seconds":
        print(f"{render_seconds(a.run_dir):g}")
        return 0
    try:
        show(a)
    except Exception as exc:  # the plan is advice: never fail the build over it
        print(f"(no plan: {type(exc).__name__}: {exc})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
