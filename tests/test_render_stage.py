"""Stage `render`: mp4 decodes back with the right frames/size, outputs stack, bad inputs are one-line errors.

Fast tests use `SphereRun`, an analytic stand-in for `model.load_trained` (an opaque sphere: exact depth
and opacity) patched into the render, depth and eval stages; the depth and eval tests import it from here.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import imageio.v2 as iio
import numpy as np
import pytest
import torch

import nerfpipe.stages.render as render_stage
from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import Frame, Scene, write_scene
from nerfpipe.data.video import to_uint8, write_png
from nerfpipe.model import camera_path, render_view
from nerfpipe.model.methods.density import DensityOptions
from nerfpipe.radiance import paths
from nerfpipe.radiance.camera import Intrinsics
from nerfpipe.radiance.metrics import psnr

SPHERE_RADIUS = 0.5  # scene units
BACKGROUND = (1.0, 1.0, 1.0)


@dataclass
class SphereRun:
    """A run (`model.run.Run`) that renders rays: an opaque sphere at the origin, colour from its normal, miss ->
    background."""

    scene: Scene
    background: torch.Tensor = torch.tensor(BACKGROUND)
    miss_depth: float = 10.0
    device: torch.device = torch.device("cpu")
    downscale: float = 1.0
    pose_refinement: dict | None = None
    appearance: None = None
    method: str = "sphere"
    capabilities: frozenset = frozenset({"rays"})
    far: float = math.inf  # rays never stop early

    def render_rays(self, rays_o, rays_d, *, infer=None, median=True):
        b = (rays_o * rays_d).sum(-1)
        c = (rays_o * rays_o).sum(-1) - SPHERE_RADIUS**2
        disc = b * b - c
        hit = disc > 0
        t = torch.where(hit, -b - torch.sqrt(disc.clamp_min(0)), torch.full_like(b, self.miss_depth))
        normal = (rays_o + t[:, None] * rays_d) / SPHERE_RADIUS
        rgb = torch.where(hit[:, None], 0.5 + 0.5 * normal.clamp(-1, 1), self.background.to(rays_o))
        return {"rgb": rgb, "depth": t, "depth_median": t, "acc": hit.to(rays_o.dtype)}


def sphere_scene(root: Path, *, views: int = 8, w: int = 33, h: int = 25, applied_scale: float = 2.0) -> Scene:
    """Cameras on an orbit (radius 3 scene units) looking at the origin; odd test split; images rendered by
    the sphere (so replay PSNR is ~ 8-bit quantisation only). Scene = applied_scale * source."""
    intr = Intrinsics(w=w, h=h, fx=30.0, fy=30.0, cx=w / 2, cy=h / 2)
    orbit = paths.Orbit(
        centre=np.zeros(3), up=np.array([0.0, 0, 1]), radius=3.0, elevation_deg=20.0, start_azimuth_deg=0.0
    )
    poses = paths.turntable(orbit, views)
    frames = tuple(Frame(file_path=f"images/v{i:03d}.png", world_from_cam=p) for i, p in enumerate(poses))
    scene = Scene(
        root=root,
        frames=frames,
        intrinsics=intr,
        applied_scale=applied_scale,
        applied_transform=np.eye(4)[:3],
        splits={"train": tuple(range(0, views, 2)), "test": tuple(range(1, views, 2))},
        near=0.1,
        far=10.0,
    )
    fake = SphereRun(scene=scene)
    for i, p in enumerate(poses):
        view = render_view(fake, intr, p, torch.device("cpu"))
        write_png(root / frames[i].file_path, to_uint8(view["rgb"]))
    write_scene(scene)
    return scene


@pytest.fixture
def sphere_run(tmp_path, monkeypatch):
    """A run dir (empty but present) whose `load_trained` yields the analytic sphere."""
    scene = sphere_scene(tmp_path / "scene")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    fake = SphereRun(scene=scene)
    import nerfpipe.stages.depth
    import nerfpipe.stages.eval

    for stage in (render_stage, nerfpipe.stages.depth, nerfpipe.stages.eval):
        monkeypatch.setattr(stage, "load_trained", lambda run_dir, device: fake)
    return run_dir, fake


def _read_video(path: Path) -> np.ndarray:
    reader = iio.get_reader(str(path), format="ffmpeg")
    try:
        return np.stack([frame for frame in reader.iter_data()])
    finally:
        reader.close()


def test_turntable_mp4_decodes_with_frames_size_and_motion(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    out = tmp_path / "out" / "turn.mp4"
    res = render_stage.run(
        render_stage.Config(
            run_dir=run_dir,
            out=out,
            frames=10,
            fps=10,
            outputs=("rgb", "depth", "accumulation"),
            frames_dir=tmp_path / "frames",
        )
    )
    video = _read_video(out)
    assert video.shape == (10, 26, 100, 3)  # 25 x (3 * 33) padded to even
    assert res.size == (25, 99) and res.n_frames == 10
    assert video.std() > 10  # not constant
    assert np.abs(video[0].astype(int) - video[5].astype(int)).mean() > 1  # moves (sphere colour follows normal)
    assert len(res.frames) == 10 and all(p.is_file() for p in res.frames)
    png = iio.imread(res.frames[3])
    assert png.shape == (25, 99, 3)
    assert res.manifest.name == "turn.manifest.json" and res.manifest.is_file()
    assert res.metrics.read_text().startswith("step,seconds,rays_per_s,psnr")
    assert not list(out.parent.glob(".turn*"))  # no temporaries left


def test_accumulation_panel_matches_sphere_silhouette(sphere_run, tmp_path):
    run_dir, fake = sphere_run
    out = tmp_path / "acc.mp4"
    render_stage.run(
        render_stage.Config(run_dir=run_dir, out=out, frames=2, outputs=("accumulation",), frames_dir=tmp_path / "f")
    )
    frame = iio.imread(tmp_path / "f" / "frame_00000.png")
    cams = camera_path(fake.scene, "turntable", frames=2)
    acc = render_view(fake, cams.intrinsics[0], cams.world_from_cams[0], torch.device("cpu"))["acc"]
    assert np.array_equal(frame[..., 0] > 127, acc > 0.5)


def test_test_path_replays_dataset_cameras_with_psnr(sphere_run, tmp_path):
    run_dir, fake = sphere_run
    res = render_stage.run(render_stage.Config(run_dir=run_dir, out=tmp_path / "t.mp4", path="test"))
    assert res.n_frames == len(fake.scene.split("test"))
    rows = res.metrics.read_text().strip().splitlines()[1:]
    psnrs = [float(r.split(",")[3]) for r in rows]
    assert len(psnrs) == res.n_frames and min(psnrs) > 40  # the images are this renderer's own output


def _checks(manifest: Path) -> tuple[str, dict[str, dict]]:
    """A manifest's verdict and its checks by name."""
    doc = json.loads(manifest.read_text())
    return doc["check"], {c["name"]: c for c in doc["checks"]}


