"""Pose refinement (NeRF--, BARF, nerfstudio's camera optimiser): per-camera SE(3) corrections, optionally one
shared focal scale, optimised jointly with the field by their own Adam, learning rate and warm-up.

Conventions (docs/DESIGN.md): cameras `world_from_cam` 4x4, OpenGL axes (x right, y up, looking down -z), scene
frame. Camera k's correction xi_k = (omega, v) [6] acts in its own camera frame:
    world_from_cam_refined = world_from_cam @ se3_exp(xi_k)      (radiance.se3)
so a ray (o, d) of that camera becomes d' = R R_d R^T d and o' = o + R t_d (R: the original rotation; R_d, t_d:
the correction's). The correction is parameterised about a pivot on the optical axis, at the depth p_k of the
scene centre (CamP, Park et al. 2023, on why the parameterisation matters):
    se3_exp(xi_k) is replaced by  T(p_k) se3_exp(xi_k) T(-p_k),   T(p) = translation by (0, 0, -p)
so omega turns the camera about the object it looks at (an orbit, which changes the view only through parallax)
and v shifts it (which moves the whole image): the weakly and strongly observed motions fall on different
coordinates, and Adam's per-coordinate step sizes move the weak one as fast as the strong one. About the camera
centre (p_k = 0) an orbit is a mix of omega and v whose gradient the image shift swamps. p_k = 0 gives the plain
camera-frame correction (runs from before the pivot load that way).
The focal scale s = exp(log_s) multiplies fx and fy of every camera: a ray's direction in the camera frame
(x, y, -1) / norm becomes (x / s, y / s, -1) / norm (exact for pinhole cameras; the distortion of
the original intrinsics is kept as it was). Corrections start at zero (the identity): with refinement off the
rays are untouched.

Adam's steps (`step_scale`): the orbit angles at ORBIT_STEP of the rate, the translation at TRANSLATION_STEP times
the camera's distance to the scene centre (the same share of the distance at any scene scale). After every step
`CameraOpt.fix_gauge` removes the part of the corrections that moves all cameras by one similarity (`gauge_basis`:
rotation, translation and scale of the world, to first order): the field could follow such a motion, so the photos
hardly resist it, and Adam lets it drift; the input cameras' frame is kept instead.

Trust region (`TrustRegion`, applied after every camera step by `CameraOpt.guard`): the size of a correction is
its rotation angle theta_k (degrees) and its camera-centre displacement tau_k as a fraction of the camera's distance
d_k to the scene centre (both independent of the pivot: they measure the refined camera against the input one). A
correction past a bound is projected back onto it (the rotation angle scaled down about the same axis, the centre
displacement shortened along its direction) and that camera's Adam moments are zeroed; when the median over
cameras of max(theta_k / max_rotation, tau_k / max_translation) passes `stop_median`, refinement stops for the
rest of the run: every correction (and the focal scale) goes back to zero and the field keeps training on the
input cameras. `guard_record` is what the manifest gets (`pose_report`'s "guard").

Rollback (the training loop, `stages.train.loop`): the field's state is copied at the cameras' first move (the field
has seen only the input cameras until then), and when the guard stops refinement the field goes back to that copy
(resampled to the grid's resolution of the moment), so what it learned against cameras that were running away does
not stay in it; `GuardLog.rolled_back_to` records the step of the copy. After a stop, rays skip the corrections (they
are the input cameras). Without the rollback the refined runs that the guard stopped ended under plain training
(docs/MEASUREMENTS.md, "Pose refinement"). A run resumed between the first move
and the stop has no copy: the stop then keeps the field as it is (`rolled_back_to` None).

Test views: the field learns in the frame the refined cameras define, which may drift from the input frame by a
small rigid motion (`fix_gauge` holds the first-order similarity, not its higher orders). `align_test_poses` fits a
similarity (Umeyama on camera centres) from the input training cameras to the refined ones and maps every other
camera through it (nerfstudio's and NeRF--'s alternative to optimising test poses against the frozen field: it
needs no render time, cannot fit the test photos' content, and with zero-mean pose noise on many cameras it
recovers the frame to a fraction of the noise).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from nerfpipe.data.transforms import Scene, write_scene
from nerfpipe.radiance.align import umeyama
from nerfpipe.radiance.camera import Intrinsics
from nerfpipe.radiance.se3 import hat, se3_exp, se3_log, so3_exp

__all__ = [
    "ORBIT_STEP",
    "TRANSLATION_STEP",
    "CameraSchedule",
    "TrustRegion",
    "GuardLog",
    "pivot_depths",
    "correction_sizes",
    "project_corrections",
    "pivoted_exp",
    "CameraOpt",
    "refined_scene",
    "align_test_poses",
    "corrections_record",
    "pose_report",
    "guard_record",
    "GUARD_RULE",
    "write_refined_transforms",
    "TEST_POSE_RULE",
    "TEST_POSE_OPT_RULE",
    "optimise_test_pose",
    "test_pose_placement",
]


ORBIT_STEP = 0.3
"""With pivots, the orbit angles (omega_x, omega_y) move at this fraction of the learning rate: Adam steps each
coordinate by about the rate whatever its gradient's size, and an orbit, seen only through parallax, has a noisy
gradient while the field is rough (at the full rate some runs lost a camera). At 0.1 (before 2026-12) the orbit
was still far from its true value at the end of the posed 100 px scene's 1200 steps (median rotation error 0.95
deg, 0.41 at 0.3); at 0.5 it overshot (the median camera 4.9 % off its input centre at step 266)."""
TRANSLATION_STEP = 0.4
"""With pivots, the translation (v) moves at this fraction of the learning rate times the camera's distance to
the scene centre, so a step is the same share of the distance at any scene scale (before 2026-12 it was the rate in
scene units: the tuned 0.01 a step at the bench scenes' 2.4 m, but 4 % of the distance a step on the same scene at
`scene --scale 0.1`, where the corrections ran to 20-60 % of the distance in 100 steps and ended worse than the
input poses). 0.4 keeps the bench scenes' step (0.4 x 2.4 ~ 1)."""


