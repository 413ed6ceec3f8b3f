"""Per-image appearance: identity at the start, exact on composited colour, off by default, saved and used by
load_trained with the mean-code rule, and learning per-image gains on a tiny scene."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.bench_refine import degrade_scene
from nerfpipe.model import load_trained
from nerfpipe.model.appearance import EVAL_RULE, EVAL_RULES, Appearance, apply_transform, fit_code
from nerfpipe.stages import eval as eval_stage
from nerfpipe.stages import scene as scene_stage
from nerfpipe.stages import train
from tests.test_refine import tiny_config


def test_starts_as_the_identity_and_commutes_with_compositing():
    app = Appearance(4, dim=3)
    rgb, acc, bg = torch.rand(6, 3), torch.rand(6), torch.tensor([1.0, 0.5, 0.0])
    composited = rgb * acc[:, None] + (1 - acc)[:, None] * bg
    assert torch.allclose(app(composited, acc, bg, torch.tensor([0, 1, 2, 3, 0, 1])), composited, atol=1e-7)
    with torch.no_grad():
        app.head.weight.normal_()
        app.head.bias.normal_()
    view = torch.tensor([0, 1, 2, 3, 0, 1])
    a, b = app.transform(view)
    # per sample: two samples of weights w1, w2 with colours c1, c2 on each ray
    w = torch.rand(6, 2) * 0.5
    c = torch.rand(6, 2, 3)
    per_sample = (w[..., None] * ((a[:, None] @ c[..., None])[..., 0] + b[:, None])).sum(1)
    acc2 = w.sum(1)
    expected = per_sample + (1 - acc2)[:, None] * bg
    got = app((w[..., None] * c).sum(1) + (1 - acc2)[:, None] * bg, acc2, bg, view)
    assert torch.allclose(got, expected, atol=1e-6)
    mean_a, mean_b = app.transform(None)
    assert torch.allclose(mean_a[0], app.transform(torch.arange(4))[0].mean(0), atol=1e-6)
    assert torch.allclose(mean_b[0], app.transform(torch.arange(4))[1].mean(0), atol=1e-6)


def test_fit_code_recovers_a_code_from_half_a_view():
    """NeRF-W's rule: the code whose transform maps the field's colours to the photo, by least squares."""
    torch.manual_seed(0)
    app = Appearance(5, dim=4)
    with torch.no_grad():
        app.head.weight.normal_(std=0.2)
        app.head.bias.normal_(std=0.05)
    rgb, acc, bg = torch.rand(400, 3), torch.rand(400), torch.tensor([1.0, 1.0, 1.0])
    rgb = rgb * acc[:, None] + (1 - acc)[:, None] * bg
    code = torch.tensor([0.5, -1.0, 0.25, 2.0])
    target = apply_transform(app.code_transform(code[None]), rgb, acc, bg).detach()
    got = fit_code(app, rgb, acc, bg, target, ridge=1e-9)
    assert torch.allclose(got, code, atol=1e-4), got
    with pytest.raises(ValueError, match="expected rgb, target"):
        fit_code(app, rgb, acc, bg, target[:10])


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("appearance")
    scene_stage.run(scene_stage.Config(out_dir=root / "clean", kind="rgba", size=24, views=12, seed=0))
    return root / "clean", degrade_scene(root / "clean", root / "varied")


def test_off_by_default_and_same_first_loss(scenes, tmp_path):
    assert not train.Config(scene_dir=Path("s"), run_dir=Path("r")).appearance
    off = train.run(tiny_config(scenes[1], tmp_path / "off"))
    assert torch.load(off.checkpoint, weights_only=True)["appearance"] is None
    assert "appearance" in json.loads(off.manifest.read_text())["left_out"]
    on = train.run(tiny_config(scenes[1], tmp_path / "on", appearance=True))
    runs = (tmp_path / "off", tmp_path / "on")
    first = [float((p / "metrics.csv").read_text().splitlines()[1].split(",")[2]) for p in runs]
    assert first[1] == pytest.approx(first[0], rel=1e-4) and on.steps == off.steps  # float rounding of A c + b
    assert load_trained(tmp_path / "off", "cpu").model.appearance is None


def test_codes_learn_the_gains_and_eval_uses_the_mean(scenes, tmp_path):
    run = tmp_path / "run"
    out = train.run(tiny_config(scenes[1], run, max_steps=300, batch_rays=512, appearance=True, log_every=100))
    trained = load_trained(run, "cpu")
    app = trained.model.appearance
    assert app is not None and app.n_views == len(trained.scene.split("train"))
    a, _ = app.transform(torch.arange(app.n_views))
    gains = a.diagonal(dim1=1, dim2=2).mean(1).detach().numpy()  # learned, relative to the field's colour
    rng = np.random.default_rng(0)  # degrade_scene's draws, in its order
    truth = np.array([rng.uniform(0.6, 1.4) * rng.uniform(0.85, 1.15, size=3).mean() for _ in range(app.n_views)])
    assert np.corrcoef(gains, truth)[0, 1] > 0.8, (gains, truth)
    used = json.loads(out.manifest.read_text())["used"]["appearance"]
    assert used["evaluation"] == EVAL_RULE
    res = eval_stage.run(eval_stage.Config(run_dir=run, out=tmp_path / "eval.json", device="cpu")).result
    assert res["appearance"] == EVAL_RULE and res["appearance_rule"] == "mean"
    assert res["scored_pixels"] == "whole views"
    half = eval_stage.run(
        eval_stage.Config(run_dir=run, out=tmp_path / "half.json", device="cpu", appearance_rule="half")
    ).result
    assert half["appearance"] == EVAL_RULES["half"] and half["scored_pixels"].startswith("right half")
    assert np.isfinite(half["psnr"])
