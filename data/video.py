"""Images and videos on disk: 8/16-bit PNGs, H.264 mp4, and the colouring of depth / opacity maps.

- mp4: H.264 (libx264) through imageio-ffmpeg, yuv420p (what browsers play), `+faststart`; yuv420p needs even
  width and height, so odd sizes are padded by one row/column repeating the edge. Written to a temporary name
  in the same folder and renamed when the `video_writer` block ends: a stage that writes a manifest for the video
  writes it inside the block (after `VideoWriter.finish`), so the mp4, which `make` takes as done, appears only
  after it, and a failure anywhere (a full disk at the manifest, Ctrl-C, SIGTERM) leaves no mp4.
- `removed_on_failure`: the other files a stage writes beside it (PNG frames, the manifest) are deleted when the
  block fails, with the frames folder when the stage made it; `check_output` refuses an output path that is a
  folder where a file is wanted (or a file where a folder is) in one line, before any work.
- PNG: RGB uint8, grey uint8 or grey uint16 (written with OpenCV, which keeps 16 bits), atomically.
- Colour maps: depth -> matplotlib `turbo` over a fixed [lo, hi] (near = blue/dark end, far = red end),
  pixels marked invalid -> black; opacity -> grey.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.errors import UserError

__all__ = [
    "to_uint8",
    "pad_even",
    "write_png",
    "colorize",
    "grey",
    "depth_legend_png",
    "VideoWriter",
    "check_output",
    "removed_on_failure",
    "video_writer",
]


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] (any shape) -> uint8, rounded; NaN -> 0."""
    img = np.nan_to_num(np.asarray(img, dtype=np.float32), nan=0.0)
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def pad_even(img: np.ndarray) -> np.ndarray:
    """[H, W, C] -> [H', W', C] with H', W' even, repeating the last row/column when odd."""
    h, w = img.shape[:2]
    pad = ((0, h % 2), (0, w % 2)) + ((0, 0),) * (img.ndim - 2)
    return np.pad(img, pad, mode="edge") if h % 2 or w % 2 else img


def write_png(path: str | os.PathLike, img: np.ndarray) -> Path:
    """Write uint8 [H, W] / [H, W, 3] (RGB) / [H, W, 4] (RGBA) or uint16 [H, W] as PNG, atomically."""
    import cv2

    img = np.asarray(img)
    if img.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"expected uint8 or uint16 image, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    elif img.ndim != 2:
        raise ValueError(f"expected [H, W], [H, W, 3] or [H, W, 4], got {img.shape}")
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img)):
            raise OSError(f"{path}: could not write PNG")
    return path


def colorize(values: np.ndarray, lo: float, hi: float, valid: np.ndarray | None = None, cmap: str = "turbo"):
    """[H, W] values -> [H, W, 3] float32 RGB in [0, 1] via `cmap` over [lo, hi] (clipped); invalid -> black."""
    from matplotlib import colormaps

    values = np.asarray(values, dtype=np.float64)
    span = hi - lo if hi > lo else 1.0
    x = np.clip((np.nan_to_num(values, nan=lo) - lo) / span, 0.0, 1.0)
    rgb = colormaps[cmap](x)[..., :3].astype(np.float32)
    if valid is not None:
        rgb[~np.asarray(valid, dtype=bool)] = 0.0
    return rgb


def grey(values: np.ndarray) -> np.ndarray:
    """[H, W] in [0, 1] -> [H, W, 3] float32 grey."""
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float32)), 0.0, 1.0)
    return np.repeat(v[..., None], 3, axis=-1)