@dataclass(frozen=True, kw_only=True)
class CameraSchedule:
    """Learning rates and warm-up of the camera optimiser."""

    lr: float = 1e-2
    """Adam learning rate of the corrections at full strength: radians for the rotation (the orbit at
    `ORBIT_STEP` of it), `TRANSLATION_STEP` x the camera's distance to the scene centre for the translation."""
    focal_lr: float = 1e-3
    """Adam learning rate of the log focal scale."""
    delay: float = 0.1
    """Run-progress fraction before the cameras move (the field first needs a rough shape to register to: earlier,
    the cameras moved while the field was a fog and walked away from the truth first; docs/MEASUREMENTS.md, "Pose
    refinement")."""
    warmup: float = 0.05
    """Run-progress fraction over which the learning rate ramps linearly from 0 to `lr` (after `delay`)."""
    decay: float = 0.01
    """Final learning-rate factor at the end of the run (exponential, like the field's). With the pivoted
    corrections, bench_refine's perturbed scene (1200 steps, 1 thread): median rotation error 0.258 deg at 0.1,
    0.224 at 0.03, 0.176 at 0.02, 0.166 at 0.01 (about the camera centre, before the pivot: 0.37 at 0.1, 0.58 at
    0.01)."""

    def factor(self, frac: float) -> float:
        """Learning-rate factor at run progress frac in [0, 1]."""
        if frac < self.delay:
            return 0.0
        ramp = min(1.0, (frac - self.delay) / self.warmup) if self.warmup > 0 else 1.0
        return ramp * self.decay**frac


@dataclass(frozen=True, kw_only=True)
class TrustRegion:
    """How far refinement may move a camera (`CameraOpt.guard`; module docstring). The bounds sit far beyond what
    the poses of a capture that registered can be off by, and beyond what joint refinement can recover, so a
    correction that reaches them is the optimiser chasing the field's noise, not a pose error."""

    max_rotation_deg: float = 10.0
    """Largest rotation of a correction, degrees. COLMAP poses of a capture that registers are off by well under
    a degree (bench_poses: within 0.3 deg of instant-ngp's COLMAP poses), the refine benchmark perturbs by 3, and
    joint refinement from a rough field recovers a few degrees (NeRF--, and BARF's ~15 deg only with its
    coarse-to-fine encoding): past 10 deg a camera has left the basin it can be registered from."""
    max_translation: float = 0.15
    """Largest displacement of the camera centre, as a fraction of the camera's distance to the scene centre
    (its pivot depth). 5x the benchmark's 3 % and far more than a registered capture is off by; about what a turn
    about the scene centre at the rotation bound moves a camera (2 sin 5 deg = 17 %): a lower bound would pull back
    orbits the rotation bound allows. (At 10 %, runs that recovered their poses passed half the bound on the way:
    the orbit moves the centre by up to 5 % while it converges.)"""
    stop_median: float = 0.5
    """Refinement stops (every correction reset to zero) when the median camera's correction passes this share of
    its bound (the larger of its rotation and translation shares): a few cameras at the bound can be a few bad
    poses, most of them is the whole refinement running away. The benchmark's 3 deg / 3 % sits at 0.3."""

    def __post_init__(self) -> None:
        if not (self.max_rotation_deg > 0 and self.max_translation > 0 and 0 < self.stop_median <= 1):
            raise ValueError(f"expected bounds > 0 and 0 < stop_median <= 1, got {self}")


