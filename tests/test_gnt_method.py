"""The gnt method (model.methods.gnt): its fast gather against its plain twin, projection, source choice, the
masked attention's extremes, the batches' hook, and a tiny scene through train, eval, render and depth; a run
made from another run's weights with no step renders what that run renders (weights plus a scene)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nerfpipe.data.errors import UserError
from nerfpipe.model.methods.gnt.hooks import GntBatches
from nerfpipe.model.methods.gnt.model import RayRange
from nerfpipe.model.methods.gnt.net import GntNet, masked_softmax, stored_config, unpremultiply
from nerfpipe.model.methods.gnt.options import GntOptions
from nerfpipe.model.methods.gnt.sources import Sources, gather, gather_plain
from nerfpipe.model.methods.gnt.weights import read_weights
from nerfpipe.radiance.camera import Intrinsics, project
from nerfpipe.stages import depth as depth_stage
from nerfpipe.stages import eval as eval_stage
from nerfpipe.stages import mesh as mesh_stage
from nerfpipe.stages import render as render_stage
from nerfpipe.stages import scene as scene_stage
from nerfpipe.stages import train
from nerfpipe.stages.view.run_view import render_camera


def test_gather_matches_grid_sample_in_values_and_gradients():
    torch.manual_seed(0)
    maps = torch.randn(3, 5, 7, 9, dtype=torch.float64, requires_grad=True)
    view = torch.randint(0, 3, (300,))
    uv = (torch.rand(300, 2, dtype=torch.float64) * torch.tensor([13.0, 11.0]) - 2).requires_grad_()  # some outside
    fast, plain = gather(maps, view, uv), gather_plain(maps, view, uv)
    torch.testing.assert_close(fast, plain, atol=1e-12, rtol=0)
    grads_fast = torch.autograd.grad(fast.square().sum(), [maps, uv])
    grads_plain = torch.autograd.grad(plain.square().sum(), [maps, uv])
    for a, b in zip(grads_fast, grads_plain, strict=True):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def _sources(distortion: tuple[float, ...] = (0.0,) * 5) -> tuple[Sources, list[Intrinsics]]:
    g = torch.Generator().manual_seed(1)
    cams, intrs, rows = [], [], []
    for i in range(4):
        a = 2 * np.pi * i / 4
        eye = np.array([3 * np.cos(a), 3 * np.sin(a), 0.5])
        fwd = -eye / np.linalg.norm(eye)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, -fwd, eye
        cams.append(torch.tensor(m, dtype=torch.float32))
        k1, k2, k3, p1, p2 = distortion
        intr = Intrinsics(w=40, h=30, fx=35.0 + i, fy=36.0, cx=20.5, cy=14.5, k1=k1, k2=k2, k3=k3, p1=p1, p2=p2)
        intrs.append(intr)
        rows.append([intr.fx, intr.fy, intr.cx, intr.cy, k1, k2, k3, p1, p2])
    images = torch.rand(4, 4, 30, 40, generator=g)
    return Sources(images, torch.stack(cams), torch.tensor(rows)), intrs


@pytest.mark.parametrize("distortion", [(0.0,) * 5, (0.05, -0.01, 0.0, 0.002, -0.001)])
def test_projection_agrees_with_the_camera_module(distortion):
    src, intrs = _sources(distortion)
    x = torch.randn(5, 6, 3, generator=torch.Generator().manual_seed(0)) * 0.2  # [R, S, 3] seen by every camera
    chosen = torch.tensor([[0, 1, 2, 3]] * 5)
    uv, seen = src.project(x, chosen)
    assert bool(seen.all())
    for k in range(4):
        want, z = project(x.reshape(-1, 3).double(), src.world_from_cams[k].double(), intrs[k])
        torch.testing.assert_close(uv[:, :, k].reshape(-1, 2).double(), want, atol=1e-3, rtol=0)
    behind = src.centres[0] + 2 * (src.centres[0] - 0)  # behind camera 0, looking away from the scene
    _, seen = src.project(behind.reshape(1, 1, 3), torch.tensor([[0]]))
    assert not bool(seen.any())


def test_sources_are_chosen_by_angle_and_a_ray_never_reads_its_own_photo():
    src, _ = _sources()
    o = src.centres[[1, 2]]  # rays from cameras 1 and 2 towards the origin
    d = -o / torch.linalg.vector_norm(o, dim=-1, keepdim=True)
    point = torch.zeros(2, 3)
    assert src.select(point, d, 1).tolist() == [[1], [2]]  # the same camera is the closest view
    picked = src.select(point, d, 2, exclude=torch.tensor([1, 2]))
    assert 1 not in picked[0].tolist() and 2 not in picked[1].tolist()
    assert set(picked[0].tolist()) == {0, 2}  # the neighbours on the circle, not the opposite camera (3)


def test_masked_softmax_matches_its_plain_twin_in_values_and_gradients():
    g = torch.Generator().manual_seed(0)
    logits = (torch.randn(40, 7, 3, generator=g, dtype=torch.float64) * 30).requires_grad_()
    mask = torch.rand(40, 7, 1, generator=g) > 0.6  # some slices with no entry at all

    def plain(x):
        w = torch.softmax(x.masked_fill(~mask, -torch.inf), dim=1)  # nan where a slice has no entry
        return torch.where(mask.any(dim=1, keepdim=True), w, torch.zeros_like(w))

    weights = torch.randn(40, 7, 3, generator=g, dtype=torch.float64)
    fast, slow = masked_softmax(logits, mask, dim=1), plain(logits)
    torch.testing.assert_close(fast, slow, atol=1e-15, rtol=0)
    (a,) = torch.autograd.grad((fast * weights).sum(), logits)
    (b,) = torch.autograd.grad((slow * weights).sum(), logits)
    torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def test_masked_softmax_is_zero_without_entries_and_finite_at_extremes():
    logits = torch.tensor([[1e30, -1e30, 0.0], [5.0, 6.0, 7.0]], requires_grad=True)
    mask = torch.tensor([[True, True, False], [False, False, False]])
    w = masked_softmax(logits, mask, dim=1)
    assert torch.allclose(w[0], torch.tensor([1.0, 0.0, 0.0])) and bool((w[1] == 0).all())
    (g,) = torch.autograd.grad((w * torch.arange(3.0)).sum(), logits)
    assert bool(torch.isfinite(g).all())


def test_a_point_no_source_sees_gives_finite_outputs_and_gradients():
    net = GntNet(channels=8, width=8, blocks=1, heads=2)
    views = torch.randn(2, 4, 3, 12)
    seen = torch.zeros(2, 4, 3, dtype=torch.bool)
    seen[0, :2, 0] = True  # the second ray: seen by none
    out = net(views, torch.randn(2, 4, 3, 4), seen, torch.linspace(0, 1, 4).expand(2, 4))
    loss = sum(v.sum() for v in out.values())
    loss.backward()
    assert all(bool(torch.isfinite(v).all()) for v in out.values())
    assert all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in net.parameters())


def test_the_blend_read_out_copies_the_colour_every_source_shows_and_unpremultiplies_it():
    """Sources that agree on a colour at every sample give that colour whatever the network's other weights are
    (the token's own colour given no weight); half-covered source pixels give the colour, not its half."""
    torch.manual_seed(0)
    net = GntNet(channels=8, width=8, blocks=1, heads=2, readout="blend")
    with torch.no_grad():
        net.own.weight.zero_()
        net.own.bias.fill_(-1e4)
    colour = torch.tensor([0.9, 0.2, 0.6])
    alpha = torch.tensor([1.0, 0.5, 0.25])[None, None, :, None].expand(3, 5, 3, 1)  # per view
    rgba = torch.cat([colour * alpha, alpha], dim=-1)  # premultiplied, [3, 5, 3, 4]
    views = torch.cat([torch.randn(3, 5, 3, 8), rgba], dim=-1)
    seen = torch.ones(3, 5, 3, dtype=torch.bool)
    out = net(views, torch.randn(3, 5, 3, 4), seen, torch.linspace(0, 1, 5).expand(3, 5))
    torch.testing.assert_close(out["rgb"], colour.expand(3, 3), atol=1e-5, rtol=0)
    zero = unpremultiply(torch.zeros(2, 4))
    assert bool((zero == 0).all())


def test_the_blend_read_out_trains_both_ways_and_old_weights_read_out_directly():
    """Gradients reach the blending logits and the token's own colour (finite, non-zero), also where a sample is
    seen by no source; a configuration stored before the read-out existed names the direct read-out."""
    torch.manual_seed(1)
    net = GntNet(channels=8, width=8, blocks=1, heads=2)
    assert net.readout == "blend"
    views = torch.rand(2, 4, 3, 12)
    seen = torch.rand(2, 4, 3) > 0.3
    seen[1] = False
    out = net(views, torch.randn(2, 4, 3, 4), seen, torch.linspace(0, 1, 4).expand(2, 4))
    out["rgb"].sum().backward()
    for p in (net.blend[0].weight, net.own.weight, net.rgb[0].weight):
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()) and float(p.grad.abs().sum()) > 0
    assert stored_config({"extractor": "shallow"})["readout"] == "direct"
    assert GntNet.from_config({"extractor": "shallow", "readout": "blend"}).readout == "blend"


