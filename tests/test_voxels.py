"""Single-view voxels (issue 50): shape families with exact occupancy, the input preprocessing, the network, the
fusion of several photos, the stages shapes / pretrain-voxels / voxels, and the shipped weights."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from nerfpipe import cli
from nerfpipe.data.errors import UserError
from nerfpipe.data.synthetic.families import FAMILIES, HELD_OUT, TRAINED, inside, primitives, shape
from nerfpipe.data.synthetic.raycast import _cast
from nerfpipe.data.synthetic.shape_views import grid_points, shape_photos, view_occupancy, view_rotation
from nerfpipe.model.voxels.fuse import fuse, turn
from nerfpipe.model.voxels.infer import occupancy
from nerfpipe.model.voxels.inputs import SIDE, prepare
from nerfpipe.model.voxels.net import VoxelNet
from nerfpipe.model.voxels.pretrain import iou, unpack
from nerfpipe.model.voxels.preview import render_grid
from nerfpipe.model.voxels.weights import PRETRAINED, load_net, write_weights
from nerfpipe.stages import pretrain_voxels, shapes

# ---------------------------------------------------------------- families


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_family_shapes_fit_the_grid_from_any_azimuth(family):
    """Normalised shapes fill the vertical cylinder of radius 0.5 and height 1 (module doc): touching it, never out."""
    for seed in range(5):
        s = shape(family, seed)
        p = grid_points(64, 1) * 1.2  # a cube 20 % larger than the grid
        occ = inside(s.parts, p)
        assert occ.any()
        q = p[occ]
        assert np.abs(q[:, 2]).max() <= 0.5 + 1e-9
        assert np.hypot(q[:, 0], q[:, 1]).max() <= 0.5 + 1e-9
        reach = max(np.hypot(q[:, 0], q[:, 1]).max(), 2 * np.abs(q[:, 2]).max() / 2)
        assert reach > 0.45  # normalised: the larger of the two fits touches the bound (up to a sample step)


def test_families_differ_by_seed_and_one_is_held_out():
    assert HELD_OUT in FAMILIES and HELD_OUT not in TRAINED and len(TRAINED) == len(FAMILIES) - 1
    a, b = shape("chair", 1), shape("chair", 2)
    assert a.parts != b.parts and shape("chair", 1).parts == a.parts


def test_occupancy_agrees_with_the_rendered_surface():
    """The exact occupancy and the renderer meet at the surface: just before a ray's first hit is outside every
    part, just after it is inside (the ground truth is the shape the photos show)."""
    rng = np.random.default_rng(0)
    for family in ("chair", "lamp", "mug"):
        s = shape(family, 3)
        prims = primitives(s, np.random.default_rng(1))
        o = rng.normal(size=(4000, 3))
        o = 2.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
        d = rng.uniform(-0.4, 0.4, (4000, 3)) - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t, which = _cast(prims, o, d)
        hit = which >= 0
        assert hit.sum() > 200
        eps = 1e-6
        before = o[hit] + (t[hit] - eps)[:, None] * d[hit]
        after = o[hit] + (t[hit] + eps)[:, None] * d[hit]
        assert not inside(s.parts, before).any()
        assert inside(s.parts, after).mean() > 0.99  # grazing hits on an edge may leave at once


def test_view_frame_quarter_turn_is_a_grid_rotation():
    """A camera 90 deg further counter-clockwise sees the grid turned: exact for a quarter turn, and `fuse.turn`
    undoes it (the sense of the azimuths)."""
    s = shape("chair", 4)
    a = view_occupancy(s, 0.3)
    b = view_occupancy(s, 0.3 + math.pi / 2)
    # b at (x, y) is a at Rz(+90) (x, y) = (-y, x): a quarter turn of the grid (points on a boundary may round
    # either way: the sub-sample points are turned in floating point)
    assert np.mean(np.rot90(a, k=-1, axes=(0, 1)) != b) < 1e-3
    back = turn(torch.from_numpy(b), math.pi / 2).numpy()
    assert np.abs(back - a).max() < 1e-5


def test_fuse_of_one_object_from_two_sides_matches_either():
    s = shape("table", 5)
    g0 = torch.from_numpy(view_occupancy(s, 1.0))
    g1 = torch.from_numpy(view_occupancy(s, 1.0 + math.pi))
    fused = fuse(torch.stack([g0, g1]), torch.tensor([1.0, 1.0 + math.pi], dtype=torch.float64))
    assert iou(fused, g0) > 0.99
    with pytest.raises(ValueError, match="azimuths"):
        fuse(torch.stack([g0, g1]), torch.tensor([1.0]))


def test_shape_photos_are_consistent():
    s, photos = shape_photos("stool", 7, 3, 48)
    assert len(photos) == 3
    for p in photos:
        assert p.rgb.shape == (48, 48, 3) and p.mask.shape == (48, 48) and p.occupancy.shape == (32, 32, 32)
        assert 0 < p.mask.mean() < 0.8 and p.occupancy.any()
        assert np.array_equal(p.occupancy, view_occupancy(s, p.azimuth) >= 0.5)
    assert view_rotation(0.0) @ np.array([1.0, 0.0, 0.0]) == pytest.approx([0.0, 1.0, 0.0])  # camera on +x


# ---------------------------------------------------------------- inputs, network, preview


def test_prepare_removes_framing():
    """The same object framed smaller and off-centre gives nearly the same input (crop about the mask)."""
    img = np.zeros((200, 200, 3), np.float32)
    mask = np.zeros((200, 200), np.float32)
    mask[50:150, 70:130] = 1.0
    img[50:150, 70:130] = [0.2, 0.6, 0.9]
    small_img = cv2.resize(img, (100, 100), interpolation=cv2.INTER_AREA)
    small_mask = cv2.resize(mask, (100, 100), interpolation=cv2.INTER_AREA)
    shifted_img = np.zeros_like(img)
    shifted_mask = np.zeros_like(mask)
    shifted_img[:100, 90:190], shifted_mask[:100, 90:190] = small_img, small_mask
    a, b = prepare(img, mask), prepare(shifted_img, shifted_mask)
    assert a.shape == (4, SIDE, SIDE)
    assert (a - b).abs().mean() < 0.02
    assert float(a[3].sum()) > 0 and float(a[:3, 0, 0].abs().max()) == 0  # background removed
    with pytest.raises(ValueError, match="empty"):
        prepare(img, np.zeros_like(mask))
    with pytest.raises(ValueError, match="expected rgb"):
        prepare(img[..., :2], mask)


def test_net_shapes_and_gradients():
    torch.manual_seed(0)  # the initial weights: their outputs' mean lies near the prior, how near depends on them
    net = VoxelNet()
    x = torch.rand(2, 4, 64, 64, requires_grad=True)
    logits = net(x)
    assert logits.shape == (2, 32, 32, 32)
    assert float(torch.sigmoid(logits.detach()).mean()) == pytest.approx(1 / (1 + math.exp(2.5)), abs=0.05)  # the prior
    logits.sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="expected"):
        net(torch.rand(2, 3, 64, 64))


def test_mirrored_prediction_is_mirror_consistent():
    """`occupancy(mirror=True)`: the mirrored photo's grid is the photo's grid mirrored in x (exactly, not by
    training), and the mean of the two single passes; `mirror=False` is one pass; batching changes nothing."""
    torch.manual_seed(1)
    net, _ = load_net("pretrained", torch.device("cpu"))  # trained: an untrained net's output is nearly constant
    x = torch.rand(3, 4, 64, 64)
    plain = occupancy(net, x, mirror=False)
    with torch.no_grad():
        assert torch.equal(plain, torch.sigmoid(net(x)))
        back = torch.sigmoid(net(x.flip(-1))).flip(1)
    assert float((plain - back).abs().max()) > 0.01  # the net alone is not mirror-symmetric
    both = occupancy(net, x, mirror=True, batch=2)
    torch.testing.assert_close(both, 0.5 * (plain + back))
    torch.testing.assert_close(occupancy(net, x.flip(-1)), both.flip(1))
    with pytest.raises(ValueError, match="expected photos"):
        occupancy(net, x[0])


def test_preview_renders_what_is_there():
    empty = render_grid(torch.zeros(32, 32, 32), 0.0, 20.0, 48)
    assert np.allclose(empty, 1.0)  # white
    ball = torch.from_numpy((np.linalg.norm(grid_points(32, 1), axis=1) < 0.3).reshape(32, 32, 32).astype(np.float32))
    img = render_grid(ball, 0.0, 20.0, 48)
    assert img[24, 24].max() < 0.95 and np.allclose(img[0, 0], 1.0)


# ---------------------------------------------------------------- stages


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny shapes dataset, weights pretrained on it for a few steps, and a photo with alpha."""
    root = tmp_path_factory.mktemp("voxels")
    data = shapes.run(shapes.Config(out_dir=root / "shapes", families=("chair", "mug"), count=2, views=2, workers=1))
    w = pretrain_voxels.run(pretrain_voxels.Config(shapes=root / "shapes", out_dir=root / "w", max_steps=3, batch=4))
    _, photos = shape_photos("chair", 424242, 2, 96)
    paths = []
    for i, p in enumerate(photos):
        rgba = np.concatenate([p.rgb[..., ::-1], p.mask[..., None]], -1)
        cv2.imwrite(str(root / f"chair{i}.png"), (rgba * 255).round().astype(np.uint8))
        cv2.imwrite(str(root / f"chair{i}.jpg"), (p.rgb[..., ::-1] * 255).round().astype(np.uint8))
        cv2.imwrite(str(root / f"chair{i}_mask.png"), (p.mask * 255).round().astype(np.uint8))
        paths.append(root / f"chair{i}.png")
    return root, data, w, photos


