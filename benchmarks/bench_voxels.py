"""Single-view voxels (issue 50): IoU on held-out objects of the trained families and on the family never seen,
one photo and five fused, against the mean shape; the real scanned meshes pymeshlab ships; a real masked photo.

Run: .venv/bin/python -m benchmarks.bench_voxels --out runs/bench/voxels [--weights pretrained|FILE]
     [--count 30] [--only families,scans,photo] [--no-mirror]

- families: `nerfpipe shapes` (the command a user types) draws objects the network never saw: seeds 100000 and up
  of the trained families (pretraining used 0-99999), and the held-out family; 5 photos each (random cameras,
  textures, lights, backgrounds, mask edges). IoU of `prob >= level` against the exact occupancy of each photo's
  view frame, levels 0.2-0.5 (Pix2Vox's sweep); 1 view: each photo alone; 5 views: the five fused in the first
  photo's frame (`model.voxels.fuse`, the cameras' azimuths). Baseline: the mean occupancy of the test objects
  themselves (a prior that knows the test set), at its best level.
- scans: bunny, cow and airplane from pymeshlab's sample meshes (y up in their files), normalised as the families
  are, rendered grey-textured by a z-buffer rasteriser from 5 random cameras; occupancy by ray parity along z.
- photo: `nerfpipe voxels` on the shared head (a real DSLR photo and its mask) and on 5 photos of it with the
  azimuths of its capture's own cameras, and on scikit-image's photo of a coffee cup with a hand-drawn mask (a
  real object of a trained family); the previews are copied to docs/voxels/.
Prints markdown tables and writes OUT/bench_voxels.json with the commit.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.provenance import commit
from nerfpipe.model.voxels.pretrain import iou

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DOCS = Path(__file__).resolve().parents[1] / "docs" / "voxels"
LEVELS = (0.2, 0.3, 0.4, 0.5)
SCANS = ("bunny", "cow", "airplane")


def _ious(prob: torch.Tensor, truth: torch.Tensor) -> dict[float, float]:
    """IoU at each of `LEVELS` (the test shapes are never empty: no union is 0)."""
    return {level: iou(prob, truth, level) for level in LEVELS}


def _predict(net, inputs: torch.Tensor, mirror: bool) -> torch.Tensor:
    """uint8 inputs [B, 4, S, S] -> probabilities [B, R, R, R], as `nerfpipe voxels [--no-mirror]` predicts."""
    from nerfpipe.model.voxels.infer import occupancy

    return occupancy(net, inputs.float() / 255.0, mirror=mirror)


def _score(net, path: Path, mirror: bool) -> dict:
    """Per-family mean IoUs (1 view, 5 views fused) of a shapes dataset."""
    from nerfpipe.model.voxels.fuse import fuse
    from nerfpipe.model.voxels.pretrain import unpack
    from nerfpipe.stages.pretrain_voxels import load_shapes

    data, meta = load_shapes(path)
    truth = unpack(data.bits, data.res)
    t0 = time.perf_counter()
    prob = _predict(net, data.inputs, mirror)
    per_photo = (time.perf_counter() - t0) / len(prob)
    fams, seeds, az = meta["family"], meta["seed"], torch.from_numpy(meta["azimuth"])
    mean_shape = truth.mean(0)
    rows: dict[str, dict] = {}
    for f, name in enumerate(meta["families"]):
        one, five, base = [], [], []
        for s in np.unique(seeds[fams == f]):
            idx = np.flatnonzero((fams == f) & (seeds == s))
            one += [_ious(prob[i], truth[i]) for i in idx]
            five.append(_ious(fuse(prob[idx], az[idx]), truth[idx[0]]))
            base += [_ious(mean_shape, truth[i]) for i in idx]
        rows[str(name)] = {
            "objects": len(five),
            "one": {lv: float(np.mean([r[lv] for r in one])) for lv in LEVELS},
            "five": {lv: float(np.mean([r[lv] for r in five])) for lv in LEVELS},
            "mean_shape": max(float(np.mean([r[lv] for r in base])) for lv in LEVELS),
        }
    return {"families": rows, "seconds_per_photo": per_photo}


def _table(title: str, rows: dict[str, dict]) -> str:
    lines = [
        f"### {title}",
        "",
        "| family | objects | 1 view IoU @0.2 / 0.3 / 0.4 / **0.5** | 5 views IoU @0.2 / 0.3 / 0.4 / **0.5** "
        "| mean shape (best level) |",
        "|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        one = " / ".join(f"{r['one'][lv]:.3f}" for lv in LEVELS[:-1]) + f" / **{r['one'][0.5]:.3f}**"
        five = " / ".join(f"{r['five'][lv]:.3f}" for lv in LEVELS[:-1]) + f" / **{r['five'][0.5]:.3f}**"
        lines.append(f"| {name} | {r['objects']} | {one} | {five} | {r['mean_shape']:.3f} |")
    return "\n".join(lines)


def _overall(rows: dict[str, dict], key: str, level: float = 0.5) -> float:
    n = sum(r["objects"] for r in rows.values())
    return sum(r[key][level] * r["objects"] for r in rows.values()) / n


def _families(net, out: Path, count: int, mirror: bool) -> dict:
    from nerfpipe.data.synthetic.families import HELD_OUT

    sets = {
        "trained": ["--first-seed", "100000", "--count", str(count)],
        "held_out": ["--families", HELD_OUT, "--first-seed", "100000", "--count", str(2 * count)],
    }
    result = {}
    for name, args in sets.items():
        folder = out / f"shapes_{name}"
        if not (folder / "manifest.json").is_file():
            cmd = [sys.executable, "-m", "nerfpipe.cli", "shapes", str(folder), "--views", "5", *args, "--overwrite"]
            subprocess.run(cmd, check=True)
        result[name] = _score(net, folder, mirror)
        print(_table(f"{name} families (held-out objects)", result[name]["families"]))
        rows = result[name]["families"]
        print(
            f"\noverall IoU@0.5: 1 view {_overall(rows, 'one'):.3f}, 5 views {_overall(rows, 'five'):.3f}; "
            f"{1000 * result[name]['seconds_per_photo']:.1f} ms a photo\n"
        )
    return result


# ---------------------------------------------------------------- scanned meshes


def _scan(name: str):
    import trimesh

    from benchmarks.mesh_metrics import scanned_mesh_file

    m = trimesh.load(scanned_mesh_file(name), force="mesh")
    v = np.asarray(m.vertices, np.float64)[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # y up -> z up
    lo, hi = v.min(0), v.max(0)
    axis = 0.5 * (lo[:2] + hi[:2])
    reach = float(np.max(np.linalg.norm(v[:, :2] - axis, axis=1)))
    scale = 1.0 / max(2 * reach, float(hi[2] - lo[2]))
    v = (v - np.array([axis[0], axis[1], 0.5 * (lo[2] + hi[2])])) * scale
    return v, np.asarray(m.faces, np.int64)


def _parity_occupancy(v: np.ndarray, f: np.ndarray, res: int = 32, sub: int = 2) -> np.ndarray:
    """Occupancy [res]^3 (fraction of sub^3 points inside >= 0.5) of a closed mesh in the cube [-0.5, 0.5]^3, by
    counting the surface crossings below each point along +z (ray parity)."""
    from nerfpipe.stages.mesh.texture import rasterize

    n = res * sub
    tri = v[f]  # [F, 3, 3]
    rows, cols, face, bary = rasterize(tri[..., :2] + 0.5, n, n)  # image rows: y = n - 1 - row
    z = np.einsum("nk,nk->n", bary.astype(np.float64), tri[face][..., 2])
    zc = (np.arange(n) + 0.5) / n - 0.5
    inside = np.zeros((n, n, n), bool)  # (x, y, z)
    column = cols * n + (n - 1 - rows)  # x * n + y
    order = np.argsort(column, kind="stable")
    column, z = column[order], z[order]
    starts = np.searchsorted(column, np.arange(n * n))
    ends = np.searchsorted(column, np.arange(n * n), side="right")
    for c in np.flatnonzero(ends > starts):
        crossings = np.sort(z[starts[c] : ends[c]])
        count = np.searchsorted(crossings, zc)  # crossings below each sample
        inside[c // n, c % n] = count % 2 == 1
    return inside.reshape(res, sub, res, sub, res, sub).mean((1, 3, 5)) >= 0.5


def _mesh_photo(v: np.ndarray, f: np.ndarray, azimuth: float, elevation: float, distance: float, size: int):
    """A grey Lambert-shaded photo of a mesh (2x supersampled z-buffer): rgb [size, size, 3], alpha [size, size]."""
    from benchmarks.bench_mesh_texture import nearest_fragments
    from nerfpipe.data.synthetic.shape_views import camera

    s = 2 * size
    intr, world_from_cam = camera(azimuth, elevation, distance, s)
    pixel, face, _ = nearest_fragments(v, f, world_from_cam, intr)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    light = np.array([0.4, 0.3, 0.85]) / np.linalg.norm([0.4, 0.3, 0.85])
    shade = 0.3 + 0.6 * np.abs(n @ light)  # both sides lit: a mesh's winding may be either
    rgb = np.zeros((s * s, 3))
    rgb[pixel] = shade[face, None] * np.array([0.8, 0.7, 0.6])
    alpha = np.zeros(s * s)
    alpha[pixel] = 1.0
    rgb = rgb.reshape(size, 2, size, 2, 3).mean((1, 3))
    alpha = alpha.reshape(size, 2, size, 2).mean((1, 3))
    return rgb / np.maximum(alpha, 1e-6)[..., None] * (alpha > 0)[..., None], alpha


def _scans(net, mirror: bool) -> dict:
    from nerfpipe.data.synthetic.shape_views import DISTANCE, ELEVATION_DEG, view_rotation
    from nerfpipe.model.voxels.fuse import fuse
    from nerfpipe.model.voxels.inputs import prepare

    out = {}
    rng = np.random.default_rng(50)
    lines = [
        "### scanned meshes (pymeshlab's samples)",
        "",
        "| mesh | 1 view IoU@0.5 (mean of 5) | 5 views fused | occupied share of the grid |",
        "|---|---|---|---|",
    ]
    for name in SCANS:
        v, f = _scan(name)
        inputs, truths, azs = [], [], []
        for _ in range(5):
            az = float(rng.uniform(0, 2 * math.pi))
            el = math.radians(float(rng.uniform(*ELEVATION_DEG)))
            rgb, alpha = _mesh_photo(v, f, az, el, float(rng.uniform(*DISTANCE)), 112)
            inputs.append(prepare(rgb.astype(np.float32), alpha.astype(np.float32)))
            turned = v @ view_rotation(az)  # unit -> view frame: p_view = R^T p_unit
            truths.append(torch.from_numpy(_parity_occupancy(turned, f).astype(np.float32)))
            azs.append(az)
        prob = _predict(net, (torch.stack(inputs) * 255).round(), mirror)
        one = float(np.mean([_ious(p, t)[0.5] for p, t in zip(prob, truths, strict=True)]))
        five = _ious(fuse(prob, torch.tensor(azs, dtype=torch.float64)), truths[0])[0.5]
        out[name] = {"one": one, "five": five, "occupied": float(truths[0].mean())}
        lines.append(f"| {name} | {one:.3f} | {five:.3f} | {out[name]['occupied']:.3f} |")
    print("\n".join(lines) + "\n")
    return out


# ---------------------------------------------------------------- a real photo


def _head_azimuths(names: list[str]) -> list[float]:
    """Azimuths (degrees, counter-clockwise seen from above) of the head's cameras about the turntable's axis: the
    normal of the plane through the camera centres (the capture's LLFF poses_bounds.npy: columns down, right, back,
    centre), pointing the way the cameras' image up points on average."""
    pb = np.load(DATA / "head" / "poses_bounds.npy")
    poses = pb[:, :15].reshape(-1, 3, 5)
    centres, ups = poses[:, :, 3], -poses[:, :, 0]
    all_names = sorted(p.name for p in (DATA / "head" / "images").iterdir())
    c = centres - centres.mean(0)
    axis = np.linalg.svd(c)[2][2]
    axis = axis if float(np.mean(ups @ axis)) > 0 else -axis
    e1 = c[0] - (c[0] @ axis) * axis
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    az = np.degrees(np.arctan2(c @ e2, c @ e1))
    return [float(az[all_names.index(n)] - az[all_names.index(names[0])]) for n in names]


