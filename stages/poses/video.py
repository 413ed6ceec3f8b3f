"""Video -> about `target` sharp frames (imageio-ffmpeg, one decoding pass).

The video is cut into `target` equal windows of frames (frame count from the container's duration x fps,
or counted when unknown); in each window the frame with the largest variance of the Laplacian (on a grey
copy, long side `SHARPNESS_SIZE` px) is kept. Only the best frame so far is held in memory.
ffmpeg applies the rotation stored in the container, so frames come out upright.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import imageio_ffmpeg
import numpy as np

from nerfpipe.data.errors import UserError

__all__ = ["VIDEO_SUFFIXES", "VideoFrames", "extract_frames", "sharpness"]

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mts", ".wmv", ".mpg", ".mpeg")
SHARPNESS_SIZE = 640


@dataclass(frozen=True, kw_only=True)
class VideoFrames:
    names: tuple[str, ...]  # written frame files, in time order
    source_index: tuple[int, ...]  # index of each kept frame in the video
    sharpness: tuple[float, ...]  # its variance of the Laplacian
    total_frames: int  # frames decoded
    fps: float
    size: tuple[int, int]  # (width, height)


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of a grey copy of `rgb` [H, W, 3] uint8 (long side <= SHARPNESS_SIZE)."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    scale = SHARPNESS_SIZE / max(grey.shape)
    if scale < 1:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def _estimate_count(path: Path, meta: dict) -> int:
    fps, duration = meta.get("fps") or 0.0, meta.get("duration") or 0.0
    if fps > 0 and 0 < duration < math.inf:
        return max(1, int(round(fps * duration)))
    return max(1, imageio_ffmpeg.count_frames_and_secs(str(path))[0])


def extract_frames(path: Path, out_dir: Path, target: int) -> VideoFrames:
    """Write about `target` frames as `frame_00001.jpg`, ... into `out_dir` (UserError if undecodable)."""
    if target < 1:
        raise UserError(f"video_frames must be >= 1, got {target}")
    try:
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        estimate = _estimate_count(path, meta)
    except (OSError, RuntimeError, StopIteration) as e:
        first = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        raise UserError(f"could not decode video {path}: {first}") from None
    width, height = meta["size"]
    window = max(1.0, estimate / target)
    names: list[str] = []
    kept: list[int] = []
    scores: list[float] = []
    best: tuple[float, int, np.ndarray] | None = None
    current_window = 0
    count = 0

    def flush() -> None:
        score, index, frame = best
        name = f"frame_{len(names) + 1:05d}.jpg"
        ok = cv2.imwrite(str(out_dir / name), frame[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        if not ok:
            raise OSError(f"could not write {out_dir / name}")
        names.append(name)
        kept.append(index)
        scores.append(score)

    try:
        for index, raw in enumerate(reader):
            frame = np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 3)
            w = min(int(index / window), target - 1)  # a low estimate never adds frames
            if w != current_window and best is not None:
                flush()
                best = None
            current_window = w
            score = sharpness(frame)
            if best is None or score > best[0]:
                best = (score, index, frame.copy())
            count = index + 1
    except (OSError, RuntimeError) as e:
        if count == 0:
            raise UserError(f"could not decode video {path}: {str(e).strip().splitlines()[-1]}") from None
    finally:
        reader.close()
    if best is not None:
        flush()
    if count == 0:
        raise UserError(f"video {path} has no decodable frames; check the file plays and is not truncated")
    return VideoFrames(
        names=tuple(names),
        source_index=tuple(kept),
        sharpness=tuple(scores),
        total_frames=count,
        fps=float(meta.get("fps") or 0.0),
        size=(width, height),
    )
