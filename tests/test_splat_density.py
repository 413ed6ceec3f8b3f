"""Densification of splats (`model.splat_density`): which Gaussians are cloned, split and pruned, the cap, the Adam
moments carried over, and the splat stage refining on its own loop (the report lists every refinement)."""

from __future__ import annotations

import json
import math

import torch

import nerfpipe.stages.splat as splat_stage
from nerfpipe.data.splat_ply import read_ply
from nerfpipe.model import splat_density as dens
from nerfpipe.radiance import splats as sp
from nerfpipe.stages.splat import steps as splat_steps

try:
    from test_splats import sphere_splat_run  # noqa: F401  (the fixture)
except ImportError:
    from tests.test_splats import sphere_splat_run  # noqa: F401


def _four() -> tuple[sp.Splats, dens.GradStats]:
    """0: small, large gradient (clone); 1: large, large gradient (split); 2: nearly transparent (prune); 3: quiet."""
    scales = torch.tensor([0.005, 0.2, 0.005, 0.005])
    opacity = torch.tensor([0.5, 0.5, 0.001, 0.5])
    splats = sp.Splats(
        means=torch.arange(12.0).reshape(4, 3),
        log_scales=torch.log(scales)[:, None].repeat(1, 3),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(4, 1),
        opacity_logits=torch.logit(opacity),
        sh=torch.arange(12.0).reshape(4, 1, 3),
    )
    stats = dens.GradStats.zeros(4)
    grad = torch.tensor([[1e-3, 0.0], [0.0, 2e-3], [1e-3, 0.0], [1e-6, 0.0]])  # half-image units at w = h = 2
    stats.add(grad, torch.tensor([True, True, True, True]), 2, 2)
    stats.add(grad, torch.tensor([True, True, False, True]), 2, 2)
    return splats, stats


def test_clone_split_prune_and_what_each_new_row_comes_from():
    splats, stats = _four()
    assert torch.allclose(stats.mean(), torch.tensor([1e-3, 2e-3, 1e-3, 1e-6]))  # means over the views that drew it
    new, source, fresh, counts = dens.refine(splats, stats, extent=1.0, limit=100, gen=torch.Generator().manual_seed(0))
    assert counts == {"cloned": 1, "split": 1, "pruned": 1, "gaussians": 5}
    assert source.tolist() == [0, 3, 0, 1, 1] and fresh.tolist() == [False, False, True, True, True]
    assert torch.equal(new.means[2], splats.means[0]) and torch.equal(new.sh[2], splats.sh[0])  # the clone
    halves = new.means[3:]
    assert not torch.equal(halves[0], halves[1])
    assert float(torch.linalg.norm(halves - splats.means[1], dim=-1).max()) < 5 * 0.2  # drawn from the Gaussian
    assert torch.allclose(new.log_scales[3:], splats.log_scales[1] - math.log(dens.SPLIT_SHRINK))
    assert torch.equal(new.opacity_logits[3:], splats.opacity_logits[[1, 1]])


def test_the_cap_takes_the_largest_gradients_first():
    splats, stats = _four()
    new, source, _, counts = dens.refine(splats, stats, extent=1.0, limit=4, gen=torch.Generator().manual_seed(0))
    # 3 left after pruning, room for one more: the split (gradient 2e-3) goes, the clone (1e-3) waits
    assert counts == {"cloned": 0, "split": 1, "pruned": 1, "gaussians": 4} and source.tolist() == [0, 3, 1, 1]
    _, _, _, none = dens.refine(splats, stats, extent=1.0, limit=3, gen=torch.Generator().manual_seed(0))
    assert none["cloned"] == none["split"] == 0 and none["gaussians"] == 3


def test_adam_moments_follow_their_rows_and_new_rows_start_at_zero():
    splats, stats = _four()
    params = [p.clone().requires_grad_(True) for p in splats.parameters()]
    opt = torch.optim.Adam([{"params": [p], "lr": 1e-3} for p in params])
    sum(p.square().sum() for p in params).backward()
    opt.step()
    new, source, fresh, _ = dens.refine(
        sp.Splats(*params), stats, extent=1.0, limit=100, gen=torch.Generator().manual_seed(0)
    )
    new_params = [p.requires_grad_(True) for p in new.parameters()]
    old_state = {i: {k: v.clone() for k, v in opt.state[p].items()} for i, p in enumerate(params)}
    dens.carry_adam(opt, params, new_params, source, fresh)
    for i, q in enumerate(new_params):
        assert opt.param_groups[i]["params"] == [q]
        for key in ("exp_avg", "exp_avg_sq"):
            moved = opt.state[q][key]
            assert torch.equal(moved[~fresh], old_state[i][key][source[~fresh]])
            assert bool((moved[fresh] == 0).all())
    sum(p.square().sum() for p in new_params).backward()
    opt.step()  # Adam runs on the new shapes
    assert all(bool(torch.isfinite(p).all()) for p in new_params)


def test_the_stage_densifies_on_its_loop_and_writes_what_it_ends_with(sphere_splat_run, tmp_path, monkeypatch):
    monkeypatch.setattr(splat_steps, "DENSIFY_EVERY", 10)  # read where the step uses it
    run_dir, _ = sphere_splat_run
    out = splat_stage.run(
        splat_stage.Config(
            run_dir=run_dir,
            out=tmp_path / "s.ply",
            gaussians=150,
            max_steps=60,
            max_seconds=120,
            device="cpu",
            densify=True,
        )
    )
    report = json.loads(out.report.read_text())
    refinements = report["used"]["densification"]["refinements"]
    assert [r["step"] for r in refinements] == [10, 20, 30]  # progress 1/6 .. 1/2, inside DENSIFY_SPAN
    assert refinements[-1]["gaussians"] > 150 and sum(r["cloned"] + r["split"] for r in refinements) > 0
    assert len(read_ply(out.out)) == out.gaussians == report["gaussians"]
    assert out.gaussians == refinements[-1]["gaussians"] - report["used"]["dropped_invisible"]
    assert out.psnr_final > out.psnr_init and report["check"] == "ok"
    assert "densification" not in report["left_out"]
    off = splat_stage.run(
        splat_stage.Config(
            run_dir=run_dir, out=tmp_path / "n.ply", gaussians=150, max_steps=60, max_seconds=120, device="cpu"
        )
    )
    off_report = json.loads(off.report.read_text())  # the default
    assert off_report["used"]["densification"] == "off (--densify turns it on)"
    assert off_report["left_out"]["densification"] == splat_stage.DENSIFY_OFF and off.gaussians <= 150


def test_refine_with_nothing_to_do_keeps_every_gaussian():
    splats, _ = _four()
    splats = splats.subset(torch.tensor([0, 1, 3]))
    stats = dens.GradStats.zeros(len(splats))
    new, source, fresh, counts = dens.refine(splats, stats, extent=1.0, limit=10, gen=torch.Generator())
    assert counts == {"cloned": 0, "split": 0, "pruned": 0, "gaussians": 3} and not bool(fresh.any())
    assert torch.equal(new.means, splats.means) and source.tolist() == [0, 1, 2]
