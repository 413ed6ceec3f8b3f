"""The mesh's self-check (`OUT.report.json` `check`: ok | suspect, `checks`: `data.checks`): does the mesh show what
the field shows, and is it an object, or the box?

- `missed_surface` and `extra_surface` (`agreement_checks`): the mesh against the field from the training cameras
  (`stages.mesh.agreement`). `missed_surface`: the share of the training rays whose field surface lies in the
  meshed region where the mesh has none there (no face, or the nearest beyond it), at most `MAX_MISSED`: the
  objects the field renders but the mesh lacks (a level set by the brightest surface, pieces removed as small).
  `extra_surface`: the share of the rays hitting the mesh where it lies before the field's surface, or where the
  field shows none, at most `MAX_EXTRA`: fog, floaters or a fattened surface meshed.

Conventions: vertices [V, 3] and the scene's box `aabb` [2, 3] (min, max) in the scene (training) frame, where the
box is the region of interest `convert` chose (transforms.json `aabb`; not the occupancy crop, which hugs whatever
was meshed, nor a `--bbox`); faces [F, 3] int index the vertices.

- `box_fill`: the smallest, over the three axes, of the mesh's extent (its bounding box clipped to the scene's box)
  over the box's extent; at most `MAX_BOX_FILL`. A mesh that reaches across the box on every axis is what the box
  cuts out of the surroundings (a wall, the floor, fog), closed where it meets the box: a slab, not an object.
  That is the real capture's failure (a fox head on a papered wall: 637k faces, one component, the wall across the
  box with the fox as a blob in it); the synthetic scene's objects on their round slab fill 94 % x 94 % x 83 % of
  their box, and an object inside a looser box less.
- `large_components`: connected components holding at least `LARGE_COMPONENT` of the faces each, at most
  `MAX_LARGE_COMPONENTS`. Cleanup already drops small floaters; many sizeable pieces left mean a surface broken up
  (fog or floaters meshed, or an iso-level that cuts the surface apart).

Not checked: an empty mesh never gets here (`extract` refuses a field with no surface, or none left after
cleanup, as an error); watertightness is not required (a surface seen from one side is open).
"""

from __future__ import annotations

import numpy as np

from nerfpipe.data.checks import Check
from nerfpipe.stages.mesh.agreement import Agreement
from nerfpipe.stages.mesh.cleanup import vertex_components

__all__ = [
    "MAX_BOX_FILL",
    "MAX_LARGE_COMPONENTS",
    "LARGE_COMPONENT",
    "MAX_MISSED",
    "MAX_EXTRA",
    "box_fill",
    "component_faces",
    "mesh_checks",
    "agreement_checks",
]

MAX_MISSED = 0.03
"""At most this share of the field's surface (seen by the training rays, in the meshed region) missing in the mesh:
one of the demo's five objects is 3-8 % of the surface its training views see."""
MAX_EXTRA = 0.2
"""At most this share of the mesh (seen by the training rays) before the field's surface or where it shows none."""

MAX_BOX_FILL = 0.95
"""A mesh may span at most this share of the scene's box on at least one axis."""
LARGE_COMPONENT = 0.01
"""A connected component with at least this share of the mesh's faces counts as large."""
MAX_LARGE_COMPONENTS = 10
"""At most this many large components."""


def box_fill(verts: np.ndarray, aabb: np.ndarray) -> np.ndarray:
    """Per axis [3]: the extent of the vertices' bounding box, clipped to `aabb`, over the extent of `aabb`."""
    box = np.asarray(aabb, np.float64).reshape(2, 3)
    if len(verts) == 0:
        return np.zeros(3)
    lo = np.maximum(np.min(verts, axis=0), box[0])
    hi = np.minimum(np.max(verts, axis=0), box[1])
    return np.clip(hi - lo, 0.0, None) / (box[1] - box[0])


def component_faces(faces: np.ndarray) -> np.ndarray:
    """Faces per connected component (vertices joined by faces) [C], largest first."""
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return np.zeros(0, np.int64)
    _, labels = vertex_components(faces, int(faces.max()) + 1)
    counts = np.bincount(labels[faces[:, 0]])
    return np.sort(counts[counts > 0])[::-1]


def mesh_checks(verts: np.ndarray, faces: np.ndarray, aabb: np.ndarray) -> list[Check]:
    """The two checks of the module doc, for a mesh in the scene frame and the scene's box."""
    fill = box_fill(verts, aabb)
    counts = component_faces(faces)
    large = int((counts >= LARGE_COMPONENT * max(len(faces), 1)).sum())
    fills = " x ".join(f"{f:.0%}" for f in fill)
    return [
        Check.upper(
            "box_fill",
            float(fill.min()),
            MAX_BOX_FILL,
            f"the mesh spans the scene's box on every axis ({fills}): it is the surroundings the box cuts out (a "
            "wall, the floor, fog), not an object; mesh a --bbox round the object (or raise --threshold if it is fog)",
        ),
        Check.upper(
            "large_components",
            large,
            MAX_LARGE_COMPONENTS,
            f"the surface breaks into {large} sizeable pieces (each >= {LARGE_COMPONENT:.0%} of the faces): fog or "
            "floaters meshed, or an iso-level that cuts the surface apart; try --threshold or a longer training",
        ),
    ]


def agreement_checks(agreement: Agreement) -> list[Check]:
    """`missed_surface` and `extra_surface` (module doc)."""
    return [
        Check.upper(
            "missed_surface",
            round(agreement.missed_share, 4),
            MAX_MISSED,
            f"the mesh lacks {agreement.missed_share:.0%} of the surface the field shows to the training cameras "
            "(objects missing: a level above their density, or pieces removed as small); try --threshold auto, a "
            "lower --threshold or --no-cleanup",
        ),
        Check.upper(
            "extra_surface",
            round(agreement.extra_share, 4),
            MAX_EXTRA,
            f"{agreement.extra_share:.0%} of the mesh the training cameras see lies before the field's surface or "
            "where the field shows none: fog, floaters or a fattened surface meshed; try a higher --threshold",
        ),
    ]
