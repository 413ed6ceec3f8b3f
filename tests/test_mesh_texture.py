"""Texture baking (`stages.mesh.texture`) on an analytic field: a unit sphere whose colour is a smooth function of
position, baked and sampled back through the UVs; the rasteriser against a per-texel loop; OBJ + MTL + PNG and
GLB round trips through trimesh; atomic writes."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
import torch
import trimesh

from nerfpipe.data.errors import WriteFailed
from nerfpipe.stages.mesh import texture_files
from nerfpipe.stages.mesh.texture import (
    Textured,
    auto_texture_size,
    bake_texture,
    rasterize,
    sample_texture,
)
from nerfpipe.stages.mesh.texture_files import write_glb_textured, write_obj_textured
from nerfpipe.stages.mesh.texture_views import ViewSource, project_views, spread_views


def sphere_color(x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """The analytic field's colour: 0.5 + 0.5 * the outward unit vector at x (every hue on the sphere)."""
    return 0.5 + 0.5 * x / x.norm(dim=1, keepdim=True)


def _sphere(subdivisions: int = 3) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions)


def _surface_samples(t: Textured, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n random points on the textured mesh's faces -> (positions [n, 3], uv [n, 2])."""
    rng = np.random.default_rng(seed)
    fi = rng.integers(0, len(t.faces), n)
    b = rng.dirichlet([1.0, 1.0, 1.0], n)
    tri = t.faces[fi]
    return np.einsum("nk,nkd->nd", b, t.vertices[tri]), np.einsum("nk,nkd->nd", b, t.uv[tri].astype(np.float64))


def _field_error(loaded: trimesh.Trimesh, image: np.ndarray) -> float:
    """Mean error of the colours read through a loaded mesh's UVs and image against the field, at random surface
    points; its UVs must lie in [0, 1]."""
    uv = np.asarray(loaded.visual.uv, np.float32)
    assert uv.shape == (len(loaded.vertices), 2) and uv.min() >= 0 and uv.max() <= 1
    t = Textured(np.asarray(loaded.vertices), np.asarray(loaded.faces), uv, image, np.zeros(0, np.int64), {})
    x, uv_s = _surface_samples(t, 5000)
    return float(np.abs(sample_texture(image, uv_s) / 255.0 - sphere_color(torch.as_tensor(x), None).numpy()).mean())


@pytest.fixture(scope="module")
def baked() -> Textured:
    m = _sphere()
    return bake_texture(m.vertices, m.faces, sphere_color, texture_size=256)


def test_baked_texels_match_the_field(baked):
    """Colours read back through the UVs at random surface points agree with the field there: a flipped v, a
    misplaced chart or texel centres off by half a texel would give errors of tenths, not thousandths."""
    x, uv = _surface_samples(baked, 20000)
    got = sample_texture(baked.image, uv) / 255.0
    want = sphere_color(torch.as_tensor(x), None).numpy()
    err = np.abs(got - want)
    assert err.mean() < 0.004 and np.percentile(err, 99) < 0.01 and err.max() < 0.03, (err.mean(), err.max())
    assert baked.image.shape == (256, 256, 3) and baked.image.dtype == np.uint8
    assert baked.uv.min() >= 0 and baked.uv.max() <= 1
    m = _sphere()
    assert np.allclose(baked.vertices, m.vertices[baked.source_vertex])
    assert np.allclose(baked.vertices[baked.faces], m.vertices[m.faces])  # the input's faces, in its order
    info = baked.info
    assert info["faces_without_texel"] == 0 and 0.2 < info["coverage"] < 1
    assert set(info["timing_seconds"]) == {"unwrap", "bake"}


def test_view_directions_are_the_inward_normals():
    """A colour that depends only on the view direction: 0.5 - 0.5 * d equals the outward normal's colour when
    d is the inward normal (the camera looking straight at the surface)."""
    m = _sphere(2)
    t = bake_texture(m.vertices, m.faces, lambda x, d: 0.5 - 0.5 * d, texture_size=128)
    x, uv = _surface_samples(t, 5000)
    err = np.abs(sample_texture(t.image, uv) / 255.0 - sphere_color(torch.as_tensor(x), None).numpy())
    assert err.mean() < 0.01, err.mean()


def test_empty_texels_are_filled_so_filtering_reads_no_black(baked):
    """Every texel holds a colour of the field (dilated around the charts, push-pull beyond): no black texel that
    bilinear filtering or a mip level could mix into a chart's edge."""
    assert baked.image.reshape(-1, 3).sum(axis=1).min() > 0
    small = baked.image.reshape(64, 4, 64, 4, 3).mean(axis=(1, 3)) / 255.0  # a mip level, 4x smaller
    assert small.sum(axis=-1).min() > 0.5  # the sphere's darkest colour is (0.5 - 0.29) * 3 > 0.6


def test_rasterize_matches_a_per_texel_loop():
    """The vectorised rasteriser against the plain twin: each texel centre tested against each triangle."""
    rng = np.random.default_rng(3)
    tri = rng.uniform(0, 1, (40, 3, 2))
    tri[:5] *= 0.05  # small ones
    rows, cols, face, bary = rasterize(tri, 24, 20, budget=64)
    got = {(int(r), int(c), int(f)) for r, c, f in zip(rows, cols, face, strict=True)}
    want = set()
    for f, t in enumerate(tri):
        for r in range(20):
            for c in range(24):
                q = np.array([(c + 0.5) / 24, 1 - (r + 0.5) / 20])
                m = np.array([t[1] - t[0], t[2] - t[0]]).T
                b1, b2 = np.linalg.solve(m, q - t[0])
                if min(b1, b2, 1 - b1 - b2) >= 1e-6:
                    want.add((r, c, f))
    assert want <= got and len(got - want) <= 2, (len(want), len(got))  # texels exactly on an edge may differ
    uv = np.stack([(cols + 0.5) / 24, 1 - (rows + 0.5) / 20], axis=1)
    assert np.allclose(np.einsum("nk,nkd->nd", bary, tri[face]), uv, atol=1e-6)


def test_auto_texture_size():
    assert auto_texture_size(100) == 256
    assert auto_texture_size(100_000) == 1024
    assert auto_texture_size(300_000) == 2048
    assert auto_texture_size(10_000_000) == 2048


def test_bad_color_fn_and_inputs():
    m = _sphere(1)
    with pytest.raises(ValueError, match=r"rgb \[\d+, 3\]"):
        bake_texture(m.vertices, m.faces, lambda x, d: x[:, :2], texture_size=32)
    with pytest.raises(ValueError, match="faces"):
        bake_texture(m.vertices, np.zeros((0, 3), np.int64), sphere_color)
    t = bake_texture(m.vertices, m.faces, lambda x, d: torch.full_like(x, float("nan")), texture_size=32)
    assert np.isfinite(t.image).all()  # NaN colours become 0, not garbage


def test_obj_round_trip(baked, tmp_path):
    paths = write_obj_textured(tmp_path / "mesh.obj", baked)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.mtl", "mesh.obj", "mesh.png"]
    assert paths["png"].name in paths["mtl"].read_text() and "mtllib mesh.mtl" in paths["obj"].read_text()
    loaded = trimesh.load(paths["obj"], process=False, maintain_order=True)
    assert len(loaded.faces) == len(baked.faces)
    img = np.asarray(loaded.visual.material.image.convert("RGB"))
    assert np.array_equal(img, baked.image)
    assert _field_error(loaded, img) < 0.004  # the loaded UVs address the loaded image as the baked ones did
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(paths["obj"]))  # MeshLab's reader: the same faces, per-corner UVs and one texture
    pm = ms.current_mesh()
    assert pm.face_number() == len(baked.faces) and pm.has_wedge_tex_coord() and pm.texture_number() == 1
    assert np.allclose(pm.wedge_tex_coord_matrix().reshape(-1, 3, 2), baked.uv[baked.faces], atol=1e-6)


