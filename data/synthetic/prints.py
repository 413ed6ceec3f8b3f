"""Printed boxes: a flat label texture that repeats on several faces of a box, for objects whose faces look alike.

A product shot (a carton, a box of tea) shows the same print on two or four of its sides. Structure from motion
matches those faces to one another, and a reconstruction can fold onto itself and still reproject well (issue 53):
these subjects make such captures with exact poses.

Conventions (`objects`' module doc): metres, up +z, the box turned by `yaw` about z. A print is a function of
face-local coordinates (u, v) in metres, u to the right and v up as seen from outside the face, origin at the
face's centre, so the same print on two faces is the same picture; shading (`objects.shade`, lights fixed in the
world) still makes each face a little brighter or darker, as a real object's faces are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nerfpipe.data.synthetic.objects import Box, Material, _unit, _value_noise, material

__all__ = ["Label", "PrintedBox", "label_texture", "SUBJECTS", "subject_primitives"]

FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
"""Box faces in `PrintedBox.labels` order."""


@dataclass(frozen=True, kw_only=True)
class Label:
    """One print (deterministic from `key`): a coloured ground, blocks of colour, rows of 'text' and discs."""

    key: int
    ground: tuple[float, float, float]
    """Base colour of the print (RGB in [0, 1])."""


def _hash2(i: np.ndarray, j: np.ndarray, key: int) -> np.ndarray:
    """A uniform [0, 1) value per integer lattice point (i, j) [N] (`objects`' hash on (i, j, key))."""
    from nerfpipe.data.synthetic.objects import _hash

    return _unit(_hash(np.stack([i, j, np.full_like(i, 7)], axis=-1), key))


def label_texture(uv: np.ndarray, label: Label) -> np.ndarray:
    """Albedo [N, 3] in [0, 1] of a print at face-local points uv [N, 2] (metres).

    Layers: the ground colour with smooth value noise; coloured blocks on a 6 cm grid (about half of them);
    'text': rows 1.6 cm tall of dark marks of random width; a few discs (logos). Contrast at 1-10 cm, so SIFT
    finds features at working sizes of 300-1000 px where the box fills a fifth of the frame.
    """
    k = label.key
    u, v = uv[:, 0], uv[:, 1]
    q = np.column_stack([u, v, np.zeros_like(u)])
    colour = np.array(label.ground)[None, :] * (0.8 + 0.4 * _value_noise(q, 0.08, k + 1))[:, None]
    bi, bj = np.floor(u / 0.06), np.floor(v / 0.06)
    block = _hash2(bi, bj, k + 2) < 0.45
    block_colour = np.stack([_hash2(bi, bj, k + 3 + c) for c in range(3)], axis=-1)
    colour = np.where(block[:, None], 0.1 + 0.85 * block_colour, colour)
    row = np.floor(v / 0.016)
    text_row = (_hash2(row, row * 0, k + 7) < 0.5) & ((v / 0.016 - row) < 0.7)
    mark = np.floor(u / 0.011 + 3.7 * _hash2(row, row * 0, k + 8))
    dark = text_row & (_hash2(mark, row, k + 9) < 0.55)
    colour = np.where(dark[:, None], 0.08 * colour, colour)
    for d in range(4):
        cu = 0.3 * (_hash2(np.array([d]), np.array([0]), k + 20)[0] - 0.5)
        cv = 0.5 * (_hash2(np.array([d]), np.array([1]), k + 20)[0] - 0.5)
        r = 0.02 + 0.03 * _hash2(np.array([d]), np.array([2]), k + 20)[0]
        ring = np.hypot(u - cu, v - cv) < r
        tint = np.array([_hash2(np.array([d]), np.array([3 + c]), k + 21)[0] for c in range(3)])
        colour = np.where(ring[:, None], 0.05 + 0.9 * tint[None, :], colour)
    return np.clip(colour, 0.0, 1.0)


@dataclass(frozen=True, kw_only=True)
class PrintedBox(Box):
    """A box whose six faces carry prints: `labels[i]` on face FACES[i] (the same Label on several faces gives
    faces that look alike), instead of a solid texture."""

    labels: tuple[Label, ...]

    def albedo(self, p: np.ndarray) -> np.ndarray:
        local = self._local(p, False)  # [N, 3] box frame, origin at the centre
        scaled = local / self.half
        axis = np.argmax(np.abs(scaled), axis=-1)
        sign = np.sign(scaled[np.arange(len(p)), axis])
        face = 2 * axis + (sign < 0)  # index into FACES
        x, y, z = local[:, 0], local[:, 1], local[:, 2]
        # (u, v) as seen from outside each face: u to the right, v up (for the top and bottom, v along +-y)
        u = np.select([face == 0, face == 1, face == 2, face == 3, face == 4], [y, -y, -x, x, x], x)
        v = np.select([face <= 3, face == 4], [z, y], -y)
        out = np.zeros((len(p), 3))
        for f, label in enumerate(self.labels):
            m = face == f
            if m.any():
                out[m] = label_texture(np.column_stack([u[m], v[m]]), label)
        return out


SUBJECTS = ("objects", "carton", "cube")
"""`scene --subject`: the five textured objects on their slab (the default), or one printed box on nothing:
carton (a tall box: the same print on front and back, another on both sides, a third on top) or cube (the same
print on all four sides)."""


def subject_primitives(subject: str, seed: int) -> tuple[Box, ...]:
    """The printed box of `subject` ('carton' or 'cube'; the seed picks the prints' colours and marks), centred
    over the scene's look-at point, standing on z = -0.2 (no ground: a product shot on white)."""
    rng = np.random.default_rng([seed, 20261201])
    keys = [int(k) for k in rng.integers(0, 2**31, size=4)]
    grounds = [tuple(float(c) for c in 0.35 + 0.6 * rng.uniform(size=3)) for _ in range(4)]
    a, b, top, bottom = (Label(key=k, ground=g) for k, g in zip(keys, grounds, strict=True))
    texture: Material = material(rng, keys[0], 0.1, 0.03)  # unused by the prints; Box requires one
    if subject == "carton":
        half, labels = np.array([0.19, 0.19, 0.4]), (b, b, a, a, top, bottom)
    elif subject == "cube":
        half, labels = np.array([0.3, 0.3, 0.3]), (a, a, a, a, top, bottom)
    else:
        raise ValueError(f"expected subject 'carton' or 'cube', got {subject!r}")
    centre = np.array([0.0, 0.0, half[2] - 0.2])
    return (PrintedBox(center=centre, half=half, yaw=0.0, material=texture, labels=labels),)