def test_self_check_passes_the_sphere_turntable(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    res = render_stage.run(
        render_stage.Config(run_dir=run_dir, out=tmp_path / "v.mp4", frames=6, outputs=("rgb", "depth"))
    )
    check, checks = _checks(res.manifest)
    assert check == "ok" and set(checks) == {"empty_frames", "still_frames", "non_finite"}, checks
    assert 0.8 < checks["empty_frames"]["value"] < render_stage.MAX_EMPTY  # the sphere covers ~10 % of a frame
    assert checks["still_frames"]["value"] == 0 and checks["non_finite"]["value"] == 0


def test_self_check_flags_a_path_that_misses_the_object(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    # 100 user units away the sphere (radius 0.25 user units) is a tenth of a pixel: every frame is background
    res = render_stage.run(render_stage.Config(run_dir=run_dir, out=tmp_path / "far.mp4", frames=4, radius=100.0))
    check, checks = _checks(res.manifest)
    assert check == "suspect" and not checks["empty_frames"]["ok"] and checks["empty_frames"]["value"] > 0.99
    assert not checks["still_frames"]["ok"]  # all background: nothing changes either
    assert checks["non_finite"]["ok"]


def test_self_check_flags_a_camera_path_that_stands_still(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    pose = paths.look_at(np.array([0.0, -3.0, 1.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    entry = {"camera_to_world": pose.reshape(-1).tolist(), "fov": 40.0, "aspect": 1.0}
    path = tmp_path / "still.json"
    path.write_text(json.dumps({"camera_path": [entry] * 4, "render_width": 24, "render_height": 24, "fps": 10}))
    res = render_stage.run(render_stage.Config(run_dir=run_dir, out=tmp_path / "s.mp4", path=str(path)))
    check, checks = _checks(res.manifest)
    assert check == "suspect" and checks["still_frames"]["value"] == 1.0 and not checks["still_frames"]["ok"]
    assert checks["empty_frames"]["ok"]  # the sphere is in view: only the stillness is wrong


@dataclass
class _NaNSphere(SphereRun):
    """The sphere with NaN colour on its left half (a broken field)."""

    def render_rays(self, rays_o, rays_d, *, infer=None):
        out = super().render_rays(rays_o, rays_d)
        out["rgb"] = torch.where((rays_o + 3 * rays_d)[:, :1] < 0, torch.nan, out["rgb"])
        return out


def test_self_check_flags_non_finite_colour(sphere_run, tmp_path, monkeypatch):
    run_dir, fake = sphere_run
    monkeypatch.setattr(render_stage, "load_trained", lambda run_dir, device: _NaNSphere(scene=fake.scene))
    res = render_stage.run(render_stage.Config(run_dir=run_dir, out=tmp_path / "n.mp4", frames=3))
    check, checks = _checks(res.manifest)
    assert check == "suspect" and checks["non_finite"]["value"] > 0 and not checks["non_finite"]["ok"]
    assert checks["empty_frames"]["ok"] and checks["still_frames"]["ok"]


def test_turntable_uses_training_median_radius_unless_given(sphere_run):
    _, fake = sphere_run
    cams = camera_path(fake.scene, "turntable", frames=6)
    dist = np.linalg.norm(cams.world_from_cams[:, :3, 3], axis=1)
    assert np.allclose(dist, 3.0) and cams.used["elevation_deg"] == pytest.approx(20.0)
    cams = camera_path(fake.scene, "turntable", frames=6, radius=2.0, elevation=45.0, downscale=2)
    rel = cams.world_from_cams[:, :3, 3]
    assert np.allclose(np.linalg.norm(rel, axis=1), 4.0)  # user units * applied_scale (2)
    assert np.allclose(np.degrees(np.arcsin(rel[:, 2] / 4.0)), 45.0)
    assert (cams.intrinsics[0].w, cams.intrinsics[0].h) == (16, 12)  # round(33 / 2), round(25 / 2)
    assert np.allclose(-cams.world_from_cams[:, :3, 2], -rel / 4.0)


def test_spiral_path_renders(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    res = render_stage.run(render_stage.Config(run_dir=run_dir, out=tmp_path / "s.mp4", path="spiral", frames=4))
    assert _read_video(res.video).shape[0] == 4


def ring_scene(root: Path, azimuths_deg, *, names=None, elevation: float = 20.0) -> Scene:
    """A Scene (nothing on disk) whose cameras sit at these azimuths round the origin, 3 units away, looking at
    it; `names` are their file names (default: in azimuth order)."""
    intr = Intrinsics(w=33, h=25, fx=30.0, fy=30.0, cx=16.5, cy=12.5)
    orbit = paths.Orbit(
        centre=np.zeros(3), up=np.array([0.0, 0, 1]), radius=3.0, elevation_deg=elevation, start_azimuth_deg=0.0
    )
    poses = [paths.turntable(dataclasses.replace(orbit, start_azimuth_deg=a), 1)[0] for a in azimuths_deg]
    names = names or [f"images/IMG_{i + 1}.jpg" for i in range(len(poses))]
    frames = tuple(Frame(file_path=n, world_from_cam=p) for n, p in zip(names, poses, strict=True))
    return Scene(root=root, frames=frames, intrinsics=intr)


def test_auto_path_follows_a_half_circle_capture_and_orbits_a_full_one(tmp_path):
    half = camera_path(ring_scene(tmp_path, np.linspace(-90, 90, 19)), "auto", frames=40)
    assert half.used["path"] == "trajectory" and half.used["auto"]["chose"] == "trajectory"
    assert half.used["coverage"]["covered_deg"] == pytest.approx(180.0)
    assert half.used["coverage"]["largest_gap_deg"] == pytest.approx(180.0)
    assert "180 degrees" in half.used["auto"]["reason"] and "capture order" in half.used["order"]
    rel = half.world_from_cams[:, :3, 3]
    az = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]))
    assert az.min() > -91 and az.max() < 91  # never leaves what was photographed
    assert az[0] == pytest.approx(-90, abs=1) and az[-1] == pytest.approx(90, abs=1)  # end to end, in order
    assert np.allclose(np.linalg.norm(rel, axis=1), 3.0, atol=0.05)
    full = camera_path(ring_scene(tmp_path, np.arange(0, 360, 30)), "auto", frames=40)
    assert full.used["path"] == "turntable" and full.used["coverage"]["largest_gap_deg"] == pytest.approx(30.0)
    assert "radius_scene" in full.used


def test_trajectory_sorts_shuffled_file_names_by_azimuth_and_arc_spans_the_coverage(tmp_path):
    order = np.random.default_rng(0).permutation(19)  # file names say nothing about where the photo was taken
    scene = ring_scene(tmp_path, np.linspace(-90, 90, 19), names=[f"images/{k:02d}.jpg" for k in order])
    cams = camera_path(scene, "trajectory", frames=30, radius=9.0)
    assert cams.used["order"].startswith("azimuth order") and "radius" in cams.used["ignored"]
    rel = cams.world_from_cams[:, :3, 3]
    az = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))
    assert (np.diff(az) > 0).all() or (np.diff(az) < 0).all()  # one sweep, no back and forth
    arc = camera_path(scene, "arc", frames=7)
    rel = arc.world_from_cams[:, :3, 3]
    assert np.allclose(np.degrees(np.arctan2(rel[:, 1], rel[:, 0])), np.linspace(-90, 90, 7))
    assert arc.used["sweep_deg"] == pytest.approx(180.0)


def test_fit_budget_shrinks_images_then_drops_frames():
    fox = {"rays_per_frame": 1080 * 1920, "frames": 120, "short_side": 1080, "drop_frames": True}
    assert render_stage.fit_budget(seconds=1e6, rays_per_s=13_000, **fox)[:2] == (1.0, 120)
    scale, frames, reason = render_stage.fit_budget(seconds=1200, rays_per_s=13_000, **fox)  # 5.3 h asked for
    assert frames == 120 and 1080 * scale >= render_stage.MIN_SHORT_SIDE
    assert 120 * 1080 * 1920 * scale**2 / 13_000 == pytest.approx(1200, rel=1e-6) and "scaled" in reason
    scale, frames, reason = render_stage.fit_budget(seconds=200, rays_per_s=13_000, **fox)
    assert 1080 * scale == pytest.approx(render_stage.MIN_SHORT_SIDE) and render_stage.MIN_FRAMES <= frames < 120
    assert frames * 1080 * 1920 * scale**2 / 13_000 <= 200 and "frames" in reason
    _, frames, reason = render_stage.fit_budget(seconds=1, rays_per_s=13_000, **fox)
    assert frames == render_stage.MIN_FRAMES and "over" in reason
    replay = {**fox, "drop_frames": False}
    assert render_stage.fit_budget(seconds=1, rays_per_s=13_000, **replay)[1] == 120


def test_time_budget_bounds_the_video_and_is_recorded(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    assert 80 * 33 * 25 > render_stage.PREVIEW_VIEWS * render_stage.PREVIEW_RAYS  # worth measuring
    roomy = render_stage.run(render_stage.Config(run_dir=run_dir, out=tmp_path / "a.mp4", frames=80, max_seconds=600))
    assert roomy.n_frames == 80
    budget = json.loads((tmp_path / "a.manifest.json").read_text())["used"]["budget"]
    assert budget["reason"].startswith("fits") and budget["preview"]["rays_per_s"] > 0
    tight = render_stage.run(render_stage.Config(run_dir=run_dir, out=tmp_path / "b.mp4", frames=80, max_seconds=1e-3))
    assert tight.n_frames == render_stage.MIN_FRAMES == _read_video(tight.video).shape[0]
    budget = json.loads((tmp_path / "b.manifest.json").read_text())["used"]["budget"]
    assert budget["asked"]["frames"] == 80 and budget["chosen"]["frames"] == render_stage.MIN_FRAMES
    assert budget["chosen"]["size_hw"] == [25, 33]  # already under the short-side floor: not shrunk
    # fewer frames play slower, so the video keeps the asked length: 24 of 80 at 30 fps -> 9 fps (>= MIN_FPS)
    assert budget["fps"]["chosen"] == pytest.approx(max(render_stage.MIN_FPS, 30 * 24 / 80))
    assert json.loads((tmp_path / "b.manifest.json").read_text())["used"]["fps"] == budget["fps"]["chosen"]
    assert "fps" not in json.loads((tmp_path / "a.manifest.json").read_text())["used"]["budget"]
    small = render_stage.run(render_stage.Config(run_dir=run_dir, out=tmp_path / "c.mp4", frames=5, max_seconds=1e-3))
    assert small.n_frames == 5  # fewer pixels than the speed preview: rendered as asked
    assert "as asked" in json.loads((tmp_path / "c.manifest.json").read_text())["used"]["budget"]["reason"]


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"outputs": ("rgb", "normals")}, "--outputs"),
        ({"path": "zigzag"}, "--path"),
        ({"out": Path("x.avi")}, ".mp4"),
        ({"frames": 0}, "^frames:"),
        ({"elevation": 95.0}, "^elevation:"),
        ({"fps": 0}, "--fps"),
        ({"max_seconds": 0.0}, "--max-seconds"),
    ],
)
def test_bad_inputs_are_one_line_user_errors(sphere_run, tmp_path, changes, match):
    run_dir, _ = sphere_run
    config = {"run_dir": run_dir, "out": tmp_path / "o.mp4", "frames": 2, **changes}
    with pytest.raises(UserError, match=match) as e:
        render_stage.run(render_stage.Config(**config))
    assert "\n" not in str(e.value)
    assert not (tmp_path / "o.mp4").exists()


