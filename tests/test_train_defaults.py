"""train's data-driven defaults (stages.train.defaults): background detection, grid size from the object's
size in pixels, scale invariance, and the unbounded (room) scene where contraction beats the box."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from nerfpipe.data.transforms import read_scene
from nerfpipe.model.background import Background
from nerfpipe.model.views import Views
from nerfpipe.stages import convert as convert_stage
from nerfpipe.stages import scene as scene_stage
from nerfpipe.stages import train
from nerfpipe.stages.train.background import background_conflict, choose_background, detect_plain_colour


def _views(images: list[np.ndarray]) -> Views:
    """Views holding only colours (rays are not needed to detect a background)."""
    rgba = [np.concatenate([im, np.full(im.shape[:2] + (1,), 255, np.uint8)], -1).reshape(-1, 4) for im in images]
    n = len(images)
    offsets = torch.tensor([0] + [len(r) for r in rgba]).cumsum(0)
    return Views(
        rgba=torch.from_numpy(np.concatenate(rgba)),
        offsets=offsets,
        world_from_cams=torch.eye(4, dtype=torch.float64).repeat(n, 1, 1),
        intrinsics=torch.ones(n, 9, dtype=torch.float64),
        shapes=[im.shape[:2] for im in images],
    )


def _object_on(colour: int | None, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (32, 40, 3), dtype=np.uint8)  # textured everywhere (no plain colour)
    if colour is not None:
        img[:] = colour
        img[8:24, 10:30] = rng.integers(0, 256, (16, 20, 3), dtype=np.uint8)  # the object in the middle
    return img


@pytest.mark.parametrize(("colour", "expected"), [(0, (0.0, 0.0, 0.0)), (255, (1.0, 1.0, 1.0))])
def test_plain_border_colour_is_detected(colour, expected):
    views = _views([_object_on(colour, s) for s in range(3)])
    bg, plain, why = choose_background("auto", views, has_alpha=False)
    assert plain and bg.mode == "plain" and "transparent" in why  # its pixels train as alpha 0
    assert np.allclose(bg.eval_colour().numpy(), expected, atol=1e-6)


def test_plain_background_is_random_only_behind_the_rays_marked_random():
    bg = Background("plain", (0.0, 0.0, 0.0))
    random = torch.tensor([True, False, True, False])
    colour = bg.train_colour(4, torch.Generator().manual_seed(0), random=random)  # [4, 3]
    assert colour.shape == (4, 3) and (colour[~random] == 0).all()  # edge and object pixels: as made
    assert (colour[random] > 0).all() and not torch.equal(colour[0], colour[2])
    with pytest.raises(ValueError, match="random"):
        bg.train_colour(4)


def test_textured_border_trains_on_random_and_alpha_too():
    views = _views([_object_on(None, s) for s in range(3)])
    bg, plain, why = choose_background("auto", views, has_alpha=False)
    assert not plain and bg.mode == "random" and "no plain border colour" in why
    assert choose_background("learned", views, has_alpha=False)[0].mode == "learned"
    assert choose_background("auto", views, has_alpha=True)[0].mode == "random"
    assert choose_background("black", views, has_alpha=False)[0].eval_colour().tolist() == [0.0, 0.0, 0.0]


def test_a_background_asked_for_against_the_photos_plain_colour_is_a_conflict():
    """White-backed photos trained on black (or random colours) cannot be fitted: said in one line; the same colour,
    auto, alpha, or photos without a plain border are no conflict."""
    white = _views([_object_on(255, s) for s in range(3)])
    black_says = background_conflict("black", white, has_alpha=False)
    assert black_says is not None and "(1.00, 1.00, 1.00)" in black_says and "--background black" in black_says
    assert "random colours" in background_conflict("random", white, has_alpha=False)
    assert background_conflict("white", white, has_alpha=False) is None
    assert background_conflict("auto", white, has_alpha=False) is None
    assert background_conflict("black", white, has_alpha=True) is None
    assert background_conflict("black", _views([_object_on(None, s) for s in range(3)]), has_alpha=False) is None


def test_detect_plain_colour_thresholds():
    rgb = np.zeros((100, 3))
    rgb[:5] = 1.0  # 95 % plain
    colour, frac = detect_plain_colour(rgb)
    assert colour == (0.0, 0.0, 0.0) and frac == pytest.approx(0.95)
    rgb[:20] = 1.0  # 80 %: not plain
    assert detect_plain_colour(rgb)[0] is None
    assert detect_plain_colour(np.zeros((0, 3))) == (None, 0.0)


def _train(scene_dir: Path, run_dir: Path, **kw) -> train.Outputs:
    base = dict(
        scene_dir=scene_dir,
        run_dir=run_dir,
        max_steps=120,
        max_seconds=600.0,
        eval_every=0,
        final_eval_views=2,
        device="cpu",
        threads=1,
        seed=0,
    )
    base.update(kw)
    return train.run(train.Config(**base))


def test_scene_scale_does_not_change_training(tmp_path):
    """The same object at 0.01 and 100 units (Blender layout, as people export them) trains alike: the box,
    the grid and the steps follow the data, not a convention."""
    psnr, used = {}, {}
    for scale in (0.01, 100.0):
        src, scene = tmp_path / f"src{scale}", tmp_path / f"scene{scale}"
        scene_stage.run(scene_stage.Config(out_dir=src, kind="blender", size=32, views=16, seed=0, scale=scale))
        convert_stage.run(convert_stage.Config(source=src, scene_dir=scene, downscales=()))
        out = _train(scene, tmp_path / f"run{scale}")
        psnr[scale] = out.test_psnr
        used[scale] = json.loads(out.manifest.read_text())["used"]["defaults"]["resolved"]
    assert used[0.01] == used[100.0]
    assert abs(psnr[0.01] - psnr[100.0]) < 0.3, psnr
    assert min(psnr.values()) > 16.0, psnr


def test_room_scene_contraction_beats_the_box(tmp_path):
    """An object in a textured room (the background lies beyond the box): auto picks contraction, which scores
    above the box model with the same steps."""
    src, scene = tmp_path / "src", tmp_path / "scene"
    scene_stage.run(scene_stage.Config(out_dir=src, kind="posed", layout="room", size=32, views=24, seed=0))
    convert_stage.run(convert_stage.Config(source=src, scene_dir=scene, downscales=()))
    box = _train(scene, tmp_path / "box", scene_model="box", max_steps=250)
    auto = _train(scene, tmp_path / "auto", max_steps=250)
    used = json.loads(auto.manifest.read_text())["used"]
    assert used["scene_model"] == "contract" and used["background"]["mode"] == "random"
    assert auto.test_psnr > box.test_psnr + 0.3, (auto.test_psnr, box.test_psnr)


@pytest.mark.parametrize(("layout", "kind"), [("orbit", "box"), ("forward", "ndc"), ("room", "contract")])
def test_each_kind_of_capture_gets_its_own_rules(tmp_path, layout, kind):
    """scene --layout orbit|forward|room: the scene model is chosen first, then that kind's grid, step, TV and
    density activation rules (`RULES`), each reason naming its kind; no rule of one kind applies to another."""
    from nerfpipe.model.methods.density.rules import NDC_MIN_STEP_VOXELS, NDC_RANK, NDC_SAMPLES, RULES
    from nerfpipe.model.views import load_views
    from nerfpipe.stages.train.defaults import Photos, resolve_defaults

    src, scene_dir = tmp_path / "src", tmp_path / "scene"
    scene_kind = "rgba" if layout == "orbit" else "posed"
    scene_stage.run(scene_stage.Config(out_dir=src, kind=scene_kind, layout=layout, size=48, views=12, seed=0))
    convert_stage.run(convert_stage.Config(source=src, scene_dir=scene_dir, downscales=()))
    scene = read_scene(scene_dir)
    idx = scene.split("train")
    config = train.Config(scene_dir=scene_dir, run_dir=tmp_path / "run")
    photos = Photos(scene=scene, train=load_views(scene, idx), test=None, train_idx=idx)
    found = resolve_defaults(config, photos, torch.device("cpu"), 1.0)
    assert found.space.name == kind and found.reasons["scene_model"].startswith(kind)
    fast = found.config.options
    assert fast.tv == RULES[type(found.space)].tv()[0]
    if kind == "ndc":  # the march takes NDC_SAMPLES steps across z' in [-1, 1], whatever the grid
        assert "z'" in found.reasons["step_ratio"] and "image" in found.reasons["resolution"]
        from nerfpipe.model.spaces import scene_ndc

        poses = np.stack([f.world_from_cam for f in scene.frames])
        box = scene_ndc(scene).box(poses, [scene.frame_intrinsics(i) for i in range(len(scene.frames))])
        step = float(np.mean(box[1] - box[0])) / fast.resolution[1] * fast.step_ratio
        assert 2.0 / step == pytest.approx(NDC_SAMPLES) or fast.step_ratio == NDC_MIN_STEP_VOXELS
    else:
        assert "object" in found.reasons["resolution"] and "z'" not in found.reasons["step_ratio"]
    assert (fast.tv > 0) == (kind != "box")
    # components per plane: NDC's own (more steps), TensoRF's for the others
    assert fast.rank == (NDC_RANK if kind == "ndc" else (16, 48)) and "components" in found.reasons["rank"]
    # density through relu on NDC scenes only (TensoRF's LLFF setting), softplus for objects and contracted scenes
    assert fast.density_activation == ("relu" if kind == "ndc" else "softplus")
    assert found.reasons["density_activation"].startswith(fast.density_activation)
    # a colour MLP 64 wide for every kind (128, TensoRF's LLFF width, only when asked for)
    assert fast.mlp_width == 64
    assert found.reasons["mlp_width"].startswith(str(fast.mlp_width))


def test_plain_colour_clears_only_the_background_around_the_object():
    """A white object on a whitened background: only the white region that touches the image border becomes
    transparent; the object's own white face (inside, enclosed by other colours) stays opaque."""
    img = np.full((20, 24, 3), 255, np.uint8)
    img[4:16, 6:18] = (200, 30, 30)  # the object
    img[7:13, 9:15] = 255  # its white face, enclosed by the object's red
    views = _views([img])
    share = views.mask_colour((1.0, 1.0, 1.0))
    alpha = views.rgba[:, 3].reshape(20, 24).numpy()
    assert (alpha[7:13, 9:15] == 255).all() and (alpha[4:16, 6:18] == 255).all()
    assert (alpha[:4] == 0).all() and (alpha[:, :6] == 0).all()
    assert share == pytest.approx((20 * 24 - 12 * 12) / (20 * 24))
    idx = torch.arange(20 * 24)
    transparent = views.rgba[:, 3] == 0
    assert torch.equal(views.random_behind(idx, transparent), transparent)  # the object on the plain colour


