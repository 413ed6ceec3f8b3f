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

Test views: the field learns in the frame the refined cameras define, which may drift from the input frame by a
small rigid motion (the gauge is free). `align_test_poses` fits a similarity (Umeyama on camera centres) from the
input training cameras to the refined ones and maps every other camera through it (nerfstudio's and NeRF--'s
alternative to optimising test poses against the frozen field: it needs no render time, cannot fit the test
photos' content, and with zero-mean pose noise on many cameras it recovers the frame to a fraction of the noise).
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

from data.transforms import Scene, write_scene
from radiance.align import umeyama
from radiance.camera import Intrinsics
from radiance.se3 import se3_exp

__all__ = [
    "ORBIT_STEP",
    "CameraSchedule",
    "pivot_depths",
    "pivoted_exp",
    "CameraOpt",
    "refined_scene",
    "align_test_poses",
    "corrections_record",
    "pose_report",
    "write_refined_transforms",
    "TEST_POSE_RULE",
    "TEST_POSE_OPT_RULE",
    "optimise_test_pose",
]


ORBIT_STEP = 0.1
"""With pivots, the orbit angles (omega_x, omega_y) move at this fraction of the learning rate: Adam steps each
coordinate by about the rate whatever its gradient's size, and an orbit, seen only through parallax, has a noisy
gradient while the field is rough (at the full rate some runs lost a camera)."""


@dataclass(frozen=True, kw_only=True)
class CameraSchedule:
    """Learning rates and warm-up of the camera optimiser."""

    lr: float = 1e-2
    """Adam learning rate of the rotation (radians) and translation (scene units) corrections at full strength."""
    focal_lr: float = 1e-3
    """Adam learning rate of the log focal scale."""
    delay: float = 0.02
    """Run-progress fraction before the cameras move (the field first needs a rough shape to register to)."""
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


class CameraOpt(nn.Module):
    """Corrections of V cameras; `forward(o, d, view)` moves a batch of their rays."""

    def __init__(self, world_from_cam: Tensor | np.ndarray, *, focal: bool = False,
                 schedule: CameraSchedule | None = None, pivot: np.ndarray | None = None) -> None:  # fmt: skip
        super().__init__()
        w = torch.as_tensor(np.asarray(world_from_cam), dtype=torch.float64)
        if w.ndim != 3 or w.shape[1:] != (4, 4):
            raise ValueError(f"expected world_from_cam [V, 4, 4], got {tuple(w.shape)}")
        piv = torch.zeros(w.shape[0], dtype=torch.float64) if pivot is None else torch.as_tensor(pivot).double()
        if piv.shape != w.shape[:1] or not bool(torch.isfinite(piv).all()) or bool((piv < 0).any()):
            raise ValueError(f"expected pivot depths [{w.shape[0]}], finite and >= 0, got {tuple(piv.shape)}")
        self.register_buffer("world_from_cam", w)  # [V, 4, 4] float64, the input cameras
        self.register_buffer("pivot", piv)  # [V] float64, depth of each correction's pivot on the optical axis
        self.raw = nn.Parameter(torch.zeros(w.shape[0], 6))  # [V, 6] what Adam moves: delta / step_scale
        self.log_focal = nn.Parameter(torch.zeros(1), requires_grad=focal)  # shared focal scale exp(log_focal)
        self.focal = focal
        self.schedule = schedule or CameraSchedule()
        self.opt: torch.optim.Adam | None = None

    @property
    def step_scale(self) -> Tensor:
        """[6] how far each of (omega, v) moves per unit of Adam's variable: the orbit angles at ORBIT_STEP when the
        corrections have pivots, all 1 without."""
        orbit = ORBIT_STEP if bool((self.pivot > 0).any()) else 1.0
        return torch.tensor([orbit, orbit, 1.0, 1.0, 1.0, 1.0], dtype=self.raw.dtype, device=self.raw.device)

    @property
    def delta(self) -> Tensor:
        """The corrections (omega, v) [V, 6] in each camera's frame: Adam's variables times `step_scale`."""
        return self.raw * self.step_scale

    def optimizer(self) -> torch.optim.Adam:
        """The camera optimiser (own Adam, kept across the field's optimizer rebuilds at grid upsampling)."""
        if self.opt is None:
            groups = [{"params": [self.raw], "lr": self.schedule.lr, "base_lr": self.schedule.lr}]
            if self.focal:
                groups.append({"params": [self.log_focal], "lr": self.schedule.focal_lr,
                               "base_lr": self.schedule.focal_lr})  # fmt: skip
            self.opt = torch.optim.Adam(groups, betas=(0.9, 0.99))
        return self.opt

    def forward(self, o: Tensor, d: Tensor, view: Tensor) -> tuple[Tensor, Tensor]:
        """Rays o, d [B, 3] (unit d) of cameras view [B] -> refined o', d' [B, 3] (unit d', same dtype)."""
        if o.shape != d.shape or o.ndim != 2 or o.shape[-1] != 3 or view.shape != o.shape[:1]:
            raise ValueError(f"expected o, d [B, 3] and view [B], got {tuple(o.shape)}, {tuple(d.shape)}, "
                             f"{tuple(view.shape)}")  # fmt: skip
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

    def step(self, frac: float) -> None:
        """One Adam step on the gradients left by the field's backward pass, at the schedule's rate for frac."""
        opt = self.optimizer()
        k = self.schedule.factor(frac)
        for g in opt.param_groups:
            g["lr"] = g["base_lr"] * k
        if k > 0:
            opt.step()
        opt.zero_grad(set_to_none=True)

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
        return {"world_from_cam": self.world_from_cam.cpu(), "delta": self.delta.detach().cpu(),
                "pivot": self.pivot.cpu(),
                "log_focal": self.log_focal.detach().cpu(), "focal": self.focal,
                "optimizer": self.optimizer().state_dict()}  # fmt: skip

    def load_dict(self, doc: dict[str, Any]) -> None:
        with torch.no_grad():
            self.pivot.copy_(_pivot(doc))
            self.raw.copy_(doc["delta"] / self.step_scale)
            self.log_focal.copy_(doc["log_focal"])
        if doc.get("optimizer") is not None:
            self.optimizer().load_state_dict(doc["optimizer"])


def corrections_record(world_from_cam: np.ndarray, refined: np.ndarray, names: list[str]) -> list[dict[str, Any]]:
    """Per camera: the correction's rotation angle (degrees) and translation length (scene units)."""
    out = []
    for name, a, b in zip(names, world_from_cam, refined, strict=True):
        rel = np.linalg.inv(a) @ b
        cos = np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1.0, 1.0)
        out.append({"name": name, "rotation_deg": round(math.degrees(math.acos(cos)), 5),
                    "translation": round(float(np.linalg.norm(b[:3, 3] - a[:3, 3])), 6)})  # fmt: skip
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
    record = {"method": "similarity", "scale": float(s), "rotation": rot.tolist(), "translation": t.tolist(),
              "rms_centre_residual": float(np.sqrt((res**2).mean()))}  # fmt: skip
    return mapped, record


