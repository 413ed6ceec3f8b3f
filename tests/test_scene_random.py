"""The random scene generator (`data.synthetic.random_scene`, `scene --subject random`): layouts that vary with
the seed, objects that never meet, view-consistent photo textures, lights that leave the fixed scenes unchanged."""

from __future__ import annotations

import json
import socket

import numpy as np
import pytest

from nerfpipe import cli
from nerfpipe.data.errors import UserError
from nerfpipe.data.synthetic.objects import DEFAULT_LIGHTS, Box, Cylinder, Lights, Sphere, default_primitives, shade
from nerfpipe.data.synthetic.photo import GREYS, PHOTOS, PhotoTexture, PhotoTextured, photo
from nerfpipe.data.synthetic.random_scene import (
    SIZE,
    SLAB_RADIUS,
    TOP,
    random_lights,
    random_primitives,
    random_scene,
)
from nerfpipe.data.synthetic.raycast import render_view
from nerfpipe.data.transforms import read_scene
from nerfpipe.stages import scene


def _geometry(prim) -> tuple[float, float, float, float]:
    """A drawn object's largest extent, farthest reach from the z axis, bottom and top (metres), from its shape."""
    shape = prim.shape if isinstance(prim, PhotoTextured) else prim
    if isinstance(shape, Sphere):
        c, r = shape.center, shape.radius
        return 2 * r, float(np.hypot(*c[:2])) + r, c[2] - r, c[2] + r
    if isinstance(shape, Box):
        corners = np.array([[sx, sy] for sx in (-1, 1) for sy in (-1, 1)]) * shape.half[:2]
        yaw = np.array([[np.cos(shape.yaw), -np.sin(shape.yaw)], [np.sin(shape.yaw), np.cos(shape.yaw)]])
        reach = np.linalg.norm(corners @ yaw.T + shape.center[:2], axis=-1).max()
        return 2 * float(shape.half.max()), reach, shape.center[2] - shape.half[2], shape.center[2] + shape.half[2]
    assert isinstance(shape, Cylinder)
    reach = float(np.hypot(*shape.center)) + shape.radius
    return max(2 * shape.radius, shape.z1 - shape.z0), reach, shape.z0, shape.z1


def test_layouts_vary_with_the_seed():
    drawn = [random_scene(s) for s in range(50)]
    counts = {len(d.objects) for d in drawn}
    assert len(counts) >= 5 and min(counts) >= 1 and max(counts) <= 8, counts
    layouts = {tuple((o.shape, *np.round(o.primitive.bounding_sphere()[0], 6)) for o in d.objects) for d in drawn}
    assert len(layouts) == 50  # no two seeds draw the same layout
    assert {o.shape for d in drawn for o in d.objects} == {"sphere", "box", "cylinder"}
    kinds = {o.texture.split(":")[0] for d in drawn for o in d.objects}
    assert kinds == {"noise", "photo"}
    assert {d.surround for d in drawn} == {"none", "wall", "room"}
    assert len({d.ground_texture for d in drawn}) >= 4
    assert len({len(d.lights.intensities) for d in drawn}) == 3  # 1, 2 and 3 lights
    assert len(random_primitives(0)) == 1 + len(drawn[0].objects) + len(drawn[0].surroundings())


def test_objects_never_meet_and_stay_on_the_slab():
    for seed in range(300):
        d = random_scene(seed)
        spheres = [o.primitive.bounding_sphere() for o in d.objects]
        for i, (ci, ri) in enumerate(spheres):
            for cj, rj in spheres[:i]:
                assert np.linalg.norm(ci - cj) > ri + rj, (seed, i)
        for o in d.objects:
            extent, reach, bottom, top = _geometry(o.primitive)
            assert SIZE[0] <= o.size <= SIZE[1] and extent == pytest.approx(o.size)
            assert reach <= SLAB_RADIUS and top <= TOP + 1e-9, (seed, o.shape, reach, top)
            assert bottom >= 0.05 if o.floating else bottom == pytest.approx(-0.01, abs=1e-9)


def test_same_seed_same_bytes_other_seed_other_images(tmp_path):
    def make(name, seed):
        out = scene.run(scene.Config(out_dir=tmp_path / name, subject="random", size=16, views=2, seed=seed))
        return [p.read_bytes() for p in (*out.images, *out.depths, out.mesh)]

    a, again, other = make("a", 4), make("b", 4), make("c", 5)
    assert a == again
    assert all(x != y for x, y in zip(a[:2], other[:2], strict=True))


def _texture(name: str) -> PhotoTexture:
    rot = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    return PhotoTexture(name=name, tint=np.ones(3), rotation=rot, origin=np.array([0.1, -0.2, 0.3]), scale=0.3)


def test_photo_texture_is_solid_every_view_sees_one_colour():
    ball = PhotoTextured(
        shape=Sphere(center=np.array([0.0, 0.0, 0.3]), radius=0.3, material=default_primitives(0)[1].material),
        photo=_texture("astronaut"),
    )
    rng = np.random.default_rng(0)
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    target = ball.shape.center + ball.shape.radius * n  # [N, 3] surface points
    seen = []
    for eye in (np.array([2.0, 0.0, 1.0]), np.array([-1.0, 2.0, 0.5])):  # two cameras
        d = target - eye
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(eye, d.shape).copy()
        t = ball.intersect(o, d)
        hit = o + t[:, None] * d
        front = np.linalg.norm(hit - target, axis=-1) < 1e-9  # the point is the first hit from this camera
        seen.append((front, ball.albedo(hit)))
    both = seen[0][0] & seen[1][0]
    assert both.sum() > 50
    np.testing.assert_allclose(seen[0][1][both], seen[1][1][both], atol=1e-9)
    albedo = ball.albedo(target)
    assert albedo.std(0).min() > 0.05  # a picture, not a flat colour
    other = PhotoTextured(shape=ball.shape, photo=_texture("coffee")).albedo(target)
    assert np.abs(other - albedo).mean() > 0.05  # and which picture matters


