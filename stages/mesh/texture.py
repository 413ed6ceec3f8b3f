"""Texture baking for `stages.mesh`: UV unwrap (xatlas) and colours per texel (the files: `texture_files`).

Conventions:
- Positions: `bake_texture` takes the mesh in the field's frame (the scene frame) as float64 [V, 3] vertices and
  int64 [F, 3] faces wound counter-clockwise seen from outside; `Textured.transformed` maps the result into the
  output frame afterwards (the texture does not change).
- UVs: float32 [V', 2] in [0, 1], u to the right, v up (OBJ's and OpenGL's convention). The image is uint8
  [H, W, 3] with row 0 at the top, so texel (row r, column c) is centred at u = (c + 0.5) / W,
  v = 1 - (r + 0.5) / H. glTF puts v = 0 at the top; trimesh's glTF writer flips v, so one `Textured` serves both.
- Colour: with `views` (`stages.mesh.texture_views.ViewSource`), a texel the cameras see takes the cosine-weighted
  mean of their renders there (`project_views`); every other texel (all of them without `views`) takes
  `color_fn(points [N, 3], view_dirs [N, 3]) -> rgb [N, 3]` in [0, 1] (a torch tensor or an array), called with
  float32 tensors on `device`: the surface point under its centre and the unit inward normal there (interpolated
  vertex normals), the colour a camera looking straight at the surface sees. The baker knows no model (the stage
  passes `trained.color` and the run's renderer).

Steps: charts by box projection, packed by xatlas (`unwrap`); each texel whose centre lies in a UV triangle gets
its barycentrics (`rasterize`, vectorised per bounding-box size); the texels' surface points are coloured (from the
views, then by `color_fn` in chunks); empty texels take their neighbours' mean for `dilate` rounds, then a push-pull
fill, so neither bilinear filtering nor a mip level mixes a chart with black.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from nerfpipe.stages.mesh.cleanup import transform_mesh, vertex_normals
from nerfpipe.stages.mesh.texture_views import ViewSource, project_views

__all__ = ["Textured", "bake_texture", "auto_texture_size", "unwrap", "rasterize", "sample_texture"]

ColorFn = Callable[[torch.Tensor, torch.Tensor], Any]

TEXELS_PER_FACE = 8
"""`auto_texture_size` aims at about this many texels per face (a few texels per triangle after packing)."""
SIZE_RANGE = (256, 2048)
"""The automatic texture side, a power of two, lies in this range (2048: about 4 M field queries)."""
PADDING = 2
"""Texels between charts (xatlas' padding). A noisy 300k-face mesh has ~16k charts: each texel of padding costs a
tenth of the atlas, and 1 texel let bilinear filtering bleed colours across charts."""
DILATE = 4
"""Rounds of neighbour-mean dilation into empty texels before the push-pull fill."""
PACKING = 0.6
"""Expected share of the atlas that xatlas' charts fill; sets its texels per unit of surface."""


@dataclasses.dataclass(frozen=True)
class Textured:
    """A mesh with one texture: what the writers take."""

    vertices: np.ndarray  # [V', 3] float64, the input vertices split along chart seams
    faces: np.ndarray  # [F, 3] int64 into `vertices`
    uv: np.ndarray  # [V', 2] float32 in [0, 1], v up
    image: np.ndarray  # [H, W, 3] uint8, row 0 at the top (v = 1)
    source_vertex: np.ndarray  # [V'] int64: the input vertex each one copies
    info: dict  # texture size, charts, coverage, timing_seconds {"unwrap", "bake"}

    def transformed(self, target_from_source: np.ndarray) -> Textured:
        """Positions mapped by a 4x4 affine (winding reversed where it mirrors); UVs and texture unchanged."""
        verts, faces = transform_mesh(self.vertices, self.faces, target_from_source)
        return dataclasses.replace(self, vertices=verts, faces=faces)


def auto_texture_size(n_faces: int) -> int:
    """The smallest power of two with at least TEXELS_PER_FACE texels per face, within SIZE_RANGE."""
    side = math.sqrt(max(1, n_faces) * TEXELS_PER_FACE)
    return int(min(max(2 ** math.ceil(math.log2(side)), SIZE_RANGE[0]), SIZE_RANGE[1]))


def unwrap(verts: np.ndarray, faces: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Charts by box projection, packed by xatlas into one atlas of about size x size texels
    -> (source_vertex [V'], faces [F, 3] in the input's order, uv [V', 2], info).

    A chart is a connected set of faces (sharing edges) whose normals have the same dominant axis and sign,
    projected onto the plane across that axis; all its triangles keep their orientation there, and the texel
    density varies by at most sqrt(3) (a normal 54.7 degrees off its axis). xatlas then packs the charts
    (`use_input_mesh_uvs`). Its own chart search was too slow for our meshes: 36 s for a 66k-face noisy
    marching-cubes sphere and over 8 minutes for a 330k-face smooth one (box charts: 0.9 s for the first).
    """
    import xatlas

    fn = _cross3(verts, faces)
    axis = np.abs(fn).argmax(axis=1)
    label = axis * 2 + (fn[np.arange(len(fn)), axis] > 0)  # 6 directions
    comp = _edge_components(faces, label, len(verts))
    pair = comp[:, None] * len(verts) + faces  # a vertex is copied into each chart that uses it
    uniq, inv = np.unique(pair.ravel(), return_inverse=True)
    source, chart, new_faces = uniq % len(verts), uniq // len(verts), inv.reshape(-1, 3)
    chart_label = np.zeros(comp.max() + 1, np.int64)
    chart_label[comp] = label
    ax = chart_label[chart] // 2
    p = verts[source]
    rows = np.arange(len(p))
    uv = np.stack([p[rows, (ax + 1) % 3], p[rows, (ax + 2) % 3]], axis=1)
    uv[chart_label[chart] % 2 == 0, 0] *= -1  # seen from the negative side: mirror, so triangles stay CCW
    atlas = xatlas.Atlas()
    atlas.add_mesh(p.astype(np.float32), new_faces.astype(np.uint32), None, uv.astype(np.float32))
    options = xatlas.ChartOptions()
    options.use_input_mesh_uvs = True
    pack = xatlas.PackOptions()
    area = float(np.linalg.norm(fn, axis=1).sum() / 2)
    pack.texels_per_unit = float(math.sqrt(PACKING * size * size / max(area, 1e-30)))  # one pack, no search
    pack.padding = PADDING
    pack.bilinear = True
    pack.blockAlign = True  # faster packing
    atlas.generate(options, pack)
    if atlas.atlas_count != 1:
        raise RuntimeError(f"xatlas packed {atlas.atlas_count} atlases, expected 1")
    vmap, out_faces, out_uv = atlas[0]
    source, out_faces = source[vmap.astype(np.int64)], out_faces.astype(np.int64)
    if out_faces.shape != faces.shape or not np.array_equal(source[out_faces], faces):
        raise RuntimeError("xatlas changed the mesh's faces or their order")  # the rest relies on both
    # xatlas normalises UVs by its atlas' size, which differs from size x size by some percent: the charts then
    # fill the square image with a little more or less padding than PADDING texels
    info = {"charts": int(atlas.chart_count), "atlas_size": [int(atlas.width), int(atlas.height)]}
    return source, out_faces, out_uv.astype(np.float32), info


def _edge_components(faces: np.ndarray, label: np.ndarray, n_verts: int) -> np.ndarray:
    """Connected components [F] of faces joined by a shared edge when both carry the same label."""
    import scipy.sparse
    import scipy.sparse.csgraph

    n = len(faces)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    key = edges[:, 0] * n_verts + edges[:, 1]
    face = np.tile(np.arange(n), 3)
    order = np.argsort(key, kind="stable")
    ks, fs = key[order], face[order]
    same = ks[1:] == ks[:-1]
    a, b = fs[:-1][same], fs[1:][same]
    keep = label[a] == label[b]
    graph = scipy.sparse.coo_matrix((np.ones(int(keep.sum())), (a[keep], b[keep])), shape=(n, n))
    return scipy.sparse.csgraph.connected_components(graph, directed=False)[1].astype(np.int64)


def _cross3(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = verts[faces]
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def rasterize(tri_uv: np.ndarray, width: int, height: int, budget: int = 1 << 20) -> tuple[np.ndarray, ...]:
    """Texels whose centres lie inside the UV triangles tri_uv [F, 3, 2] (v up).

    -> (rows [N], cols [N], face [N], bary [N, 3] float32); a texel on an edge shared by two triangles is listed
    once per triangle (the later one wins when written). Triangles are grouped by bounding-box side so each group
    is one vectorised test over candidates [faces, side, side], in chunks of at most `budget` candidates.
    """
    p = tri_uv.astype(np.float64) * np.array([width, height], np.float64)  # texel units, y up
    lo = np.ceil(p.min(axis=1) - 0.5).astype(np.int64)  # first texel index whose centre can be inside
    hi = np.floor(p.max(axis=1) - 0.5).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, np.array([width - 1, height - 1]))
    n = hi - lo + 1  # [F, 2]
    area2 = _cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # twice the signed area
    ok = (n > 0).all(axis=1) & (np.abs(area2) > 1e-12)
    side = np.where(ok, n.max(axis=1), 0)
    out: list[tuple[np.ndarray, ...]] = []
    for s in np.unique(side[side > 0]):
        ids = np.flatnonzero(side == s)
        oy, ox = (g.reshape(-1) for g in np.mgrid[0:s, 0:s])
        step = max(1, budget // int(s * s))
        for a in range(0, len(ids), step):
            out.append(_inside(p, lo, n, area2, ids[a : a + step], ox, oy))
    if not out:
        empty = np.zeros(0, np.int64)
        return empty, empty, empty, np.zeros((0, 3), np.float32)
    cols, rows_up, face, bary = (np.concatenate(parts) for parts in zip(*out, strict=True))
    return height - 1 - rows_up, cols, face, bary


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _inside(p, lo, n, area2, ids, ox, oy) -> tuple[np.ndarray, ...]:
    """The texel centres of the candidates (ids x offsets) inside their triangle: (cols, rows up, face, bary)."""
    cx = lo[ids, 0, None] + ox[None]  # [f, s*s]
    cy = lo[ids, 1, None] + oy[None]
    valid = (ox[None] < n[ids, 0, None]) & (oy[None] < n[ids, 1, None])
    q = np.stack([cx + 0.5, cy + 0.5], axis=-1)  # [f, s*s, 2]
    t = p[ids]  # [f, 3, 2]
    inv = 1.0 / area2[ids, None]
    b0 = _cross(t[:, None, 1] - q, t[:, None, 2] - q) * inv  # [f, s*s]
    b1 = _cross(t[:, None, 2] - q, t[:, None, 0] - q) * inv
    b2 = 1.0 - b0 - b1
    eps = -1e-7
    keep = valid & (b0 >= eps) & (b1 >= eps) & (b2 >= eps)
    f_idx, c_idx = np.nonzero(keep)
    bary = np.stack([b0[keep], b1[keep], b2[keep]], axis=1).clip(0, 1).astype(np.float32)
    return cx[f_idx, c_idx], cy[f_idx, c_idx], ids[f_idx], bary


def bake_texture(
    verts: np.ndarray,
    faces: np.ndarray,
    color_fn: ColorFn,
    *,
    texture_size: int | None = None,
    views: ViewSource | None = None,
    dilate: int = DILATE,
    chunk: int = 1 << 18,
    device: str | torch.device = "cpu",
) -> Textured:
    """UV-unwrap the mesh (verts [V, 3] float64, faces [F, 3] int64, field frame) and bake a texture_size x
    texture_size texture (None: `auto_texture_size`): with `views`, each texel the cameras see takes the
    cosine-weighted mean of their renders (`stages.mesh.texture_views.project_views`), the rest `color_fn` along the
    inward normal; without, every texel `color_fn`. See the module doc for the conventions."""
    verts = np.asarray(verts, np.float64)
    faces = np.asarray(faces, np.int64)
    if verts.ndim != 2 or verts.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"expected verts [V, 3] and faces [F, 3] (F > 0), got {verts.shape} and {faces.shape}")
    size = auto_texture_size(len(faces)) if texture_size is None else int(texture_size)
    if not 16 <= size <= 16384:
        raise ValueError(f"texture_size: expected 16..16384, got {size}")
    t0 = time.perf_counter()
    source, new_faces, uv, info = unwrap(verts, faces, size)
    t1 = time.perf_counter()
    rows, cols, face, bary = rasterize(uv[new_faces], size, size)
    normals = vertex_normals(verts, faces)[source]  # [V', 3]
    pos = verts[source]
    tri = new_faces[face]  # [N, 3]
    x = np.einsum("nk,nkd->nd", bary, pos[tri])
    d = -np.einsum("nk,nkd->nd", bary, normals[tri])
    d, rgb, seen = _normalised(d, _face_normals(pos, new_faces)[face]), np.zeros((len(x), 3), np.float32), None
    if views is not None:
        rgb, weight, skipped = project_views(x, -d, verts, faces, views)
        seen = weight > 0
        info["views"] = {
            **views.info,
            "texels_seen": round(float(seen.mean()), 4) if len(seen) else 0.0,
            "skipped": skipped,
        }
    rest = np.flatnonzero(~seen) if seen is not None else np.arange(len(x))
    rgb[rest] = _query(color_fn, x[rest], d[rest], chunk, torch.device(device))
    image = np.zeros((size, size, 3), np.float32)
    filled = np.zeros((size, size), bool)
    image[rows, cols] = rgb
    filled[rows, cols] = True
    coverage = float(filled.mean())
    image = _fill(image, filled, dilate)
    t2 = time.perf_counter()
    info.update(
        size=[size, size],
        texels_baked=int(filled.sum()),
        coverage=round(coverage, 4),
        faces_without_texel=int(len(new_faces) - len(np.unique(face))),
        timing_seconds={"unwrap": round(t1 - t0, 3), "bake": round(t2 - t1, 3)},
    )
    img8 = np.rint(np.clip(image, 0, 1) * 255).astype(np.uint8)
    return Textured(vertices=pos, faces=new_faces, uv=uv, image=img8, source_vertex=source, info=info)


def _face_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    n = _cross3(verts, faces)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def _normalised(d: np.ndarray, face_n: np.ndarray) -> np.ndarray:
    """Inward directions [N, 3] made unit; a degenerate one takes its face's inward normal, else -z."""
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    fallback = np.where(np.linalg.norm(face_n, axis=1, keepdims=True) > 0, -face_n, [0.0, 0.0, -1.0])
    return np.where(norm > 1e-12, d / np.maximum(norm, 1e-12), fallback)


def _query(color_fn: ColorFn, x: np.ndarray, d: np.ndarray, chunk: int, device) -> np.ndarray:
    """color_fn over the texel points [N, 3] along unit d [N, 3], in chunks -> float32 [N, 3] in [0, 1] (non-finite
    values become 0)."""
    out = np.zeros((len(x), 3), np.float32)
    with torch.inference_mode():
        for a in range(0, len(x), chunk):
            xt = torch.as_tensor(x[a : a + chunk], dtype=torch.float32, device=device)
            dt = torch.as_tensor(d[a : a + chunk], dtype=torch.float32, device=device)
            rgb = color_fn(xt, dt)
            rgb = rgb.detach().float().cpu().numpy() if isinstance(rgb, torch.Tensor) else np.asarray(rgb, np.float32)
            if rgb.shape != (len(xt), 3):
                raise ValueError(f"color_fn: expected rgb [{len(xt)}, 3], got {tuple(rgb.shape)}")
            out[a : a + chunk] = rgb
    return np.clip(np.nan_to_num(out, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)


def _fill(image: np.ndarray, filled: np.ndarray, dilate: int) -> np.ndarray:
    """Empty texels: `dilate` rounds of their filled 8-neighbours' mean, then a push-pull fill of the rest."""
    image, filled = image.copy(), filled.copy()
    for _ in range(dilate):
        if filled.all():
            break
        pi = np.pad(image * filled[..., None], ((1, 1), (1, 1), (0, 0)))
        pm = np.pad(filled.astype(np.float32), 1)
        h, w = filled.shape
        acc = sum(pi[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1))
        cnt = sum(pm[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1))
        grow = ~filled & (cnt > 0)
        image[grow] = acc[grow] / cnt[grow, None]
        filled |= grow
    return _push_pull(image, filled)


def _push_pull(image: np.ndarray, filled: np.ndarray) -> np.ndarray:
    """Empty texels take the mean of the filled ones in the smallest 2^k block around them that has any."""
    if filled.all() or not filled.any():
        return image
    h, w = filled.shape
    hp, wp = h + h % 2, w + w % 2
    img = np.zeros((hp, wp, 3), np.float32)
    m = np.zeros((hp, wp), np.float32)
    img[:h, :w] = image * filled[..., None]
    m[:h, :w] = filled
    s = img.reshape(hp // 2, 2, wp // 2, 2, 3).sum(axis=(1, 3))
    c = m.reshape(hp // 2, 2, wp // 2, 2).sum(axis=(1, 3))
    coarse = _push_pull(s / np.maximum(c, 1.0)[..., None], c > 0)
    up = coarse.repeat(2, axis=0).repeat(2, axis=1)[:h, :w]
    return np.where(filled[..., None], image, up)


def sample_texture(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup (clamped at the borders) of image [H, W, C] at uv [N, 2] (v up) -> float [N, C] in the
    image's units. The plain reference the tests sample baked textures with."""
    h, w = image.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1.0 - uv[:, 1]) * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    im = image.astype(np.float64)
    top = im[y0, x0] * (1 - fx) + im[y0, x1] * fx
    bottom = im[y1, x0] * (1 - fx) + im[y1, x1] * fx
    return top * (1 - fy) + bottom * fy
