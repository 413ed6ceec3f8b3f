"""Gaussian splats: the tiled rasteriser against its per-pixel twin (values, gradients, gradcheck), the PLY and
.splat layouts byte for byte, and the `splat` stage end to end on the analytic sphere (PSNR improves)."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
import torch

import nerfpipe.stages.splat as splat_stage
from nerfpipe import cli
from nerfpipe.data.errors import UserError
from nerfpipe.data.splat_ply import SH_C0, SPLAT_DTYPE, SplatData, ply_properties, read_ply, splat_bytes, write_ply
from nerfpipe.radiance import splat_cpu
from nerfpipe.radiance import splats as sp
from nerfpipe.radiance.camera import Intrinsics, project

try:  # the analytic stand-in lives with the render tests
    from test_render_stage import SphereRun, sphere_scene
except ImportError:  # tests/ imported as a package
    from tests.test_render_stage import SphereRun, sphere_scene

F64 = torch.float64


def _camera(w: int = 20, h: int = 14, f: float = 25.0) -> tuple[torch.Tensor, Intrinsics]:
    """A camera 3 units up +z looking at the origin, turned a little (OpenGL world_from_cam)."""
    a = 0.3
    rot = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]], dtype=F64)
    pose = torch.eye(4, dtype=F64)
    pose[:3, :3] = rot
    pose[:3, 3] = torch.tensor([0.1, -0.05, 3.0])
    return pose, Intrinsics(w=w, h=h, fx=f, fy=f * 1.1, cx=w / 2 + 0.3, cy=h / 2 - 0.2)


def _splats(n: int, *, seed: int = 0, degree: int = 0, opacity: float = 0.0, size: float = 0.08) -> sp.Splats:
    g = torch.Generator().manual_seed(seed)
    return sp.Splats(
        means=(torch.rand(n, 3, generator=g, dtype=F64) - 0.5) * torch.tensor([1.2, 0.8, 1.0], dtype=F64),
        log_scales=torch.log(size * (0.4 + torch.rand(n, 3, generator=g, dtype=F64))),
        quats=torch.randn(n, 4, generator=g, dtype=F64),
        opacity_logits=opacity + torch.randn(n, generator=g, dtype=F64),
        sh=0.6 * torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=F64),
    )


BG = torch.tensor([0.2, 0.5, 0.9], dtype=F64)


# ---------------------------------------------------------------------------------------------- rasteriser
KERNELS = ["torch", pytest.param("numba", marks=pytest.mark.skipif(not splat_cpu.available(), reason="no numba"))]


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize(("opacity", "degree", "tile"), [(0.0, 0, 16), (4.0, 1, 4), (6.0, 3, 8)])
def test_tiled_render_matches_the_per_pixel_twin(opacity, degree, tile, kernel):
    """Translucent to opaque (T stops below 1e-4 at high opacity), SH 0..3, several tile sizes, both kernels."""
    pose, intr = _camera()
    s = _splats(16, seed=1, degree=degree, opacity=opacity, size=0.12)
    fast = sp.render(s, pose, intr, BG, tile=tile, kernel=kernel)
    ref = sp.render_reference(s, pose, intr, BG)
    assert 0.05 < float(fast["alpha"].mean()) and float(fast["alpha"].max()) > 0.5
    assert torch.allclose(fast["rgb"], ref["rgb"], atol=1e-12) and torch.allclose(
        fast["alpha"], ref["alpha"], atol=1e-12
    )


@pytest.mark.parametrize("kernel", KERNELS)
def test_saturated_pixels_stop_as_the_3dgs_kernel_does(kernel):
    """Gaussians on the optical axis (the first nearest the camera), alphas 0.98, 0.98, 0.9, 0.5 at the centre
    pixel: T = 4e-4 after two, the third would bring it below 1e-4, so the pixel stops there and the fourth (which
    would leave 2e-4) is not drawn either, though it comes in a later chunk."""
    pose = torch.eye(4, dtype=F64)
    pose[2, 3] = 3.0
    intr = Intrinsics(w=9, h=9, fx=20.0, fy=20.0, cx=4.5, cy=4.5)  # the axis hits pixel (4, 4)'s centre
    o = torch.tensor([0.98, 0.98, 0.9, 0.5], dtype=F64)
    n = len(o)
    s = sp.Splats(
        means=torch.linspace(0.5, 0, n, dtype=F64)[:, None] * torch.tensor([0, 0, 1.0], dtype=F64),
        log_scales=torch.full((n, 3), math.log(0.3), dtype=F64),
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=F64).expand(n, 4),
        opacity_logits=torch.log(o / (1 - o)),
        sh=torch.randn(n, 1, 3, dtype=F64, generator=torch.Generator().manual_seed(0)),
    )
    fast = sp.rasterize(sp.project(s, pose, intr), intr.w, intr.h, BG, chunk=1, kernel=kernel)
    ref = sp.render_reference(s, pose, intr, BG)
    assert 1 - float(fast["alpha"][4, 4]) == pytest.approx(0.02 * 0.02, rel=1e-9)
    assert torch.allclose(fast["rgb"], ref["rgb"], atol=1e-12) and torch.allclose(
        fast["alpha"], ref["alpha"], atol=1e-12
    )


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("opacity", [1.0, 5.0])
def test_gradients_match_the_twin(kernel, opacity):
    """Translucent, and opaque enough that pixels stop and alphas clamp at 0.99 (no gradient through the clamp)."""
    pose, intr = _camera()
    s = _splats(10, seed=2, degree=1, opacity=opacity, size=0.15)
    weights = torch.rand(intr.h, intr.w, 3, dtype=F64, generator=torch.Generator().manual_seed(3))
    grads = []
    for fn in (
        lambda x: sp.render(x, pose, intr, BG, tile=8, kernel=kernel),
        lambda x: sp.render_reference(x, pose, intr, BG),
    ):
        params = [p.clone().requires_grad_(True) for p in s.parameters()]
        out = fn(sp.Splats(*params))
        ((out["rgb"] * weights).sum() + out["alpha"].sum()).backward()
        grads.append([p.grad for p in params])
    for name, g_fast, g_ref in zip(("means", "log_scales", "quats", "opacity", "sh"), *grads, strict=True):
        assert g_ref.abs().max() > 0, name
        assert torch.allclose(g_fast, g_ref, rtol=1e-8, atol=1e-10), name


@pytest.mark.parametrize("kernel", KERNELS)
def test_gradcheck_float64_three_gaussians(kernel):
    pose, intr = _camera(w=8, h=8, f=12.0)
    s = _splats(3, seed=4, opacity=1.5, size=0.25)

    def fn(*params):
        out = sp.render(sp.Splats(*params), pose, intr, BG, tile=4, kernel=kernel)
        return out["rgb"], out["alpha"]

    params = tuple(p.clone().requires_grad_(True) for p in s.parameters())
    assert torch.autograd.gradcheck(fn, params, eps=1e-6, atol=1e-6)


@pytest.mark.skipif(not splat_cpu.available(), reason="no numba")
def test_numba_kernel_gradcheck_on_its_own_inputs_with_background():
    """The compositing alone, float64: means2d, conics, opacities, colours and the background, pixels that stop."""
    g = torch.Generator().manual_seed(7)
    n, w, h, tile = 6, 7, 5, 4
    means2d = torch.rand(n, 2, generator=g, dtype=F64) * torch.tensor([w, h], dtype=F64)
    conics = torch.stack(
        [
            0.3 + torch.rand(n, generator=g, dtype=F64),
            0.1 * torch.randn(n, generator=g, dtype=F64),
            0.3 + torch.rand(n, generator=g, dtype=F64),
        ],
        dim=-1,
    )
    opac = 0.3 + 0.65 * torch.rand(n, generator=g, dtype=F64)
    rgb = torch.rand(n, 3, generator=g, dtype=F64)
    nx, ny = -(-w // tile), -(-h // tile)
    gauss = torch.arange(n).repeat(nx * ny)  # every Gaussian in every tile, in this depth order
    starts = torch.arange(nx * ny + 1) * n

    def fn(m, c, o, col, bg):
        tiles = splat_cpu.Tiles(gauss=gauss, starts=starts, w=w, h=h, tile=tile, nx=nx)
        return splat_cpu.composite(
            m, c, o, col, bg, tiles, alpha_min=sp.ALPHA_MIN, alpha_max=sp.ALPHA_MAX, t_min=sp.T_MIN
        )

    inputs = tuple(x.clone().requires_grad_(True) for x in (means2d, conics, opac, rgb, BG.clone()))
    out = fn(*inputs)
    assert float(out[1].detach().min()) < 0.2  # some pixels nearly opaque
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6)


@pytest.mark.skipif(not splat_cpu.available(), reason="no numba")
def test_numba_kernel_float32_matches_the_torch_path():
    """A few hundred Gaussians in float32, as training runs: both kernels' images and gradients agree."""
    pose, intr = _camera(w=48, h=40, f=60.0)
    s = _splats(300, seed=8, degree=1, opacity=0.5, size=0.05)
    s = sp.Splats(*(p.float() for p in s.parameters()))
    results = []
    for kernel in ("numba", "torch"):
        params = [p.clone().requires_grad_(True) for p in s.parameters()]
        out = sp.render(sp.Splats(*params), pose, intr, BG.float(), kernel=kernel)
        (out["rgb"].square().sum() + out["alpha"].sum()).backward()
        results.append((out["rgb"].detach(), [p.grad for p in params]))
    (img_a, grads_a), (img_b, grads_b) = results
    assert float((img_a - img_b).abs().max()) < 1e-4
    for ga, gb in zip(grads_a, grads_b, strict=True):
        assert float((ga - gb).abs().max()) <= 1e-3 * float(gb.abs().max()) + 1e-7


