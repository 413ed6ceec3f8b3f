"""The evidence of train's fog check (stages.train.fog): the field's occupied share of the cells its cameras see.

One camera above a box looks straight down; the field is either a solid floor filling the box's lower half (what a
disk seen from above trains: its underside never seen) or a fog filling the whole box. The floor's share counts
only the cells above it (and the layers within a cell diagonal under its surface), whatever the hidden half
holds; the fog's front is all the camera sees, and all of it is occupied.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfpipe.radiance.camera import Intrinsics, generate_rays
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.stages.train.fog import ViewDepth, seen_cells, seen_occupied_share

G = 16
HEIGHT = 3.0  # the camera's height over z = 0; the box is [-1, 1]^3


def _view(surface_z: float) -> ViewDepth:
    """The camera at (0, 0, HEIGHT) looking down -z (OpenGL), seeing the whole box; every ray stops at z =
    surface_z."""
    intr = Intrinsics(w=64, h=64, fx=12.0, fy=12.0, cx=32.0, cy=32.0)
    c2w = np.eye(4)
    c2w[2, 3] = HEIGHT
    _, d = generate_rays(intr, torch.as_tensor(c2w))
    depth = ((HEIGHT - surface_z) / -d[:, 2]).reshape(64, 64).numpy()
    return ViewDepth(intr=intr, world_from_cam=c2w, depth=depth, acc=np.ones((64, 64)))


def _grid() -> OccupancyGrid:
    return OccupancyGrid([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], G, threshold=0.5)


def test_a_floor_seen_from_above_counts_only_the_space_above_it():
    floor = _view(0.0)
    share = seen_occupied_share(_grid(), lambda x: 100.0 * (x[:, 2] < 0).float(), [floor])
    # seen: the 8 layers above z = 0 and the 2 under it whose centres lie within a cell diagonal (0.22) of the
    # surface; occupied: those 2
    assert share == pytest.approx(2 / 10, abs=1e-6)
    # what the hidden half holds changes nothing: a floor a quarter thick, empty under it, scores the same
    thin = seen_occupied_share(_grid(), lambda x: 100.0 * ((x[:, 2] < 0) & (x[:, 2] > -0.25)).float(), [floor])
    assert thin == pytest.approx(share, abs=1e-9)


def test_a_fog_filling_the_box_is_all_the_camera_sees():
    front = _view(1.0)  # the fog's front: the rays stop at the box's top
    assert seen_occupied_share(_grid(), lambda x: torch.full(x.shape[:1], 100.0), [front]) == 1.0


def test_cells_behind_the_surface_are_not_seen_and_see_through_rays_see_everything():
    g = _grid()
    idx = torch.arange(G, dtype=torch.float64)
    ijk = torch.stack(torch.meshgrid(idx, idx, idx, indexing="ij"), dim=-1).reshape(-1, 3)
    centres = -1.0 + (ijk + 0.5) * 2.0 / G
    tol = math.sqrt(3) * 2.0 / G
    seen = seen_cells(centres, [_view(0.0)], tol)
    z = centres[:, 2]
    assert bool(seen[z > 0].all()) and not bool(seen[z < -tol].any())
    clear = _view(0.0)
    clear = ViewDepth(intr=clear.intr, world_from_cam=clear.world_from_cam, depth=clear.depth, acc=clear.acc * 0.2)
    assert bool(seen_cells(centres, [clear], tol).all())
    assert seen_occupied_share(g, lambda x: torch.zeros(x.shape[:1]), []) is None


def test_refusals():
    with pytest.raises(ValueError, match=r"expected depth and acc \(64, 64\)"):
        ViewDepth(intr=_view(0.0).intr, world_from_cam=np.eye(4), depth=np.zeros((8, 8)), acc=np.zeros((64, 64)))
    with pytest.raises(ValueError, match=r"expected centres \[M, 3\]"):
        seen_cells(torch.zeros(4, 2), [], 0.1)