def test_missing_run_dir_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="run directory not found"):
        render_stage.run(render_stage.Config(run_dir=tmp_path / "nope", out=tmp_path / "o.mp4"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="checkpoint.pt"):
        render_stage.run(render_stage.Config(run_dir=tmp_path / "empty", out=tmp_path / "o.mp4"))


def test_parse_outputs():
    assert render_stage.parse_outputs("rgb, depth") == ("rgb", "depth")
    for bad in ("", "rgb,rgb", "rgb,normal"):
        with pytest.raises(UserError):
            render_stage.parse_outputs(bad)


def test_psnr_is_capped_for_identical_images():
    a = np.random.default_rng(0).random((4, 4, 3))
    assert psnr(a, a) == pytest.approx(100.0)
    assert psnr(a, a + 0.1) == pytest.approx(20.0, abs=1e-6)
    assert math.isfinite(psnr(a, 1 - a))


# --- integration: a real (2-step) training run -------------------------------------------------------------


def train_tiny_run(root: Path, kind: str = "posed") -> Path:
    """A synthetic scene and a 2-step training on it (seconds on CPU): a real `load_trained` run dir."""
    from nerfpipe.stages import scene as scene_stage
    from nerfpipe.stages import train

    scene_dir = root / "scene"
    scene_stage.run(scene_stage.Config(out_dir=scene_dir, kind=kind, size=24, views=10, seed=0))
    train.run(
        train.Config(
            scene_dir=scene_dir,
            run_dir=root / "run",
            max_steps=2,
            max_seconds=60.0,
            batch_rays=256,
            options=DensityOptions(resolution=(16, 24), occupancy_resolution=16),
            eval_every=0,
            final_eval_views=1,
            device="cpu",
        )
    )
    return root / "run"


def test_render_from_a_real_training_run(tmp_path):
    run_dir = train_tiny_run(tmp_path)
    out = render_stage.run(
        render_stage.Config(
            run_dir=run_dir, out=tmp_path / "v.mp4", frames=3, device="cpu", outputs=("rgb", "depth", "accumulation")
        )
    )
    video = _read_video(out.video)
    assert video.shape == (3, 24, 72, 3)
    manifest = (tmp_path / "v.manifest.json").read_text()
    assert '"stage": "render"' in manifest and '"radius_scene"' in manifest and '"largest_gap_deg"' in manifest