def test_shapes_dataset_layout(tiny):
    _, data, _, _ = tiny
    with np.load(data.shapes) as z:
        assert z["inputs"].shape == (8, 4, SIDE, SIDE) and z["inputs"].dtype == np.uint8
        assert list(z["families"]) == ["chair", "mug"]
        occ = unpack(z["bits"], int(z["res"]))
        assert occ.shape == (8, 32, 32, 32)
        s = shape("chair", int(z["seed"][0]))
        assert np.array_equal(occ[0].numpy() > 0.5, view_occupancy(s, float(z["azimuth"][0])) >= 0.5)
    assert data.examples == 8


def test_pretrain_writes_weights_that_load(tiny):
    _, _, w, _ = tiny
    assert w.steps == 3 and math.isfinite(w.loss_end)
    net, prov = load_net(w.weights, torch.device("cpu"))
    assert prov["steps"] == 3 and not net.training
    manifest = json.loads(w.manifest.read_text())
    assert manifest["used"]["parameters"] == sum(p.numel() for p in net.parameters())


def test_pretrain_continues_weights_and_keeps_their_provenance(tiny):
    root, _, w, _ = tiny
    more = pretrain_voxels.run(
        pretrain_voxels.Config(shapes=root / "shapes", out_dir=root / "w2", init=str(w.weights), max_steps=2, batch=4)
    )
    _, prov = load_net(more.weights, torch.device("cpu"))
    assert prov["steps"] == 2 and prov["init_provenance"]["steps"] == 3
    assert json.loads(more.manifest.read_text())["used"]["steps_before"] == 3
    with pytest.raises(UserError):  # not weights: refused before anything is written
        pretrain_voxels.run(
            pretrain_voxels.Config(shapes=root / "shapes", out_dir=root / "w3", init=str(more.manifest))
        )
    assert not (root / "w3").exists()


