"""Texture baking (`stages.mesh.texture`) on an analytic field: a unit sphere whose colour is a smooth function of
position, baked and sampled back through the UVs; the rasteriser against a per-texel loop; OBJ + MTL + PNG and
GLB round trips through trimesh; atomic writes."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import torch
import trimesh

from nerfpipe.data.errors import WriteFailed
from nerfpipe.stages.mesh import texture
from nerfpipe.stages.mesh.texture import (
    Textured,
    auto_texture_size,
    bake_texture,
    rasterize,
    sample_texture,
    write_glb_textured,
    write_obj_textured,
)


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

    monkeypatch.setattr(texture.np if fails == "savetxt" else texture, fails, broken)
    name = "mesh.obj" if fails == "savetxt" else "mesh.png"
    with pytest.raises(WriteFailed, match=f"no space left on device writing .*{name}"):
        write_obj_textured(tmp_path / "mesh.obj", baked)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.obj"]
    assert (tmp_path / "mesh.obj").read_text() == "old"
