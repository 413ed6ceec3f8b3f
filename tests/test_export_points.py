"""Stage `export-points` (issue 29 item 4): a coloured point cloud with normals from a run's training rays.

Fast tests use `Rendered`, the analytic stand-in of `benchmarks.standin` (a sphere and a box, exact surface,
non-trivial applied transform and scale) made renderable: its rays are volume-rendered through the real compositing
(`radiance.render`), so the expected depth, opacity and colour are those of a soft density, not exact hits. One test
exports a real (tiny) training run through the command line.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from benchmarks.standin import StandIn
from nerfpipe import cli
from nerfpipe.data.errors import UserError
from nerfpipe.model.methods.density import DensityOptions
from nerfpipe.model.surface_points import density_normals, sdf_normals
from nerfpipe.radiance.render import StratifiedSampler, render_rays
from nerfpipe.stages import export_points as ep
from nerfpipe.stages.export_points.geometry import statistical_outliers, to_frame
from nerfpipe.stages.export_points.ply import write_ply

BACKGROUND = (1.0, 1.0, 1.0)


class Rendered(StandIn):
    """StandIn with `render_rays` (400 intervals over t in [2, 4]: the cameras are 3 from the origin, the object
    within 0.7 of it), a white background, and optional flying points: every `fly`-th ray's depth pulled 5-30 %
    towards its camera (as a ray across a depth edge averages two surfaces)."""

    def __init__(self, root, *, fly: int = 0, size: int = 40, **kw):
        super().__init__(root, size=size, **kw)
        self.background = torch.tensor(BACKGROUND)
        self.fly = fly
        self.rays_seen = 0

    def render_rays(self, rays_o, rays_d, *, infer=None, median=True):
        o, d = rays_o.double(), rays_d.double()

        def rgb_sigma(x, _d):
            return self.color(x, None), self.density(x)

        out = render_rays(
            o,
            d,
            near=2.0,
            far=4.0,
            sampler=StratifiedSampler(n_samples=400),
            rgb_sigma_fn=rgb_sigma,
            background=self.background.double(),
        )
        depth = out["depth"].clone()
        if self.fly:
            k = torch.arange(self.rays_seen, self.rays_seen + len(depth))
            hit = k % self.fly == 0
            depth[hit] *= (
                1
                - 0.05
                - 0.25 * torch.rand(int(hit.sum()), generator=torch.Generator().manual_seed(1), dtype=depth.dtype)
            )
        self.rays_seen += len(depth)
        return {"rgb": out["rgb"].float(), "depth": depth.float(), "acc": out["acc"].float()}


def _export(s: StandIn, tmp_path: Path, name: str = "cloud.ply", **kw) -> tuple[ep.Outputs, dict]:
    """The stage on the stand-in, in the user's frame as it came in unless `frame` is given."""
    kw.setdefault("frame", "user")
    config = ep.Config(run_dir=tmp_path, out=tmp_path / name, num_points=kw.pop("num_points", 2500), **kw)
    out = ep.export(s, config)
    return out, json.loads(out.report.read_text())


