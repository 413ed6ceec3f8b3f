"""`data.export_frame`: the frame exports are written in (upright per format, the user's, the scene's)."""

from __future__ import annotations

import numpy as np
import pytest

from nerfpipe.data.export_frame import FORMAT_UP, export_frame, rotation_onto


def _source_from_scene(seed: int = 0) -> np.ndarray:
    """A similarity scene -> source: a random rotation, scale 4, a translation (as convert's inverse)."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    m = np.eye(4)
    m[:3, :3] = 4.0 * q
    m[:3, 3] = rng.normal(size=3) * 10
    return m


WANT_UP = {"gltf": [0, 1, 0], "obj": [0, 1, 0], "ply": [0, 0, 1], "points": [0, 0, 1], "splat": [0, -1, 0]}


@pytest.mark.parametrize("fmt", sorted(FORMAT_UP))
def test_upright_puts_the_scenes_up_on_the_formats_up_axis(fmt):
    m = _source_from_scene()
    out_from_scene, info = export_frame(m, "upright", fmt)
    up = out_from_scene[:3, :3] @ np.array([0.0, 0.0, 1.0])
    assert np.allclose(up / np.linalg.norm(up), WANT_UP[fmt], atol=1e-12), (fmt, up)
    out_from_source = np.asarray(info["out_from_source"])
    r = out_from_source[:3, :3]
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(r), 1.0)  # a turn, no scale
    assert np.allclose(out_from_source @ m, out_from_scene)
    assert np.allclose(out_from_scene[:3, 3], 0)  # the scene's centre is the file's origin (viewers orbit it)
    assert info["frame"] == "upright" and info["up"]["format_up"] == FORMAT_UP[fmt][0]
    # lengths are the user's: the scene's unit is 4 user units
    assert np.isclose(np.linalg.norm(out_from_scene[:3, 0]), 4.0)


def test_a_source_already_z_up_is_only_turned_to_the_formats_axes():
    m = np.diag([2.0, 2.0, 2.0, 1.0])  # the scene frame's axes are the source's (convert's "keep")
    out_from_scene, info = export_frame(m, "upright", "gltf")
    assert np.allclose(np.asarray(info["out_from_source"])[:3, :3], [[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    assert np.allclose(export_frame(m, "upright", "ply")[0], m)  # PLY is z-up: nothing to turn


def test_a_given_up_in_the_users_frame_wins():
    m = _source_from_scene(1)
    given = (0.3, -0.2, 0.9)
    _, info = export_frame(m, "upright", "gltf", up=given)
    r = np.asarray(info["out_from_source"])[:3, :3]
    assert np.allclose(r @ (np.array(given) / np.linalg.norm(given)), [0, 1, 0], atol=1e-12)
    assert info["up"]["rule"] == "given (up)"


def test_user_and_normalized_keep_their_frames():
    m = _source_from_scene(2)
    user, info = export_frame(m, "user", "gltf")
    assert np.allclose(user, m) and np.allclose(info["out_from_source"], np.eye(4))
    norm, info = export_frame(m, "normalized", "splat")
    assert np.allclose(norm, np.eye(4)) and np.allclose(np.asarray(info["out_from_source"]) @ m, np.eye(4))
    with pytest.raises(ValueError, match="frame"):
        export_frame(m, "sideways", "gltf")
    with pytest.raises(ValueError, match="format"):
        export_frame(m, "upright", "stl")


def test_rotation_onto_is_the_smallest_turn_and_handles_opposites():
    rng = np.random.default_rng(3)
    for _ in range(20):
        u, v = rng.normal(size=3), rng.normal(size=3)
        r = rotation_onto(u, v)
        assert np.allclose(r @ (u / np.linalg.norm(u)), v / np.linalg.norm(v), atol=1e-12)
        axis = np.cross(u, v)  # the smallest turn is about u x v: it keeps that axis
        assert np.allclose(r @ axis, axis, atol=1e-9)
    for u in ([0.0, 0.0, 1.0], [1.0, 2.0, 3.0]):
        r = rotation_onto(np.array(u), -np.array(u))
        assert np.allclose(r @ np.array(u), -np.array(u), atol=1e-12) and np.isclose(np.linalg.det(r), 1.0)


def test_frame_options_are_refused_in_one_line_naming_the_option():
    from nerfpipe.data.errors import UserError
    from nerfpipe.data.export_frame import check_frame_options

    check_frame_options("upright", (0.0, 0.0, 1.0))
    check_frame_options("user", None)
    for frame, up, flag, says in (
        ("sideways", None, "--", "--frame: expected one of upright, user, normalized"),
        ("upright", (0.0, 0.0, 0.0), "", "up: expected three numbers x,y,z, not all 0"),
        ("upright", (0.0, float("nan"), 1.0), "--", "--up: expected three numbers"),
        ("upright", (1.0, 2.0), "", "up: expected three numbers"),
    ):
        with pytest.raises(UserError, match=says.replace(".", r"\.")) as err:
            check_frame_options(frame, up, flag=flag)
        assert "\n" not in str(err.value)
