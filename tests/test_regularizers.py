"""radiance.regularizers.distortion_loss against its O(N^2) twin (values and gradients, float64), its extremes,
and the warped distance it is measured in (radiance.contraction.normalized_distance)."""

from __future__ import annotations

import pytest
import torch

from nerfpipe.data.errors import UserError
from nerfpipe.model.methods.density import DensityOptions
from nerfpipe.radiance.contraction import Contraction, normalized_distance
from nerfpipe.radiance.regularizers import distortion_loss, distortion_loss_reference


def _packed(seed: int, counts: list[int]):
    g = torch.Generator().manual_seed(seed)
    idx = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    edges = [torch.sort(torch.rand(c + 1, generator=g, dtype=torch.float64)).values for c in counts]
    s0 = torch.cat([e[:-1] for e in edges])
    s1 = torch.cat([e[1:] for e in edges])
    w = torch.rand(idx.numel(), generator=g, dtype=torch.float64) / 4
    return w, s0, s1, idx


def test_matches_the_plain_twin_with_gradients():
    w, s0, s1, idx = _packed(0, [5, 1, 0, 9, 3])
    w.requires_grad_(True)
    got, ref = distortion_loss(w, s0, s1, idx, 5), distortion_loss_reference(w, s0, s1, idx, 5)
    torch.testing.assert_close(got, ref)
    (g_got,) = torch.autograd.grad(got, w)
    (g_ref,) = torch.autograd.grad(distortion_loss_reference(w, s0, s1, idx, 5), w)
    torch.testing.assert_close(g_got, g_ref)
    assert torch.autograd.gradcheck(lambda v: distortion_loss(v, s0, s1, idx, 5), (w,))


def test_one_peak_costs_less_than_fog():
    s = torch.linspace(0, 1, 65, dtype=torch.float64)
    s0, s1, idx = s[:-1], s[1:], torch.zeros(64, dtype=torch.long)
    peak = torch.zeros(64, dtype=torch.float64)
    peak[30] = 1.0
    fog = torch.full((64,), 1 / 64, dtype=torch.float64)
    lp, lf = distortion_loss(peak, s0, s1, idx, 1), distortion_loss(fog, s0, s1, idx, 1)
    assert lp == pytest.approx(1 / 64 / 3) and lf > 10 * lp  # a peak costs only its own width
    assert distortion_loss(torch.zeros(0), torch.zeros(0), torch.zeros(0), torch.zeros(0, dtype=torch.long), 3) == 0
    with pytest.raises(ValueError, match=r"\[N\]"):
        distortion_loss(peak[:, None], s0, s1, idx, 1)