def test_weights_file_halves_and_predicts_the_same(tmp_path):
    net = VoxelNet().eval()
    path = write_weights(tmp_path / "w.pt", net.config(), net.state_dict(), {})
    back, _ = load_net(path, torch.device("cpu"))
    x = torch.rand(1, 4, 64, 64)
    with torch.no_grad():
        a, b = torch.sigmoid(net(x)), torch.sigmoid(back(x))
    assert (a - b).abs().max() < 2e-3


def _cli(capsys, *args):
    with pytest.raises(SystemExit) as e:
        cli.main([str(a) for a in args])
    out = capsys.readouterr()
    return e.value.code, out.out + out.err


def test_voxels_stage_outputs(tiny, capsys):
    root, _, w, _ = tiny
    code, text = _cli(capsys, "voxels", root / "chair0.png", root / "one", "--weights", w.weights)
    assert code == 0, text
    prob = np.load(root / "one" / "occupancy.npy")
    assert prob.shape == (32, 32, 32) and prob.dtype == np.float32 and 0 <= prob.min() <= prob.max() <= 1
    frame = json.loads((root / "one" / "occupancy.json").read_text())
    assert frame["cell"] == 1 / 32 and "view frame" in frame["frame"]
    assert (root / "one" / "preview.png").is_file() and (root / "one" / "manifest.json").is_file()
    masks = f"{root / 'chair0_mask.png'},{root / 'chair1_mask.png'}"
    photos = [root / "chair0.jpg", root / "chair1.jpg"]
    code, text = _cli(
        capsys, "voxels", *photos, root / "two", "--weights", w.weights, "--masks", masks, "--azimuths", "0,40"
    )
    assert code == 0, text
    assert json.loads((root / "two" / "occupancy.json").read_text())["azimuths_deg"] == [0.0, 40.0]


