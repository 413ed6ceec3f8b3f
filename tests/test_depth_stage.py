"""Stage `depth`: npy in the user's units, mm PNG consistent with it, colour/opacity PNGs, cameras, errors."""

from __future__ import annotations

import dataclasses
import json

import cv2
import imageio.v2 as iio
import numpy as np
import pytest
import torch

import nerfpipe.stages.depth as depth_stage
from nerfpipe.data.errors import UserError
from nerfpipe.model import render_view

try:  # the analytic stand-in lives with the render tests
    from test_render_stage import SPHERE_RADIUS, SphereRun, sphere_run  # noqa: F401  (fixture)
except ImportError:  # tests/ imported as a package
    from tests.test_render_stage import SPHERE_RADIUS, SphereRun, sphere_run  # noqa: F401


def test_depth_maps_in_user_units_and_consistent_pngs(sphere_run, tmp_path):
    run_dir, fake = sphere_run
    out = depth_stage.run(depth_stage.Config(run_dir=run_dir, out_dir=tmp_path / "d"))
    test_idx = fake.scene.split("test")
    assert len(out.names) == len(test_idx) == len(out.depth)
    scale = fake.scene.applied_scale  # 2: scene = 2 x user units
    for k, i in enumerate(test_idx):
        depth = np.load(out.depth[k])
        assert depth.dtype == np.float32 and depth.shape == (25, 33)
        # analytic: the sphere's nearest point is 3 - r scene units from the camera (at the image centre)
        hit = depth > 0
        assert 0.05 < hit.mean() < 0.9
        assert depth[hit].min() == pytest.approx((3.0 - SPHERE_RADIUS) / scale, abs=0.02)
        pose = fake.scene.frames[i].world_from_cam
        view = render_view(fake, fake.scene.frame_intrinsics(i), pose, torch.device("cpu"))
        assert np.allclose(depth[hit], view["depth"][hit] / scale, rtol=1e-6)
        mm = cv2.imread(str(out.depth_mm[k]), cv2.IMREAD_UNCHANGED)
        assert mm.dtype == np.uint16 and mm.shape == depth.shape
        assert np.array_equal(mm == 0, ~hit)
        assert np.abs(mm.astype(np.float64) - depth * 1000).max() <= 0.5 + 1e-3
        acc = iio.imread(out.accumulation[k])
        assert np.array_equal(acc > 127, hit)
        color = iio.imread(out.depth_color[k])
        assert color.ndim == 3 and color.shape[1] > color.shape[0]  # image plus a colour bar
    lo, hi = out.depth_range
    assert (3.0 - SPHERE_RADIUS) / scale - 0.05 < lo < hi < 3.0 / scale
    cams = json.loads(out.cameras.read_text())["frames"]
    first = np.array(cams[out.names[0]]["world_from_cam"])
    assert np.allclose(np.linalg.norm(first[:3, 3]), 3.0 / scale)  # camera centre in user units
    assert np.allclose(first[:3, :3].T @ first[:3, :3], np.eye(3))
    manifest = json.loads(out.manifest.read_text())
    assert manifest["stage"] == "depth" and manifest["used"]["applied_scale"] == scale
    assert out.video is None