def test_projection_agrees_with_the_camera_module_and_culls_behind():
    pose, intr = _camera()
    s = _splats(20, seed=5)
    s.means[0] = torch.tensor([0.0, 0.0, 4.0], dtype=F64)  # behind the camera (at z = 3, looking down -z)
    proj = sp.project(s, pose, intr)
    uv, z = project(s.means, pose, intr)
    assert torch.allclose(proj.means2d[1:], uv[1:]) and torch.allclose(proj.depths, z)
    assert not bool(proj.visible[0]) and bool(proj.visible[1:].any())


def test_quaternions_round_trip_and_transform_is_a_similarity():
    q = torch.randn(50, 4, dtype=F64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    assert torch.allclose(sp.rotmat_to_quat(sp.quat_to_rotmat(q)), q, atol=1e-12)
    s = _splats(5, seed=6)
    m = torch.eye(4, dtype=F64)
    m[:3, :3] = 2.0 * sp.quat_to_rotmat(q[:1])[0] @ torch.diag(torch.tensor([1.0, 1, -1], dtype=F64))  # a mirror
    m[:3, 3] = torch.tensor([1.0, 2, 3])
    moved = sp.transformed(s, m)
    cov = sp.covariance(s.log_scales, s.quats)
    a = m[:3, :3]
    assert torch.allclose(sp.covariance(moved.log_scales, moved.quats), a @ cov @ a.T, atol=1e-12)
    assert torch.allclose(moved.means, s.means @ a.T + m[:3, 3])


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_transformed_splats_render_the_same_image_from_the_transformed_camera(degree):
    """A similarity (rotation, scale, shift) applied to the splats and to the camera changes no pixel: the SH
    coefficients turn with the view directions (`sp.sh_rotation`), band by band; and under a mirror each colour
    seen along d is the one seen along the mirrored d."""
    s = _splats(12, seed=11, degree=degree, opacity=2.0, size=0.12)
    pose, intr = _camera()
    rot = sp.quat_to_rotmat(torch.randn(1, 4, generator=torch.Generator().manual_seed(3), dtype=F64))[0]
    m = torch.eye(4, dtype=F64)
    m[:3, :3], m[:3, 3] = 1.7 * rot, torch.tensor([0.3, -1.0, 2.0], dtype=F64)
    cam = m @ pose
    cam[:3, :3] = rot @ pose[:3, :3]  # the camera's axes turned, not scaled
    moved = sp.transformed(s, m)
    before = sp.render_reference(s, pose, intr, BG)["rgb"].detach()
    after = sp.render_reference(moved, cam, intr, BG)["rgb"].detach()
    dc_only = sp.Splats(*moved.parameters()[:4], sh=moved.sh[:, :1])
    assert torch.allclose(after, before, atol=1e-9), float((after - before).abs().max())
    assert not torch.allclose(sp.render_reference(dc_only, cam, intr, BG)["rgb"].detach(), before, atol=1e-3)
    mirror = torch.eye(4, dtype=F64)
    mirror[:3, :3] = rot @ torch.diag(torch.tensor([1.0, 1, -1], dtype=F64))
    d = torch.nn.functional.normalize(torch.randn(12, 3, generator=torch.Generator().manual_seed(4), dtype=F64), dim=-1)
    seen = sp.sh_to_rgb(sp.transformed(s, mirror).sh, d @ mirror[:3, :3].T)
    assert torch.allclose(seen, sp.sh_to_rgb(s.sh, d), atol=1e-12)


def test_sh_rotation_composes_like_the_rotations_it_turns():
    """M(R2) M(R1) = M(R2 R1), M(I) = I, M(R) orthogonal (INRIA's basis is orthonormal up to one scale a band), and a
    matrix that is not a rotation or mirror is refused."""
    r1, r2 = sp.quat_to_rotmat(torch.tensor([[0.9, 0.1, -0.3, 0.2], [0.2, -0.7, 0.4, 0.5]], dtype=F64))
    mirror = r2 @ torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=F64))
    for a, b in ((r1, r2), (r1, mirror)):
        assert torch.allclose(sp.sh_rotation(b, 3) @ sp.sh_rotation(a, 3), sp.sh_rotation(b @ a, 3), atol=1e-10)
    assert torch.allclose(sp.sh_rotation(torch.eye(3, dtype=F64), 3), torch.eye(16, dtype=F64), atol=1e-12)
    m = sp.sh_rotation(r1, 3)
    assert torch.allclose(m @ m.T, torch.eye(16, dtype=F64), atol=1e-10)
    with pytest.raises(ValueError, match="orthogonal"):
        sp.sh_rotation(2.0 * r1, 2)


