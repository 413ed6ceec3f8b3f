"""Meshes with their colours to files: textured, OBJ + MTL + PNG (`write_obj_textured`) and one GLB with the PNG
embedded (`write_glb_textured`), from a `stages.mesh.texture.Textured` (its UV and image conventions); vertex-coloured,
a GLB with the colours in linear light (`glb_vertex_coloured`). Every GLB material is unlit."""

from __future__ import annotations

import contextlib
import io
import json
import struct
from pathlib import Path

import numpy as np

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.images import srgb_to_linear
from nerfpipe.stages.mesh.texture import Textured

__all__ = ["write_obj_textured", "write_glb_textured", "glb_vertex_coloured", "texture_paths", "MATERIAL"]

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
    doc, binary = _glb_chunks(glb)
    return _glb_bytes(_unlit(doc), binary)


def _unlit(doc: dict) -> dict:
    """A glTF document with KHR_materials_unlit on every material (in place; returned)."""
    for mat in doc.get("materials", []):
        mat.setdefault("extensions", {})["KHR_materials_unlit"] = {}
    used = doc.setdefault("extensionsUsed", [])
    if "KHR_materials_unlit" not in used:
        used.append("KHR_materials_unlit")
    return doc


def glb_vertex_coloured(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray) -> bytes:
    """A GLB of a mesh with vertex colours as glTF means them: COLOR_0 in linear light (float32 RGB; the colours
    [V, 3+] are sRGB bytes, as trimesh and PLY hold them) and an unlit white material, so that a client draws the
    colours as the photos show them, with or without lights (with trimesh's bytes as COLOR_0 and no material, a
    default three.js scene drew them black; read as linear they would come out washed out). trimesh reads the
    colours back as `visual.vertex_attributes["color"]` (a mesh with a material)."""
    import trimesh

    if colours.ndim != 2 or colours.shape[0] != len(vertices) or colours.shape[1] not in (3, 4):
        raise ValueError(f"expected colours [V, 3 or 4] for {len(vertices)} vertices, got {colours.shape}")
    doc, binary = _glb_chunks(trimesh.Trimesh(vertices=vertices, faces=faces, process=False).export(file_type="glb"))
    linear = srgb_to_linear(np.asarray(colours[:, :3], np.float64) / 255.0)  # [V, 3] float32
    binary += b"\0" * (-len(binary) % 4)
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": linear.nbytes, "target": 34962})
    doc["accessors"].append(
        {"bufferView": len(doc["bufferViews"]) - 1, "componentType": 5126, "count": len(linear), "type": "VEC3"}
    )
    binary += linear.tobytes()
    doc["buffers"][0]["byteLength"] = len(binary)
    pbr = {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0}
    doc["materials"] = [{"name": MATERIAL, "pbrMetallicRoughness": pbr, "doubleSided": True}]
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            prim["attributes"]["COLOR_0"] = len(doc["accessors"]) - 1
            prim["material"] = 0
    return _glb_bytes(_unlit(doc), binary)


def _glb_chunks(glb: bytes) -> tuple[dict, bytes]:
    """A GLB -> (its JSON document, its binary chunk's bytes)."""
    magic, version, _ = struct.unpack_from("<4sII", glb, 0)
    json_len, json_type = struct.unpack_from("<I4s", glb, 12)
    if magic != b"glTF" or version != 2 or json_type != b"JSON":
        raise ValueError("trimesh wrote something other than a GLB 2.0")
    doc = json.loads(glb[20 : 20 + json_len])
    rest = glb[20 + json_len :]
    if not rest:
        return doc, b""
    bin_len, bin_type = struct.unpack_from("<I4s", rest, 0)
    if bin_type != b"BIN\0":
        raise ValueError("expected a GLB's second chunk to be BIN")
    return doc, rest[8 : 8 + bin_len]


def _glb_bytes(doc: dict, binary: bytes) -> bytes:
    """A JSON document and a binary chunk -> GLB 2.0 bytes (chunks 4-byte aligned: JSON padded with spaces, BIN
    with zeros)."""
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text
    if binary:
        binary += b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks
