"""COLMAP sparse model (binary or text) -> `Source`.

Where models are looked for, under SOURCE: SOURCE itself, SOURCE/sparse, SOURCE/colmap/sparse (the `poses`
stage's layout), and each one's sub-folders (`sparse/0`, `sparse/1`, ...). With several models the one with the
most registered images (then most points) is taken; the others are listed in `left_out`.
Images: the `images` override, else the first of <model>/../images, <model>/../../images, SOURCE/images,
SOURCE/colmap/images that holds at least one of the model's images.
Cameras: COLMAP `cam_from_world` is world -> camera in OpenCV axes; we invert it and flip to OpenGL axes.
Supported models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV (distortion kept as k1 k2 p1 p2).
Masks: `masks/<image name>.png` beside the image folder (COLMAP's mask layout, which `poses --masks` writes),
when present, become the frames' masks (white = keep, `data.masks`).
An image name is a path relative to the image folder (COLMAP allows sub-folders): it must stay inside it, and
its mask inside the mask folder (`data.confine.inside`; no `..`, absolute path or symlink leading out).
`read_world_from_cam`: only the poses of one model folder, by image name (pose-accuracy checks).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfpipe.data.confine import inside
from nerfpipe.data.errors import UserError
from nerfpipe.data.importers import Source, SourceFrame, flat_name
from nerfpipe.radiance.camera import Intrinsics

__all__ = ["find_models", "load", "intrinsics_from_camera", "read_world_from_cam"]

_MODEL_FILES = ("cameras", "images")


def _is_model(folder: Path) -> bool:
    return all((folder / f"{n}.bin").is_file() or (folder / f"{n}.txt").is_file() for n in _MODEL_FILES)


def find_models(source: Path) -> list[Path]:
    """Model folders under `source` (see the module docstring), sorted by path."""
    if not source.is_dir():
        return []
    found = []
    for base in (source, source / "sparse", source / "colmap" / "sparse"):
        if not base.is_dir():
            continue
        if _is_model(base):
            found.append(base)
        found.extend(sub for sub in sorted(base.iterdir()) if sub.is_dir() and _is_model(sub))
    return sorted(set(found))


def intrinsics_from_camera(cam) -> Intrinsics:
    """pycolmap.Camera -> Intrinsics (UserError for models we cannot represent)."""
    name = cam.model.name
    p = [float(v) for v in cam.params]
    w, h = int(cam.width), int(cam.height)
    if name == "SIMPLE_PINHOLE":
        return Intrinsics(w=w, h=h, fx=p[0], fy=p[0], cx=p[1], cy=p[2])
    if name == "PINHOLE":
        return Intrinsics(w=w, h=h, fx=p[0], fy=p[1], cx=p[2], cy=p[3])
    if name == "SIMPLE_RADIAL":
        return Intrinsics(w=w, h=h, fx=p[0], fy=p[0], cx=p[1], cy=p[2], k1=p[3])
    if name == "RADIAL":
        return Intrinsics(w=w, h=h, fx=p[0], fy=p[0], cx=p[1], cy=p[2], k1=p[3], k2=p[4])
    if name == "OPENCV":
        return Intrinsics(w=w, h=h, fx=p[0], fy=p[1], cx=p[2], cy=p[3], k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    raise UserError(
        f"COLMAP camera {cam.camera_id} uses the {name} model; supported: SIMPLE_PINHOLE, PINHOLE, "
        "SIMPLE_RADIAL, RADIAL, OPENCV (undistort the images with COLMAP first)"
    )


def _read(folder: Path):
    import pycolmap

    try:
        return pycolmap.Reconstruction(str(folder))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError on unreadable files
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        raise UserError(f"{folder}: cannot read the COLMAP model ({msg})") from None


def _world_from_cam_gl(image) -> np.ndarray:
    """A registered pycolmap.Image's pose -> world_from_cam [4, 4], OpenGL axes, the model's world frame."""
    import torch

    from nerfpipe.radiance.camera import opengl_from_opencv

    cam_from_world_cv = np.eye(4)
    cam_from_world_cv[:3] = image.cam_from_world().matrix()
    world_from_cam_cv = torch.from_numpy(np.linalg.inv(cam_from_world_cv))
    return opengl_from_opencv(world_from_cam_cv).numpy()  # OpenCV -> OpenGL camera axes


def read_world_from_cam(model: str | Path) -> dict[str, np.ndarray]:
    """The registered images of one model folder: COLMAP image name -> world_from_cam [4, 4] (OpenGL axes)."""
    rec = _read(Path(model))
    return {im.name: _world_from_cam_gl(im) for im in rec.images.values() if im.has_pose}


def _image_dir(model: Path, source: Path, names: list[str], override: Path | None) -> Path:
    if override is not None:
        if not Path(override).is_dir():
            raise UserError(f"{override}: image folder not found")
        return Path(override)
    candidates = [model.parent / "images", model.parent.parent / "images", source / "images"]
    candidates.append(source / "colmap" / "images")
    for c in candidates:
        if c.is_dir() and any((c / n).is_file() for n in names):
            return c
    raise UserError(
        f"{model}: none of the model's images (e.g. {names[0]!r}) found in "
        f"{', '.join(str(c) for c in dict.fromkeys(candidates))}; give the image folder (images=FOLDER)"
    )


def _mask_dir(image_dir: Path, names: list[str]) -> Path | None:
    """COLMAP's mask folder beside the image folder (`masks/<image name>.png`, the `poses --masks` layout)
    when it holds a mask of at least one of the images, else None."""
    masks = image_dir.parent / "masks"
    return masks if masks.is_dir() and any((masks / f"{n}.png").is_file() for n in names) else None


def load(source: Path, *, images: Path | None = None) -> Source:
    source = Path(source)
    models = find_models(source)
    if not models:
        raise UserError(f"{source}: no COLMAP model (cameras + images .bin/.txt) here, in sparse/ or sparse/N/")
    recs = [(m, _read(m)) for m in models]
    sizes = {m: (r.num_reg_images(), r.num_points3D()) for m, r in recs}
    model, rec = max(recs, key=lambda mr: sizes[mr[0]])
    if rec.num_reg_images() == 0:
        raise UserError(f"{model}: the COLMAP model has no registered images")
    left_out = {
        str(m): f"smaller model ({sizes[m][0]} images, {sizes[m][1]} points) than {model.name}"
        for m, _ in recs
        if m != model
    }

    posed = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    names = [im.name for im in posed]
    image_dir = _image_dir(model, source, names, images)
    cams = {cid: intrinsics_from_camera(cam) for cid, cam in rec.cameras.items()}
    mask_dir = _mask_dir(image_dir, names)
    ids = sorted(rec.points3D)
    row = {pid: k for k, pid in enumerate(ids)}
    frames = []
    for im in posed:
        what = f"image {im.image_id} name"
        frames.append(
            SourceFrame(
                name=flat_name(im.name),
                world_from_cam=_world_from_cam_gl(im),
                intrinsics=cams[im.camera_id],
                image=inside(image_dir, im.name, what, file=model),
                mask=inside(mask_dir, f"{im.name}.png", f"mask of {what}", file=model) if mask_dir else None,
                point_ids=np.unique(
                    np.array(
                        [row[p.point3D_id] for p in im.points2D if p.has_point3D() and p.point3D_id in row],
                        dtype=np.int64,
                    )
                ),
            )
        )
    points = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([rec.points3D[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    unposed = rec.num_images() - len(posed)
    if unposed:
        left_out["unregistered images"] = f"{unposed} images in the model have no pose"
    inputs = tuple(sorted(p for p in model.iterdir() if p.is_file()))
    if mask_dir is not None:
        left_out.update({f"mask of {n}": f"not in {mask_dir}" for n in names if not (mask_dir / f"{n}.png").is_file()})
    return Source(
        kind="colmap",
        frames=tuple(frames),
        up="cameras",
        points=points,
        colors=colors,
        inputs=inputs,
        used={
            "model": str(model),
            "images": str(image_dir),
            "models_found": len(models),
            "cameras": sorted({rec.cameras[c].model.name for c in rec.cameras}),
            "masks": str(mask_dir) if mask_dir is not None else None,
        },
        left_out=left_out,
    )