# ---------------------------------------------------------------------------------------------- file layouts
def _data(n: int = 5, degree: int = 1) -> SplatData:
    rng = np.random.default_rng(0)
    k = (degree + 1) ** 2 - 1
    return SplatData(
        means=rng.normal(size=(n, 3)),
        f_dc=rng.normal(size=(n, 3)),
        f_rest=rng.normal(size=(n, 3, k)),
        opacity=rng.normal(size=n),
        scales=rng.normal(size=(n, 3)) - 3,
        quats=rng.normal(size=(n, 4)),
    )


def test_ply_layout_is_inrias_and_round_trips(tmp_path):
    data = _data(5, degree=1)
    path = write_ply(tmp_path / "s.ply", data)
    raw = path.read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    lines = head.decode().splitlines()
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 5"]
    names = [
        "x",
        "y",
        "z",
        "nx",
        "ny",
        "nz",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        *[f"f_rest_{i}" for i in range(9)],
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    assert lines[3:] == [f"property float {n}" for n in names] and ply_properties(1) == names
    assert len(body) == 5 * len(names) * 4
    rows = np.frombuffer(body, "<f4").reshape(5, len(names))
    assert np.array_equal(rows[:, :3], data.means) and np.array_equal(rows[:, 3:6], np.zeros((5, 3)))
    assert np.array_equal(rows[:, 9:18], data.f_rest.reshape(5, 9))  # channel-major: red's 3, green's 3, blue's 3
    assert np.array_equal(rows[:, 18], data.opacity) and np.array_equal(rows[:, 22:], data.quats)
    back = read_ply(path)
    for key in ("means", "f_dc", "f_rest", "opacity", "scales", "quats"):
        assert np.array_equal(getattr(back, key), getattr(data, key)), key


def test_ply_reader_takes_other_orders_and_refuses_bad_files(tmp_path):
    names = [
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
        "x",
        "y",
        "z",
        "opacity",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "scale_0",
        "scale_1",
        "scale_2",
    ]
    values = np.arange(2 * len(names), dtype="<f8").reshape(2, -1)
    header = "ply\nformat binary_little_endian 1.0\ncomment x\nelement vertex 2\n"
    header += "".join(f"property double {n}\n" for n in names) + "end_header\n"
    (tmp_path / "o.ply").write_bytes(header.encode() + values.tobytes())
    got = read_ply(tmp_path / "o.ply")
    assert np.array_equal(got.means, values[:, 4:7]) and np.array_equal(got.quats, values[:, :4])
    (tmp_path / "short.ply").write_bytes(header.encode() + values.tobytes()[:-8])
    with pytest.raises(UserError, match=r"short\.ply: the header declares 2 vertices"):
        read_ply(tmp_path / "short.ply")
    (tmp_path / "a.ply").write_bytes(header.replace("binary_little_endian", "ascii").encode())
    with pytest.raises(UserError, match=r"a\.ply: PLY format 'ascii'; expected binary_little_endian"):
        read_ply(tmp_path / "a.ply")
    (tmp_path / "m.ply").write_bytes(header.replace("property double opacity\n", "").encode())
    with pytest.raises(UserError, match=r"m\.ply: not a Gaussian splat PLY: no opacity"):
        read_ply(tmp_path / "m.ply")


def test_splat_layout_is_antimatter15s():
    data = _data(6, degree=0)
    raw = splat_bytes(data)
    assert len(raw) == 6 * 32 and SPLAT_DTYPE.itemsize == 32
    key = np.exp(data.scales.sum(1)) / (1 + np.exp(-data.opacity))
    order = np.argsort(-key)
    for rank, i in enumerate(order):
        rec = raw[32 * rank : 32 * (rank + 1)]
        pos_scale = struct.unpack("<6f", rec[:24])
        assert np.allclose(pos_scale[:3], data.means[i]) and np.allclose(pos_scale[3:], np.exp(data.scales[i]))
        rgba = np.frombuffer(rec[24:28], np.uint8)
        colour = np.append(0.5 + SH_C0 * data.f_dc[i], 1 / (1 + np.exp(-data.opacity[i])))
        assert np.abs(rgba - np.clip(colour * 255, 0, 255)).max() < 1  # truncated, not rounded
        rot = np.frombuffer(rec[28:32], np.uint8).astype(np.float64)
        q = data.quats[i] / np.linalg.norm(data.quats[i])
        assert np.abs(rot - np.clip(q * 128 + 128, 0, 255)).max() < 1


# ---------------------------------------------------------------------------------------------- the stage
@pytest.fixture
def sphere_splat_run(tmp_path, monkeypatch):
    scene = sphere_scene(tmp_path / "scene", views=6, w=24, h=18)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    fake = SphereRun(scene=scene)
    monkeypatch.setattr(splat_stage, "load_trained", lambda run_dir, device: fake)
    return run_dir, fake


def test_splat_stage_end_to_end_improves_psnr_and_writes_the_user_frame(sphere_splat_run, tmp_path):
    run_dir, fake = sphere_splat_run
    out = splat_stage.run(
        splat_stage.Config(
            run_dir=run_dir,
            out=tmp_path / "o" / "s.ply",
            gaussians=400,
            max_steps=150,
            max_seconds=120,
            device="cpu",
            frame="user",
        )
    )
    assert out.backend == "torch" and out.steps == 150
    assert out.psnr_final > out.psnr_init + 1.0, (out.psnr_init, out.psnr_final)
    data = read_ply(out.out)
    assert len(data) == out.gaussians > 100  # of 400 asked (about 40 % of the rays hit the sphere: rounds of rays)
    # user frame: scene = 2 x user, the sphere (radius 0.5 scene units) is 0.25 user units around the origin
    radius = np.linalg.norm(data.means, axis=1)
    assert np.median(radius) == pytest.approx(0.25, abs=0.03)
    report = json.loads(out.report.read_text())
    assert report["stage"] == "splat" and report["used"]["backend"] == "torch" and report["check"] == "ok"
    assert np.allclose(report["out_from_scene"], fake.scene.source_from_scene())
    assert report["used"]["kernel"] == ("numba (radiance.splat_cpu)" if splat_cpu.available() else "torch")
    rows = out.metrics.read_text().splitlines()
    assert rows[0] == "step,seconds,loss,psnr" and len(rows) == 151


def test_view_dependent_splats_read_back_from_the_users_frame_are_the_ones_optimised(
    sphere_splat_run, tmp_path, monkeypatch
):
    """SH degree 3 by default: the file holds 45 f_rest coefficients (INRIA's channel-major layout), learned, in a
    user frame turned and scaled from the scene frame; read back and mapped to the scene frame they are the
    Gaussians the stage optimised (higher bands turned back with the frame), and score on the training views what
    the stage scored."""
    import dataclasses

    from nerfpipe.model.splat_run import splats_from_data
    from nerfpipe.model.splat_views import load_training_photos

    run_dir, fake = sphere_splat_run
    applied = np.eye(4)[:3].copy()
    applied[:, :3] = sp.quat_to_rotmat(torch.tensor([[0.8, 0.3, -0.4, 0.2]], dtype=F64))[0].numpy()
    fake.scene = dataclasses.replace(fake.scene, applied_transform=applied)
    optimised = []
    to_file = splat_stage._to_file
    monkeypatch.setattr(splat_stage, "_to_file", lambda s, m: (optimised.append(s), to_file(s, m))[1])
    out = splat_stage.run(
        splat_stage.Config(
            run_dir=run_dir, out=tmp_path / "s.ply", gaussians=300, max_steps=60, max_seconds=120, device="cpu"
        )
    )
    data = read_ply(out.out)
    report = json.loads(out.report.read_text())
    assert data.sh_degree == 3 and report["used"]["sh"]["degree"] == 3
    splats = splats_from_data(data, np.asarray(report["out_from_scene"]))
    want = optimised[0].subset(torch.sigmoid(optimised[0].opacity_logits) >= sp.ALPHA_MIN)
    assert float(want.sh[:, 1:].abs().max()) > 1e-4  # the higher bands learned something to turn
    assert torch.allclose(splats.sh, want.sh, rtol=1e-4, atol=1e-7)
    assert torch.allclose(splats.means, want.means, atol=1e-5)
    a = np.asarray(report["out_from_scene"])[:3, :3]
    rot = torch.as_tensor(a / abs(np.linalg.det(a)) ** (1 / 3))  # the user frame: the scene frame turned and scaled
    d = torch.nn.functional.normalize(
        torch.randn(len(want), 3, generator=torch.Generator().manual_seed(0), dtype=F64), dim=-1
    )
    sh_user = torch.as_tensor(np.concatenate([data.f_dc[:, None], np.transpose(data.f_rest, (0, 2, 1))], 1), dtype=F64)
    assert torch.allclose(sp.sh_to_rgb(sh_user, d @ rot.T), sp.sh_to_rgb(want.sh, d), atol=2e-6)  # seen the same
    photos = load_training_photos(fake.scene, fake.scene.split("train"), 1.0, fake.background.numpy().reshape(3))
    psnrs = []
    for k in report["used"]["scored_views"]:
        rgb = sp.render(splats, photos.world_from_cams[k], photos.intrinsics[k], fake.background.reshape(3).double())
        psnrs.append(-10 * math.log10(float(torch.mean((rgb["rgb"] - photos.target(k, torch.device("cpu"))) ** 2))))
    assert np.mean(psnrs) == pytest.approx(report["psnr_train_final"], abs=0.02)


def test_splat_stage_writes_splat_format_and_refuses_unknown(sphere_splat_run, tmp_path):
    run_dir, _ = sphere_splat_run
    out = splat_stage.run(
        splat_stage.Config(
            run_dir=run_dir, out=tmp_path / "s.splat", gaussians=50, max_steps=2, device="cpu", frame="normalized"
        )
    )
    assert out.out.stat().st_size == 32 * out.gaussians
    left_out = json.loads((tmp_path / "s.report.json").read_text())["left_out"]
    assert left_out["view_dependent_colour"] == "optimised to degree 3; the .splat layout holds degree 0 only"
    with pytest.raises(UserError, match=r"s\.xyz: unknown splat format"):
        splat_stage.run(splat_stage.Config(run_dir=run_dir, out=tmp_path / "s.xyz", device="cpu"))
    with pytest.raises(UserError, match="backend: gsplat cannot run here"):
        splat_stage.run(splat_stage.Config(run_dir=run_dir, out=tmp_path / "g.ply", backend="gsplat", device="cpu"))


@pytest.mark.parametrize("field", ["empty", "two surfaces"])
def test_a_field_with_no_surface_to_start_from_is_one_clear_error(field, sphere_splat_run, tmp_path, monkeypatch):
    """Nothing opaque, or every ray's weight split between two depths (expected and median depth disagree): the
    stage refuses, and writes nothing."""
    run_dir, fake = sphere_splat_run
    render = fake.render_rays

    def broken(rays_o, rays_d, **kw):
        out = render(rays_o, rays_d, **kw)
        if field == "empty":
            return {**out, "acc": torch.zeros_like(out["acc"])}
        return {**out, "depth": out["depth"] * 1.5}

    monkeypatch.setattr(fake, "render_rays", broken)
    with pytest.raises(UserError, match="training rays end on one surface in the field"):
        splat_stage.run(splat_stage.Config(run_dir=run_dir, out=tmp_path / "s.ply", gaussians=40, device="cpu"))
    assert not list(tmp_path.glob("s.*"))


def _cli(capsys, *args: str) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        cli.main([str(a) for a in args])
    captured = capsys.readouterr()
    return e.value.code, captured.out, captured.err


def test_cli_help_and_one_line_errors(sphere_splat_run, tmp_path, capsys):
    code, out, _ = _cli(capsys, "splat", "--help")
    assert code == 0 and "--max-seconds" in out and "--format" in out and "run_dir" in out.lower()
    run_dir, _ = sphere_splat_run
    code, _, err = _cli(capsys, "splat", run_dir, tmp_path / "s.txt")
    assert code == 2 and err.strip().splitlines() == [
        f"error: {tmp_path / 's.txt'}: unknown splat format; expected a .ply or .splat file (or format ply|splat)"
    ]
    code, out, _ = _cli(
        capsys, "splat", run_dir, tmp_path / "s.ply", "--gaussians", "40", "--max-steps", "1", "--device", "cpu"
    )
    assert code in (0, None) and "Gaussians, 1 steps" in out and (tmp_path / "s.report.json").is_file()