def _pivot(doc: dict[str, Any]) -> Tensor:
    """The pivot depths [V] float64 of a stored `CameraOpt.to_dict`; runs from before the pivot have none: 0."""
    pivot = doc.get("pivot")
    return torch.zeros(len(doc["world_from_cam"]), dtype=torch.float64) if pivot is None else pivot.double()


def refined_scene(scene: Scene, doc: dict[str, Any], train_idx: tuple[int, ...]) -> tuple[Scene, dict[str, Any]]:
    """The scene as the run sees it after refinement: training frames at their refined poses, every other frame
    mapped into the refined frame by `align_test_poses`, focal lengths times the shared focal scale. Returns the
    scene and a record of what was done (for eval's JSON and the manifest)."""
    w_in = doc["world_from_cam"].double()
    refined = (w_in @ pivoted_exp(doc["delta"].double(), _pivot(doc))).numpy()
    train_in = w_in.numpy()
    others = [i for i in range(len(scene.frames)) if i not in set(train_idx)]
    poses = {i: refined[k] for k, i in enumerate(train_idx)}
    record: dict[str, Any] = {"train_views": len(train_idx), "focal_scale": 1.0}
    if others:
        mapped, record["test_poses"] = align_test_poses(
            train_in, refined, np.stack([scene.frames[i].world_from_cam for i in others])
        )
        poses.update({i: m for i, m in zip(others, mapped, strict=True)})  # fmt: skip
    scale = float(torch.exp(doc["log_focal"]).item()) if doc.get("focal") else 1.0
    record["focal_scale"] = scale

    frames = tuple(dataclasses.replace(f, world_from_cam=poses[i], intrinsics=_focal_times(f.intrinsics, scale))
                   for i, f in enumerate(scene.frames))  # fmt: skip
    return scene.replace(frames=frames, intrinsics=_focal_times(scene.intrinsics, scale)), record