def test_inverse_depth_samples_reach_far_and_stay_finite_without_a_far_plane():
    rng = RayRange(near=0.5, far=float("inf"))
    o, d = torch.zeros(3, 3), torch.tensor([[0.0, 0.0, -1.0]] * 3)
    t, s = rng.samples(o, d, 8, None)
    assert bool(torch.isfinite(t).all()) and bool((t.diff(dim=1) > 0).all()) and float(t[0, 0]) > 0.5
    assert float(t[0, -1]) == pytest.approx(0.5 * 16)  # 1/t = (1 - s)/near at s = 1 - 1/16
    box = RayRange(0.0, 10.0, ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)))
    t, _ = box.samples(torch.tensor([[0.0, 0.0, 3.0]]), d[:1], 4, None)
    torch.testing.assert_close(t, torch.tensor([[2.25, 2.75, 3.25, 3.75]]))


def test_batches_come_from_the_asked_number_of_photos():
    offsets = torch.tensor([0, 100, 250, 300, 420])
    hook = GntBatches(offsets, per_step=2)

    class Loop:
        gen = torch.Generator().manual_seed(0)

    idx = hook.draw(Loop(), 64)
    photos = torch.searchsorted(offsets, idx, right=True) - 1
    assert idx.shape == (64,) and photos.unique().numel() == 2 and int(idx.max()) < 420


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("gnt")
    scene_stage.run(scene_stage.Config(out_dir=root / "scene", kind="posed", size=24, views=10, seed=2))
    out = train.run(
        train.Config(
            scene_dir=root / "scene",
            run_dir=root / "run",
            method="gnt",
            max_steps=60,
            batch_rays=256,
            eval_every=0,
            device="cpu",
            seed=0,
            options=GntOptions(source_views=4, gnt_samples=12),
        )
    )
    return root, out