def test_glb_round_trip_embeds_the_texture_unlit(baked, tmp_path):
    path = write_glb_textured(tmp_path / "mesh.glb", baked)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.glb"]  # one file, the image inside
    data = path.read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + n])
    assert doc["images"][0]["mimeType"] == "image/png" and "bufferView" in doc["images"][0]
    assert doc["materials"][0]["extensions"] == {"KHR_materials_unlit": {}}
    assert struct.unpack_from("<I", data, 8)[0] == len(data)
    loaded = trimesh.load(path, force="mesh", process=False)
    assert len(loaded.faces) == len(baked.faces)
    img = np.asarray(loaded.visual.material.baseColorTexture.convert("RGB"))
    assert np.array_equal(img, baked.image)
    assert _field_error(loaded, img) < 0.004  # v flipped for glTF and back: the same texel at the same point


def test_transformed_keeps_the_texture_and_faces_outward(baked):
    mirror = np.diag([-2.0, 2.0, 2.0, 1.0])
    t = baked.transformed(mirror)
    assert np.allclose(t.vertices, baked.vertices * [-2, 2, 2]) and t.image is baked.image
    tri = t.vertices[t.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (np.einsum("nd,nd->n", n, tri.mean(axis=1)) > 0).all()  # still outward after the mirror


@pytest.mark.parametrize("fails", ["savetxt", "_png_bytes"])
def test_obj_files_appear_only_together(baked, tmp_path, monkeypatch, fails):
    """A full disk while writing the OBJ's body (the first file written) or the PNG (the last) leaves none of the
    three files and no temporary, names the file being written, and an earlier OBJ keeps its content."""
    (tmp_path / "mesh.obj").write_text("old")

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(texture_files.np if fails == "savetxt" else texture_files, fails, broken)
    name = "mesh.obj" if fails == "savetxt" else "mesh.png"
    with pytest.raises(WriteFailed, match=f"no space left on device writing .*{name}"):
        write_obj_textured(tmp_path / "mesh.obj", baked)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.obj"]
    assert (tmp_path / "mesh.obj").read_text() == "old"


# ---------------------------------------------------------------------------------------------- from the views
def _two_spheres() -> tuple[np.ndarray, np.ndarray]:
    """A unit sphere at the origin and a small one (radius 0.3) in front of it along +z, one mesh."""
    big, small = _sphere(3), _sphere(2)
    verts = np.concatenate([big.vertices, 0.3 * small.vertices + [0.0, 0.0, 1.6]])
    return verts, np.concatenate([big.faces, small.faces + len(big.vertices)])


def _two_spheres_render(rays_o: torch.Tensor, rays_d: torch.Tensor) -> torch.Tensor:
    """The exact render of `_two_spheres`: the big sphere in `sphere_color`, the small one pure green, black beyond."""
    best = torch.full((len(rays_o),), torch.inf, dtype=rays_o.dtype)
    rgb = torch.zeros(len(rays_o), 3, dtype=rays_o.dtype)
    for centre, radius, green in (((0.0, 0.0, 0.0), 1.0, False), ((0.0, 0.0, 1.6), 0.3, True)):
        oc = rays_o - torch.tensor(centre, dtype=rays_o.dtype)
        b = (oc * rays_d).sum(-1)
        disc = b * b - (oc * oc).sum(-1) + radius * radius
        t = -b - torch.sqrt(disc.clamp_min(0))
        hit = (disc > 0) & (t > 0) & (t < best)
        best = torch.where(hit, t, best)
        x = rays_o + t[:, None] * rays_d
        colour = torch.tensor([0.0, 1.0, 0.0], dtype=rgb.dtype).expand_as(rgb) if green else sphere_color(x, None)
        rgb = torch.where(hit[:, None], colour, rgb)
    return rgb


def _view_source(eyes: list, size: int = 96, render=None) -> ViewSource:
    from nerfpipe.radiance.camera import Intrinsics
    from nerfpipe.radiance.paths import look_at

    f = 0.5 * size / math.tan(math.radians(25.0))
    intr = Intrinsics(w=size, h=size, fx=f, fy=f, cx=size / 2, cy=size / 2)
    up = np.array([0.0, 1.0, 0.0])
    return ViewSource(
        cameras=tuple((intr, look_at(np.asarray(e, float), np.zeros(3), up)) for e in eyes),
        render=render or _two_spheres_render,
    )


def test_texels_take_the_colour_the_cameras_render_where_they_see_them():
    """Texel points on the big sphere, coloured from one camera on +z: the ones it sees take the colour it renders
    there (the field's, within bilinear sampling's error), the ones the small sphere hides from it or that face
    away take none (weight 0), and none of them takes the occluder's green."""
    verts, faces = _two_spheres()
    rng = np.random.default_rng(0)
    p = rng.normal(size=(20000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)  # points on the big sphere; their outward normal is p itself
    rgb, weight, skipped = project_views(p, p, verts, faces, _view_source([(0.0, 0.0, 4.0)]))
    assert skipped == 0
    r = np.hypot(p[:, 0], p[:, 1])
    seen = weight > 0
    assert not seen[p[:, 2] < 0.25].any()  # the camera at z = 4 sees the sphere down to z = 1/4
    assert not seen[r < 0.3].any()  # behind the small sphere, seen from the camera
    assert seen[(p[:, 2] > 0.5) & (r > 0.45)].mean() > 0.99  # facing it (cos > 0.3), clear of the small sphere
    want = sphere_color(torch.as_tensor(p), None).numpy()
    err = np.abs(rgb[seen] - want[seen])
    assert np.median(err) < 0.01 and np.percentile(err, 99) < 0.08, (np.median(err), np.percentile(err, 99))
    assert not ((rgb[seen, 1] > 0.95) & (rgb[seen, 0] < 0.05)).any()  # the occluder's colour reached no texel


def test_baking_from_views_colours_what_they_see_and_the_rest_from_the_field():
    """bake_texture with views: texels the cameras see hold their renders (here, the field's colour), the rest
    `color_fn` along the normal (here a marker colour); the report says how much the views covered."""
    verts, faces = _two_spheres()
    eyes = [(0.0, 0.0, 4.0), (4.0, 0.0, 0.0), (-4.0, 0.0, 0.0)]
    marker = torch.tensor([1.0, 0.0, 1.0])
    t = bake_texture(
        verts, faces, lambda x, d: marker.to(x).expand(len(x), 3), texture_size=512, views=_view_source(eyes)
    )
    assert 0.3 < t.info["views"]["texels_seen"] < 0.9
    x, uv = _surface_samples(t, 20000, seed=1)
    on_big = np.linalg.norm(x, axis=1) < 1.01
    got = sample_texture(t.image, uv) / 255.0
    front = on_big & (x[:, 2] > 0.5) & (np.hypot(x[:, 0], x[:, 1]) > 0.5)  # seen by the camera on +z
    back = on_big & (np.abs(x[:, 0]) < 0.2) & (x[:, 2] < 0)  # faces away from every camera (p . eye < |p|^2)
    want = sphere_color(torch.as_tensor(x), None).numpy()
    assert np.median(np.abs(got[front] - want[front])) < 0.02
    assert np.allclose(got[back], marker.numpy(), atol=0.02)


def test_texels_read_the_pixel_their_point_projects_to():
    """A render whose colour is the ray's direction: each texel seen takes 0.5 + 0.5 x the direction from the camera
    to its point, to bilinear interpolation's error (median 7e-6 here; texels at the sphere's silhouette, read from
    fewer pixels, up to 2e-3); a half-pixel shift would put every texel ~2e-3 off."""
    verts, faces = _two_spheres()
    eye = np.array([0.3, -0.2, 4.0])
    rng = np.random.default_rng(2)
    p = rng.normal(size=(5000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    src = _view_source([eye], render=lambda o, d: 0.5 + 0.5 * d)
    rgb, weight, _ = project_views(p, p, verts, faces, src)
    seen = weight > 0
    want = 0.5 + 0.5 * (p - eye) / np.linalg.norm(p - eye, axis=1, keepdims=True)
    err = np.abs(rgb[seen] - want[seen]).max(axis=1)
    assert seen.mean() > 0.2 and np.median(err) < 1e-4 and np.percentile(err, 90) < 5e-4, np.percentile(err, [50, 90])


def test_a_texel_at_its_surfaces_edge_takes_no_colour_from_the_wall_behind():
    """A small sphere in front of the big one: its texels at its silhouette project between pixels that show it and
    pixels that show the big sphere far behind; only its own pixels colour them (never the big sphere's colours)."""
    verts, faces = _two_spheres()
    small = 0.3 * np.random.default_rng(3).normal(size=(20000, 3))
    small = 0.3 * small / np.linalg.norm(small, axis=1, keepdims=True)
    normals = small / 0.3
    small = small + [0.0, 0.0, 1.6]
    rgb, weight, _ = project_views(small, normals, verts, faces, _view_source([(0.0, 0.0, 4.0)]))
    seen = weight > 0
    assert seen.mean() > 0.2
    assert np.allclose(rgb[seen], [0.0, 1.0, 0.0], atol=1e-6), np.abs(rgb[seen] - [0.0, 1.0, 0.0]).max()


def test_a_camera_inside_the_mesh_is_skipped():
    """A camera inside the big sphere: faces cross its plane, so it has no depth buffer and colours nothing (the
    texels, turned to face it, would otherwise be seen)."""
    verts, faces = _two_spheres()
    rgb, weight, skipped = project_views(verts[:10], -verts[:10], verts, faces, _view_source([(0.0, 0.0, 0.5)]))
    assert skipped == 1 and not (weight > 0).any()


def test_spread_views_picks_far_apart_cameras_and_never_one_twice():
    from nerfpipe.radiance.paths import look_at

    up = np.array([0.0, 0.0, 1.0])
    eyes = [[3.0, 0, 0], [3.1, 0, 0], [-3.0, 0, 0], [-3.1, 0, 0], [0.0, 3, 0]]
    c2w = np.stack([look_at(np.array(e), np.zeros(3), up) for e in eyes])
    assert spread_views(c2w, 3) == [0, 3, 4]  # the first, the farthest from it, the farthest from both
    assert spread_views(c2w, 9) == [0, 1, 2, 3, 4] and spread_views(c2w, 0) == []
    still = np.stack([c2w[0]] * 4)  # one camera position and direction four times: one view
    assert spread_views(still, 3) == [0]
    turning = np.stack([look_at(np.zeros(3), np.array(e), up) for e in eyes[::2]])  # one centre, three directions
    assert spread_views(turning, 3) == [0, 1, 2]