@dataclass
class GuardLog:
    """What the guard did during a run (kept in the checkpoint, so a resumed run continues it)."""

    pulled_back: int = 0
    """Camera-steps at which a correction was projected back onto a bound."""
    cameras: list[int] = dataclasses.field(default_factory=list)
    """Indices (into the training cameras) of the cameras pulled back at least once, ascending."""
    first_step: int | None = None
    """Training step of the first pull-back."""
    stopped_at: int | None = None
    """Training step at which refinement stopped (None: it ran to the end)."""
    at_stop: dict[str, float] | None = None
    """The corrections' sizes when it stopped (they are zero afterwards)."""
    largest_rotation_deg: float = 0.0
    """Largest rotation any correction reached (before a pull-back), degrees."""
    largest_translation: float = 0.0
    """Largest centre displacement any correction reached (before a pull-back), fraction of its distance."""
    rolled_back_to: int | None = None
    """After a stop: the training step whose field state the field went back to (the cameras' first move); None:
    no stop, or no copy to go back to (the field kept what it learned)."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, doc: dict[str, Any] | None) -> GuardLog:
        return cls() if doc is None else cls(**{k: doc[k] for k in doc if k in cls.__dataclass_fields__})


def pivot_depths(world_from_cam: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Depth [V] of the point `centre` [3] along each camera's optical axis (-z), 0 where it is behind."""
    w = np.asarray(world_from_cam, dtype=np.float64)
    if w.ndim != 3 or w.shape[1:] != (4, 4) or np.shape(centre) != (3,):
        raise ValueError(f"expected world_from_cam [V, 4, 4] and centre [3], got {w.shape}, {np.shape(centre)}")
    rel = np.asarray(centre, dtype=np.float64) - w[:, :3, 3]  # [V, 3]
    return np.maximum(-np.einsum("vi,vi->v", rel, w[:, :3, 2]), 0.0)


def pivoted_exp(delta: Tensor, pivot: Tensor) -> Tensor:
    """Corrections delta [V, 6] about pivots at depths pivot [V] on the optical axes -> [V, 4, 4]:
    T(p) se3_exp(delta) T(-p) with T(p) the translation by (0, 0, -p) (conjugation only moves the translation:
    t' = t + (I - R) (0, 0, -p))."""
    if delta.ndim != 2 or delta.shape[-1] != 6 or pivot.shape != delta.shape[:1]:
        raise ValueError(f"expected delta [V, 6] and pivot [V], got {tuple(delta.shape)}, {tuple(pivot.shape)}")
    m = se3_exp(delta)  # [V, 4, 4]
    p = torch.zeros_like(delta[:, :3])
    p[:, 2] = -pivot.to(delta)
    t = m[:, :3, 3] + p - (m[:, :3, :3] @ p[:, :, None])[..., 0]
    return torch.cat([torch.cat([m[:, :3, :3], t[:, :, None]], dim=2), m[:, 3:]], dim=1)


def correction_sizes(delta: Tensor, pivot: Tensor, distance: Tensor) -> tuple[Tensor, Tensor]:
    """Corrections delta [V, 6] about pivots [V] -> (rotation angle [V] in radians, |omega|; camera-centre
    displacement [V] as a fraction of distance [V]). Both compare the refined camera with the input one, whatever
    the pivot (the centre moves by the translation of `pivoted_exp`, in the camera's frame)."""
    moved = pivoted_exp(delta, pivot)[:, :3, 3].norm(dim=1)
    return delta[:, :3].norm(dim=1), moved / distance.to(delta)


def project_corrections(delta: Tensor, pivot: Tensor, distance: Tensor, region: TrustRegion) -> tuple[Tensor, Tensor]:
    """Corrections delta [V, 6] -> (the same projected onto `region`, mask [V] of those that moved). A rotation past
    its bound is scaled down about the same axis, keeping the camera centre where it was; a centre displacement past
    its bound is shortened along its direction, keeping the rotation."""
    theta, moved = correction_sizes(delta, pivot, distance)
    max_rot = math.radians(region.max_rotation_deg)
    over = (theta > max_rot) | (moved > region.max_translation)
    if not bool(over.any()):
        return delta, over
    one = torch.ones_like(theta)
    omega = delta[:, :3] * torch.minimum(one, max_rot / theta.clamp_min(1e-300))[:, None]
    t = pivoted_exp(delta, pivot)[:, :3, 3]  # [V, 3] centre displacement, camera frame
    t = t * torch.minimum(one, region.max_translation / moved.clamp_min(1e-300))[:, None]
    target = torch.eye(4, dtype=delta.dtype, device=delta.device).repeat(len(delta), 1, 1)
    target[:, :3, :3], target[:, :3, 3] = so3_exp(omega), t
    shift = torch.eye(4, dtype=delta.dtype, device=delta.device).repeat(len(delta), 1, 1)
    shift[:, 2, 3] = -pivot.to(delta)  # T(p); target = T(p) se3_exp(xi) T(-p)
    xi = se3_log(torch.linalg.inv(shift) @ target @ shift)
    return torch.where(over[:, None], xi, delta), over


def gauge_basis(world_from_cam: Tensor, pivot: Tensor) -> Tensor:
    """The 7 directions [V, 6, 7] in which corrections (omega, v) about pivots [V] move every camera of
    world_from_cam [V, 4, 4] together by one small similarity (to first order): a rotation Omega (columns 0-2), a
    translation tau (3-5) and a scale lambda (6) of the world, all about the mean camera centre c. For camera k
    with R_k its rotation and a_k = R_k^T (c_k - c): omega = R_k^T Omega; v = omega x (a_k - p_k e_z) + R_k^T tau +
    lambda a_k (the centre moves by v + p_k omega x e_z in the camera frame, `pivoted_exp` to first order)."""
    rot, centres = world_from_cam[:, :3, :3], world_from_cam[:, :3, 3]
    rt = rot.transpose(1, 2)  # [V, 3, 3]
    a = (rt @ (centres - centres.mean(0))[:, :, None])[..., 0]  # [V, 3]
    arm = a.clone()
    arm[:, 2] = arm[:, 2] - pivot.to(a)
    basis = torch.zeros(len(rot), 6, 7, dtype=rot.dtype, device=rot.device)
    basis[:, :3, :3] = rt
    basis[:, 3:, :3] = -hat(arm) @ rt  # omega x arm = -arm^ omega
    basis[:, 3:, 3:6] = rt
    basis[:, 3:, 6] = a
    return basis


