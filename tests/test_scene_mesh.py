"""`scene --subject mesh --mesh FILE`: a mesh file photographed as a posed scene (issue 48's scanned meshes)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from nerfpipe.cli import main
from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import load_image
from nerfpipe.radiance.camera import generate_rays
from nerfpipe.stages import scene
from nerfpipe.stages.scene.rig import LOOK_AT
from nerfpipe.stages.scene.subject import MESH_RADIUS

CENTRE, RADIUS = np.array([5.0, -3.0, 2.0]), 2.0
"""The source sphere, far from the rig's frame and of another size: the stage must move and scale it."""


@pytest.fixture(scope="module")
def sphere_scene(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mesh_subject")
    source = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)
    source.apply_translation(CENTRE)
    path = tmp / "ball.ply"
    source.export(path)
    out = scene.run(scene.Config(out_dir=tmp / "s", kind="rgba", subject="mesh", mesh=path, size=32, views=4))
    return out, source


def test_the_mesh_is_placed_at_the_look_at_point_and_the_transform_maps_back(sphere_scene):
    out, source = sphere_scene
    placed = json.loads(out.manifest.read_text())["used"]["mesh_subject"]
    tf = np.array(placed["scene_from_source"])
    scale = MESH_RADIUS / np.sqrt(3 * RADIUS**2)  # the sphere's box has half-diagonal sqrt(3) r
    np.testing.assert_allclose(tf[:3, :3], scale * np.eye(3), rtol=1e-3)
    np.testing.assert_allclose(tf[:3, :3] @ CENTRE + tf[:3, 3], LOOK_AT, atol=1e-3)
    truth = trimesh.load(out.mesh, force="mesh")
    np.testing.assert_allclose(truth.vertices, source.vertices @ tf[:3, :3].T + tf[:3, 3], atol=1e-5)


def test_a_y_up_file_is_turned_to_stand_on_z(tmp_path):
    post = trimesh.creation.box(extents=(0.2, 2.0, 0.4))  # tall along the file's y
    path = tmp_path / "post.obj"
    post.export(path)
    config = scene.Config(out_dir=tmp_path / "s", kind="rgba", subject="mesh", mesh=path, mesh_up="y", size=16, views=2)
    out = scene.run(config)
    truth = trimesh.load(out.mesh, force="mesh")
    extents = truth.extents
    assert extents[2] > 4 * extents[1] and extents[2] > 9 * extents[0]  # tall along the scene's z
    tf = np.array(json.loads(out.manifest.read_text())["used"]["mesh_subject"]["scene_from_source"])
    np.testing.assert_allclose(truth.vertices, post.vertices @ tf[:3, :3].T + tf[:3, 3], atol=1e-6)
    assert np.linalg.det(tf[:3, :3]) > 0  # turned, not mirrored


def test_depth_is_the_distance_to_the_placed_sphere(sphere_scene):
    out, _ = sphere_scene
    cams = json.loads(out.cameras.read_text())
    r = MESH_RADIUS / np.sqrt(3)  # the placed sphere's radius
    for depth_path in out.depths:
        world_from_cam = torch.tensor(cams["frames"][depth_path.stem]["world_from_cam"], dtype=torch.float64)
        z = torch.from_numpy(np.load(depth_path).astype(np.float64)).reshape(-1)
        o, d = generate_rays(scene.intrinsics(cams["w"]), world_from_cam)
        hit = z > 0
        assert 0.05 < hit.double().mean() < 0.9  # the ball in view, background around it
        points = o[hit] + (z[hit] / (d[hit] @ -world_from_cam[:3, 2]))[:, None] * d[hit]
        dist = (points - torch.from_numpy(LOOK_AT)).norm(dim=-1).numpy()
        np.testing.assert_allclose(dist, r, rtol=2e-3)  # the icosphere's facets: sagitta ~2e-4 r


def test_the_ball_is_shaded_and_textured(sphere_scene):
    out, _ = sphere_scene
    img = load_image(out.images[0])  # [H, W, 4]
    alpha = img[..., 3]
    assert alpha[16, 16] == 1.0 and alpha[0, 0] == 0.0
    inside = img[..., :3][alpha == 1.0]
    assert inside.std(0).max() > 0.03  # light, shade and solid texture vary over it


def test_bad_mesh_input_says_so_in_one_line(tmp_path, capsys):
    with pytest.raises(UserError, match="--subject mesh and --mesh FILE go together"):
        scene.run(scene.Config(out_dir=tmp_path / "a", subject="mesh"))
    junk = tmp_path / "junk.ply"
    junk.write_text("not a mesh\n")
    with pytest.raises(SystemExit) as exit_:
        main(["scene", str(tmp_path / "b"), "--subject", "mesh", "--mesh", str(junk)])
    err = capsys.readouterr().err
    assert exit_.value.code != 0
    assert err.startswith("error: ") and "junk.ply" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "b" / "manifest.json").exists()
