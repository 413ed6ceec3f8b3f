"""The synthetic scene generator: determinism, exact ground truth, texture for SIFT, file contracts."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from nerfpipe.data.synthetic.objects import default_primitives
from nerfpipe.data.transforms import load_image, read_scene
from nerfpipe.radiance.camera import generate_rays, project
from nerfpipe.stages import scene


@pytest.fixture(scope="module")
def posed(tmp_path_factory) -> scene.Outputs:
    return scene.run(scene.Config(out_dir=tmp_path_factory.mktemp("posed"), size=64, views=10, seed=0))


@pytest.fixture(scope="module")
def rgba(tmp_path_factory) -> scene.Outputs:
    return scene.run(scene.Config(out_dir=tmp_path_factory.mktemp("rgba"), kind="rgba", size=64, views=10, seed=0))


def _bytes(paths) -> list[bytes]:
    return [Path(p).read_bytes() for p in paths]


def test_deterministic_for_a_seed(posed, tmp_path):
    again = scene.run(scene.Config(out_dir=tmp_path / "a", size=64, views=10, seed=0))
    assert _bytes(again.images) == _bytes(posed.images)
    assert _bytes(again.depths) == _bytes(posed.depths)
    assert again.mesh.read_bytes() == posed.mesh.read_bytes()
    other = scene.run(scene.Config(out_dir=tmp_path / "b", size=64, views=10, seed=1))
    assert all(a != b for a, b in zip(_bytes(other.images), _bytes(posed.images), strict=True))


def _distance_to_mesh(mesh: trimesh.Trimesh, points: np.ndarray, k: int = 16) -> np.ndarray:
    """Exact distance from points [N, 3] to the mesh (trimesh.proximity would need rtree, not installed).

    Per connected part: brute force over all triangles of small parts (boxes; cylinders, whose caps and sides
    are long thin triangles), the k triangles with the nearest centroids on the fine, even icospheres.
    """
    best = np.full(len(points), np.inf)
    for part in mesh.split(only_watertight=False):
        if len(part.faces) <= 5000:
            for chunk in np.array_split(np.arange(len(points)), max(1, len(points) * len(part.faces) // 200_000)):
                rep = np.repeat(points[chunk], len(part.faces), axis=0)
                tri = np.tile(part.triangles, (len(chunk), 1, 1))
                d = np.linalg.norm(trimesh.triangles.closest_point(tri, rep) - rep, axis=-1)
                best[chunk] = np.minimum(best[chunk], d.reshape(len(chunk), -1).min(-1))
        else:
            _, idx = cKDTree(part.triangles_center).query(points, k=k)
            rep = np.repeat(points, k, axis=0)
            d = np.linalg.norm(trimesh.triangles.closest_point(part.triangles[idx.reshape(-1)], rep) - rep, axis=-1)
            best = np.minimum(best, d.reshape(-1, k).min(-1))
    return best


def test_depth_back_projects_onto_mesh(posed):
    cams = json.loads(posed.cameras.read_text())
    mesh = trimesh.load(posed.mesh, force="mesh")
    intr = scene.intrinsics(cams["w"])
    near_far = read_scene(posed.out_dir)
    points = []
    for depth_path in posed.depths[:4]:
        world_from_cam = torch.tensor(cams["frames"][depth_path.stem]["world_from_cam"], dtype=torch.float64)
        z = torch.from_numpy(np.load(depth_path).astype(np.float64)).reshape(-1)  # [H * W]
        o, d = generate_rays(intr, world_from_cam)  # the project's camera model, not the generator's
        forward = -world_from_cam[:3, 2]
        valid = z > 0
        assert 0.2 < valid.double().mean() < 0.95  # object in view, background around it
        t = z[valid] / (d[valid] @ forward)
        assert near_far.near < t.min() and t.max() < near_far.far
        points.append((o[valid] + t[:, None] * d[valid]).numpy())
    points = np.concatenate(points)
    dist = _distance_to_mesh(mesh, points[np.random.default_rng(0).choice(len(points), 300, replace=False)])
    scene_size = float(np.linalg.norm(mesh.extents))
    assert dist.mean() < 1e-4 * scene_size, dist.mean()
    print(f"distance to mesh: mean {dist.mean():.2e} m, max {dist.max():.2e} m")
    assert dist.max() < 1e-4, dist.max()  # metres: tessellation error << 1 mm


def test_everything_in_view(posed):
    cams = json.loads(posed.cameras.read_text())
    intr = scene.intrinsics(cams["w"])
    vertices = torch.from_numpy(trimesh.load(posed.mesh, force="mesh").vertices)
    for frame in cams["frames"].values():
        uv, z = project(vertices, torch.tensor(frame["world_from_cam"], dtype=torch.float64), intr)
        assert (z > 0).all()
        assert (uv >= 0).all() and (uv <= intr.w).all()


def test_sift_finds_hundreds_of_keypoints_at_256px():
    prims = default_primitives(0)
    intr = scene.intrinsics(256)
    sift = cv2.SIFT_create()
    for world_from_cam in scene.cameras(40, 0)[[0, 13, 27]]:
        colour, alpha, _ = scene.render_view(prims, intr, world_from_cam)
        grey = cv2.cvtColor(
            np.round(255 * (alpha[..., None] * colour + 1 - alpha[..., None])).astype(np.uint8), cv2.COLOR_RGB2GRAY
        )
        assert len(sift.detect(grey)) >= 200  # ~300-750 per view; at 64 px only ~15-30


def test_transforms_match_ground_truth(posed):
    s = read_scene(posed.out_dir)
    cams = json.loads(posed.cameras.read_text())
    assert len(s.frames) == 10 and not s.has_alpha
    assert s.splits["test"] == (0, 8) and 8 not in s.splits["train"]
    np.testing.assert_allclose(s.applied_transform, np.eye(4)[:3])
    assert s.applied_scale == 1.0
    for f in s.frames:
        np.testing.assert_array_equal(
            f.world_from_cam, np.array(cams["frames"][Path(f.file_path).stem]["world_from_cam"])
        )
    intr = s.intrinsics
    assert (intr.w, intr.h, intr.cx, intr.cy) == (64, 64, 32.0, 32.0)
    assert intr.fx == pytest.approx(cams["fl_x"]) and not intr.has_distortion
    mesh = trimesh.load(posed.mesh, force="mesh")
    assert (s.aabb[0] <= mesh.bounds[0]).all() and (s.aabb[1] >= mesh.bounds[1]).all()
    manifest = json.loads((posed.out_dir / "manifest.json").read_text())
    assert manifest["stage"] == "scene" and "transforms.json" in manifest["outputs"]


def test_rgba_alpha_and_compositing(posed, rgba):
    assert read_scene(rgba.out_dir).has_alpha
    for p_rgba, p_rgb, p_depth in zip(rgba.images[:3], posed.images[:3], rgba.depths[:3], strict=True):
        img = load_image(p_rgba)  # [H, W, 4]
        assert img.shape == (64, 64, 4)
        alpha = img[..., 3]
        hit = np.load(p_depth) > 0
        kernel = np.ones((3, 3), np.uint8)
        inside = cv2.erode(hit.astype(np.uint8), kernel).astype(bool)
        outside = cv2.erode((~hit).astype(np.uint8), kernel).astype(bool)
        assert inside.sum() > 100 and outside.sum() > 100
        assert (alpha[outside] == 0).all()
        assert (alpha[inside] == 1).mean() > 0.99  # (a sub-pixel sliver of background can hide between hits)
        assert ((alpha > 0) & (alpha < 1)).any()  # anti-aliased edge
        # rgba composited on the opaque kinds' background reproduces the posed image (8-bit rounding apart)
        composite = img[..., :3] * alpha[..., None] + (1 - alpha[..., None]) * np.array(scene.BACKGROUND)
        assert np.abs(composite - load_image(p_rgb)).max() <= 2.5 / 255


def test_photos_is_bare(tmp_path):
    out = scene.run(scene.Config(out_dir=tmp_path, kind="photos", size=16, views=3))
    assert out.transforms is None and not (tmp_path / "transforms.json").exists()
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == [f"frame_{i:04d}.png" for i in range(3)]
    assert load_image(out.images[0]).shape == (16, 16, 3)
    assert (tmp_path / "manifest.json").is_file() and out.mesh.is_file()


def test_blender_kind_at_any_scale_round_trips_through_convert(tmp_path):
    """kind=blender at scale 0.1: the NeRF-synthetic layout, the same images as at scale 1, lengths x 0.1, and
    `convert` gets the poses back in the source frame and a box that the small scene fills."""
    from nerfpipe.data.ground_truth import read_ground_truth
    from nerfpipe.stages import convert

    small = scene.run(scene.Config(out_dir=tmp_path / "small", kind="blender", size=16, views=10, scale=0.1))
    unit = scene.run(scene.Config(out_dir=tmp_path / "unit", kind="blender", size=16, views=10))
    assert [p.name for p in small.split_files] == [f"transforms_{s}.json" for s in ("train", "val", "test")]
    assert small.transforms is None and not (tmp_path / "small" / "transforms.json").exists()
    doc = json.loads((tmp_path / "small" / "transforms_val.json").read_text())
    assert doc["camera_angle_x"] == pytest.approx(np.radians(scene.FOV_X_DEG))
    assert [f["file_path"] for f in doc["frames"]] == ["./val/r_0"]  # no extension, as NeRF synthetic
    assert load_image(tmp_path / "small" / "val" / "r_0.png").shape == (16, 16, 4)

    # a similarity changes no pixel; every length scales
    assert _bytes(small.images) == _bytes(unit.images)
    for a, b in zip(small.depths, unit.depths, strict=True):
        np.testing.assert_allclose(np.load(a), np.float32(0.1) * np.load(b), rtol=1e-6)
    small_mesh, unit_mesh = trimesh.load(small.mesh, force="mesh"), trimesh.load(unit.mesh, force="mesh")
    np.testing.assert_allclose(small_mesh.vertices, 0.1 * unit_mesh.vertices, rtol=1e-6, atol=1e-9)  # float32 PLY
    gt, gt_unit = read_ground_truth(small.out_dir), read_ground_truth(unit.out_dir)
    for stem, m in gt.world_from_cam.items():
        np.testing.assert_allclose(m[:3, :3], gt_unit.world_from_cam[stem][:3, :3], atol=1e-15)
        np.testing.assert_allclose(m[:3, 3], 0.1 * gt_unit.world_from_cam[stem][:3, 3], rtol=1e-12)

    convert.run(convert.Config(source=small.out_dir, scene_dir=tmp_path / "conv"))
    s = read_scene(tmp_path / "conv")
    assert {Path(f.file_path).stem for f in s.frames} == set(gt.world_from_cam)  # eval --ground-truth matches
    assert {k: len(v) for k, v in s.splits.items()} == {"train": 7, "val": 1, "test": 2}
    for f in s.frames:
        back = s.source_from_scene() @ f.world_from_cam
        back[:3, :3] *= s.applied_scale
        np.testing.assert_allclose(back, gt.world_from_cam[Path(f.file_path).stem], atol=1e-6)
    # the box follows the cameras: the 0.15 m scene sits inside it and fills most of it
    corners = np.concatenate([s.aabb, np.ones((2, 1))], axis=1) @ s.source_from_scene().T
    lo, hi = corners[:, :3]
    assert (lo <= small_mesh.bounds[0]).all() and (small_mesh.bounds[1] <= hi).all()
    assert np.ptp(small_mesh.bounds, axis=0).max() > 0.6 * (hi - lo).max()


# ---------------------------------------------------------------- printed boxes (issue 53's folding objects)


def test_printed_box_repeats_its_print_on_look_alike_faces():
    """carton: the same print on +-x and on +-y (seen from outside, u to the right), different between the pairs;
    cube: one print on all four sides. The albedo at mirrored points of two faces with the same print is equal."""
    from nerfpipe.data.synthetic.prints import subject_primitives

    uv = np.random.default_rng(0).uniform(-0.15, 0.15, (500, 2))
    for subject, same, different in (("carton", [(0, 1), (2, 3)], [(0, 2)]), ("cube", [(0, 1), (0, 2), (0, 3)], [])):
        (box,) = subject_primitives(subject, seed=0)
        hx, hy, _ = box.half
        u, v = uv[:, 0], uv[:, 1] + box.center[2]
        faces = [  # world points on each side face at face-local (u, v)
            np.column_stack([np.full_like(u, hx), u, v]),  # +x: u along +y
            np.column_stack([np.full_like(u, -hx), -u, v]),  # -x: u along -y
            np.column_stack([-u, np.full_like(u, hy), v]),  # +y: u along -x
            np.column_stack([u, np.full_like(u, -hy), v]),  # -y: u along +x
        ]
        albedo = [box.albedo(p) for p in faces]
        for a, b in same:
            np.testing.assert_allclose(albedo[a], albedo[b], atol=1e-12)
        for a, b in different:
            assert np.abs(albedo[a] - albedo[b]).mean() > 0.05
        assert albedo[0].std() > 0.1  # a print with contrast, not a flat colour


def test_scene_subject_is_a_printed_box_on_white(tmp_path):
    out = scene.run(scene.Config(out_dir=tmp_path / "s", kind="posed", subject="carton", size=32, views=4))
    img = load_image(out.images[0])[..., :3]
    corners = np.concatenate([img[:3, :3].reshape(-1, 3), img[-3:, -3:].reshape(-1, 3)])
    assert np.allclose(corners, 1.0)  # white: no slab, no room
    assert img.min() < 0.5  # the box is drawn
    with pytest.raises(Exception, match="--subject"):
        scene.run(scene.Config(out_dir=tmp_path / "t", subject="teapot"))