def _gauge_projector(world_from_cam: Tensor, pivot: Tensor, distance: Tensor) -> tuple[Tensor | None, Tensor | None]:
    """(G [V * 6, 7], S [7, V * 6]) with G S delta the similarity part of the flattened corrections delta [V * 6]
    (`gauge_basis`, least squares with rotations in radians and translations in units of each camera's distance);
    (None, None) below 3 cameras, where a similarity is most of what the cameras can do."""
    if len(world_from_cam) < 3:
        return None, None
    basis = gauge_basis(world_from_cam, pivot).reshape(-1, 7)  # [V * 6, 7]
    weight = torch.cat([torch.ones_like(distance)[:, None].expand(-1, 3), 1 / distance[:, None].expand(-1, 3)], 1)
    weight = weight.reshape(-1)  # [V * 6]
    return basis, torch.linalg.pinv(basis * weight[:, None], rtol=1e-10) * weight[None, :]


def _distances(world_from_cam: Tensor, pivot: Tensor) -> Tensor:
    """Each camera's distance [V] to the scene centre, the unit of the translation step and bound: its pivot depth
    (the centre's depth on its optical axis: the distance for a camera that looks at the centre). Cameras without
    a pivot, or whose axis passes so far from the centre that its depth is under half the median pivot, take the
    median pivot; with no pivot at all, the RMS distance of the camera centres from their mean (1 for a single
    camera): deterministic, in the capture's own scale."""
    if bool((pivot > 0).any()):
        median = float(pivot[pivot > 0].median())
        return torch.where(pivot >= 0.5 * median, pivot, torch.full_like(pivot, median))
    centres = world_from_cam[:, :3, 3]
    spread = float((centres - centres.mean(0)).norm(dim=1).pow(2).mean().sqrt())
    return torch.full_like(pivot, spread if spread > 0 else 1.0)