def _voxels(
    images: list[Path], masks: list[Path], folder: Path, weights: str, mirror: bool, azimuths: list[float] | None = None
) -> None:
    """`nerfpipe voxels IMAGES FOLDER --masks ... --weights ... [--no-mirror] [--azimuths ...]`, as a user types it."""
    cmd = [sys.executable, "-m", "nerfpipe.cli", "voxels", *map(str, images), str(folder)]
    cmd += ["--masks", ",".join(map(str, masks)), "--weights", weights, "--mirror" if mirror else "--no-mirror"]
    cmd += ["--overwrite"] + (["--azimuths", ",".join(f"{a:.2f}" for a in azimuths)] if azimuths else [])
    subprocess.run(cmd, check=True)


def _photo(out: Path, weights: str, mirror: bool) -> dict:
    images = sorted((DATA / "head" / "images").iterdir())
    if not images:
        return {"skipped": "no head photos"}
    picks = [images[i] for i in range(0, len(images), max(1, len(images) // 5))][:5]
    masks = [DATA / "head" / "masks" / (p.stem + ".png") for p in picks]
    result = {}
    for name, chosen, mk in (("head_1", picks[:1], masks[:1]), ("head_5", picks, masks)):
        folder = out / name
        azimuths = _head_azimuths([p.name for p in chosen]) if len(chosen) > 1 else None
        t0 = time.perf_counter()
        _voxels(chosen, mk, folder, weights, mirror, azimuths)
        result[name] = {"photos": [p.name for p in chosen], "seconds": round(time.perf_counter() - t0, 1)}
        DOCS.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(folder / "preview.png", DOCS / f"{name}_preview.png")
    result["cup_1"] = _cup(out, weights, mirror)
    print(f"head and cup previews -> {DOCS}\n")
    return result


def _cup(out: Path, weights: str, mirror: bool) -> dict:
    """`nerfpipe voxels` on a real photo of an object of a trained family: scikit-image's `coffee` (a cup on a
    saucer, seen from ~55 deg above, more than the photos pretraining drew), with a mask drawn by hand as a user
    would in an editor (a polygon: the cup's rim, body and handle, not the saucer or the spoon). The stage's preview
    and the grid seen from 50 deg above go to docs/voxels/."""
    import cv2
    import skimage.data
    from PIL import Image

    from nerfpipe.model.voxels.preview import render_grid

    folder = out / "cup"
    folder.mkdir(parents=True, exist_ok=True)
    photo = skimage.data.coffee()  # [400, 600, 3]
    rim = [(290 + 118 * math.cos(t), 112 - 94 * math.sin(t)) for t in np.linspace(math.pi, 0, 40)]
    body = [(406, 150), (398, 200), (380, 240), (352, 272), (318, 288), (262, 290), (228, 276), (202, 242)]
    body += [(184, 196), (174, 150)]
    handle = [(222, 232), (203, 245), (195, 272), (203, 298), (224, 306), (246, 292), (256, 266), (246, 244)]
    mask = np.zeros(photo.shape[:2], np.uint8)
    for polygon in (rim + body, handle):
        cv2.fillPoly(mask, [np.array(polygon).round().astype(np.int32)], 255)
    Image.fromarray(photo).save(folder / "coffee.png")
    Image.fromarray(mask).save(folder / "coffee_mask.png")
    _voxels([folder / "coffee.png"], [folder / "coffee_mask.png"], folder / "out", weights, mirror)
    prob = torch.from_numpy(np.load(folder / "out" / "occupancy.npy"))
    above = [render_grid(prob, turn, 50.0, 200, 0.5) for turn in (0.0, 90.0, 180.0, 270.0)]
    DOCS.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(folder / "out" / "preview.png", DOCS / "cup_1_preview.png")
    tiles = (np.clip(np.concatenate(above, axis=1), 0.0, 1.0) * 255).round().astype(np.uint8)
    Image.fromarray(tiles).save(DOCS / "cup_1_from_above.png")
    return {"photo": "skimage.data.coffee()", "occupied_share": round(float((prob >= 0.5).float().mean()), 3)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--weights", default="pretrained")
    ap.add_argument("--count", type=int, default=30)
    ap.add_argument("--only", default="families,scans,photo")
    ap.add_argument("--no-mirror", action="store_true", help="one forward pass a photo (`voxels --no-mirror`)")
    args = ap.parse_args(argv)
    mirror = not args.no_mirror
    from nerfpipe.model.voxels.weights import load_net

    torch.set_num_threads(2)
    args.out.mkdir(parents=True, exist_ok=True)
    net, provenance = load_net(args.weights, torch.device("cpu"))
    parts = args.only.split(",")
    result: dict = {
        "commit": commit(),
        "weights": args.weights,
        "mirror": mirror,
        "weights_provenance": {k: provenance.get(k) for k in ("steps", "seconds", "examples", "objects")},
    }
    if "families" in parts:
        result["families"] = _families(net, args.out, args.count, mirror)
    if "scans" in parts:
        result["scans"] = _scans(net, mirror)
    if "photo" in parts:
        result["photo"] = _photo(args.out, args.weights, mirror)
    (args.out / "bench_voxels.json").write_text(json.dumps(result, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