@pytest.mark.parametrize(
    "args, message",
    [
        (["chair0.jpg"], "no alpha channel"),
        (["chair0.png", "chair1.png"], "need 2 azimuths"),
        (["chair0.jpg", "--masks", "chair0_mask.png,chair1_mask.png"], "one mask per photo"),
        (["missing.png"], "not found"),
    ],
)
def test_voxels_bad_input_is_one_line(tiny, capsys, args, message):
    root, _, w, _ = tiny
    args = [str(root / a) if a.endswith((".png", ".jpg")) else a for a in args]
    args = [",".join(str(root / p) for p in a.split(",")) if "," in a and "png" in a else a for a in args]
    code, text = _cli(capsys, "voxels", *args, root / "bad", "--weights", w.weights)
    assert code == 2 and message in text and "Traceback" not in text
    assert not (root / "bad").exists()


def test_opaque_alpha_is_refused(tiny, capsys):
    root, _, w, _ = tiny
    img = np.full((40, 40, 4), 255, np.uint8)
    cv2.imwrite(str(root / "opaque.png"), img)
    code, text = _cli(capsys, "voxels", root / "opaque.png", root / "bad2", "--weights", w.weights)
    assert code == 2 and "opaque everywhere" in text


# ---------------------------------------------------------------- the shipped weights


def test_shipped_weights_predict_held_out_objects():
    """The weights in the repository load and predict objects they never saw (seeds apart from pretraining's)
    far better than the mean shape of those objects would (figures: docs/VOXELS.md)."""
    net, prov = load_net("pretrained", torch.device("cpu"))
    assert PRETRAINED.stat().st_size < 10e6 and prov["steps"] > 0
    got, prior = [], []
    truths, inputs = [], []
    for family in ("chair", "table", "lamp"):
        _, photos = shape_photos(family, 990001, 2, 112)
        for p in photos:
            inputs.append(prepare(p.rgb, p.mask))
            truths.append(torch.from_numpy(p.occupancy.astype(np.float32)))
    prob = occupancy(net, torch.stack(inputs))  # as `nerfpipe voxels` predicts
    mean = torch.stack(truths).mean(0)
    for p, t in zip(prob, truths, strict=True):
        got.append(iou(p, t))
        prior.append(max(iou(mean, t, lv) for lv in (0.2, 0.3, 0.4, 0.5)))
    assert np.mean(got) > 0.5 and np.mean(got) > np.mean(prior) + 0.15, (got, prior)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_upright_matches_pillow(tmp_path, orientation):
    """`data.images.upright` turns pixels as PIL's exif_transpose does, for each EXIF orientation."""
    from PIL import Image, ImageOps

    from nerfpipe.data.images import exif_orientation, upright

    rng = np.random.default_rng(orientation)
    pixels = rng.integers(0, 255, (5, 7, 3), dtype=np.uint8)
    im = Image.fromarray(pixels)
    exif = im.getexif()
    exif[0x0112] = orientation
    path = tmp_path / "p.jpg"
    im.save(path, exif=exif.tobytes(), quality=100)
    data = path.read_bytes()
    assert exif_orientation(data) == orientation
    with Image.open(path) as reread:
        want = np.asarray(ImageOps.exif_transpose(reread))
        stored = np.asarray(reread.convert("RGB"))
    assert np.array_equal(upright(stored, orientation), want)


def test_voxels_reads_a_phone_photo_upright(tiny, capsys):
    """A JPEG stored sideways with EXIF orientation 6 and a mask drawn on the stored pixels predicts what the
    upright photo does."""
    from PIL import Image

    root, _, w, photos = tiny
    p = photos[0]
    rgb = (p.rgb * 255).round().astype(np.uint8)
    mask = (p.mask * 255).round().astype(np.uint8)
    stored = np.rot90(rgb, k=1)  # displayed upright after a quarter turn clockwise (orientation 6)
    im = Image.fromarray(np.ascontiguousarray(stored))
    exif = im.getexif()
    exif[0x0112] = 6
    im.save(root / "phone.jpg", exif=exif.tobytes(), quality=98)
    Image.fromarray(np.ascontiguousarray(np.rot90(mask, k=1))).save(root / "phone_mask.png")
    Image.fromarray(rgb).save(root / "plain.jpg", quality=98)
    Image.fromarray(mask).save(root / "plain_mask.png")
    for name in ("phone", "plain"):
        code, text = _cli(
            capsys,
            "voxels",
            root / f"{name}.jpg",
            root / f"v_{name}",
            "--masks",
            root / f"{name}_mask.png",
            "--weights",
            w.weights,
        )
        assert code == 0, text
    a, b = (np.load(root / f"v_{n}" / "occupancy.npy") for n in ("phone", "plain"))
    assert np.abs(a - b).max() < 0.05