class CameraOpt(nn.Module):
    """Corrections of V cameras; `forward(o, d, view)` moves a batch of their rays."""

    def __init__(
        self,
        world_from_cam: Tensor | np.ndarray,
        *,
        focal: bool = False,
        schedule: CameraSchedule | None = None,
        pivot: np.ndarray | None = None,
        trust: TrustRegion | None = None,
    ) -> None:
        super().__init__()
        w = torch.as_tensor(np.asarray(world_from_cam), dtype=torch.float64)
        if w.ndim != 3 or w.shape[1:] != (4, 4):
            raise ValueError(f"expected world_from_cam [V, 4, 4], got {tuple(w.shape)}")
        piv = torch.zeros(w.shape[0], dtype=torch.float64) if pivot is None else torch.as_tensor(pivot).double()
        if piv.shape != w.shape[:1] or not bool(torch.isfinite(piv).all()) or bool((piv < 0).any()):
            raise ValueError(f"expected pivot depths [{w.shape[0]}], finite and >= 0, got {tuple(piv.shape)}")
        self.register_buffer("world_from_cam", w)  # [V, 4, 4] float64, the input cameras
        self.register_buffer("pivot", piv)  # [V] float64, depth of each correction's pivot on the optical axis
        self.register_buffer("distance", _distances(w, piv))  # [V] float64, unit of the translation bound
        basis, solve = _gauge_projector(w, piv, self.distance)
        self.register_buffer("gauge_basis", basis)  # [V * 6, 7] float64 (None below 3 cameras)
        self.register_buffer("gauge_solve", solve)  # [7, V * 6] float64: the gauge part of the flattened corrections
        self.raw = nn.Parameter(torch.zeros(w.shape[0], 6))  # [V, 6] what Adam moves: delta / step_scale
        self.log_focal = nn.Parameter(torch.zeros(1), requires_grad=focal)  # shared focal scale exp(log_focal)
        self.focal = focal
        self.schedule = schedule or CameraSchedule()
        self.trust = trust or TrustRegion()
        self.log = GuardLog()
        self.steps = 0  # camera steps taken (the guard's step when the loop gives none)
        self.opt: torch.optim.Adam | None = None

    @property
    def step_scale(self) -> Tensor:
        """[V, 6] how far each of (omega, v) moves per unit of Adam's variable: with pivots, the orbit angles at
        ORBIT_STEP and the translation at TRANSLATION_STEP x the camera's distance; all 1 without (runs from before
        the pivot)."""
        scale = torch.ones(len(self.pivot), 6, dtype=self.raw.dtype, device=self.raw.device)
        if bool((self.pivot > 0).any()):
            scale[:, :2] = ORBIT_STEP
            scale[:, 3:] = TRANSLATION_STEP * self.distance[:, None].to(scale)
        return scale

    @property
    def delta(self) -> Tensor:
        """The corrections (omega, v) [V, 6] in each camera's frame: Adam's variables times `step_scale`."""
        return self.raw * self.step_scale

    def optimizer(self) -> torch.optim.Adam:
        """The camera optimiser (own Adam, kept across the field's optimizer rebuilds at grid upsampling)."""
        if self.opt is None:
            groups = [{"params": [self.raw], "lr": self.schedule.lr, "base_lr": self.schedule.lr}]
            if self.focal:
                groups.append(
                    {"params": [self.log_focal], "lr": self.schedule.focal_lr, "base_lr": self.schedule.focal_lr}
                )
            self.opt = torch.optim.Adam(groups, betas=(0.9, 0.99))
        return self.opt

    def forward(self, o: Tensor, d: Tensor, view: Tensor) -> tuple[Tensor, Tensor]:
        """Rays o, d [B, 3] (unit d) of cameras view [B] -> refined o', d' [B, 3] (unit d', same dtype)."""
        if o.shape != d.shape or o.ndim != 2 or o.shape[-1] != 3 or view.shape != o.shape[:1]:
            raise ValueError(
                f"expected o, d [B, 3] and view [B], got {tuple(o.shape)}, {tuple(d.shape)}, {tuple(view.shape)}"
            )
        view = view.to(o.device).long()
        rot = self.world_from_cam[:, :3, :3].to(o)[view]  # [B, 3, 3]
        corr = pivoted_exp(self.delta.to(o), self.pivot.to(o))[view]  # [B, 4, 4]
        d_cam = (rot.transpose(1, 2) @ d[:, :, None])[..., 0]  # [B, 3]
        if self.focal:
            scale = torch.exp(-self.log_focal.to(o))
            d_cam = torch.cat([d_cam[:, :2] * scale, d_cam[:, 2:]], dim=1)
            d_cam = d_cam / d_cam.norm(dim=1, keepdim=True)
        d_new = (rot @ (corr[:, :3, :3] @ d_cam[:, :, None]))[..., 0]
        o_new = o + (rot @ corr[:, :3, 3:4])[..., 0]
        return o_new, d_new

    def moves(self, frac: float) -> bool:
        """Whether a step at run progress frac moves the cameras (after the delay, before any stop)."""
        return self.log.stopped_at is None and self.schedule.factor(frac) > 0

    def step(self, frac: float, step: int | None = None) -> None:
        """One Adam step on the gradients left by the field's backward pass, at the schedule's rate for frac, then
        the guard (`step`: the training step it records; None: the camera steps so far). Once the guard has stopped
        refinement, the gradients are dropped and nothing moves."""
        opt = self.optimizer()
        self.steps += 1
        k = self.schedule.factor(frac) if self.log.stopped_at is None else 0.0
        for g in opt.param_groups:
            g["lr"] = g["base_lr"] * k
        if k > 0:
            opt.step()
            self.fix_gauge()
            self.guard(self.steps if step is None else step)
        opt.zero_grad(set_to_none=True)

    @torch.no_grad()
    def fix_gauge(self) -> None:
        """Remove from the corrections the part that moves every camera by one similarity (`gauge_basis`): the
        field could follow it, so the photos barely resist it, and Adam, which steps every direction by about the
        rate whatever its gradient, lets it drift (bench scenes: cameras 5 % further out, the object 5 % bigger,
        half the translation bound spent on nothing). Zero-mean pose noise has no such part to recover."""
        if self.gauge_basis is None:
            return
        scale = self.step_scale.double()
        delta = (self.raw.double() * scale).reshape(-1)
        delta = delta - self.gauge_basis @ (self.gauge_solve @ delta)
        self.raw.copy_((delta.reshape(-1, 6) / scale).to(self.raw))

    @torch.no_grad()
    def guard(self, step: int) -> None:
        """The trust region (module docstring): stop refinement when the median correction passes
        `trust.stop_median` of its bound, else project the corrections past a bound onto it and zero those
        cameras' Adam moments."""
        if self.log.stopped_at is not None:
            return
        delta = self.delta.detach().double()
        theta, moved = correction_sizes(delta, self.pivot, self.distance)
        rot_deg = torch.rad2deg(theta)
        self.log.largest_rotation_deg = max(self.log.largest_rotation_deg, float(rot_deg.max()))
        self.log.largest_translation = max(self.log.largest_translation, float(moved.max()))
        share = torch.maximum(rot_deg / self.trust.max_rotation_deg, moved / self.trust.max_translation)
        median = float(torch.quantile(share, 0.5))
        if median > self.trust.stop_median:
            self.log.at_stop = {
                "median_share": round(median, 4),
                "median_rotation_deg": round(float(torch.quantile(rot_deg, 0.5)), 4),
                "max_rotation_deg": round(float(rot_deg.max()), 4),
                "median_translation": round(float(torch.quantile(moved, 0.5)), 5),
                "max_translation": round(float(moved.max()), 5),
            }
            self.stop(step)
            return
        projected, over = project_corrections(delta, self.pivot, self.distance, self.trust)
        if not bool(over.any()):
            return
        self.raw[over] = (projected[over] / self.step_scale.double()[over]).to(self.raw)
        state = self.optimizer().state.get(self.raw, {})
        for key in ("exp_avg", "exp_avg_sq"):
            if key in state:
                state[key][over] = 0.0
        idx = over.nonzero()[:, 0].tolist()
        self.log.pulled_back += len(idx)
        self.log.cameras = sorted(set(self.log.cameras) | set(idx))
        self.log.first_step = step if self.log.first_step is None else self.log.first_step

    @torch.no_grad()
    def stop(self, step: int) -> None:
        """End refinement at training `step`: corrections and focal scale back to zero (the input cameras), Adam's
        state dropped; later steps move nothing."""
        self.raw.zero_()
        self.log_focal.zero_()
        self.optimizer().state.clear()
        self.log.stopped_at = step

    @torch.no_grad()
    def refined(self) -> np.ndarray:
        """Refined world_from_cam [V, 4, 4] float64."""
        return (self.world_from_cam @ pivoted_exp(self.delta.double(), self.pivot)).cpu().numpy()

    def test_rays(self) -> Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]:
        """(o, d) [B, 3] of a camera given in the input frame -> the same ray in the refined frame, through
        the similarity of `align_test_poses` fitted now (test views during training)."""
        train_in = self.world_from_cam.cpu().numpy()
        if len(train_in) < 3:
            return lambda o, d: (o, d)
        s, rot, t = umeyama(train_in[:, :3, 3], self.refined()[:, :3, 3])

        def move(o: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
            r = torch.as_tensor(rot, dtype=o.dtype, device=o.device)
            return s * o @ r.T + torch.as_tensor(t, dtype=o.dtype, device=o.device), d @ r.T

        return move

    @property
    def focal_scale(self) -> float:
        return float(torch.exp(self.log_focal.detach()).item()) if self.focal else 1.0

    def to_dict(self) -> dict[str, Any]:
        """What checkpoint.pt stores (tensors and primitives only)."""
        return {
            "world_from_cam": self.world_from_cam.cpu(),
            "delta": self.delta.detach().cpu(),
            "pivot": self.pivot.cpu(),
            "log_focal": self.log_focal.detach().cpu(),
            "focal": self.focal,
            "optimizer": self.optimizer().state_dict(),
            "guard": self.log.to_dict(),
            "steps": self.steps,
        }

    def load_dict(self, doc: dict[str, Any]) -> None:
        with torch.no_grad():
            self.pivot.copy_(_pivot(doc))
            self.raw.copy_(doc["delta"] / self.step_scale)
            self.log_focal.copy_(doc["log_focal"])
        if doc.get("optimizer") is not None:
            self.optimizer().load_state_dict(doc["optimizer"])
        self.log = GuardLog.from_dict(doc.get("guard"))  # runs from before the guard have none
        self.steps = int(doc.get("steps", 0))


def corrections_record(world_from_cam: np.ndarray, refined: np.ndarray, names: list[str]) -> list[dict[str, Any]]:
    """Per camera: the correction's rotation angle (degrees) and translation length (scene units)."""
    out = []
    for name, a, b in zip(names, world_from_cam, refined, strict=True):
        rel = np.linalg.inv(a) @ b
        cos = np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1.0, 1.0)
        out.append(
            {
                "name": name,
                "rotation_deg": round(math.degrees(math.acos(cos)), 5),
                "translation": round(float(np.linalg.norm(b[:3, 3] - a[:3, 3])), 6),
            }
        )
    return out


def align_test_poses(train_in: np.ndarray, train_refined: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, dict]:
    """Map cameras `other` [N, 4, 4] from the input frame into the refined frame by the similarity fitted from
    the input training cameras [V, 4, 4] to the refined ones; also returns its record (scale, rotation,
    translation, rms centre residual). With fewer than 3 training cameras, the identity."""
    if len(train_in) < 3:
        return other.copy(), {"method": "identity", "reason": "fewer than 3 training cameras"}
    s, rot, t = umeyama(train_in[:, :3, 3], train_refined[:, :3, 3])
    sim = np.eye(4)
    sim[:3, :3], sim[:3, 3] = s * rot, t
    mapped = sim @ other
    mapped[:, :3, :3] /= s  # rotation part stays orthonormal; the centre carries the scale
    res = np.linalg.norm(s * train_in[:, :3, 3] @ rot.T + t - train_refined[:, :3, 3], axis=1)
    record = {
        "method": "similarity",
        "scale": float(s),
        "rotation": rot.tolist(),
        "translation": t.tolist(),
        "rms_centre_residual": float(np.sqrt((res**2).mean())),
    }
    return mapped, record


def _pivot(doc: dict[str, Any]) -> Tensor:
    """The pivot depths [V] float64 of a stored `CameraOpt.to_dict`; runs from before the pivot have none: 0."""
    pivot = doc.get("pivot")
    return torch.zeros(len(doc["world_from_cam"]), dtype=torch.float64) if pivot is None else pivot.double()


def refined_scene(scene: Scene, doc: dict[str, Any], train_idx: tuple[int, ...]) -> tuple[Scene, dict[str, Any]]:
    """The scene as the run sees it after refinement: training frames at their refined poses, every other frame
    mapped into the refined frame by `align_test_poses`, focal lengths times the shared focal scale. Returns the
    scene and a record of what was done (for eval's JSON and the manifest; `stopped_at_step`: the step at which the
    guard stopped refinement, None when it ran to the end)."""
    w_in = doc["world_from_cam"].double()
    refined = (w_in @ pivoted_exp(doc["delta"].double(), _pivot(doc))).numpy()
    train_in = w_in.numpy()
    others = [i for i in range(len(scene.frames)) if i not in set(train_idx)]
    poses = {i: refined[k] for k, i in enumerate(train_idx)}
    stopped = (doc.get("guard") or {}).get("stopped_at")  # the guard stopped refinement: the input cameras
    record: dict[str, Any] = {"train_views": len(train_idx), "focal_scale": 1.0, "stopped_at_step": stopped}
    if others:
        mapped, record["test_poses"] = align_test_poses(
            train_in, refined, np.stack([scene.frames[i].world_from_cam for i in others])
        )
        poses.update({i: m for i, m in zip(others, mapped, strict=True)})
    scale = float(torch.exp(doc["log_focal"]).item()) if doc.get("focal") else 1.0
    record["focal_scale"] = scale

    frames = tuple(
        dataclasses.replace(f, world_from_cam=poses[i], intrinsics=_focal_times(f.intrinsics, scale))
        for i, f in enumerate(scene.frames)
    )
    return scene.replace(frames=frames, intrinsics=_focal_times(scene.intrinsics, scale)), record


def _focal_times(intr: Intrinsics | None, scale: float) -> Intrinsics | None:
    if intr is None or scale == 1.0:
        return intr
    return dataclasses.replace(intr, fx=intr.fx * scale, fy=intr.fy * scale)


def guard_record(cameras: CameraOpt, names: list[str]) -> dict[str, Any]:
    """The guard's record for the manifest (`pose_report`'s "guard"): its bounds, what it pulled back, whether and
    when it stopped refinement, the corrections' sizes, and "suspect": the reasons to distrust the refinement
    (empty when it stayed well inside its bounds), with "summary" and "limit" for the train stage's self-check."""
    trust, log = cameras.trust, cameras.log
    with torch.no_grad():
        theta, moved = correction_sizes(cameras.delta.detach().double(), cameras.pivot, cameras.distance)
    rot_deg = torch.rad2deg(theta)
    share = torch.maximum(rot_deg / trust.max_rotation_deg, moved / trust.max_translation)
    median = float(torch.quantile(share, 0.5))
    suspect = []
    if log.stopped_at is not None:
        at = log.at_stop or {}
        suspect.append(
            f"refinement stopped at step {log.stopped_at}: the median correction reached "
            f"{at.get('median_share', float('nan')):.2f} of its bound (median "
            f"{at.get('median_rotation_deg', float('nan')):.2f} deg, "
            f"{100 * at.get('median_translation', float('nan')):.1f} % of the distance); the input "
            "cameras were kept"
            + (
                f" and the field went back to its state at step {log.rolled_back_to}, before the cameras moved"
                if log.rolled_back_to is not None
                else ""
            )
        )
    if log.cameras:
        suspect.append(
            f"{len(log.cameras)} of {len(names)} cameras pulled back onto a bound ({log.pulled_back} "
            f"times, first at step {log.first_step})"
        )
    summary = (
        "; ".join(suspect)
        if suspect
        else (f"within bounds: median correction {median:.2f} of its bound, largest {float(share.max()):.2f}")
    )
    return {
        "bounds": {
            "max_rotation_deg": trust.max_rotation_deg,
            "max_translation": trust.max_translation,
            "stop_median": trust.stop_median,
        },
        "rule": GUARD_RULE,
        "pulled_back": log.pulled_back,
        "cameras_pulled_back": [names[i] for i in log.cameras],
        "first_pulled_back_step": log.first_step,
        "stopped": log.stopped_at is not None,
        "stopped_at_step": log.stopped_at,
        "at_stop": log.at_stop,
        "field_rolled_back_to_step": log.rolled_back_to,
        "largest_rotation_deg": round(log.largest_rotation_deg, 4),
        "largest_translation": round(log.largest_translation, 5),
        "median_share": round(median, 4),
        "max_share": round(float(share.max()), 4),
        "suspect": suspect,
        "summary": summary,
        "limit": (
            f"no correction past {trust.max_rotation_deg:g} deg or {100 * trust.max_translation:g} % of the "
            f"distance to the scene centre; median below {trust.stop_median:g} of that"
        ),
    }


GUARD_RULE = (
    "trust region: a correction past max_rotation_deg or max_translation (a fraction of the camera's "
    "distance to the scene centre) is projected back onto the bound and its Adam moments zeroed; when "
    "the median correction passes stop_median of its bound, refinement stops and every correction goes "
    "back to zero (the input cameras)"
)


def pose_report(cameras: CameraOpt, scene: Scene, train_idx: tuple[int, ...]) -> dict[str, Any]:
    """The manifest's record of the refinement: per-camera corrections, their median and largest sizes, the
    focal scale, how test views are placed in the refined frame, and the guard's record ("guard",
    `guard_record`)."""
    refined = cameras.refined()
    names = [scene.frames[i].file_path for i in train_idx]
    per_camera = corrections_record(cameras.world_from_cam.cpu().numpy(), refined, names)
    rot = np.array([c["rotation_deg"] for c in per_camera])
    trans = np.array([c["translation"] for c in per_camera])
    return {
        "cameras": len(per_camera),
        "focal_scale": cameras.focal_scale,
        "median_rotation_deg": float(np.median(rot)),
        "max_rotation_deg": float(rot.max()),
        "median_translation": float(np.median(trans)),
        "max_translation": float(trans.max()),
        "schedule": dataclasses.asdict(cameras.schedule),
        "test_poses": TEST_POSE_RULE,
        "guard": guard_record(cameras, names),
        "per_camera": per_camera,
    }


TEST_POSE_RULE = (
    "mapped into the refined frame by the similarity (Umeyama, camera centres) from the input "
    "training cameras to the refined ones; not optimised against the test photos"
)


def write_refined_transforms(scene: Scene, doc: dict[str, Any], train_idx: tuple[int, ...], path: Path) -> Path:
    """transforms.json at `path` with the refined cameras (`refined_scene`); image paths relative to its folder,
    so nerfstudio / instant-ngp read it in place (nerfpipe reads scenes whose images lie under their folder:
    copy it next to the images to train on it)."""
    refined, _ = refined_scene(scene, doc, train_idx)
    folder = path.parent.resolve()

    def rel(p: str | None) -> str | None:
        return None if p is None else os.path.relpath((scene.root / p).resolve(), folder)

    frames = tuple(
        dataclasses.replace(
            f, file_path=rel(f.file_path), mask_path=rel(f.mask_path), depth_file_path=rel(f.depth_file_path)
        )
        for f in refined.frames
    )
    return write_scene(refined.replace(root=folder, frames=frames), path)


def test_pose_placement(refinement: dict[str, Any] | None) -> Any:
    """How a run's test cameras are placed without test-pose optimisation (eval's JSON `test_poses`), from
    `Trained.pose_refinement` (`refined_scene`'s record; None: no refinement)."""
    if refinement is None:
        return "as in transforms.json (no pose refinement)"
    if refinement.get("stopped_at_step") is not None:
        return (
            f"as in transforms.json: the guard stopped pose refinement at step {refinement['stopped_at_step']} "
            "and the run kept its input cameras"
        )
    return refinement.get("test_poses")


TEST_POSE_OPT_RULE = (
    "as above, then each test camera's SE(3) optimised against its photo with the field frozen "
    "(NeRF--, nerfstudio: eval --test-pose-steps)"
)


def optimise_test_pose(
    run: Any,
    background: Tensor,
    world_from_cam: np.ndarray,
    intr: Intrinsics,
    photo: np.ndarray,
    steps: int,
    *,
    lr: float = 2e-3,
    batch: int = 2048,
    seed: int = 0,
    centre: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, float]]:
    """One test camera world_from_cam [4, 4] refined against its photo [H, W, 3] (composited on `background`
    [3]) by `steps` Adam steps on a correction of the camera (`CameraOpt`, pivoted at the depth of `centre` [3],
    the scene centre; None: about the camera centre), the run frozen (a `model.run.Run` with `pose_opt`); each step
    renders `batch` random pixels. Returns the refined camera and its correction's size."""
    from nerfpipe.radiance.camera import generate_rays

    if photo.shape[:2] != (intr.h, intr.w) or photo.ndim != 3 or photo.shape[2] != 3:
        raise ValueError(f"expected photo [{intr.h}, {intr.w}, 3], got {tuple(photo.shape)}")
    device = background.device
    w = np.asarray(world_from_cam, dtype=np.float64)[None]
    cam = CameraOpt(w, pivot=None if centre is None else pivot_depths(w, np.asarray(centre))).to(device)
    opt = torch.optim.Adam([cam.raw], lr=lr, betas=(0.9, 0.99))
    o_all, d_all = generate_rays(intr, torch.as_tensor(np.asarray(world_from_cam, dtype=np.float64)))
    o_all, d_all = o_all.to(device, torch.float32), d_all.to(device, torch.float32)
    target = torch.from_numpy(np.ascontiguousarray(photo, dtype=np.float32)).reshape(-1, 3).to(device)
    gen = torch.Generator().manual_seed(seed)
    frozen = [p for p in run.parameters() if p.requires_grad]
    for p in frozen:
        p.requires_grad_(False)
    try:
        for k in range(steps):
            idx = torch.randint(o_all.shape[0], (min(batch, o_all.shape[0]),), generator=gen).to(device)
            o, d = cam(o_all[idx], d_all[idx], torch.zeros_like(idx))
            pred = run.render_differentiable(o, d, background)["rgb"]  # differentiable in the pose
            loss = torch.mean((pred - target[idx]) ** 2)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            for g in opt.param_groups:
                g["lr"] = lr * 0.1 ** (k / max(steps, 1))
            opt.step()
    finally:
        for p in frozen:
            p.requires_grad_(True)
    refined = cam.refined()[0]
    rec = corrections_record(np.asarray(world_from_cam)[None], refined[None], [""])[0]
    return refined, {"rotation_deg": rec["rotation_deg"], "translation": rec["translation"]}