def depth_legend_png(
    path: str | os.PathLike, depth_rgb: np.ndarray, lo: float, hi: float, label: str, cmap: str = "turbo"
) -> Path:
    """Save a coloured depth image [H, W, 3] with a matplotlib colour bar labelled `label` over [lo, hi].

    Small images are shown enlarged (nearest neighbour) so the legend stays legible.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize

    h, w = depth_rgb.shape[:2]
    dpi = 100
    height_in = max(h / dpi, 3.0)
    width_in = height_in * w / h * 1.0 + 1.3
    fig = plt.figure(figsize=(width_in, height_in), dpi=dpi)
    try:
        ax = fig.add_axes((0.0, 0.0, (width_in - 1.3) / width_in, 1.0))
        ax.imshow(depth_rgb, interpolation="nearest")
        ax.set_axis_off()
        cax = fig.add_axes(((width_in - 1.15) / width_in, 0.08, 0.18 / width_in, 0.84))
        sm = plt.cm.ScalarMappable(norm=Normalize(vmin=lo, vmax=hi if hi > lo else lo + 1.0), cmap=cmap)
        fig.colorbar(sm, cax=cax, label=label)
        with atomic_path(path, suffix=".png") as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
    finally:
        plt.close(fig)
    return Path(path)


class VideoWriter:
    """Frames (uint8 [H, W, 3], all the same size) -> an H.264 mp4. Use `video_writer(...)` as a context."""

    def __init__(self, tmp_path: Path, fps: float, crf: int):
        self.tmp_path, self.fps, self.crf = tmp_path, fps, crf
        self.size: tuple[int, int] | None = None  # (h, w) of the first frame, before padding
        self.count = 0
        self._gen = None

    def write(self, frame: np.ndarray) -> None:
        import imageio_ffmpeg

        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            raise ValueError(f"expected uint8 [H, W, 3], got {frame.dtype} {frame.shape}")
        if self.size is None:
            self.size = frame.shape[:2]
            h, w = pad_even(frame).shape[:2]
            self._gen = imageio_ffmpeg.write_frames(
                str(self.tmp_path),
                (w, h),
                fps=self.fps,
                codec="libx264",
                pix_fmt_in="rgb24",
                pix_fmt_out="yuv420p",
                macro_block_size=1,
                quality=None,
                output_params=["-crf", str(self.crf), "-movflags", "+faststart"],
            )
            self._gen.send(None)  # start ffmpeg
        elif frame.shape[:2] != self.size:
            raise ValueError(f"frame {self.count}: size {frame.shape[:2]} differs from the first frame's {self.size}")
        self._gen.send(np.ascontiguousarray(pad_even(frame)))
        self.count += 1

    def close(self) -> None:
        if self._gen is not None:
            self._gen.close()
            self._gen = None

    def finish(self) -> None:
        """End the video (ffmpeg writes its index) and flush it to disk: it is complete, under its temporary name,
        and only its rename at the end of the `video_writer` block is left."""
        self.close()
        if self.count == 0:
            raise ValueError(f"{self.tmp_path}: no frames written")
        fd = os.open(self.tmp_path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def check_output(path: str | os.PathLike, what: str, *, folder: bool = False) -> None:
    """UserError when `path` cannot be written as a file (with `folder`: made as a folder): it exists as the other
    kind, or a file stands where one of the folders that hold it should be."""
    path = Path(path)
    if folder and path.exists() and not path.is_dir():
        raise UserError(f"{path} is a file; expected a folder for the {what}")
    if not folder and path.is_dir():
        raise UserError(f"{path} is a folder; expected a file name for the {what}")
    parent = next((p for p in path.parents if p.exists()), None)
    if parent is not None and not parent.is_dir():
        raise UserError(f"{parent} is a file; expected a folder to hold the {what} {path}")


@contextlib.contextmanager
def removed_on_failure(*folders: str | os.PathLike | None) -> Iterator[list[Path]]:
    """A list for the files the block writes: when the block fails (an error, KeyboardInterrupt, SIGTERM's
    `data.stop.Terminated`) they are deleted, then those of `folders` (None: none) and their parents that did not
    exist before the block, if empty."""
    made = {p for f in folders if f is not None for p in (Path(f), *Path(f).parents) if not p.exists()}
    written: list[Path] = []
    try:
        yield written
    except BaseException:
        for p in written:
            with contextlib.suppress(OSError):
                p.unlink(missing_ok=True)
        for p in sorted(made, key=lambda p: len(p.parts), reverse=True):  # deepest first; rmdir keeps a non-empty one
            with contextlib.suppress(OSError):
                p.rmdir()
        raise


@contextlib.contextmanager
def video_writer(path: str | os.PathLike, fps: float = 30.0, crf: int = 18) -> Iterator[VideoWriter]:
    """Context giving a `VideoWriter`; the mp4 appears at `path` only if the block completes with >= 1 frame, when
    the block ends (what the block writes after `VideoWriter.finish`, a manifest, comes before it)."""
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise UserError(f"{path}: expected an .mp4 output path")
    if not fps > 0:
        raise UserError(f"fps: expected > 0, got {fps}")
    with atomic_path(path, suffix=".mp4") as tmp:
        writer = VideoWriter(tmp, fps, crf)
        try:
            yield writer
        finally:
            writer.close()
        if writer.count == 0:
            raise ValueError(f"{path}: no frames written")
