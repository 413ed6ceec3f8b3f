"""Pose refinement: SE(3) maps (round trips, float64 gradchecks near 0 and pi), camera corrections against
regenerated rays, off by default, the run's refined cameras, and recovery of perturbed poses on a tiny scene."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.bench_refine import perturb_scene
from nerfpipe.data.transforms import read_scene
from nerfpipe.model import load_trained
from nerfpipe.model.camera_opt import (
    TEST_POSE_OPT_RULE,
    TRANSLATION_STEP,
    CameraOpt,
    CameraSchedule,
    TrustRegion,
    align_test_poses,
    correction_sizes,
    guard_record,
    pivot_depths,
    pivoted_exp,
)
from nerfpipe.model.methods.density import DensityOptions
from nerfpipe.radiance.align import pose_errors
from nerfpipe.radiance.camera import Intrinsics, generate_rays
from nerfpipe.radiance.se3 import se3_exp, se3_log, so3_exp, so3_log
from nerfpipe.stages import eval as eval_stage
from nerfpipe.stages import scene as scene_stage
from nerfpipe.stages import train

ANGLES = [0.0, 1e-12, 1e-7, 1e-4, 0.3, 2.0, math.pi - 1e-3, math.pi - 1e-7, math.pi]


def _twists(angle: float, n: int = 6, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(n, 3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm(dim=1, keepdim=True)
    return torch.cat([axis * angle, torch.randn(n, 3, generator=g, dtype=torch.float64)], dim=1)


@pytest.mark.parametrize("angle", ANGLES)
def test_se3_round_trip(angle):
    xi = _twists(angle)
    m = se3_exp(xi)
    rot = m[:, :3, :3]
    assert torch.allclose(rot.transpose(1, 2) @ rot, torch.eye(3, dtype=torch.float64).expand(6, 3, 3), atol=1e-14)
    assert torch.allclose(torch.linalg.det(rot), torch.ones(6, dtype=torch.float64), atol=1e-14)
    back = se3_log(m)
    assert torch.allclose(se3_exp(back), m, atol=1e-12)
    if angle < math.pi - 1e-3:  # at pi the axis sign is ambiguous; the transform above still matches
        assert torch.allclose(back, xi, atol=1e-10)
    assert float(back[:, :3].norm(dim=1).max()) <= math.pi + 1e-12


def test_so3_matches_rodrigues_and_float32_is_finite():
    w = torch.tensor([[0.0, 0.0, math.pi / 2]], dtype=torch.float64)
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert torch.allclose(so3_exp(w)[0], expected, atol=1e-15)
    for angle in ANGLES:
        xi = _twists(angle).float().requires_grad_()
        m = se3_exp(xi)
        (m.sum() + so3_log(m[:, :3, :3].detach().requires_grad_()).sum()).backward()
        assert torch.isfinite(m).all() and torch.isfinite(xi.grad).all()


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-3, 0.5, 2.5, math.pi - 1e-3])
def test_gradcheck_float64(angle):
    xi = _twists(angle, n=2).requires_grad_()
    assert torch.autograd.gradcheck(se3_exp, (xi,))
    m = se3_exp(xi.detach()).requires_grad_()
    assert torch.autograd.gradcheck(se3_log, (m,), atol=1e-6)


def _camera(seed: int) -> np.ndarray:
    g = np.random.default_rng(seed)
    m = np.eye(4)
    q, _ = np.linalg.qr(g.normal(size=(3, 3)))
    m[:3, :3] = q * np.sign(np.linalg.det(q))
    m[:3, 3] = g.normal(size=3) * 3
    return m


def test_corrections_equal_rays_of_the_refined_cameras():
    intr = Intrinsics(w=8, h=6, fx=7.0, fy=7.0, cx=4.0, cy=3.0)
    poses = np.stack([_camera(s) for s in range(3)])
    cams = CameraOpt(poses, focal=True, pivot=np.array([0.0, 2.0, 5.0])).double()
    with torch.no_grad():
        cams.load_dict(
            {
                "delta": torch.randn(3, 6, generator=torch.Generator().manual_seed(1)).double() * 0.1,
                "pivot": cams.pivot,
                "log_focal": cams.log_focal.detach(),
            }
        )
        cams.log_focal.fill_(math.log(1.1))
    refined = cams.refined()
    scaled = Intrinsics(w=8, h=6, fx=7.7, fy=7.7, cx=4.0, cy=3.0)
    for k in range(3):
        o, d = generate_rays(intr, torch.as_tensor(poses[k]))
        o = o.expand_as(d).double()
        o2, d2 = cams(o, d.double(), torch.full((d.shape[0],), k))
        o_ref, d_ref = generate_rays(scaled, torch.as_tensor(refined[k]))
        assert torch.allclose(o2, o_ref.expand_as(d_ref).double(), atol=1e-12)
        assert torch.allclose(d2, d_ref.double(), atol=1e-12)


def test_pivoted_corrections_turn_about_the_pivot():
    """About a pivot at depth p the correction is the conjugate T(p) exp(xi) T(-p): a pure rotation keeps the
    pivot (0, 0, -p) where it is, p = 0 is the plain exponential, and the pivot depth is the scene centre's."""
    xi = torch.randn(4, 6, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.2
    depth = torch.tensor([0.0, 1.0, 3.0, 10.0], dtype=torch.float64)
    m = pivoted_exp(xi, depth)
    shift = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    shift[:, 2, 3] = -depth
    assert torch.allclose(m, shift @ se3_exp(xi) @ torch.linalg.inv(shift), atol=1e-12)
    assert torch.allclose(pivoted_exp(xi, torch.zeros(4, dtype=torch.float64)), se3_exp(xi), atol=1e-15)
    rot = torch.cat([xi[:, :3], torch.zeros(4, 3, dtype=torch.float64)], dim=1)
    pivot = torch.stack([torch.zeros(4), torch.zeros(4), -depth, torch.ones(4)], dim=1).double()  # [4, 4]
    assert torch.allclose((pivoted_exp(rot, depth) @ pivot[:, :, None])[..., 0], pivot, atol=1e-12)
    cam = np.eye(4)
    cam[:3, 3] = [0.0, 0.0, 4.0]  # looking down -z at the origin from 4 away; a point behind gets 0
    assert np.allclose(pivot_depths(cam[None], np.zeros(3)), [4.0])
    assert np.allclose(pivot_depths(cam[None], np.array([1.0, 0.0, 5.0])), [0.0])
    xi.requires_grad_()
    assert torch.autograd.gradcheck(lambda x: pivoted_exp(x, depth), (xi,))


def test_zero_corrections_leave_rays_and_schedule_waits():
    poses = np.stack([_camera(s) for s in range(2)])
    o, d = torch.randn(5, 3), torch.nn.functional.normalize(torch.randn(5, 3), dim=1)
    o2, d2 = CameraOpt(poses)(o, d, torch.tensor([0, 1, 1, 0, 1]))
    assert torch.allclose(o2, o, atol=1e-6) and torch.allclose(d2, d, atol=1e-6)
    s = CameraSchedule(delay=0.1, warmup=0.2, decay=1.0)
    assert s.factor(0.05) == 0.0 and s.factor(0.2) == pytest.approx(0.5) and s.factor(0.9) == 1.0


def test_test_poses_follow_a_similarity_of_the_training_cameras():
    train_in = np.stack([_camera(s) for s in range(6)])
    sim = np.eye(4)
    sim[:3, :3] = 2.0 * _camera(9)[:3, :3]
    sim[:3, 3] = [0.1, -0.2, 0.3]
    refined = sim @ train_in
    refined[:, :3, :3] /= 2.0
    test = np.stack([_camera(20)])
    mapped, record = align_test_poses(train_in, refined, test)
    expected = sim @ test[0]
    expected[:3, :3] /= 2.0
    assert np.allclose(mapped[0], expected, atol=1e-9) and record["scale"] == pytest.approx(2.0)


def _ring(n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """n cameras on a circle of radius 3 looking at the origin, and their pivot depths (3)."""
    poses = []
    for k in range(n):
        a = 2 * math.pi * k / n
        back = np.array([math.cos(a), math.sin(a), 0.0])  # +z of the camera: away from the origin
        right = np.cross([0.0, 0.0, 1.0], back)
        m = np.eye(4)
        m[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
        m[:3, 3] = 3 * back
        poses.append(m)
    poses = np.stack(poses)
    return poses, pivot_depths(poses, np.zeros(3))


def _set_delta(cams: CameraOpt, delta: torch.Tensor) -> None:
    with torch.no_grad():
        cams.raw.copy_(delta / cams.step_scale)


def _sizes(cams: CameraOpt) -> tuple[np.ndarray, np.ndarray]:
    theta, moved = correction_sizes(cams.delta.detach().double(), cams.pivot, cams.distance)
    return np.degrees(theta.numpy()), moved.numpy()


def test_guard_pulls_back_corrections_past_the_bound():
    """A rotation past 10 deg goes back onto the bound about the same axis with the camera centre kept; a centre
    displacement past 10 % of the distance is shortened onto it with the rotation kept; the others are untouched,
    those cameras' Adam moments are zeroed, and the record names them."""
    poses, pivot = _ring(5)
    cams = CameraOpt(poses, pivot=pivot, trust=TrustRegion(max_rotation_deg=10.0, max_translation=0.1)).double()
    assert np.allclose(pivot, 3.0) and np.allclose(cams.distance.numpy(), 3.0)
    delta = torch.zeros(5, 6, dtype=torch.float64)
    delta[0] = torch.tensor([0.05, -0.02, 0.36, 0.05, 0.0, 0.01])  # 20.9 deg, mostly a roll; centre 1.7 %
    delta[1, 3:] = torch.tensor([0.6, 0.3, -0.2])  # moves the centre by 0.7 = 23 % of 3
    delta[2] = torch.tensor([0.01, 0.0, 0.02, 0.03, -0.02, 0.01])  # small: inside
    _set_delta(cams, delta)
    centre_before = pivoted_exp(cams.delta.detach(), cams.pivot)[0, :3, 3].clone()
    cams.raw.grad = torch.ones_like(cams.raw)
    cams.optimizer().step()  # Adam moments exist for every camera
    _set_delta(cams, delta)
    cams.guard(step=7)
    rot, moved = _sizes(cams)
    assert rot[0] == pytest.approx(10.0, abs=1e-9) and moved[1] == pytest.approx(0.1, abs=1e-9)
    after = cams.delta.detach()
    axis = delta[0, :3] / delta[0, :3].norm()
    assert torch.allclose(after[0, :3] / after[0, :3].norm(), axis, atol=1e-12)  # same axis
    assert torch.allclose(pivoted_exp(after, cams.pivot)[0, :3, 3], centre_before, atol=1e-12)  # centre kept
    assert torch.allclose(after[1, :3], delta[1, :3], atol=1e-12)  # rotation (none) kept
    assert torch.allclose(after[2:], delta[2:], atol=1e-12)
    state = cams.optimizer().state[cams.raw]
    assert (state["exp_avg"][:2] == 0).all() and (state["exp_avg_sq"][:2] == 0).all()
    assert (state["exp_avg"][2:] != 0).all()
    assert cams.log.pulled_back == 2 and cams.log.cameras == [0, 1] and cams.log.first_step == 7
    assert cams.log.stopped_at is None and cams.log.largest_rotation_deg == pytest.approx(20.856, abs=1e-3)
    record = guard_record(cams, [f"c{k}" for k in range(5)])
    assert record["cameras_pulled_back"] == ["c0", "c1"] and record["pulled_back"] == 2 and not record["stopped"]
    assert record["bounds"] == {"max_rotation_deg": 10.0, "max_translation": 0.1, "stop_median": 0.5}
    assert len(record["suspect"]) == 1 and "2 of 5 cameras pulled back" in record["summary"]


def test_guard_stops_refinement_and_resets_to_the_input_cameras():
    """When the median correction passes half its bound, every correction goes back to zero, the record says at
    which step and how large they were, later steps move nothing, and a reload keeps the stop."""
    poses, pivot = _ring(5)
    cams = CameraOpt(poses, pivot=pivot, focal=True, schedule=CameraSchedule(delay=0.0, warmup=0.0)).double()
    delta = torch.zeros(5, 6, dtype=torch.float64)
    delta[:, 2] = math.radians(6.0)  # every camera rolled by 6 deg: 0.6 of the bound
    _set_delta(cams, delta)
    with torch.no_grad():
        cams.log_focal.fill_(0.05)
    cams.guard(step=12)
    assert cams.log.stopped_at == 12 and cams.log.at_stop["median_rotation_deg"] == pytest.approx(6.0)
    assert (cams.raw == 0).all() and float(cams.log_focal.detach()) == 0.0
    assert np.allclose(cams.refined(), poses, atol=1e-12)
    cams.raw.grad = torch.ones_like(cams.raw)
    cams.step(0.5, step=13)
    assert (cams.raw == 0).all()
    record = guard_record(cams, [f"c{k}" for k in range(5)])
    assert record["stopped"] and record["stopped_at_step"] == 12 and record["median_share"] == 0.0
    assert "stopped at step 12" in record["suspect"][0]
    again = CameraOpt(poses, pivot=pivot, focal=True).double()
    again.load_dict(cams.to_dict())
    assert again.log.stopped_at == 12
    again.raw.grad = torch.ones_like(again.raw)
    again.step(0.5)
    assert (again.raw == 0).all()


def test_translation_unit_is_the_distance_to_the_scene_centre():
    """The translation steps and bounds are in units of each camera's distance to the scene centre (its pivot
    depth): the same share of it at any scene scale; a camera without a pivot takes the median one."""
    poses, pivot = _ring(5)
    pivot[0] = 0.0
    small = poses.copy()
    small[:, :3, 3] *= 0.1
    for w, p, d in ((poses, pivot, 3.0), (small, 0.1 * pivot, 0.3)):
        cams = CameraOpt(w, pivot=p)
        assert np.allclose(cams.distance.numpy(), d)
        assert torch.allclose(cams.step_scale[:, 3:], torch.full((5, 3), TRANSLATION_STEP * d))
    assert np.allclose(CameraOpt(poses).distance.numpy(), 3.0)  # no pivots: the cameras' spread about their mean


def test_guard_leaves_corrections_inside_the_bounds():
    """The benchmark's perturbation (3 deg, 3 %) is well inside: nothing pulled back, no stop, no suspicion."""
    poses, pivot = _ring(5)
    cams = CameraOpt(poses, pivot=pivot).double()
    delta = torch.randn(5, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    delta[:, :3] *= math.radians(3.0) / delta[:, :3].norm(dim=1, keepdim=True)
    delta[:, 3:] *= 0.03 * 3 / delta[:, 3:].norm(dim=1, keepdim=True)
    _set_delta(cams, delta)
    cams.guard(step=1)
    assert torch.allclose(cams.delta.detach(), delta, atol=1e-15) and cams.log.pulled_back == 0
    record = guard_record(cams, [f"c{k}" for k in range(5)])
    assert record["suspect"] == [] and not record["stopped"] and record["median_share"] < 0.5


def test_gauge_basis_is_a_common_similarity_and_fix_gauge_removes_it():
    """gauge_basis g is, to first order, the correction that moves every camera by one small similarity (rotation,
    translation, scale of the world); fix_gauge removes such a part and keeps what is left."""
    poses, _ = _camera_ring_3d()
    pivot = pivot_depths(poses, np.array([0.1, -0.2, 0.0]))
    cams = CameraOpt(poses, pivot=pivot).double()
    g = torch.tensor([0.3, -0.2, 0.5, 1.0, -0.4, 0.2, 0.6], dtype=torch.float64) * 1e-6
    w = torch.as_tensor(poses)
    centre = w[:, :3, 3].mean(0)
    rot = so3_exp(g[None, :3])[0]
    moved = w.clone()
    moved[:, :3, :3] = rot @ w[:, :3, :3]
    moved[:, :3, 3] = (1 + g[6]) * (w[:, :3, 3] - centre) @ rot.T + centre + g[3:6]
    shift = torch.eye(4, dtype=torch.float64).repeat(len(w), 1, 1)
    shift[:, 2, 3] = -cams.pivot
    exact = se3_log(torch.linalg.inv(shift) @ torch.linalg.inv(w) @ moved @ shift)  # [V, 6] about the pivots
    first_order = (cams.gauge_basis @ g).reshape(-1, 6)
    assert float((exact - first_order).abs().max()) < 1e-5 * float(first_order.abs().max())
    common = (cams.gauge_basis @ (g * 2e4)).reshape(-1, 6)  # about a degree and 2 % of the distance
    own = torch.randn(len(w), 6, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 0.02
    own = own - (cams.gauge_basis @ (cams.gauge_solve @ own.reshape(-1))).reshape(-1, 6)  # no common part
    _set_delta(cams, own + common)
    cams.fix_gauge()
    assert torch.allclose(cams.delta.detach(), own, atol=1e-12)


def _camera_ring_3d(n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """n cameras at several heights around the origin, looking at it (OpenGL axes)."""
    poses = []
    for k in range(n):
        a, elev = 2 * math.pi * k / n, math.radians(15 + 30 * (k % 3) / 2)
        back = np.array([math.cos(a) * math.cos(elev), math.sin(a) * math.cos(elev), math.sin(elev)])
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
        m[:3, 3] = (2.5 + 0.1 * k) * back
        poses.append(m)
    return np.stack(poses), np.zeros(3)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("refine")
    scene_stage.run(scene_stage.Config(out_dir=root / "exact", kind="rgba", size=24, views=12, seed=0))
    return root / "exact", perturb_scene(root / "exact", root / "perturbed", 3.0, 0.03)


TINY_GRID = DensityOptions(resolution=(16, 24), occupancy_resolution=16)
REFINE = train.RefineOptions()


def tiny_config(scene_dir: Path, run_dir: Path, **kw) -> train.Config:
    """A few-step CPU train config on a tiny grid (test_appearance uses it too)."""
    base = dict(
        scene_dir=scene_dir,
        run_dir=run_dir,
        max_steps=3,
        max_seconds=600.0,
        batch_rays=256,
        options=TINY_GRID,
        log_every=1,
        eval_every=0,
        final_eval_views=1,
        device="cpu",
        threads=1,
    )
    base.update(kw)
    return train.Config(**base)


def _losses(run_dir: Path) -> list[str]:
    return [line.split(",")[2] for line in (run_dir / "metrics.csv").read_text().splitlines()[1:4]]


def test_off_by_default_and_identity_at_start(tiny, tmp_path):
    """Defaults: no corrections in the checkpoint, the manifest says why. Switched on, the first step's loss is
    the default run's (corrections start at zero and wait for the warm-up delay)."""
    assert train.Config(scene_dir=Path("s"), run_dir=Path("r")).refine is None
    off = train.run(tiny_config(tiny[1], tmp_path / "off"))
    state = torch.load(off.checkpoint, weights_only=True)
    assert state["camera_opt"] is None
    assert "pose_refinement" in json.loads(off.manifest.read_text())["left_out"]
    assert not (tmp_path / "off" / "transforms.json").exists()
    on = train.run(tiny_config(tiny[1], tmp_path / "on", refine=REFINE))
    assert float(_losses(tmp_path / "on")[0]) == pytest.approx(float(_losses(tmp_path / "off")[0]), rel=1e-5)
    assert on.steps == off.steps


def test_refinement_trains_coarse_to_fine_by_default(tiny, tmp_path):
    """--refine-poses starts the grid at a quarter of its final size and upsamples later (BARF's coarse-to-fine in
    grid terms); without it the defaults are as before; asked-for values win."""
    from nerfpipe.model.methods.density.defaults import REFINE_UPSAMPLE_AT, UPSAMPLE_AT

    auto = DensityOptions(occupancy_resolution=16)
    asked = DensityOptions(upsample_at=(0.1,), resolution=(16, 24), occupancy_resolution=16)
    configs = {}
    for name, extra in (("off", {}), ("on", {"refine": REFINE}), ("asked", {"refine": REFINE, "options": asked})):
        train.run(tiny_config(tiny[1], tmp_path / name, **{"options": auto, "max_steps": 1, **extra}))
        configs[name] = json.loads((tmp_path / name / "config.json").read_text())["options"]
    r1 = configs["off"]["resolution"][1]
    assert configs["off"]["resolution"][0] == 64 and tuple(configs["off"]["upsample_at"]) == UPSAMPLE_AT
    assert configs["on"]["resolution"] == [max(16, round(r1 / 4)), r1]
    assert tuple(configs["on"]["upsample_at"]) == REFINE_UPSAMPLE_AT
    assert configs["asked"]["resolution"] == [16, 24] and configs["asked"]["upsample_at"] == [0.1]


def test_perturbed_poses_are_recovered(tiny, tmp_path):
    """Joint refinement on a tiny scene: the median rotation error (after similarity alignment) falls clearly;
    render/eval see the refined cameras, train writes them, the manifest lists each camera's correction."""
    exact, perturbed = read_scene(tiny[0]), read_scene(tiny[1])
    idx = exact.split("train")
    truth = np.stack([exact.frames[i].world_from_cam for i in idx])
    before = pose_errors(np.stack([perturbed.frames[i].world_from_cam for i in idx]), truth).median_rotation_deg
    run = tmp_path / "run"
    out = train.run(
        tiny_config(tiny[1], run, max_steps=600, max_seconds=1e5, batch_rays=512, refine=REFINE, log_every=100)
    )
    trained = load_trained(run, "cpu")
    after = pose_errors(np.stack([trained.scene.frames[i].world_from_cam for i in idx]), truth).median_rotation_deg
    assert 2.5 < before < 3.5  # 3 degrees each, a little of it absorbed by the alignment
    assert after < 0.7 * before, (before, after)  # 3.07 -> 1.49 deg after 600 steps (pivoted corrections)
    written = json.loads((run / "transforms.json").read_text())  # image paths relative to the run directory
    assert len(written["frames"]) == len(exact.frames)
    assert (run / written["frames"][0]["file_path"]).resolve() == perturbed.image_path(0)
    used = json.loads(out.manifest.read_text())["used"]["pose_refinement"]
    assert len(used["per_camera"]) == len(idx) and used["median_rotation_deg"] > 1.0
    assert not used["guard"]["stopped"] and used["guard"]["suspect"] == [], used["guard"]
    assert trained.pose_refinement["test_poses"]["method"] == "similarity"
    plain = eval_stage.run(
        eval_stage.Config(run_dir=run, out=tmp_path / "e.json", device="cpu", views=1, test_pose_steps=0)
    ).result
    assert plain["test_pose_optimisation"] is None and plain["test_poses"]["method"] == "similarity"
    tuned = eval_stage.run(
        eval_stage.Config(run_dir=run, out=tmp_path / "t.json", device="cpu", views=1, test_pose_steps=3)
    ).result
    assert tuned["test_poses"] == TEST_POSE_OPT_RULE and tuned["test_pose_optimisation"]["steps"] == 3
    assert 0 < tuned["test_pose_optimisation"]["median_rotation_deg"] < 1.0
    default = eval_stage.run(eval_stage.Config(run_dir=run, out=tmp_path / "d.json", device="cpu", views=1)).result
    assert default["test_pose_optimisation"]["steps"] == eval_stage.TEST_POSE_STEPS  # refined runs: on by default


STOP_AT = 12


def _stopping_guard(monkeypatch) -> None:
    """Make the guard stop refinement at training step STOP_AT whatever the corrections' size."""
    guard = CameraOpt.guard

    def stop_at(self, step: int) -> None:
        guard(self, step)
        if self.log.stopped_at is None and step >= STOP_AT:
            self.log.at_stop = {"median_share": 0.0}
            self.stop(step)

    monkeypatch.setattr(CameraOpt, "guard", stop_at)


def _field_after_each_step(monkeypatch) -> dict[int, dict]:
    """Record the field's parameters after every training step of the next run."""
    from nerfpipe.stages.train.loop import Loop

    kept: dict[int, dict] = {}
    step = Loop.train_step

    def recording(self, lr: float) -> bool:
        ok = step(self, lr)
        kept[self.step + 1] = {k: v.detach().clone() for k, v in self.model.field.state_dict().items()}
        return ok

    monkeypatch.setattr(Loop, "train_step", recording)
    return kept


def test_a_stopped_refinement_takes_the_field_back_to_before_the_cameras_moved(tiny, tmp_path, monkeypatch):
    """When the guard stops refinement, the field goes back to its state at the cameras' first move (what it
    learned against cameras that ran away does not stay in it), the manifest says so, and later steps use the input
    cameras. Checked against a run without refinement: its field after the step of the first move is the refined
    run's at the stop (the same rays up to then: corrections start at zero)."""
    grid = DensityOptions(resolution=(24, 24), upsample_at=(), occupancy_resolution=16)
    kw = dict(max_steps=STOP_AT, options=grid, log_every=100)
    recorded = _field_after_each_step(monkeypatch)
    train.run(tiny_config(tiny[1], tmp_path / "plain", **kw))
    plain_fields = dict(recorded)  # the refined run records over it
    _stopping_guard(monkeypatch)
    fast_cameras = train.RefineOptions(camera_lr=0.03)  # the cameras move in a few steps
    out = train.run(tiny_config(tiny[1], tmp_path / "refined", refine=fast_cameras, **kw))
    guard = json.loads(out.manifest.read_text())["used"]["pose_refinement"]["guard"]
    first = guard["field_rolled_back_to_step"]
    assert guard["stopped_at_step"] == STOP_AT and first is not None and 1 < first < STOP_AT - 3, guard
    assert f"the field went back to its state at step {first}" in guard["suspect"][0]
    refined = torch.load(out.checkpoint, weights_only=True)["field"]
    for name, value in plain_fields[first].items():
        assert torch.allclose(refined[name], value, rtol=1e-4, atol=1e-6), name
    moved = plain_fields[STOP_AT]  # the plain field kept learning after the first move: the check can fail
    assert not all(torch.allclose(refined[k], v, rtol=1e-4, atol=1e-6) for k, v in moved.items())
    scored = eval_stage.run(
        eval_stage.Config(run_dir=tmp_path / "refined", out=tmp_path / "e.json", device="cpu", views=1)
    ).result
    assert scored["test_pose_optimisation"] is None  # the input cameras were kept: test views as given
    stopped = f"as in transforms.json: the guard stopped pose refinement at step {STOP_AT}"
    assert scored["test_poses"].startswith(stopped)


def test_on_a_plain_background_refinement_trains_the_object_on_a_random_colour(tmp_path, monkeypatch):
    """A scene rendered on white (plain mode): without refinement every opaque pixel trains on white; with it the
    object's pixels (opaque, not white) get a random colour too, so the object must be opaque (`Views.mask_colour`
    opaque_object: on white, refinement ran away); the background's reason says so."""
    scene_stage.run(scene_stage.Config(out_dir=tmp_path / "posed", kind="posed", size=24, views=12, seed=0))
    from nerfpipe.model.background import Background

    seen: list[tuple[torch.Tensor, torch.Tensor]] = []
    plain_colour = Background.train_colour

    def spy(self, n, generator=None, random=None):
        colour = plain_colour(self, n, generator, random)
        seen.append((random.clone(), colour.clone()))
        return colour

    monkeypatch.setattr(Background, "train_colour", spy)
    shares = {}
    for name, refine in (("plain", None), ("refined", REFINE)):
        seen.clear()
        out = train.run(tiny_config(tmp_path / "posed", tmp_path / name, refine=refine))
        used = json.loads(out.manifest.read_text())["used"]
        assert used["background"]["mode"] == "plain"
        assert ("pose refinement: the object's pixels" in used["defaults"]["background"]) == (refine is not None)
        random = torch.cat([r for r, _ in seen])
        colour = torch.cat([c for _, c in seen])
        assert (colour[~random] == 1.0).all()  # the rest on the plain white
        shares[name] = float(random.float().mean())
    # the transparent background is random in both; with refinement the object is too
    assert 0.2 < shares["plain"] < shares["refined"] and shares["refined"] > shares["plain"] + 0.05, shares
