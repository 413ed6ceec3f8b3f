"""Stage `eval`: every JSON key, exact depth error on the analytic sphere (same frame and a similarity-moved
ground truth), user errors, and an integration run: a short real training clears PSNR and depth floors."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import nerfpipe.stages.eval as eval_stage
from nerfpipe.data.atomic import write_json
from nerfpipe.data.errors import UserError
from nerfpipe.model import render_view
from nerfpipe.model.methods.density import DensityOptions

try:  # the analytic stand-in lives with the render tests
    from test_render_stage import SphereRun, sphere_run  # noqa: F401  (fixture)
except ImportError:  # tests/ imported as a package
    from tests.test_render_stage import SphereRun, sphere_run  # noqa: F401

KEYS = {
    "run_dir",
    "split",
    "n_views",
    "psnr",
    "ssim",
    "lpips",
    "lpips_unavailable",
    "rays_per_second",
    "render_seconds",
    "device",
    "views",
    "depth_mae",
    "depth_median_abs_error",
    "depth_coverage",
    "depth_alignment",
    "depth_unavailable",
    "ground_truth",
}


def _rotation(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = math.radians(deg)
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


def _write_ground_truth(folder: Path, fake, gt_from_src: tuple[float, np.ndarray, np.ndarray]):
    """cameras.json + depth/<stem>.npy of the analytic sphere, in a frame gt = s R src + t (metres)."""
    s, rot, t = gt_from_src
    scene = fake.scene
    frames = {}
    for i, f in enumerate(scene.frames):
        src = scene.source_world_from_cam(f.world_from_cam)
        gt = np.eye(4)
        gt[:3, :3], gt[:3, 3] = rot @ src[:3, :3], s * rot @ src[:3, 3] + t
        stem = Path(f.file_path).stem
        frames[stem] = {"file_path": f.file_path, "world_from_cam": gt.tolist()}
        view = render_view(fake, scene.frame_intrinsics(i), f.world_from_cam, torch.device("cpu"))
        depth = np.where(view["acc"] > 0.5, view["depth"] / scene.applied_scale * s, 0.0).astype(np.float32)
        (folder / "depth").mkdir(parents=True, exist_ok=True)
        np.save(folder / "depth" / f"{stem}.npy", depth)
    write_json(folder / "cameras.json", {"frames": frames})


def test_eval_json_has_every_key_without_ground_truth(sphere_run, tmp_path):
    run_dir, fake = sphere_run
    out = eval_stage.run(eval_stage.Config(run_dir=run_dir, out=tmp_path / "e" / "eval.json"))
    doc = json.loads(out.out.read_text())
    assert KEYS <= set(doc)
    assert doc["split"] == "test" and doc["n_views"] == len(fake.scene.split("test")) == len(doc["views"])
    assert doc["psnr"] > 40 and 0.95 < doc["ssim"] <= 1.0  # the photos are this renderer's own (8-bit) output
    assert doc["lpips"] is None and doc["lpips_unavailable"]
    assert doc["rays_per_second"] > 0 and doc["depth_mae"] is None and doc["depth_unavailable"]
    assert {"name", "psnr", "ssim", "lpips"} <= set(doc["views"][0])
    assert out.manifest.name == "eval.manifest.json" and json.loads(out.manifest.read_text())["stage"] == "eval"
    assert out.metrics.read_text().startswith("step,seconds,psnr,ssim,depth_mae")


@pytest.mark.parametrize("moved", [False, True])
def test_depth_error_is_zero_for_exact_depth_in_either_frame(sphere_run, tmp_path, moved):
    run_dir, fake = sphere_run
    gt_from_src = (
        (1.7, _rotation([1, 2, 3], 40), np.array([0.3, -2.0, 5.0])) if moved else (1.0, np.eye(3), 0 * np.ones(3))
    )
    _write_ground_truth(tmp_path / "scene_gt" / "ground_truth", fake, gt_from_src)
    out = eval_stage.run(
        eval_stage.Config(run_dir=run_dir, out=tmp_path / "eval.json", ground_truth=tmp_path / "scene_gt")
    )
    doc = out.result
    align = doc["depth_alignment"]
    assert align["method"] == ("similarity" if moved else "none")
    assert align["scale"] == pytest.approx(gt_from_src[0], rel=1e-6)
    assert doc["depth_mae"] < 1e-4 and doc["depth_coverage"] == pytest.approx(1.0)
    assert all(v["depth_mae"] is not None for v in doc["views"])


def test_depth_error_sees_a_wrong_scale(sphere_run, tmp_path):
    run_dir, fake = sphere_run
    _write_ground_truth(tmp_path / "gt", fake, (1.0, np.eye(3), np.zeros(3)))
    for p in (tmp_path / "gt" / "depth").glob("*.npy"):
        np.save(p, np.load(p) * 1.1)
    doc = eval_stage.run(
        eval_stage.Config(run_dir=run_dir, out=tmp_path / "e.json", ground_truth=tmp_path / "gt")
    ).result
    assert doc["depth_mae"] == pytest.approx(0.1 * 1.3, rel=0.1)  # ~10% of ~1.3 user units


def test_user_errors_are_one_line(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    for config, match in [
        (dict(run_dir=run_dir, out=tmp_path / "e.txt"), ".json"),
        (dict(run_dir=run_dir, out=tmp_path / "e.json", ground_truth=tmp_path / "none"), "cameras.json"),
    ]:
        with pytest.raises(UserError, match=match) as e:
            eval_stage.run(eval_stage.Config(**config))
        assert "\n" not in str(e.value)


def test_missing_run_dir(tmp_path):
    with pytest.raises(UserError, match="not found"):
        eval_stage.run(eval_stage.Config(run_dir=tmp_path / "nope", out=tmp_path / "e.json"))


def _write_metrics(run_dir: Path, *train_psnrs: str) -> None:
    """A run's metrics.csv with these train_psnr values (blank: a row without one), as train writes it."""
    rows = [f"{25 * (k + 1)},{k + 1.0},0.01,{v},,0.01,10,0.5" for k, v in enumerate(train_psnrs)]
    header = "step,seconds,loss,train_psnr,test_psnr,lr,samples_per_ray,skip_fraction"
    (run_dir / "metrics.csv").write_text("\n".join([header, *rows]) + "\n")


