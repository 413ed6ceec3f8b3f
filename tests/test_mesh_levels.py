"""The mesh keeps what the field shows: levels by region, the self-check against the field from the training
cameras, and the upright output frame (`stages.mesh`, issue 52)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from benchmarks.standin import StandIn
from nerfpipe.stages import mesh
from nerfpipe.stages.mesh.threshold import LevelField, level_field

BALL = (np.array([0.0, 0.0, -0.02]), 0.3)  # centre, radius: standing on the slab (scene frame)
FAINT = 8.0
"""The ball's peak density: a rendered ball (optical depth ~5 through it), but far below the slab's level (~50)."""


class _FaintBallOnSlab(StandIn):
    """A dense slab (the stand-in's sharpness: peak density 100) with a faint, soft ball standing on it, as the
    demo's objects on their disk: one level for the whole scene is the slab's, and the ball is below it."""

    def _slab_sdf(self, x):
        q = (x - torch.tensor([0.0, 0.0, -0.37], dtype=x.dtype)).abs() - torch.tensor([0.6, 0.6, 0.05], dtype=x.dtype)
        return torch.linalg.norm(q.clamp(min=0), dim=-1) + q.amax(dim=-1).clamp(max=0)

    def _ball_sdf(self, x):
        c, r = (torch.as_tensor(v, dtype=x.dtype) for v in BALL)
        return torch.linalg.norm(x - c, dim=-1) - r

    def sdf(self, x):
        return torch.minimum(self._slab_sdf(x), self._ball_sdf(x))

    def density(self, x):
        slab = torch.sigmoid(-self._slab_sdf(x) / self.eps) / self.eps
        return slab + FAINT * torch.sigmoid(-self._ball_sdf(x) / 0.02)


def _ball_faces_share(path, s: StandIn) -> float:
    m = trimesh.load(path, force="mesh", process=False)
    centres = np.asarray(m.triangles_center)  # normalized frame: the scene's
    near_ball = np.abs(np.linalg.norm(centres - BALL[0], axis=1) - BALL[1]) < 0.06
    return float((near_ball & (centres[:, 2] > -0.2)).mean())  # above the slab (its top is at z = -0.32)


def test_a_faint_object_is_meshed_by_region_and_the_check_says_when_it_is_missing(tmp_path):
    s = _FaintBallOnSlab(tmp_path)
    kw = dict(run_dir=tmp_path, resolution=64, frame="normalized", colors=False, threshold_rays=2048)
    one = mesh.extract(s, mesh.Config(out=tmp_path / "global.ply", threshold="global", **kw))
    report = json.loads(one.report.read_text())
    checks = {c["name"]: c for c in report["checks"]}
    assert one.threshold > 2 * FAINT, report["threshold"]  # the slab's level, above the ball's peak density
    assert _ball_faces_share(one.mesh, s) < 0.01  # the ball is missing ...
    assert report["check"] == "suspect" and not checks["missed_surface"]["ok"], checks  # ... and the check says so
    by_region = mesh.extract(s, mesh.Config(out=tmp_path / "auto.ply", **kw))
    report = json.loads(by_region.report.read_text())
    checks = {c["name"]: c for c in report["checks"]}
    assert _ball_faces_share(by_region.mesh, s) > 0.2, report["threshold"]  # the ball is there
    assert report["check"] == "ok" and checks["missed_surface"]["value"] < 0.03, checks
    # the ball's top is where the rays see it: within a few voxels of the analytic surface's crossing
    m = trimesh.load(by_region.mesh, force="mesh", process=False)
    top = np.asarray(m.vertices)[np.abs(np.asarray(m.vertices)[:, :2]).max(axis=1) < 0.05, 2].max()
    assert top == pytest.approx(BALL[0][2] + BALL[1], abs=3 * 2.0 / 64), top


def test_the_level_field_is_the_mean_less_a_spread_of_the_log_levels_nearby():
    """Two regions with their own crossing levels: each gets its own (exp(m - s) there), and a point far from
    every crossing gets the global one; the field is trilinear between cells and constant beyond the grid."""
    rng = np.random.default_rng(0)
    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    a = rng.normal([-0.5, 0.0, 0.0], 0.02, size=(400, 3))
    b = rng.normal([0.5, 0.0, 0.0], 0.02, size=(400, 3))
    la, lb = np.exp(rng.normal(np.log(100.0), 0.1, 400)), np.exp(rng.normal(np.log(5.0), 0.1, 400))
    field, info = level_field(np.concatenate([a, b]), np.concatenate([la, lb]), aabb)
    got = field(torch.tensor([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.9, 0.9]])).numpy()
    # each region's own level, less its spread (0.1 in log), the global statistics weighing in a little
    assert got[0] == pytest.approx(100.0 * np.exp(-0.1), rel=0.15), got
    assert got[1] == pytest.approx(5.0 * np.exp(-0.1), rel=0.15), got
    all_logs = np.log(np.concatenate([la, lb]))
    assert got[2] == pytest.approx(np.exp(np.median(all_logs) - all_logs.std()), rel=0.05)  # the global one
    plain = LevelField(lo=np.zeros(3), cell=1.0, log_level=np.log(np.arange(1.0, 9.0)).reshape(2, 2, 2))
    x = torch.tensor([[0.5, 0.5, 0.5], [1.5, 1.5, 1.5], [1.0, 0.5, 0.5], [-3.0, -3.0, -3.0]])
    want = [1.0, 8.0, np.exp(0.5 * (np.log(1.0) + np.log(5.0))), 1.0]  # cell centres, halfway, clamped
    assert np.allclose(plain(x).numpy(), want, rtol=1e-5)


def test_upright_frame_puts_the_scenes_up_on_the_formats_axis_and_records_it(tmp_path):
    s = StandIn(tmp_path)  # the user's frame is turned 40 degrees about (1, 2, 3) from the scene's
    kw = dict(run_dir=tmp_path, resolution=40, threshold=50.0, colors=False, threshold_rays=256)
    user = mesh.extract(s, mesh.Config(out=tmp_path / "u.ply", frame="user", **kw))
    for suffix, axis in ((".glb", [0.0, 1.0, 0.0]), (".obj", [0.0, 1.0, 0.0]), (".ply", [0.0, 0.0, 1.0])):
        out = mesh.extract(s, mesh.Config(out=tmp_path / f"up{suffix}", **kw))
        report = json.loads(out.report.read_text())
        assert report["frame"] == "upright" and report["up"]["format_up"] == {0: "+Z", 1: "+Y"}[int(axis[1])]
        out_from_scene, out_from_source = (np.asarray(report[k]) for k in ("out_from_scene", "out_from_source"))
        up = out_from_scene[:3, :3] @ [0.0, 0.0, 1.0]
        assert np.allclose(up / np.linalg.norm(up), axis, atol=1e-9)
        # the same mesh as the user-frame one, turned and moved by out_from_source (the scene's centre to the origin)
        got = np.asarray(trimesh.load(out.mesh, force="mesh", process=False).vertices)
        user_verts = np.asarray(trimesh.load(user.mesh, force="mesh", process=False).vertices)
        want = user_verts @ out_from_source[:3, :3].T + out_from_source[:3, 3]
        assert np.allclose(np.sort(got, axis=0), np.sort(want, axis=0), atol=1e-4)


def test_closing_joins_a_solid_cut_by_one_voxel_thin_planes_and_leaves_a_smooth_one_as_it_was():
    """The gaps a grid field's line factors leave (stages.mesh.surface.close_gaps): a solid cube crossed by one-voxel
    planes of zero density along z (as `make demo`'s field) meshes as 3 closed slices, as one piece after the
    closing; a ball's smooth density (a bump along every line) is not changed at all."""
    from skimage.measure import marching_cubes

    from nerfpipe.stages.mesh import Config
    from nerfpipe.stages.mesh.surface import close_gaps

    window = Config.close_gaps

    n = 40
    x = np.arange(n, dtype=np.float64)
    cube = np.zeros((n, n, n))
    cube[8:32, 8:32, 8:32] = 10.0
    cube[:, :, 16] = cube[:, :, 24] = 0.0  # planes of ~0 density through the solid

    def pieces(vol):
        verts, faces, _, _ = marching_cubes(vol, level=1.0)
        return len(trimesh.Trimesh(verts, faces, process=True).split(only_watertight=False))

    assert pieces(cube) == 3 and pieces(close_gaps(cube, window)) == 1
    r2 = sum(np.square(g - 19.5) for g in np.meshgrid(x, x, x, indexing="ij"))
    ball = 10.0 * np.exp(-r2 / 80.0)
    assert np.array_equal(close_gaps(ball, window), ball)
    assert close_gaps(cube, 1) is cube
