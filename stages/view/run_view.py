"""A trained run in viser: the field rendered live from each browser's camera, coarse while the camera moves
and refined when it stops, as rgb, depth or accumulation; the training cameras; the test views' PSNR.

Each connected browser gets a render thread. A camera update renders at once with `model.preview`'s coarse
setting at `preview` pixels on the long side; when the camera has not moved for `SETTLE_SECONDS`, the same view
is rendered again at the run's inference step and `refine` pixels. A frame is shown as the scene's background
image (JPEG). Depth is shown with turbo over the 1st-99th percentile of the frame's opaque z-depth; pixels with
accumulation < `model.OPAQUE` are black. While the browser draws the run's splats instead
(`stages.view.splat_view`), rendering is paused and the background image cleared.
"""

from __future__ import annotations

import csv
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

from nerfpipe.data.video import colorize, grey, to_uint8
from nerfpipe.model import OPAQUE
from nerfpipe.model.preview import render_preview
from nerfpipe.stages.view.cameras import browser_intrinsics, world_from_cam_gl

__all__ = ["MODES", "SETTLE_SECONDS", "frame_image", "render_camera", "psnr_summary", "LiveRender"]

MODES = ("rgb", "depth", "accumulation")
SETTLE_SECONDS = 0.25
"""The camera counts as stopped after this long without an update: then the refined frame is rendered."""


def frame_image(view: dict, mode: str) -> np.ndarray:
    """A rendered view (model.preview's dict) -> uint8 [H, W, 3] for `mode` (one of MODES)."""
    if mode == "rgb":
        return to_uint8(view["rgb"])
    if mode == "accumulation":
        return to_uint8(grey(view["acc"]))
    if mode != "depth":
        raise ValueError(f"expected a mode in {MODES}, got {mode!r}")
    valid = view["acc"] >= OPAQUE
    vals = view["depth"][valid]
    lo, hi = np.percentile(vals, [1, 99]) if vals.size else (0.0, 1.0)
    return to_uint8(colorize(view["depth"], float(lo), float(max(hi, lo + 1e-6)), valid=valid))


def render_camera(
    trained, wxyz, position, fov: float, aspect: float, long_side: int, *, coarse: bool, mode: str = "rgb"
) -> np.ndarray:
    """The render callback: a browser camera (viser's pose, vertical fov in radians, aspect w/h) -> uint8 image
    [H, W, 3] with `long_side` pixels on its long side."""
    intr = browser_intrinsics(fov, aspect, long_side)
    view = render_preview(trained, intr, world_from_cam_gl(wxyz, position), coarse=coarse)
    return frame_image(view, mode)


def psnr_summary(run_dir: Path) -> str:
    """Markdown with the run's held-out PSNR: eval.json (per view) when `nerfpipe eval` wrote one into the run,
    else the last test PSNR of training's metrics.csv."""
    ev = Path(run_dir) / "eval.json"
    if ev.is_file():
        doc = json.loads(ev.read_text())
        views = doc.get("views") or []
        lines = [f"**Test PSNR {doc.get('psnr', float('nan')):.2f} dB** over {len(views)} views (eval.json)"]
        lines += [f"- {v.get('name')}: {v.get('psnr', float('nan')):.2f} dB" for v in views[:12]]
        return "\n".join(lines)
    metrics = Path(run_dir) / "metrics.csv"
    if metrics.is_file():
        with metrics.open(newline="") as fh:
            rows = [r for r in csv.DictReader(fh) if r.get("test_psnr")]
        if rows:
            r = rows[-1]
            return f"**Test PSNR {float(r['test_psnr']):.2f} dB** at step {r['step']} ({float(r['seconds']):.0f} s)"
    return "No test PSNR in this run's files (run `nerfpipe eval RUN_DIR RUN_DIR/eval.json`)."


class LiveRender:
    """One render thread per browser; `mode` is read at each frame."""

    def __init__(self, server, trained, *, preview: int, refine: int) -> None:
        self.server, self.trained, self.preview, self.refine = server, trained, preview, refine
        self.mode = "rgb"
        self.paused = False
        """True while the browser draws the run's splats instead (`stages.view.splat_view`): no frame is rendered."""
        self.last_seconds = {"coarse": None, "refined": None}
        self._stop = threading.Event()
        self._events: dict[int, threading.Event] = {}
        server.on_client_connect(self._connect)
        server.on_client_disconnect(lambda client: self._events.pop(client.client_id, threading.Event()).set())

    def stop(self) -> None:
        self._stop.set()
        for ev in list(self._events.values()):
            ev.set()

    def set_paused(self, paused: bool) -> None:
        """Pause (clearing every browser's background image) or resume (rendering every browser's view again)."""
        self.paused = paused
        if paused:
            for client in self.server.get_clients().values():
                client.scene.set_background_image(None)
        else:
            self.refresh()

    def refresh(self) -> None:
        """Re-render every browser's view (after a mode change)."""
        for ev in list(self._events.values()):
            ev.set()

    def _connect(self, client) -> None:
        changed = threading.Event()
        self._events[client.client_id] = changed
        client.camera.on_update(lambda _cam: changed.set())
        threading.Thread(target=self._loop, args=(client, changed), daemon=True, name="view-render").start()
        changed.set()

    def _render(self, client, coarse: bool) -> None:
        try:
            self._render_once(client, coarse)
        except Exception as exc:  # noqa: BLE001 - a failed frame must not end the browser's render thread
            print(f"warning: view: a frame failed: {type(exc).__name__}: {exc}", file=sys.stderr)

    def _render_once(self, client, coarse: bool) -> None:
        cam = client.camera
        if self.paused or not cam.fov > 0 or not cam.aspect > 0:
            return
        t0 = time.perf_counter()
        img = render_camera(
            self.trained,
            cam.wxyz,
            cam.position,
            cam.fov,
            cam.aspect,
            self.preview if coarse else self.refine,
            coarse=coarse,
            mode=self.mode,
        )
        self.last_seconds["coarse" if coarse else "refined"] = time.perf_counter() - t0
        if self._stop.is_set() or self.paused or client.client_id not in self._events:
            return
        client.scene.set_background_image(img, format="jpeg", jpeg_quality=90)

    def _loop(self, client, changed: threading.Event) -> None:
        while not self._stop.is_set() and client.client_id in self._events:
            if not changed.wait(0.5):
                continue
            changed.clear()
            self._render(client, coarse=True)
            if changed.wait(SETTLE_SECONDS):  # moved again: next coarse frame
                continue
            if not self._stop.is_set() and client.client_id in self._events:
                self._render(client, coarse=False)