def _read_ply(path: Path) -> np.ndarray:
    """The vertex rows of our binary PLY, parsed independently of the writer (header, then raw records)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    types = {"double": "<f8", "float": "<f4", "uchar": "u1"}
    fields = [(ln.split()[2], types[ln.split()[1]]) for ln in header if ln.startswith("property")]
    n = int(next(ln for ln in header if ln.startswith("element vertex")).split()[2])
    assert header[1] == "format binary_little_endian 1.0"
    rows = np.frombuffer(data[end:], dtype=np.dtype(fields))
    assert len(rows) == n
    return rows


def _xyz(rows, prefix=""):
    return np.stack([rows[prefix + a] for a in "xyz"], axis=1).astype(np.float64)


def _to_scene(s: StandIn, p: np.ndarray) -> np.ndarray:
    m = s.scene.scene_from_source()
    return p @ m[:3, :3].T + m[:3, 3]


def _sdf(s: StandIn, p_scene: np.ndarray) -> np.ndarray:
    return s.sdf(torch.as_tensor(p_scene)).numpy()


@pytest.mark.parametrize("mirror", [False, True])
def test_points_lie_on_the_surface_with_outward_normals_in_the_user_frame(tmp_path, mirror):
    s = Rendered(tmp_path, mirror=mirror)
    out, report = _export(s, tmp_path)
    rows = _read_ply(out.out)
    assert len(rows) == out.points == report["points"] and 2000 < out.points <= 2500
    p_user, n_user = _xyz(rows), _xyz(rows, "n")
    assert np.allclose(report["out_from_scene"], s.scene.source_from_scene())
    # near the exact surface (scene units; the object is ~1.3 across): the density's soft shell is eps = 0.01 wide;
    # head-on rays end on the surface, grazing rays along the silhouettes a few eps out (their weights spread
    # along the shell)
    sdf = np.abs(_sdf(s, _to_scene(s, p_user)))
    assert np.median(sdf) < 0.01 and np.quantile(sdf, 0.99) < 0.05, (np.median(sdf), np.quantile(sdf, 0.99))
    # outward, checked in the user frame itself: a step along the normal leaves the object (sdf grows)
    step = 0.02  # user units (applied_scale 0.25: 0.005 scene units)
    grows = _sdf(s, _to_scene(s, p_user + step * n_user)) - _sdf(s, _to_scene(s, p_user))
    assert (grows > 0.5 * step * 0.25).mean() > 0.97, np.quantile(grows, [0.01, 0.5])
    assert np.allclose(np.linalg.norm(n_user, axis=1), 1, atol=1e-5)
    # colours: the field's own colour at the point (the background taken out), as the report says they are
    colours = np.stack([rows[c] for c in ("red", "green", "blue")], axis=1).astype(float) / 255
    expect = s.color(torch.as_tensor(_to_scene(s, p_user)), None).numpy()
    assert np.median(np.abs(colours - expect)) < 3 / 255 and np.quantile(np.abs(colours - expect), 0.99) < 0.05
    assert (
        report["normals"]["facing_camera_before_reorienting"] > 0.95 and report["normals"]["from_view_direction"] == 0
    )
    assert report["check"] == "ok", report["checks"]
    assert {c["name"] for c in report["checks"]} == {
        "ray_hit_fraction",
        "outlier_fraction",
        "normals_facing_camera",
        "non_finite",
    }
    removed = {r["what"]: r["count"] for r in report["removed"]}
    assert report["rays"]["gave_points"] - removed["over num_points"] - removed["statistical outliers"] == out.points
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


def test_ply_loads_in_trimesh_and_pymeshlab_with_the_reported_points_and_colours(tmp_path):
    pymeshlab = pytest.importorskip("pymeshlab")
    s = Rendered(tmp_path)
    out, report = _export(s, tmp_path, num_points=800)
    rows = _read_ply(out.out)
    rgb = np.stack([rows[c] for c in ("red", "green", "blue")], axis=1)
    cloud = trimesh.load(out.out)
    assert isinstance(cloud, trimesh.PointCloud) and len(cloud.vertices) == report["points"] == len(rows)
    assert np.allclose(cloud.vertices, _xyz(rows)) and np.array_equal(np.asarray(cloud.colors)[:, :3], rgb)
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(out.out))
    m = ms.current_mesh()
    assert m.vertex_number() == report["points"]
    assert np.allclose(m.vertex_matrix(), _xyz(rows), atol=1e-6)
    assert np.allclose(m.vertex_normal_matrix(), _xyz(rows, "n"), atol=1e-6)
    assert np.abs(m.vertex_color_matrix()[:, :3] * 255 - rgb).max() < 0.51


def test_user_and_normalized_frames_differ_by_the_recorded_transform(tmp_path):
    s = Rendered(tmp_path)
    user, ru = _export(s, tmp_path, "u.ply", num_points=600)
    norm, rn = _export(s, tmp_path, "n.ply", num_points=600, frame="normalized")
    assert rn["frame"] == "normalized" and np.allclose(rn["out_from_scene"], np.eye(4))
    m = np.asarray(ru["out_from_scene"])
    assert not np.allclose(m, np.eye(4)) and np.allclose(m, s.scene.source_from_scene())
    a, b = _read_ply(user.out), _read_ply(norm.out)
    assert len(a) == len(b) == user.points
    assert np.allclose(_xyz(a), _xyz(b) @ m[:3, :3].T + m[:3, 3], atol=1e-5)  # float32 coordinates
    n = _xyz(b, "n") @ np.linalg.inv(m[:3, :3])
    assert np.allclose(_xyz(a, "n"), n / np.linalg.norm(n, axis=1, keepdims=True), atol=1e-6)


def test_statistical_outliers_take_the_flying_points(tmp_path):
    s = Rendered(tmp_path, fly=23)
    kept, report = _export(s, tmp_path, "kept.ply")
    s.rays_seen = 0  # the same rays fly again
    raw, raw_report = _export(s, tmp_path, "raw.ply", outlier_neighbors=0)
    off_raw = np.abs(_sdf(s, _to_scene(s, _xyz(_read_ply(raw.out)))))  # scene units from the surface
    off_kept = np.abs(_sdf(s, _to_scene(s, _xyz(_read_ply(kept.out)))))
    # the rule removes isolated points: those far out (0.2 here: the surface points' mean neighbour distance is
    # ~0.07) all but go; flying points close to the surface have the surface among their neighbours and stay
    assert (off_raw > 0.2).sum() > 40 and (off_kept > 0.2).sum() <= 0.05 * (off_raw > 0.2).sum()
    assert (off_kept > 0.05).sum() < 0.5 * (off_raw > 0.05).sum()
    outliers = next(r for r in report["removed"] if r["what"] == "statistical outliers")
    assert (
        outliers["count"] == kept.outliers >= (off_raw > 0.2).sum() - (off_kept > 0.2).sum()
        and outliers["neighbors"] == 20
    )
    assert outliers["limit_scene"] == pytest.approx(
        outliers["mean_neighbor_distance_scene"] + 2 * outliers["std_scene"]
    )
    assert raw.outliers == 0 and raw_report["left_out"]["outliers"]


def test_num_points_caps_and_bbox_crops_in_the_user_frame(tmp_path):
    s = Rendered(tmp_path)
    out, report = _export(s, tmp_path, num_points=300, outlier_neighbors=0)
    assert out.points == 300 and report["rays"]["gave_points"] >= 300
    centre = s.scene.source_from_scene() @ np.array([-0.25, 0.0, 0.0, 1.0])  # the sphere's centre, user frame
    half = 0.45 / s.scene.applied_scale  # the sphere's radius is 0.35: a box around its surface, cutting the box
    bbox = (*(centre[:3] - half), *(centre[:3] + half))
    out, report = _export(s, tmp_path, "crop.ply", num_points=400, bbox=bbox)
    p = _xyz(_read_ply(out.out))
    assert ((p >= np.array(bbox[:3])) & (p <= np.array(bbox[3:]))).all()
    assert next(r for r in report["removed"] if r["what"] == "outside bbox")["count"] > 0


def test_passes_cover_every_pixel_once_and_stop_when_enough_points_are_kept(tmp_path):
    s = Rendered(tmp_path, views=4, size=16)
    seen = []
    render = s.render_rays
    s.render_rays = lambda o, d, **kw: (seen.append(torch.cat([o, d], 1)), render(o, d, **kw))[1]
    out, report = _export(s, tmp_path, num_points=10**6, outlier_neighbors=0)  # more than there are pixels
    rays = report["rays"]
    assert rays["rendered"] == rays["pixels"] == 4 * 16 * 16 == out.rays and rays["passes"] == rays["of_passes"]
    assert len(torch.unique(torch.cat(seen)[:, 3:], dim=0)) == rays["pixels"]  # no ray twice
    seen.clear()
    out, report = _export(s, tmp_path, "few.ply", num_points=40, outlier_neighbors=0)
    rays = report["rays"]
    assert rays["stride"] > 1 and rays["passes"] < rays["of_passes"] and rays["rendered"] < rays["pixels"]
    assert rays["gave_points"] >= 40 and out.points == 40
    origins = torch.unique(torch.cat(seen)[:, :3], dim=0)
    assert len(origins) == report["used"]["cameras"]["count"] == 4  # each pass takes rays of every camera


def test_an_empty_field_is_a_one_line_user_error_and_leaves_no_file(tmp_path):
    s = Rendered(tmp_path, empty=True, views=4, size=16)  # every ray is rendered before giving up
    with pytest.raises(UserError, match="none of the .* rays rendered gave a point") as e:
        _export(s, tmp_path / "out")
    assert "\n" not in str(e.value)
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"out": Path("x.obj")}, "expected a .ply"),
        ({"acc_threshold": 0.0}, "acc_threshold"),
        ({"num_points": 0}, "num_points"),
        ({"bbox": (0, 0, 0, 1, -1, 1)}, "bbox"),
        ({"outlier_std_ratio": 0.0}, "outlier_std_ratio"),
        ({"normal_step": 2.0}, "normal_step"),
    ],
)
def test_bad_settings_are_one_line_user_errors(tmp_path, changes, match):
    config = ep.Config(**{"run_dir": tmp_path, "out": tmp_path / "c.ply", **changes})
    with pytest.raises(UserError, match=match):
        ep.run(config)


def test_missing_run_dir(tmp_path):
    with pytest.raises(UserError, match="not found"):
        ep.run(ep.Config(run_dir=tmp_path / "missing", out=tmp_path / "c.ply"))


# ---------------------------------------------------------------------------------------------- the pieces
def test_density_normals_are_minus_the_gradient_direction_and_sdf_normals_plus():
    a = np.array([0.3, -2.0, 1.0])

    def density(x):
        return (x.double() @ torch.as_tensor(a)).float() + 5  # grad sigma = a everywhere

    pts = np.random.default_rng(0).normal(size=(50, 3))
    dirs = np.tile([0.0, 0.0, -1.0], (50, 1))
    normals, good = density_normals(density, pts, dirs, 1e-2, torch.device("cpu"))
    assert good.all() and np.allclose(normals, -a / np.linalg.norm(a), atol=1e-3)
    flat, good = density_normals(lambda x: torch.zeros(len(x)), pts, dirs, 1e-2, torch.device("cpu"))
    assert not good.any() and np.allclose(flat, -dirs)  # no gradient: the normal faces the camera
    normals, good = sdf_normals(density, pts, dirs, 1e-2, torch.device("cpu"))  # a distance grows out of the object
    assert good.all() and np.allclose(normals, a / np.linalg.norm(a), atol=1e-3)


def test_statistical_rule_removes_isolated_points_only():
    g = np.stack(np.meshgrid(np.arange(30), np.arange(30), [0.0], indexing="ij"), -1).reshape(-1, 3) * 0.01
    far = np.array([[0.15, 0.15, 0.5], [2.0, 2.0, 2.0], [-1.0, 0.3, 0.2]])
    keep, info = statistical_outliers(np.concatenate([g, far]), 20, 2.0)
    assert not keep[-3:].any() and keep[:-3].mean() > 0.97 and info["removed"] == int((~keep).sum())
    keep, info = statistical_outliers(g[:10], 20, 2.0)  # fewer points than neighbours: nothing to compare
    assert keep.all() and not info["applied"]


def test_normals_map_by_the_inverse_transpose():
    m = np.diag([2.0, 1.0, -1.0, 1.0])
    m[:3, 3] = [1, 2, 3]
    p, n = to_frame(m, np.array([[1.0, 1.0, 1.0]]), np.array([[1.0, 1.0, 0.0]]) / math.sqrt(2))
    assert np.allclose(p, [[3.0, 3.0, 2.0]])
    assert np.allclose(n, np.array([[0.5, 1.0, 0.0]]) / math.hypot(0.5, 1.0))  # still perpendicular to the plane


def test_ply_writer_refuses_mismatched_arrays(tmp_path):
    with pytest.raises(ValueError, match="normals"):
        write_ply(tmp_path / "x.ply", np.zeros((3, 3)), np.zeros((2, 3)), np.zeros((3, 3), np.uint8))


# ---------------------------------------------------------------------------------------------- command line
def test_help_lists_the_options(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["export-points", "--help"])
    out = capsys.readouterr().out
    assert e.value.code == 0
    options = (
        "--num-points",
        "--acc-threshold",
        "--frame",
        "--bbox",
        "--outlier-neighbors",
        "--outlier-std-ratio",
        "--normal-step",
        "--no-reorient-normals",
        "--downscale",
        "--seed",
    )
    for option in options:
        assert option in out, option
    assert cli.config_from_args("export-points", ["r", "c.ply", "--bbox", "0,0,0,1,1,2"]).bbox == (0, 0, 0, 1, 1, 2)


def test_a_real_training_run_through_the_command_line(tmp_path, capsys):
    pymeshlab = pytest.importorskip("pymeshlab")
    from nerfpipe.stages import scene as scene_stage
    from nerfpipe.stages import train

    scene_stage.run(scene_stage.Config(out_dir=tmp_path / "scene", kind="posed", size=24, views=10, seed=0))
    run_dir = tmp_path / "run"  # 50 steps: some rays become opaque (2 steps leave every opacity below 0.01)
    train.run(
        train.Config(
            scene_dir=tmp_path / "scene",
            run_dir=run_dir,
            max_steps=50,
            max_seconds=120.0,
            batch_rays=256,
            options=DensityOptions(resolution=(16, 24), occupancy_resolution=16),
            eval_every=0,
            final_eval_views=1,
            device="cpu",
        )
    )
    out = tmp_path / "pts" / "cloud.ply"
    with pytest.raises(SystemExit) as e:
        cli.main(["export-points", str(run_dir), str(out), "--num-points", "3000", "--device", "cpu"])
    captured = capsys.readouterr()
    assert e.value.code == 0, captured.err
    report = json.loads((tmp_path / "pts" / "cloud.report.json").read_text())
    assert f"{report['points']} points" in captured.out and str(out) in captured.out
    assert report["stage"] == "export-points" and all(len(h) == 64 for h in report["inputs"].values())
    rows = _read_ply(out)
    cloud = trimesh.load(out)
    assert len(cloud.vertices) == len(rows) == report["points"] > 0
    assert np.array_equal(np.asarray(cloud.colors)[:, :3], np.stack([rows[c] for c in ("red", "green", "blue")], 1))
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(out))
    assert ms.current_mesh().vertex_number() == report["points"]
    assert np.isfinite(_xyz(rows)).all() and np.allclose(np.linalg.norm(_xyz(rows, "n"), axis=1), 1, atol=1e-5)


def test_default_is_upright_in_float32_and_double_is_an_option(tmp_path):
    """The default: the user's frame turned so that the scene's up is +Z (`data.export_frame`), coordinates as
    32-bit floats (what web clients read); `double=True` writes 64-bit coordinates, the same points."""
    s = Rendered(tmp_path)  # its user frame is turned 40 degrees about (1, 2, 3) from the scene's
    up, ru = _export(s, tmp_path, "up.ply", num_points=600, frame="upright")
    wide, rw = _export(s, tmp_path, "wide.ply", num_points=600, frame="upright", double=True)
    assert ru["frame"] == "upright" and ru["up"]["format_up"] == "+Z"
    m = np.asarray(ru["out_from_scene"])
    assert np.allclose(m[:3, :3] @ [0.0, 0.0, 1.0] / np.linalg.norm(m[:3, :3] @ [0.0, 0.0, 1.0]), [0, 0, 1])
    assert np.allclose(np.asarray(ru["out_from_source"]) @ s.scene.source_from_scene(), m)
    a, b = _read_ply(up.out), _read_ply(wide.out)
    assert a.dtype["x"] == np.float32 and b.dtype["x"] == np.float64
    assert "x double" in " ".join(rw["ply"]["properties"]) and "x float" in " ".join(ru["ply"]["properties"])
    assert np.allclose(_xyz(a), _xyz(b), atol=1e-5)
