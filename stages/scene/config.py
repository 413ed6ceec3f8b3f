"""The scene stage's interface: its `Config` (with the validation of a config) and its `Outputs`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from nerfpipe.data.errors import UserError

__all__ = ["Config", "Outputs", "check"]


@dataclass(frozen=True, kw_only=True)
class Config:
    out_dir: Path
    """Folder to write the scene into (created; one that holds an earlier scene needs --overwrite)."""
    kind: Literal["photos", "posed", "rgba", "blender"] = "posed"
    """photos: bare images for COLMAP; posed: images + transforms.json; rgba: transparent background + alpha;
    blender: the NeRF-synthetic layout (transforms_{train,val,test}.json, RGBA PNGs in train/ val/ test/)."""
    size: int = 64
    """Image width = height, pixels."""
    views: int = 24
    """Number of cameras."""
    seed: int = 0
    """Picks the textures and the camera jitter (subject random: the whole scene); same seed, byte-identical
    output."""
    layout: Literal["orbit", "forward", "room", "turntable"] = "orbit"
    """orbit, forward, room or turntable. orbit: cameras all round the scene on a hemisphere (a 360-degree capture).
    turntable: the objects turn on their slab in front of a fixed camera and a fixed room (one full turn over the
    views); truth poses are object-relative and masks/ holds each view's object mask (white = object;
    stages.scene.turntable); kinds photos, posed (mask_path per frame) and rgba (the object alone).
    room: the orbit inside a textured room (floor and walls 4 m away; transforms.json's aabb is the objects'
    box, so the room lies beyond it: an unbounded capture). forward: cameras on a
    jittered grid in one plane, all looking the same way at the scene, with a textured wall 4 m behind it (an
    LLFF-style forward-facing capture: content from ~1.5 m to ~7 m)."""
    subject: Literal["objects", "carton", "cube", "random", "mesh"] = "objects"
    """What is photographed. objects: five textured objects on a slab. carton / cube: one printed box on white,
    with no ground (a product shot; `data.synthetic.prints`): carton, a tall box with one print on front and back
    and another on both sides; cube, the same print on all four sides. Faces that look alike are what can make
    a reconstruction fold onto itself (issue 53). With layout turntable the room is left out too (white).
    random: the seed draws the scene (`data.synthetic.random_scene`): 1-8 spheres, boxes and cylinders of
    0.1-0.6 m on or above the slab, none touching, each with a noise or photo texture, the slab's texture, the
    lights, and (layout orbit) nothing, a far wall or a room around; manifest.json's `random_subject` says what
    was drawn. Pretraining data for a cross-scene model: the layouts differ from seed to seed.
    mesh: the mesh file `mesh` alone (no slab), textured like the objects, its box's centre at the rig's look-at
    point and its half-diagonal 0.6 m, the file's `mesh_up` axis up; manifest.json's `mesh_subject` holds the 4x4
    scene_from_source and ground_truth/mesh.ply is the mesh in the scene's frame."""
    mesh: Path | None = None
    """subject=mesh: the mesh file to photograph (any format trimesh reads: obj, ply, stl, off, glb)."""
    mesh_up: Literal["z", "y"] = "z"
    """subject=mesh: the file's up axis (y: turned so that its +y is the scene's +z, as glTF and most OBJ files
    have it; z: no rotation)."""
    count: int = 1
    """Scenes to write: 1 writes out_dir itself; N > 1 writes out_dir/<seed> (six digits) for the seeds seed,
    seed + 1, ..., seed + N - 1, each a whole scene, and a manifest over them (a dataset of scenes: with --subject
    random no two share a layout; `make pretrain-gnt` trains on one)."""
    scale: float = 1.0
    """Multiply every length (objects, cameras, depth, mesh) by this; the images do not change."""
    overwrite: bool = False
    """Replace an earlier scene in out_dir (set aside in OUT_DIR.previous/ until this one is written)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out_dir: Path
    """The scene folder."""
    images: tuple[Path, ...]
    """The rendered images, in view order."""
    transforms: Path | None
    """transforms.json (None for kind=photos and blender)."""
    masks: tuple[Path, ...] = ()
    """layout=turntable: masks/<stem>.png per view (white = object), in view order; empty otherwise."""
    split_files: tuple[Path, ...]
    """kind=blender: the transforms_<split>.json written; empty otherwise."""
    cameras: Path
    """ground_truth/cameras.json."""
    depths: tuple[Path, ...]
    """ground_truth/depth/*.npy, in view order."""
    mesh: Path
    """ground_truth/mesh.ply."""
    manifest: Path
    """manifest.json (written last)."""
    scenes: tuple[Path, ...] = ()
    """count > 1: every scene's folder, in seed order (the fields above then describe the first scene, but for
    out_dir and manifest, the dataset's); empty for one scene."""


def check(config: Config) -> None:
    if config.count < 1:
        raise UserError(f"scene: expected --count >= 1, got {config.count}")
    if config.size < 8 or config.views < 1:
        raise UserError(f"scene: expected --size >= 8 and --views >= 1, got size={config.size}, views={config.views}")
    if config.kind not in ("photos", "posed", "rgba", "blender"):
        raise UserError(f"scene: expected --kind photos|posed|rgba|blender, got {config.kind!r}")
    if config.layout not in ("orbit", "forward", "room", "turntable"):
        raise UserError(f"scene: expected --layout orbit|forward|room|turntable, got {config.layout!r}")
    if config.layout == "turntable" and config.kind == "blender":
        raise UserError("scene: --layout turntable writes kinds photos, posed or rgba, not blender")
    if config.subject not in ("objects", "carton", "cube", "random", "mesh"):
        raise UserError(f"scene: expected --subject objects|carton|cube|random|mesh, got {config.subject!r}")
    if (config.subject == "mesh") != (config.mesh is not None):
        raise UserError("scene: --subject mesh and --mesh FILE go together (the mesh file is the subject)")
    if config.mesh_up not in ("z", "y"):
        raise UserError(f"scene: expected --mesh-up z|y, got {config.mesh_up!r}")
    if config.subject == "random" and config.seed < 0:
        raise UserError(f"scene: --subject random draws from a seed >= 0, got --seed {config.seed}")
    scale = float(config.scale)
    if not (math.isfinite(scale) and scale > 0):
        raise UserError(f"scene: expected --scale > 0 (finite), got {config.scale!r}")