def test_normalized_distance_runs_from_near_to_infinity():
    c = Contraction([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    o = torch.tensor([[0.0, 0.0, -3.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    t = torch.tensor([0.5, 2.0, 4.0, 1e3, 1e12], dtype=torch.float64)
    u = normalized_distance(c, o, d, 0.5, t, torch.zeros(5, dtype=torch.long))
    assert u[0] == 0 and bool((u[1:] > u[:-1]).all()) and u[-1] == pytest.approx(1.0, abs=1e-9)
    assert u[2] == pytest.approx((4.0 - 0.5) / (1.5 * 4.0 - 0.5))  # the box's exit (t_s = 4): uniform until there


def test_train_refuses_distortion_outside_contracted_scenes(tmp_path):
    from nerfpipe.stages import scene as scene_stage
    from nerfpipe.stages import train

    scene_stage.run(scene_stage.Config(out_dir=tmp_path / "s", kind="posed", size=16, views=4, seed=0))
    cfg = dict(scene_dir=tmp_path / "s", run_dir=tmp_path / "r", max_steps=1, device="cpu")
    with pytest.raises(UserError, match="contracted scenes only"):
        train.run(train.Config(**cfg, options=DensityOptions(distortion=0.01)))  # an object with alpha: box
    with pytest.raises(UserError, match="distortion >= 0"):
        train.run(train.Config(**cfg, options=DensityOptions(distortion=-1.0)))


def test_depth_nll_prefers_weight_at_the_known_depth_and_matches_a_loop():
    """DS-NeRF's loss: lower for a ray whose weight peaks at its depth than for fog in front; a per-sample loop
    gives the same value; gradients are finite even for zero weights."""
    import math

    from nerfpipe.radiance.regularizers import depth_nll_loss

    t = torch.linspace(0.0, 2.0, 41, dtype=torch.float64)
    t0, t1 = t[:-1].repeat(2), t[1:].repeat(2)
    idx = torch.repeat_interleave(torch.arange(2), 40)
    mid = 0.5 * (t0 + t1)
    peak = torch.exp(-0.5 * ((mid[:40] - 1.0) / 0.05) ** 2)
    fog = torch.full((40,), 1.0 / 40, dtype=torch.float64)
    w = torch.cat([peak / peak.sum(), fog]).requires_grad_(True)
    depth, sigma = torch.tensor([1.0, 1.0], dtype=torch.float64), torch.tensor([0.05, 0.05], dtype=torch.float64)
    wd = w.detach()
    per_ray = [
        float(depth_nll_loss(wd[idx == r], t0[idx == r], t1[idx == r], idx[idx == r] * 0, depth[:1], sigma[:1]))
        for r in range(2)
    ]
    assert per_ray[0] < per_ray[1]
    loop = 0.0
    for i in range(80):
        r = int(idx[i])
        z = (float(mid[i]) - float(depth[r])) / float(sigma[r])
        kernel = math.exp(-0.5 * z * z) / (float(sigma[r]) * math.sqrt(2 * math.pi))
        loop -= math.log(float(w.detach()[i]) + torch.finfo(torch.float64).eps) * kernel * float(t1[i] - t0[i])
    total = depth_nll_loss(w, t0, t1, idx, depth, sigma)
    assert float(total.detach()) == pytest.approx(loop / 2, rel=1e-12)
    wz = torch.zeros(80, dtype=torch.float64, requires_grad=True)
    (gz,) = torch.autograd.grad(depth_nll_loss(wz, t0, t1, idx, depth, sigma), wz)
    assert torch.isfinite(gz).all() and float(gz.min()) < 0  # more weight near the depth lowers the loss
    with pytest.raises(ValueError, match="expected depth, sigma"):
        depth_nll_loss(w, t0, t1, idx, depth, sigma[:1])


def test_train_uses_colmap_tracks_as_depth_in_contracted_scenes_and_refuses_elsewhere(tmp_path):
    """A COLMAP scene through convert trains with the depth loss by default (contracted) and says so; asking for
    it in a box scene, or with a negative weight, is one clear error."""
    import json

    import fixtures_convert as fx

    from nerfpipe.stages import convert, train

    fx.make_colmap(tmp_path / "src" / "sparse" / "0", tmp_path / "src" / "images", 10)
    convert.run(convert.Config(source=tmp_path / "src", scene_dir=tmp_path / "s"))
    cfg = dict(scene_dir=tmp_path / "s", max_steps=3, batch_rays=64, eval_every=0, final_eval_views=1, device="cpu")
    train.run(train.Config(**cfg, run_dir=tmp_path / "r", scene_model="contract"))
    used = json.loads((tmp_path / "r" / "manifest.json").read_text())["used"]
    assert used["scene_model"] == "contract"
    # the fixture's tracks: one training photo sees all 60 points
    assert used["defaults"]["depth_loss"].startswith("0.01 on 60 sparse-point rays")
    with pytest.raises(UserError, match="depth_loss: applies to contracted scenes only"):
        train.run(
            train.Config(**cfg, run_dir=tmp_path / "b", scene_model="box", options=DensityOptions(depth_loss=0.01))
        )
    with pytest.raises(UserError, match="depth_loss: expected >= 0"):
        train.run(train.Config(**cfg, run_dir=tmp_path / "n", options=DensityOptions(depth_loss=-1.0)))