def test_a_tiny_scene_trains_and_goes_through_eval_render_and_depth(tiny):
    root, out = tiny
    rows = (root / "run" / "metrics.csv").read_text().splitlines()
    header = rows[0].split(",")
    cells = [r.split(",")[header.index("loss")] for r in rows[1:]]
    mse = [float(c) for c in cells if c]
    assert mse[-1] < 0.8 * mse[0]  # it learns (60 steps: 0.070 -> 0.049 when written)
    manifest = json.loads(out.manifest.read_text())
    assert manifest["used"]["method"] == "gnt" and manifest["used"]["gnt"]["source_views"] == 4
    ev = eval_stage.run(eval_stage.Config(run_dir=root / "run", out=root / "eval.json", device="cpu"))
    assert ev.result["psnr"] == pytest.approx(out.test_psnr, abs=0.3)
    dm = depth_stage.run(depth_stage.Config(run_dir=root / "run", out_dir=root / "depth", device="cpu"))
    assert len(dm.names) == ev.result["n_views"]
    video = render_stage.run(
        render_stage.Config(run_dir=root / "run", out=root / "turn.mp4", path="turntable", frames=2, device="cpu")
    )
    assert video.n_frames == 2
    from nerfpipe.model import load_trained

    image = render_camera(
        load_trained(root / "run", "cpu"), (1.0, 0.0, 0.0, 0.0), (0.1, -3.0, 0.2), 0.8, 1.0, 16, coarse=True
    )
    assert image.shape == (16, 16, 3) and image.dtype == np.uint8  # what `view` shows
    with pytest.raises(UserError, match="a gnt run cannot give a signed distance at points or give a density"):
        mesh_stage.run(mesh_stage.Config(run_dir=root / "run", out=root / "m.ply", device="cpu"))


def test_a_run_of_given_weights_and_no_step_renders_what_their_run_renders(tiny):
    root, out = tiny
    zero = train.run(
        train.Config(
            scene_dir=root / "scene",
            run_dir=root / "zero",
            method="gnt",
            max_steps=0,
            eval_every=0,
            device="cpu",
            options=GntOptions(init=str(out.checkpoint), source_views=4, gnt_samples=12),
        )
    )
    assert zero.test_psnr == pytest.approx(out.test_psnr, abs=0.05)
    refused = (
        ("not gnt weights", GntOptions(init=str(root / "scene" / "transforms.json"))),
        (
            "readout: the initial weights use 'blend', not 'direct'",
            GntOptions(init=str(out.checkpoint), readout="direct"),
        ),
    )
    for line, options in refused:
        with pytest.raises(UserError, match=line):
            train.run(
                train.Config(
                    scene_dir=root / "scene",
                    run_dir=root / "bad",
                    method="gnt",
                    max_steps=0,
                    device="cpu",
                    options=options,
                )
            )
    assert not (root / "bad" / "checkpoint.pt").exists()


