"""Depth renders of whole cameras kept in the run folder, so that `eval` and `depth` render each test view once.

`eval` renders every test view in full (colour, depth, opacity) to score it; `depth` needs the same rays' depth and
opacity. `eval` puts what `depth` needs into `RUN_DIR/renders/KEY.npz` (float32 `depth`, `depth_median`, `acc`
[H, W], as `model.cameras.render_view` returns them), and `depth` takes them from there instead of rendering again;
`make`'s chain runs eval before depth for that. KEY is a hash of the checkpoint's sha256, the camera (its
intrinsics and world_from_cam, rounded to 1e-6) and the inference settings: a retrained run, another resolution,
another pose or `--exact` on one side only misses and is rendered. The folder is a cache: deleting it costs only
time. Colour is not kept (12 bytes a pixel that no other stage reads back: eval scores its own render).

A run folder that cannot be written (read-only, full) leaves the cache out: `put` returns False and the stage says
so in its manifest; nothing fails for it.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.errors import WriteFailed
from nerfpipe.radiance.camera import Intrinsics

__all__ = ["CACHE_DIR", "KEPT", "ViewCache", "open_view_cache"]

CACHE_DIR = "renders"
KEPT = ("depth", "depth_median", "acc")
"""The render outputs kept (float32 [H, W] each)."""


class ViewCache:
    """Renders of one run's checkpoint (`identity`: its sha256) in `folder`."""

    def __init__(self, folder: Path, identity: str):
        if not identity:
            raise ValueError("expected a checkpoint identity (its sha256), got an empty string")
        self.folder, self.identity = Path(folder), identity

    def key(self, intr: Intrinsics, world_from_cam: np.ndarray, infer: Any = None) -> str:
        cam = [intr.w, intr.h, intr.fx, intr.fy, intr.cx, intr.cy, intr.k1, intr.k2, intr.k3, intr.p1, intr.p2]
        pose = np.asarray(world_from_cam, dtype=np.float64).reshape(-1)[:12]
        doc = {"checkpoint": self.identity, "camera": [round(float(v), 6) for v in [*cam, *pose]], "infer": repr(infer)}
        return hashlib.sha256(json.dumps(doc).encode()).hexdigest()[:32]

    def get(self, intr: Intrinsics, world_from_cam: np.ndarray, infer: Any = None) -> dict[str, np.ndarray] | None:
        """The kept render of this camera at `infer` (`model.field_model.Inference`), or None (never stored,
        unreadable, or of another size)."""
        path = self.folder / f"{self.key(intr, world_from_cam, infer)}.npz"
        if not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as f:
                out = {k: np.asarray(f[k], dtype=np.float32) for k in KEPT}
        except (OSError, KeyError, ValueError):
            return None
        if any(v.shape != (intr.h, intr.w) for v in out.values()):
            return None
        return out

    def put(self, intr: Intrinsics, world_from_cam: np.ndarray, view: dict[str, np.ndarray], infer: Any = None) -> bool:
        """Keep `view`'s depth outputs for this camera rendered at `infer`; False when the folder cannot be
        written."""
        missing = [k for k in KEPT if k not in view]
        if missing:
            raise ValueError(f"expected a render with {', '.join(KEPT)}, missing {', '.join(missing)}")
        try:  # atomic_path makes the folder; a full disk or a read-only folder comes back as WriteFailed
            with atomic_path(self.folder / f"{self.key(intr, world_from_cam, infer)}.npz", suffix=".npz") as tmp:
                np.savez(tmp, **{k: np.asarray(view[k], dtype=np.float32) for k in KEPT})
        except (OSError, WriteFailed):
            return False
        return True


def open_view_cache(run_dir: Path) -> ViewCache | None:
    """The cache of a train run folder (its manifest's checkpoint_sha256), None for anything else (a splat file, a
    run without a finished manifest)."""
    manifest = Path(run_dir) / "manifest.json"
    if not manifest.is_file():
        return None
    try:
        sha = json.loads(manifest.read_text()).get("checkpoint_sha256")
    except (OSError, ValueError):
        return None
    return ViewCache(Path(run_dir) / CACHE_DIR, sha) if isinstance(sha, str) and sha else None