def _focal_times(intr: Intrinsics | None, scale: float) -> Intrinsics | None:
    if intr is None or scale == 1.0:
        return intr
    return dataclasses.replace(intr, fx=intr.fx * scale, fy=intr.fy * scale)


def pose_report(cameras: CameraOpt, scene: Scene, train_idx: tuple[int, ...]) -> dict[str, Any]:
    """The manifest's record of the refinement: per-camera corrections, their median and largest sizes, the
    focal scale, and how test views are placed in the refined frame."""
    refined = cameras.refined()
    names = [scene.frames[i].file_path for i in train_idx]
    per_camera = corrections_record(cameras.world_from_cam.cpu().numpy(), refined, names)
    rot = np.array([c["rotation_deg"] for c in per_camera])
    trans = np.array([c["translation"] for c in per_camera])
    return {
        "cameras": len(per_camera), "focal_scale": cameras.focal_scale,
        "median_rotation_deg": float(np.median(rot)), "max_rotation_deg": float(rot.max()),
        "median_translation": float(np.median(trans)), "max_translation": float(trans.max()),
        "schedule": dataclasses.asdict(cameras.schedule),
        "test_poses": TEST_POSE_RULE, "per_camera": per_camera,
    }  # fmt: skip


TEST_POSE_RULE = ("mapped into the refined frame by the similarity (Umeyama, camera centres) from the input "
                  "training cameras to the refined ones; not optimised against the test photos")  # fmt: skip


def write_refined_transforms(scene: Scene, doc: dict[str, Any], train_idx: tuple[int, ...], path: Path) -> Path:
    """transforms.json at `path` with the refined cameras (`refined_scene`); image paths relative to its folder,
    so nerfstudio / instant-ngp read it in place (nerfpipe reads scenes whose images lie under their folder:
    copy it next to the images to train on it)."""
    refined, _ = refined_scene(scene, doc, train_idx)
    folder = path.parent.resolve()

    def rel(p: str | None) -> str | None:
        return None if p is None else os.path.relpath((scene.root / p).resolve(), folder)

    frames = tuple(dataclasses.replace(f, file_path=rel(f.file_path), mask_path=rel(f.mask_path),
                                       depth_file_path=rel(f.depth_file_path)) for f in refined.frames)  # fmt: skip
    return write_scene(refined.replace(root=folder, frames=frames), path)


TEST_POSE_OPT_RULE = ("as above, then each test camera's SE(3) optimised against its photo with the field frozen "
                      "(NeRF--, nerfstudio: eval --test-pose-steps)")  # fmt: skip


def optimise_test_pose(model: Any, background: Tensor, world_from_cam: np.ndarray, intr: Intrinsics,
                       photo: np.ndarray, steps: int, *, lr: float = 2e-3, batch: int = 2048,
                       seed: int = 0, centre: np.ndarray | None = None
                       ) -> tuple[np.ndarray, dict[str, float]]:  # fmt: skip
    """One test camera world_from_cam [4, 4] refined against its photo [H, W, 3] (composited on `background`
    [3]) by `steps` Adam steps on a correction of the camera (`CameraOpt`, pivoted at the depth of `centre` [3],
    the scene centre; None: about the camera centre), the field (`model`, a FieldModel) frozen; each step
    renders `batch` random pixels. Returns the refined camera and its correction's size."""
    from radiance.camera import generate_rays

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
    frozen = [p for p in model.field.parameters() if p.requires_grad]
    for p in frozen:
        p.requires_grad_(False)
    try:
        for k in range(steps):
            idx = torch.randint(o_all.shape[0], (min(batch, o_all.shape[0]),), generator=gen).to(device)
            o, d = cam(o_all[idx], d_all[idx], torch.zeros_like(idx))
            pred = model.render(o, d, background, train=False, infer=None)["rgb"]  # differentiable in the pose
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
