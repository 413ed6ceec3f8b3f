"""Scene spaces (radiance.space): serialisation, the maps in and out, and what a run folder keeps of them."""

import json
import shutil

import numpy as np
import pytest
import torch

from nerfpipe.model.checkpoint import restore_space
from nerfpipe.radiance.contraction import Contraction
from nerfpipe.radiance.ndc import NDC
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.space import SPACES, Box, Contracted, NDCSpace, space_from_dict

BOX = ((-1.0, -1.0, -0.5), (1.0, 1.0, 0.5))


def _ndc_space() -> NDCSpace:
    pose = np.eye(4)
    pose[:3, 3] = (0.0, 0.0, 3.0)
    return NDCSpace(ndc=NDC(world_from_ref=pose, a=-2.0, b=-2.0, near=0.5), box=((-1.2, -1.1, -1.0), (1.2, 1.1, 1.0)))


def _spaces():
    return [Box(aabb=BOX, near=0.1, far=7.0), _ndc_space(), Contracted(contraction=Contraction(BOX), near=0.2)]


@pytest.mark.parametrize("space", _spaces(), ids=lambda s: s.name)
def test_round_trip_through_json(space):
    doc = json.loads(json.dumps(space.to_dict()))
    back = space_from_dict(doc)
    assert type(back) is type(space) and back.to_dict() == space.to_dict()
    assert (back.near, back.far) == (space.near, space.far)
    torch.testing.assert_close(back.field_box, space.field_box)
    assert SPACES[space.name] is type(space)


def test_unknown_or_broken_spaces_are_refused():
    with pytest.raises(ValueError, match="expected a scene space of kind box, ndc, contract"):
        space_from_dict({"kind": "sphere"})
    with pytest.raises(ValueError, match="expected a box"):
        space_from_dict({"kind": "box", "aabb": [[0, 0], [1, 1]], "near": 0, "far": 1})


def test_checkpoints_from_before_the_space_read_as_trained():
    """Checkpoints that stored `ndc` / `contraction` alone (box and bounds from the scene) restore the same space."""
    made = []

    def from_scene(kind):
        made.append(kind)
        return {Box: _spaces()[0], NDCSpace: _ndc_space(), Contracted: _spaces()[2]}[kind]

    ndc = _ndc_space()
    old_ndc = restore_space({"ndc": ndc.ndc.to_dict(), "contraction": None}, from_scene)
    assert isinstance(old_ndc, NDCSpace) and old_ndc.to_dict() == ndc.to_dict()
    old_con = restore_space({"ndc": None, "contraction": Contraction(BOX).to_dict()}, from_scene)
    assert isinstance(old_con, Contracted) and old_con.near == 0.2
    assert isinstance(restore_space({}, from_scene), Box)
    new = restore_space({"space": ndc.to_dict()}, lambda kind: pytest.fail("a space in the checkpoint needs no scene"))
    assert new.to_dict() == ndc.to_dict() and made == [NDCSpace, Contracted, Box]


@pytest.mark.parametrize("space", _spaces(), ids=lambda s: s.name)
def test_march_points_lie_in_the_field_box_and_steps_agree(space):
    """The training march (jitter 0) and the inference steps give the same first step on every ray, and every
    sample's field point lies in the field's box."""
    g = torch.Generator().manual_seed(0)
    o = torch.tensor([0.0, 0.0, 3.0]).expand(64, 3) + 0.05 * torch.randn(64, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    grid = OccupancyGrid(space.field_box, 8)  # every cell occupied before its first update
    o_m, d_m, valid = space.to_march(o, d)
    keep = torch.ones(64, dtype=torch.bool) if valid is None else valid
    o_m, d_m = o_m[keep], d_m[keep]
    packed = space.march(grid, o_m, d_m, 0.05, None)
    box = space.field_box
    assert packed.points.numel() > 0
    assert bool(((packed.points >= box[0] - 1e-5) & (packed.points <= box[1] + 1e-5)).all())
    steps = space.steps(grid, o_m, d_m, 0.05)
    first = steps.u0 + (steps.k_first if steps.k_first is not None else 0) * steps.step
    t_first = steps.warp(first[:, None], torch.arange(o_m.shape[0]))[:, 0]
    rows = torch.unique(packed.ray_indices)
    starts = torch.full((o_m.shape[0],), float("inf")).scatter_reduce(0, packed.ray_indices, packed.t_starts, "amin")
    torch.testing.assert_close(starts[rows], t_first[rows], atol=1e-4, rtol=0)


def test_density_query_maps_scene_points():
    x = torch.tensor([[0.5, 0.0, 0.0], [5.0, 0.0, 0.0]])
    p, scale = Box(aabb=BOX, near=0.0, far=1.0).density_query(x)
    assert torch.equal(p, x) and scale is None
    c = Contracted(contraction=Contraction(BOX), near=0.0)
    p, scale = c.density_query(x)
    assert float(p[1].abs().max()) < 2.0 and float(p[0, 0]) == 0.5 and scale is not None and float(scale[0]) == 2.0
    ndc = _ndc_space()
    p, scale = ndc.density_query(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 2.9]]))  # in front / behind the near plane
    assert float(scale[0]) > 0 and float(scale[1]) == 0.0


def test_a_run_moved_with_its_scene_still_loads(tmp_path, monkeypatch):
    """config.json records the scene relative to the run: OUT/run and OUT/scene moved together load from anywhere."""
    from nerfpipe.model.run import load_trained
    from nerfpipe.stages import scene as scene_stage
    from nerfpipe.stages import train

    out = tmp_path / "out"
    scene_stage.run(scene_stage.Config(out_dir=out / "scene", kind="rgba", size=24, views=6, seed=0))
    monkeypatch.chdir(tmp_path)  # a relative scene_dir, as a user types it
    train.run(train.Config(scene_dir="out/scene", run_dir="out/run", max_steps=5, max_seconds=60.0, eval_every=0))
    doc = json.loads((out / "run" / "config.json").read_text())
    assert doc["scene_from_run"] == "../scene"
    shutil.move(str(out), str(tmp_path / "moved"))
    monkeypatch.chdir(tmp_path / "moved" / "run")
    trained = load_trained(tmp_path / "moved" / "run", "cpu")
    assert trained.scene.root.resolve() == (tmp_path / "moved" / "scene").resolve()
    assert trained.space.name == "box"