def test_photos_ship_with_scikit_image(monkeypatch):
    def refuse(*_a, **_k):
        raise OSError("network is off in this test")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    photo.cache_clear()
    for name in PHOTOS + GREYS:
        img = photo(name)
        assert img.ndim == 3 and img.shape[2] == 3 and min(img.shape[:2]) >= 256, (name, img.shape)
        assert 0.0 <= img.min() and img.max() <= 1.0 and img.std() > 0.05, name
    with pytest.raises(ValueError, match="expected a photo"):
        photo("retina")


def _old_shade(albedo, n):
    """`objects.shade` before lights were a parameter (copied as it was)."""
    lights = (
        (np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84]), 0.62),
        (np.array([-0.6, -0.5, 0.62]) / np.linalg.norm([-0.6, -0.5, 0.62]), 0.25),
    )
    light = np.full(len(n), 0.3)
    for direction, intensity in lights:
        light += intensity * np.clip(
            n[:, 0] * direction[0] + n[:, 1] * direction[1] + n[:, 2] * direction[2], 0.0, None
        )
    return np.clip(albedo * light[:, None], 0.0, 1.0)


def test_default_lights_shade_exactly_as_before_and_random_lights_differ():
    rng = np.random.default_rng(3)
    albedo = rng.uniform(size=(10_000, 3))
    n = rng.normal(size=(10_000, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    old = _old_shade(albedo, n)
    np.testing.assert_array_equal(shade(albedo, n), old)
    np.testing.assert_array_equal(shade(albedo, n, DEFAULT_LIGHTS), old)
    for seed in range(5):
        assert np.abs(shade(albedo, n, random_lights(seed)) - old).mean() > 0.01
    intr = scene.intrinsics(16)
    w = scene.cameras(1, 0)[0]
    default = render_view(default_primitives(0), intr, w)
    np.testing.assert_array_equal(render_view(default_primitives(0), intr, w, DEFAULT_LIGHTS)[0], default[0])


def test_lights_say_what_they_expected():
    with pytest.raises(ValueError, match=r"expected directions \[L, 3\]"):
        Lights(directions=np.zeros((2, 2)), intensities=np.ones(2), ambient=0.3)
    with pytest.raises(ValueError, match="expected unit light directions"):
        Lights(directions=np.ones((1, 3)), intensities=np.ones(1), ambient=0.3)


def _seed_with(surround: str) -> int:
    return next(s for s in range(100) if random_scene(s).surround == surround)


@pytest.mark.parametrize(
    ("layout", "kind", "surround"),
    [
        ("orbit", "posed", "room"),
        ("orbit", "rgba", "none"),
        ("orbit", "rgba", "room"),
        ("forward", "posed", "none"),
        ("forward", "rgba", "wall"),
    ],
)
def test_random_subject_through_the_stage(tmp_path, layout, kind, surround):
    seed = _seed_with(surround)
    out = scene.run(
        scene.Config(out_dir=tmp_path / "s", subject="random", layout=layout, kind=kind, size=24, views=3, seed=seed)
    )
    assert len(out.images) == 3 and len(out.depths) == 3
    drawn = random_scene(seed)
    used = json.loads(out.manifest.read_text())["used"]["random_subject"]
    assert used["count"] == len(drawn.objects) and [o["shape"] for o in used["objects"]] == [
        o.shape for o in drawn.objects
    ]
    assert used["lights"]["ambient"] == pytest.approx(drawn.lights.ambient, abs=1e-4)
    orbit = "none" if kind == "rgba" else surround  # with alpha: the object alone, whatever the seed drew around it
    assert used["surroundings"] == {"orbit": orbit, "forward": "room" if surround == "room" else "wall"}[layout]
    s = read_scene(out.out_dir)
    assert s.has_alpha == (kind == "rgba")
    depth = np.stack([np.load(p) for p in out.depths])
    assert (depth > 0).mean() > 0.1  # the slab and its objects are in view
    aabb = np.asarray(s.aabb)
    if layout == "orbit":  # the objects' box: a room around lies beyond it
        assert np.all(np.abs(aabb[:, :2]) < SLAB_RADIUS + 0.1) and aabb[1, 2] < TOP + 0.1
    else:  # forward: the far wall (or room) is in it, as for the fixed subjects
        assert aabb[1, 1] > 4.0


def test_random_subject_on_a_turntable_and_its_checks(tmp_path):
    out = scene.run(
        scene.Config(out_dir=tmp_path / "t", subject="random", layout="turntable", kind="rgba", size=16, views=2)
    )
    assert len(out.masks) == 2
    used = json.loads(out.manifest.read_text())["used"]["random_subject"]
    assert used["surroundings"] == "room"
    with pytest.raises(UserError, match="seed >= 0"):
        scene.run(scene.Config(out_dir=tmp_path / "n", subject="random", seed=-1))


def test_scene_help_lists_the_random_subject(capsys):
    with pytest.raises(SystemExit):
        cli.main(["scene", "--help"])
    assert "objects|carton|cube|random" in capsys.readouterr().out