def test_self_check_without_a_train_psnr_checks_the_floor_only(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    out = eval_stage.run(eval_stage.Config(run_dir=run_dir, out=tmp_path / "e.json"))
    manifest = json.loads(out.manifest.read_text())
    assert manifest["check"] == out.result["check"] == "ok"
    assert [c["name"] for c in manifest["checks"]] == ["holdout_psnr"] and out.result["train_psnr"] is None


def test_self_check_flags_a_held_out_psnr_far_under_the_train_psnr(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    held_out = eval_stage.run(eval_stage.Config(run_dir=run_dir, out=tmp_path / "a.json")).result["psnr"]
    _write_metrics(run_dir, "20.0", f"{held_out + eval_stage.MAX_GAP_DB - 1:.3f}", "")  # the last row has none
    close = eval_stage.run(eval_stage.Config(run_dir=run_dir, out=tmp_path / "b.json")).result
    gap = {c["name"]: c for c in close["checks"]}["holdout_gap"]
    assert close["check"] == "ok" and gap["ok"] and gap["value"] == pytest.approx(eval_stage.MAX_GAP_DB - 1, abs=0.01)
    assert close["train_psnr_from"] == "metrics.csv, step 50"
    _write_metrics(run_dir, f"{held_out + eval_stage.MAX_GAP_DB + 1:.3f}")
    far = eval_stage.run(eval_stage.Config(run_dir=run_dir, out=tmp_path / "c.json"))
    manifest = json.loads(far.manifest.read_text())
    assert manifest["check"] == "suspect" and [c["name"] for c in manifest["checks"] if not c["ok"]] == ["holdout_gap"]


@dataclasses.dataclass
class _BlackRun(SphereRun):
    """Renders black everywhere: nothing like the (mostly white) photos."""

    def render_rays(self, rays_o, rays_d, *, infer=None):
        out = super().render_rays(rays_o, rays_d)
        return {**out, "rgb": torch.zeros_like(out["rgb"])}


def test_self_check_flags_a_low_held_out_psnr(sphere_run, tmp_path, monkeypatch):
    run_dir, fake = sphere_run
    monkeypatch.setattr(eval_stage, "load_trained", lambda run_dir, device: _BlackRun(scene=fake.scene))
    doc = eval_stage.run(eval_stage.Config(run_dir=run_dir, out=tmp_path / "e.json")).result
    floor = {c["name"]: c for c in doc["checks"]}["holdout_psnr"]
    assert doc["psnr"] < eval_stage.MIN_PSNR and doc["check"] == "suspect" and not floor["ok"]
    assert floor["limit"] == f">= {eval_stage.MIN_PSNR:g} dB"


def test_lpips_status_reports_a_reason_when_unavailable():
    fn, reason = eval_stage.lpips_status()
    assert (fn is None) == (reason is not None)


# --- integration: real training (stages.train) ------------------------------------------------------------

STEPS, PSNR_FLOOR, DEPTH_MAE_M = 120, 16.0, 0.15


def test_short_training_gives_depth_near_ground_truth(tmp_path):
    """~15 s idle (the same budget as test_train's PSNR floor). The synthetic scene spans ~1.6 m seen from
    2.4 m; after 120 steps the depth MAE is ~0.07 m (a constant-depth guess is several times worse)."""
    from nerfpipe.stages import scene as scene_stage
    from nerfpipe.stages import train

    scene_dir = tmp_path / "posed"
    scene_stage.run(scene_stage.Config(out_dir=scene_dir, kind="posed", size=32, views=16, seed=1))
    train.run(
        train.Config(
            scene_dir=scene_dir,
            run_dir=tmp_path / "run",
            max_steps=STEPS,
            max_seconds=600.0,
            batch_rays=512,
            options=DensityOptions(resolution=(24, 48), occupancy_resolution=32),
            log_every=50,
            eval_every=0,
            eval_pixels=256,
            device="cpu",
        )
    )
    doc = eval_stage.run(
        eval_stage.Config(run_dir=tmp_path / "run", out=tmp_path / "eval.json", ground_truth=scene_dir, device="cpu")
    ).result
    assert KEYS <= set(doc)
    assert doc["psnr"] > PSNR_FLOOR, doc["psnr"]
    assert doc["depth_alignment"]["method"] == "none"
    assert doc["depth_mae"] < DEPTH_MAE_M, doc["depth_mae"]
    assert doc["depth_coverage"] > 0.9
    assert doc["check"] == "ok" and {c["name"] for c in doc["checks"]} == {"holdout_psnr", "holdout_gap"}, doc
    # a constant guess (the median ground-truth depth) is far worse: the test has teeth
    gts = [np.load(p) for p in sorted((scene_dir / "ground_truth" / "depth").glob("*.npy"))]
    valid = np.concatenate([g[g > 0] for g in gts])
    assert np.abs(valid - np.median(valid)).mean() > 1.5 * doc["depth_mae"]