def test_pretraining_across_scenes_writes_weights_a_run_starts_from(tmp_path):
    from nerfpipe.stages import pretrain_gnt

    data = scene_stage.run(
        scene_stage.Config(out_dir=tmp_path / "scenes", subject="random", kind="rgba", size=16, views=5, count=2)
    )
    assert [p.name for p in data.scenes] == ["000000", "000001"]
    out = pretrain_gnt.run(
        pretrain_gnt.Config(
            scenes=tmp_path / "scenes", out_dir=tmp_path / "pre", max_steps=30, batch_rays=64, gnt_samples=8
        )
    )
    manifest = json.loads(out.manifest.read_text())
    assert out.steps == 30 and manifest["used"]["scene_count"] == 2 and manifest["used"]["photos"] == 10
    assert out.loss_end < out.loss_start  # it learns across scenes
    assert not (tmp_path / "pre" / "weights.partial.pt").exists()
    run = train.run(
        train.Config(
            scene_dir=tmp_path / "scenes" / "000001",
            run_dir=tmp_path / "zero",
            method="gnt",
            max_steps=0,
            device="cpu",
            options=GntOptions(init=str(out.weights), gnt_samples=8),
        )
    )
    assert run.steps == 0 and run.test_psnr is not None
    more = pretrain_gnt.run(  # continued: the new weights keep what made the ones they started from
        pretrain_gnt.Config(
            scenes=tmp_path / "scenes",
            out_dir=tmp_path / "more",
            max_steps=2,
            batch_rays=64,
            gnt_samples=8,
            init=str(out.weights),
        )
    )
    prov = read_weights(str(more.weights), torch.device("cpu"))[2]
    assert prov["steps"] == 2 and prov["init_provenance"]["steps"] == 30
    assert json.loads(more.manifest.read_text())["used"]["steps_before"] == 30
    with pytest.raises(UserError, match="no scene folders"):
        pretrain_gnt.run(pretrain_gnt.Config(scenes=tmp_path / "pre", out_dir=tmp_path / "pre2", max_steps=1))
    with pytest.raises(UserError, match="not gnt weights"):
        pretrain_gnt.run(
            pretrain_gnt.Config(scenes=tmp_path / "scenes", out_dir=tmp_path / "pre3", init=str(out.manifest))
        )
    assert not (tmp_path / "pre2").exists() and not (tmp_path / "pre3").exists()  # bad input: nothing written


def test_a_training_ray_reads_every_photo_but_its_own_and_a_new_view_reads_them_all():
    from nerfpipe.model.methods.gnt.model import GntModel

    src, _ = _sources()
    model = GntModel(
        net=GntNet(channels=8, width=8, blocks=1, heads=2),
        sources=src,
        range=RayRange(0.5, 6.0, ((-1.0,) * 3, (1.0,) * 3)),
        samples=4,
        k=4,
    )
    picked = []
    select = src.select
    src.select = lambda *a, **kw: picked.append(select(*a, **kw)) or picked[-1]
    o = src.centres[[1, 2]]
    d = -o / torch.linalg.vector_norm(o, dim=-1, keepdim=True)
    model.render(o, d, torch.ones(3), train=True, view=torch.tensor([1, 2]))
    model.render(o, d, torch.ones(3), train=False)
    assert picked[0].shape == (2, 3) and 1 not in picked[0][0].tolist() and 2 not in picked[0][1].tolist()
    assert picked[1].shape == (2, 4)


def test_the_shipped_weights_render_a_scene_they_never_saw_better_than_a_constant_colour(tmp_path):
    """A fresh clone renders zero-shot: `--init pretrained --max-steps 0` on a generated scene of a seed the
    pretraining never drew (it drew 100000-399999), scored against the best constant colour (the test photos' mean)."""
    from nerfpipe.model.methods.gnt.weights import PRETRAINED

    provenance = read_weights("pretrained", torch.device("cpu"))[2]
    assert PRETRAINED.stat().st_size < 10e6 and provenance["stage"] == "pretrain-gnt" and provenance["steps"] > 0
    scene_stage.run(
        scene_stage.Config(out_dir=tmp_path / "s", subject="random", kind="rgba", size=64, views=12, seed=990001)
    )
    out = train.run(
        train.Config(
            scene_dir=tmp_path / "s",
            run_dir=tmp_path / "zero",
            method="gnt",
            max_steps=0,
            device="cpu",
            options=GntOptions(init="pretrained"),
        )
    )
    from nerfpipe.model import load_trained
    from nerfpipe.model.views import load_views

    run = load_trained(tmp_path / "zero", "cpu")
    test = load_views(run.scene, run.scene.split("test"))
    rgba = test.rgba.float() / 255
    white = rgba[:, :3] * rgba[:, 3:] + (1 - rgba[:, 3:])  # the photos on the white evaluation background
    constant_psnr = float(-10 * torch.log10(((white - white.mean(0)) ** 2).mean()))
    print(f"zero-shot {out.test_psnr:.2f} dB, the best constant colour {constant_psnr:.2f} dB")
    assert out.test_psnr > constant_psnr + 1.0
