"""Textured meshes to files: OBJ + MTL + PNG (`write_obj_textured`) and one GLB with the PNG embedded
(`write_glb_textured`), from a `stages.mesh.texture.Textured` (its UV and image conventions)."""

from __future__ import annotations

import contextlib
import io
import json
import struct
from pathlib import Path

import numpy as np

from nerfpipe.data.atomic import atomic_path
from nerfpipe.stages.mesh.texture import Textured

__all__ = ["write_obj_textured", "write_glb_textured", "texture_paths", "MATERIAL"]

MATERIAL = "material0"


def texture_paths(path: str | Path) -> dict[str, Path]:
    """The files a textured OBJ consists of: OUT.obj, OUT.mtl and OUT.png side by side."""
    path = Path(path)
    return {"obj": path, "mtl": path.with_suffix(".mtl"), "png": path.with_suffix(".png")}


def _png_bytes(image: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image, np.uint8), "RGB").save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def write_obj_textured(path: str | Path, textured: Textured, *, into: Path | None = None) -> dict[str, Path]:
    """OUT.obj + OUT.mtl + OUT.png (the MTL names the PNG, the OBJ the MTL, by relative name), each atomic.

    The PNG and the MTL take their names first, the OBJ (make's target) last, and none does unless all were
    written. `into`: write the OBJ's bytes there instead (a temporary the caller renames to `path` later, e.g.
    after its report); the MTL and PNG are still named after `path`.
    """
    paths = texture_paths(path)
    mtl = (
        f"# nerfpipe baked texture\nnewmtl {MATERIAL}\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\n"
        f"map_Kd {paths['png'].name}\n"
    )
    with contextlib.ExitStack() as stack:  # exits run innermost first: the PNG, then the MTL, then the OBJ
        obj_tmp = into if into is not None else stack.enter_context(atomic_path(paths["obj"]))
        with open(obj_tmp, "w") as f:  # written first, so that a failure here is reported as the OBJ's
            f.write(f"# nerfpipe textured mesh\nmtllib {paths['mtl'].name}\n")
            np.savetxt(f, textured.vertices, fmt="v %.7g %.7g %.7g")
            np.savetxt(f, textured.uv, fmt="vt %.7g %.7g")
            f.write(f"usemtl {MATERIAL}\n")
            idx = np.repeat(textured.faces + 1, 2, axis=1)  # v/vt with the same index: one UV per vertex
            np.savetxt(f, idx, fmt="f %d/%d %d/%d %d/%d")
        stack.enter_context(atomic_path(paths["mtl"])).write_text(mtl)
        stack.enter_context(atomic_path(paths["png"])).write_bytes(_png_bytes(textured.image))
    return paths


def write_glb_textured(path: str | Path, textured: Textured, *, into: Path | None = None) -> Path:
    """One GLB with the PNG embedded: a PBR material (base colour texture, metallic 0, double sided) marked
    KHR_materials_unlit, since the baked texture already is what a camera sees (clients without the extension
    fall back to lit PBR). Atomic; `into`: write the bytes there instead (see write_obj_textured)."""
    import trimesh
    from PIL import Image

    material = trimesh.visual.material.PBRMaterial(
        name=MATERIAL,
        baseColorTexture=Image.fromarray(textured.image, "RGB"),
        metallicFactor=0.0,
        roughnessFactor=1.0,
        doubleSided=True,
    )
    visual = trimesh.visual.TextureVisuals(uv=textured.uv, material=material)
    mesh = trimesh.Trimesh(vertices=textured.vertices, faces=textured.faces, visual=visual, process=False)
    data = _mark_unlit(mesh.export(file_type="glb"))
    if into is not None:
        Path(into).write_bytes(data)
        return Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def _mark_unlit(glb: bytes) -> bytes:
    """Add KHR_materials_unlit to every material of a GLB (its JSON chunk rewritten, the binary chunk kept)."""
    magic, version, _ = struct.unpack_from("<4sII", glb, 0)
    json_len, json_type = struct.unpack_from("<I4s", glb, 12)
    if magic != b"glTF" or json_type != b"JSON":
        raise ValueError("trimesh wrote something other than a GLB")
    doc = json.loads(glb[20 : 20 + json_len])
    for mat in doc.get("materials", []):
        mat.setdefault("extensions", {})["KHR_materials_unlit"] = {}
    used = doc.setdefault("extensionsUsed", [])
    if "KHR_materials_unlit" not in used:
        used.append("KHR_materials_unlit")
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)  # chunks are 4-byte aligned, JSON padded with spaces
    rest = glb[20 + json_len :]
    total = 12 + 8 + len(text) + len(rest)
    return struct.pack("<4sII", magic, version, total) + struct.pack("<I4s", len(text), b"JSON") + text + rest