def test_turntable_median_depth_with_video(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    out = depth_stage.run(
        depth_stage.Config(
            run_dir=run_dir, out_dir=tmp_path / "d", views="turntable", kind="median", frames=3, video=True, downscale=2
        )
    )
    assert out.names == ("frame_00000", "frame_00001", "frame_00002")
    assert np.load(out.depth[0]).shape == (12, 16)
    reader = iio.get_reader(str(out.video), format="ffmpeg")
    frames = [f for f in reader.iter_data()]
    reader.close()
    assert len(frames) == 3 and frames[0].shape == (12, 16, 3)


def _checks(manifest) -> tuple[dict, dict[str, dict]]:
    """A manifest and its checks by name."""
    doc = json.loads(manifest.read_text())
    return doc, {c["name"]: c for c in doc["checks"]}


def test_self_check_passes_the_sphere(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    doc, checks = _checks(depth_stage.run(depth_stage.Config(run_dir=run_dir, out_dir=tmp_path / "d")).manifest)
    assert doc["check"] == "ok" and set(checks) == {"depth_coverage", "depth_beyond_far", "non_finite"}, checks
    assert 0.05 < checks["depth_coverage"]["value"] < 0.2  # the sphere covers ~10 % of each view
    assert checks["depth_beyond_far"]["value"] == 0  # hits at 2.5-3 scene units, far bound 10


def _run_with(monkeypatch, run_dir, tmp_path, fake) -> tuple[dict, dict[str, dict]]:
    monkeypatch.setattr(depth_stage, "load_trained", lambda run_dir, device: fake)
    return _checks(depth_stage.run(depth_stage.Config(run_dir=run_dir, out_dir=tmp_path / "d")).manifest)


def test_self_check_flags_depth_beyond_the_far_bound(sphere_run, tmp_path, monkeypatch):
    run_dir, fake = sphere_run
    near = dataclasses.replace(fake.scene, far=2.0)  # the sphere's front is 2.5 scene units from every camera
    doc, checks = _run_with(monkeypatch, run_dir, tmp_path, SphereRun(scene=near))
    assert doc["check"] == "suspect" and checks["depth_beyond_far"]["value"] == 1.0
    assert not checks["depth_beyond_far"]["ok"] and checks["depth_coverage"]["ok"] and checks["non_finite"]["ok"]


def test_self_check_leaves_out_the_far_bound_of_a_box_run(sphere_run, tmp_path, monkeypatch):
    run_dir, fake = sphere_run
    near = dataclasses.replace(fake.scene, far=2.0)
    box_run = SphereRun(scene=near)
    box_run.far = near.far  # rays stop at the far bound: nothing beyond
    doc, checks = _run_with(monkeypatch, run_dir, tmp_path, box_run)
    assert "depth_beyond_far" not in checks and "check depth_beyond_far" in doc["left_out"]


@dataclasses.dataclass
class _EmptyRun(SphereRun):
    """A field with nothing in it: every ray misses."""

    def render_rays(self, rays_o, rays_d, *, infer=None):
        out = super().render_rays(rays_o, rays_d)
        return {**out, "rgb": self.background.expand_as(out["rgb"]), "acc": torch.zeros_like(out["acc"])}


@dataclasses.dataclass
class _NaNDepthRun(SphereRun):
    """The sphere with NaN depth where it is hit on its left half (a broken field)."""

    def render_rays(self, rays_o, rays_d, *, infer=None):
        out = super().render_rays(rays_o, rays_d)
        bad = (rays_o + 3 * rays_d)[:, 0] < 0
        return {**out, "depth": torch.where(bad, torch.nan, out["depth"])}


def test_self_check_flags_an_empty_field_and_non_finite_depth(sphere_run, tmp_path, monkeypatch):
    run_dir, fake = sphere_run
    doc, checks = _run_with(monkeypatch, run_dir, tmp_path / "empty", _EmptyRun(scene=fake.scene))
    assert doc["check"] == "suspect" and checks["depth_coverage"]["value"] == 0 and not checks["depth_coverage"]["ok"]
    assert "depth_beyond_far" not in checks and doc["left_out"]["check depth_beyond_far"] == "no pixel has depth"
    doc, checks = _run_with(monkeypatch, run_dir, tmp_path / "nan", _NaNDepthRun(scene=fake.scene))
    assert doc["check"] == "suspect" and checks["non_finite"]["value"] > 0 and not checks["non_finite"]["ok"]


def test_depth_mm_rounds_clips_and_keeps_zero():
    d = np.array([[0.0, 0.0004, 1.2344, 70.0, np.nan]])
    assert depth_stage.depth_mm(d).tolist() == [[0, 0, 1234, 65535, 0]]


@pytest.mark.parametrize(
    ("changes", "match"),
    [({"views": "val"}, "--views"), ({"kind": "mean"}, "--kind"), ({"acc_threshold": 2.0}, "--acc-threshold")],
)
def test_bad_inputs_are_one_line_user_errors(sphere_run, tmp_path, changes, match):
    run_dir, _ = sphere_run
    with pytest.raises(UserError, match=match) as e:
        depth_stage.run(depth_stage.Config(run_dir=run_dir, out_dir=tmp_path / "d", **changes))
    assert "\n" not in str(e.value)


def test_missing_run_dir(tmp_path):
    with pytest.raises(UserError, match="not found"):
        depth_stage.run(depth_stage.Config(run_dir=tmp_path / "missing", out_dir=tmp_path / "d"))


def test_depth_from_a_real_training_run(tmp_path):
    try:
        from test_render_stage import train_tiny_run
    except ImportError:
        from tests.test_render_stage import train_tiny_run

    run_dir = train_tiny_run(tmp_path, kind="rgba")
    out = depth_stage.run(depth_stage.Config(run_dir=run_dir, out_dir=tmp_path / "d", device="cpu"))
    assert len(out.names) >= 1 and (tmp_path / "d" / "manifest.json").is_file()
    depth = np.load(out.depth[0])
    mm = cv2.imread(str(out.depth_mm[0]), cv2.IMREAD_UNCHANGED)
    assert depth.shape == mm.shape == (24, 24) and np.isfinite(depth).all() and (depth >= 0).all()
    assert np.abs(mm.astype(np.float64) - np.minimum(depth * 1000, 65535)).max() <= 0.5 + 1e-3


def test_depth_takes_the_test_views_eval_rendered_from_the_run_cache(sphere_run, tmp_path, monkeypatch):
    """eval keeps each test view's depth in RUN/renders (model.view_cache); depth then renders none of them again
    and writes the same maps as a depth that renders them (issue 54: the phone capture's 23 test views were
    rendered twice, 325 + 359 s)."""
    import nerfpipe.stages.eval as eval_stage

    run_dir, fake = sphere_run
    (run_dir / "manifest.json").write_text(json.dumps({"checkpoint_sha256": "ab" * 32}))
    eval_stage.run(eval_stage.Config(run_dir=run_dir, out=tmp_path / "eval.json"))
    n = len(fake.scene.split("test"))
    assert len(list((run_dir / "renders").glob("*.npz"))) == n
    calls = []
    monkeypatch.setattr(depth_stage, "render_view", lambda *a, **k: calls.append(1) or render_view(*a, **k))
    cached = depth_stage.run(depth_stage.Config(run_dir=run_dir, out_dir=tmp_path / "cached"))
    assert calls == [] and json.loads(cached.manifest.read_text())["used"]["views_from_render_cache"] == n
    assert json.loads((tmp_path / "eval.json").read_text())["inference"]["name"] == "fast"
    exact = depth_stage.run(depth_stage.Config(run_dir=run_dir, out_dir=tmp_path / "exact", exact=True))
    assert len(calls) == n and json.loads(exact.manifest.read_text())["used"]["inference"]["name"] == "exact"
    calls.clear()  # eval rendered FAST: an exact depth misses the cache
    (run_dir / "manifest.json").write_text(json.dumps({"checkpoint_sha256": "cd" * 32}))  # retrained: a miss
    fresh = depth_stage.run(depth_stage.Config(run_dir=run_dir, out_dir=tmp_path / "fresh"))
    assert len(calls) == n and json.loads(fresh.manifest.read_text())["used"]["views_from_render_cache"] == 0
    for a, b in zip(cached.depth, fresh.depth, strict=True):
        assert np.array_equal(np.load(a), np.load(b))


def test_view_cache_keys_on_checkpoint_and_camera(tmp_path):
    from nerfpipe.model.view_cache import ViewCache
    from nerfpipe.radiance.camera import Intrinsics

    intr, pose = Intrinsics(w=4, h=3, fx=5.0, fy=5.0, cx=2.0, cy=1.5), np.eye(4)
    view = {k: np.full((3, 4), v, np.float32) for k, v in (("depth", 2.0), ("depth_median", 2.5), ("acc", 1.0))}
    cache = ViewCache(tmp_path / "r", "a" * 64)
    assert cache.get(intr, pose) is None and cache.put(intr, pose, view)
    assert np.array_equal(cache.get(intr, pose)["depth_median"], view["depth_median"])
    moved = pose.copy()
    moved[0, 3] = 1e-3
    assert cache.get(intr, moved) is None and ViewCache(tmp_path / "r", "b" * 64).get(intr, pose) is None
    assert cache.get(dataclasses.replace(intr, w=5, cx=2.5), pose) is None
    with pytest.raises(ValueError, match="missing acc"):
        cache.put(intr, pose, {"depth": view["depth"], "depth_median": view["depth"]})
    (tmp_path / "file").write_text("")
    assert not ViewCache(tmp_path / "file" / "r", "a" * 64).put(intr, pose, view)  # cannot be written: False


def test_view_cache_on_a_full_disk_is_left_out(tmp_path, monkeypatch):
    """A full disk while keeping a render (atomic_path raises WriteFailed, not an OSError): put says False and
    leaves no file; eval goes on without the cache."""
    import errno

    from nerfpipe.model import view_cache
    from nerfpipe.radiance.camera import Intrinsics

    def full(path, **arrays):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(view_cache.np, "savez", full)
    intr, view = Intrinsics(w=2, h=2, fx=2.0, fy=2.0, cx=1.0, cy=1.0), {k: np.ones((2, 2)) for k in view_cache.KEPT}
    cache = view_cache.ViewCache(tmp_path / "renders", "a" * 64)
    assert not cache.put(intr, np.eye(4), view) and not any((tmp_path / "renders").iterdir())