def test_with_pose_refinement_the_object_trains_on_a_random_colour_but_its_plain_face_does_not():
    """opaque_object (pose refinement): the object's pixels get a random colour behind them, as with alpha; its
    own white face (it may be a hole) and the transparent background keep theirs (plain colour / random)."""
    img = np.full((20, 24, 3), 255, np.uint8)
    img[4:16, 6:18] = (200, 30, 30)
    img[7:13, 9:15] = 255
    views = _views([img])
    views.mask_colour((1.0, 1.0, 1.0), opaque_object=True)
    rand = views.random_behind(torch.arange(20 * 24), views.rgba[:, 3] == 0).reshape(20, 24)
    assert not rand[7:13, 9:15].any()  # the white face: on the plain colour
    red = torch.zeros(20, 24, dtype=torch.bool)
    red[4:16, 6:18], red[7:13, 9:15] = True, False
    assert rand[red].all() and rand[:4].all() and rand[:, :6].all()  # the object and the background: random


def test_the_background_joins_the_training_device(tmp_path):
    """Every CUDA training failed at its first step (bench-gpu on an H200: the background colours stayed on the CPU
    while the batch was on the GPU): the resolved background lives on the device it is resolved for. The meta
    device stands in for CUDA here."""
    from nerfpipe.model.views import load_views
    from nerfpipe.stages.train.defaults import Photos, resolve_defaults

    src, scene_dir = tmp_path / "src", tmp_path / "scene"
    scene_stage.run(scene_stage.Config(out_dir=src, kind="rgba", size=24, views=6, seed=0))
    convert_stage.run(convert_stage.Config(source=src, scene_dir=scene_dir, downscales=()))
    scene = read_scene(scene_dir)
    idx = scene.split("train")
    photos = Photos(scene=scene, train=load_views(scene, idx), test=None, train_idx=idx)
    config = train.Config(scene_dir=scene_dir, run_dir=tmp_path / "run")
    found = resolve_defaults(config, photos, torch.device("meta"), 1.0)
    assert found.context.background.fixed.device.type == "meta"
