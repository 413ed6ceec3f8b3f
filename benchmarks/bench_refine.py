"""Pose refinement and per-image appearance benchmark (issue 17), through the commands a user types.

Pose refinement: a `nerfpipe scene --kind rgba` scene; the benchmark copies it and perturbs every training camera
of transforms.json by a rotation of `--rot-deg` degrees about a random axis and a translation of `--trans-frac`
of its distance to the scene centre in a random direction (test cameras stay exact). Three runs of the same
time budget: exact poses, perturbed poses, perturbed poses with `--refine-poses`. Reported: test PSNR of each
(`nerfpipe eval`), and the refined cameras' errors against the true ones after a similarity alignment
(`radiance.align.pose_errors`; the frame of a refined run is free up to a similarity).
Goals: median rotation error < 0.2 deg and PSNR within 0.5 dB of the exact-pose run.

Appearance: the same scene, every training image multiplied by a random exposure gain in [0.6, 1.4] and a random
per-channel colour cast in [0.85, 1.15] (clipped to [0, 1]; alpha kept). Two protocols (`--test-views`):
"varied", NeRF-W's, where every test photo has its own gain and cast too (photos of a real capture do), and
"clean", where the test photos are the clean renders (the clean scene bounds what any run can score). Per
protocol two runs of the same budget: without and with `--appearance`, each evaluated with the mean code (whole
test views) and with NeRF-W's rule (`eval --appearance-rule half`: code fitted on the left half, right half
scored; the run without codes is scored on the same right halves). Goal: >= 2 dB on the test views.

Run:  make bench-refine  (= .venv/bin/python -m benchmarks.bench_refine --out runs/bench/refine)
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

from benchmarks.bench_train import nerfpipe
from data.transforms import load_image, read_scene, write_scene

__all__ = ["perturb_scene", "degrade_scene", "main"]


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def perturb_scene(src: Path, dst: Path, rot_deg: float, trans_frac: float, seed: int = 0) -> Path:
    """Copy the scene folder src to dst with every training camera rotated by rot_deg about a random axis (in its
    own frame) and moved by trans_frac of its distance to the aabb centre in a random direction."""
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    scene = read_scene(dst)
    rng = np.random.default_rng(seed)
    centre = np.asarray(scene.aabb).mean(0)
    frames = list(scene.frames)
    for i in scene.split("train"):
        w = frames[i].world_from_cam.copy()
        w[:3, :3] = w[:3, :3] @ _rotation(rng.normal(size=3), np.radians(rot_deg))
        step = rng.normal(size=3)
        w[:3, 3] += trans_frac * np.linalg.norm(w[:3, 3] - centre) * step / np.linalg.norm(step)
        frames[i] = frames[i].__class__(**{**frames[i].__dict__, "world_from_cam": w})
    write_scene(scene.replace(frames=tuple(frames)), dst / "transforms.json")
    return dst


def degrade_scene(src: Path, dst: Path, gain: tuple[float, float] = (0.6, 1.4), cast: float = 0.15,
                  seed: int = 0, splits: tuple[str, ...] = ("train",)) -> Path:  # fmt: skip
    """Copy the scene folder src to dst with each image of `splits` times a random gain in `gain` and a random
    per-channel cast in [1 - cast, 1 + cast] (clipped; alpha kept). Other images are left as they are. Each
    split draws from its own generator, so the training images are the same whichever splits are degraded."""
    import imageio.v3 as iio

    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    scene = read_scene(dst)
    for k, split in enumerate(splits):
        rng = np.random.default_rng(seed + 1000 * k if split != "train" else seed)
        for i in scene.split(split):
            path = scene.image_path(i)
            img = load_image(path)
            factor = rng.uniform(*gain) * rng.uniform(1 - cast, 1 + cast, size=3)
            img[..., :3] = np.clip(img[..., :3] * factor, 0.0, 1.0)
            iio.imwrite(path, np.round(img * 255).astype(np.uint8))
    return dst


BUDGET = {"args": "--max-seconds 120"}
"""The training budget of every run (main sets it: seconds, or steps on a machine shared with other work)."""


def _scene(out: Path, size: int, views: int) -> Path:
    """`nerfpipe scene --kind rgba` at out/scene, made anew (deterministic, seconds) so that a folder left by a run
    at another --size or --views is never reused."""
    nerfpipe("scene", f"{out / 'scene'} --kind rgba --size {size} --views {views} --overwrite")
    return out / "scene"


def _train_eval(scene: Path, run: Path, seconds: float, extra: str = "") -> dict:
    out = nerfpipe("train", f"{scene} {run} {BUDGET['args']} --threads 1 --overwrite {extra}".strip())
    ev = nerfpipe("eval", f"{run} {run}/eval.json").result
    return {"steps": out.steps, "train_seconds": round(out.seconds, 1), "eval_psnr": round(ev["psnr"], 3),
            "eval_ssim": round(ev["ssim"], 4), "test_poses": ev.get("test_poses")}  # fmt: skip


def bench_poses(out: Path, seconds: float, size: int, views: int, rot_deg: float, trans_frac: float) -> dict:
    from model import load_trained
    from radiance.align import pose_errors

    exact = _scene(out, size, views)
    noisy = perturb_scene(exact, out / "scene_perturbed", rot_deg, trans_frac)
    truth = read_scene(exact)
    train_idx = truth.split("train")
    true_poses = np.stack([truth.frames[i].world_from_cam for i in train_idx])
    noisy_poses = np.stack([read_scene(noisy).frames[i].world_from_cam for i in train_idx])
    res = {"exact": _train_eval(exact, out / "exact", seconds),
           "perturbed": _train_eval(noisy, out / "perturbed", seconds),
           "refined": _train_eval(noisy, out / "refined", seconds, "--refine-poses")}  # fmt: skip
    refined = load_trained(out / "refined", "cpu").scene
    refined_poses = np.stack([refined.frames[i].world_from_cam for i in train_idx])
    for key, poses in (("perturbed", noisy_poses), ("refined", refined_poses)):
        err = pose_errors(poses, true_poses)
        res[key]["median_rotation_error_deg"] = round(err.median_rotation_deg, 4)
        res[key]["median_centre_error_rel"] = round(err.median_centre_error_rel, 5)
    res["psnr_drop_without_refinement"] = round(res["exact"]["eval_psnr"] - res["perturbed"]["eval_psnr"], 3)
    res["psnr_gap_with_refinement"] = round(res["exact"]["eval_psnr"] - res["refined"]["eval_psnr"], 3)
    res["goals"] = {"median_rotation_below_0.2deg": res["refined"]["median_rotation_error_deg"] < 0.2,
                    "psnr_within_0.5dB": res["psnr_gap_with_refinement"] <= 0.5}  # fmt: skip
    return res


def bench_appearance(out: Path, seconds: float, size: int, views: int, test_views: str) -> dict:
    """test_views: "varied" (NeRF-W's protocol: the test photos have their own exposure and cast, as photos of a
    real capture do) or "clean" (test photos as rendered: the clean scene is the ceiling)."""
    clean = _scene(out, size, views)
    splits = ("train", "test") if test_views == "varied" else ("train",)
    tag = f"_{test_views}"
    varied = degrade_scene(clean, out / f"scene_appearance{tag}", splits=splits)
    res: dict = {"test_views": test_views,
                 "without": _train_eval(varied, out / f"appearance_off{tag}", seconds),
                 "with": _train_eval(varied, out / f"appearance_on{tag}", seconds, "--appearance")}  # fmt: skip
    res["gain_db"] = round(res["with"]["eval_psnr"] - res["without"]["eval_psnr"], 3)
    for key, name in (("without", f"appearance_off{tag}"), ("with", f"appearance_on{tag}")):  # NeRF-W's rule
        ev = nerfpipe("eval", f"{out / name} {out / name}/eval_half.json --appearance-rule half").result
        res[key]["eval_psnr_half_rule"] = round(ev["psnr"], 3)
    res["gain_db_half_rule"] = round(res["with"]["eval_psnr_half_rule"] - res["without"]["eval_psnr_half_rule"], 3)
    res["goals"] = {"gain_at_least_2dB": res["gain_db"] >= 2.0,
                    "gain_at_least_2dB_half_rule": res["gain_db_half_rule"] >= 2.0}  # fmt: skip
    return res


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench/refine"))
    p.add_argument("--part", choices=["poses", "appearance", "both"], default="both")
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="budget in steps instead of seconds (a CPU shared with other work makes seconds noise)",
    )
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--views", type=int, default=32)
    p.add_argument("--rot-deg", type=float, default=3.0)
    p.add_argument("--trans-frac", type=float, default=0.03)
    p.add_argument(
        "--test-views",
        choices=["varied", "clean", "both"],
        default="both",
        help="appearance part: test photos with their own exposure and cast (NeRF-W), clean, or both",
    )
    a = p.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    BUDGET["args"] = f"--max-seconds {a.seconds}" if a.steps is None else f"--max-steps {a.steps} --max-seconds 1e6"
    res: dict = {"budget": BUDGET["args"], "size": a.size, "views": a.views}
    if a.part in ("poses", "both"):
        res["poses"] = bench_poses(a.out, a.seconds, a.size, a.views, a.rot_deg, a.trans_frac)
    if a.part in ("appearance", "both"):
        for tv in ("varied", "clean") if a.test_views == "both" else (a.test_views,):
            res[f"appearance_{tv}"] = bench_appearance(a.out, a.seconds, a.size, a.views, tv)
    (a.out / f"summary_{a.part}.json").write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()
