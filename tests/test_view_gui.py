"""The viewer's controls in a real browser (headless Chromium over DevTools, test_view's `Browser`): a run's
rgb / depth / accumulation switch and the camera-path recorder, clicked in the page; the X-ray controls; the
scene view's camera click and rays toggle. Each browser test takes a few seconds on the analytic sphere."""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as iio
import numpy as np
import pytest

import nerfpipe.stages.render as render_stage
import nerfpipe.stages.view as view
from nerfpipe.stages.view.scene_view import thumbnail
from nerfpipe.stages.view.xray_view import projection_image, slice_image

# the browser driver and the sphere stand-ins live with the viewer's and render's tests
from tests.test_render_stage import SphereRun, sphere_scene
from tests.test_view import (
    BROWSER_SECONDS,
    CHROMIUM,
    NO_CHROMIUM,
    Browser,
    _shows_sphere,
    _sphere_run,
    button,
    labelled,
    option,
    wait_until,
)
from tests.test_xray_stages import phantom


def _middle(img: np.ndarray) -> np.ndarray:
    """The part of the page where the sphere is drawn (as in _shows_sphere), RGB in [0, 1]."""
    h, w = img.shape[:2]
    return img[h // 4 : 3 * h // 4, w // 4 : 13 * w // 20, :3].astype(float) / 255


def _shows_depth(img: np.ndarray) -> bool:
    """Depth mode: the sphere in turbo colours (saturated) on black (no opacity), no white background left."""
    rgb = _middle(img)
    sat = rgb.max(-1) - rgb.min(-1)
    black, white = rgb.max(-1) < 0.1, rgb.min(-1) > 0.9
    return (sat > 0.3).mean() > 0.03 and black.mean() > 0.3 and white.mean() < 0.01


def _shows_accumulation(img: np.ndarray) -> bool:
    """Accumulation mode: the opaque sphere white on black (the colours left are the box's and up axis' lines)."""
    rgb = _middle(img)
    sat = rgb.max(-1) - rgb.min(-1)
    black, white = rgb.max(-1) < 0.1, rgb.min(-1) > 0.9
    return white.mean() > 0.03 and black.mean() > 0.3 and (sat > 0.3).mean() < white.mean()


def _choose(browser: Browser, label: str, value: str) -> None:
    """Open the dropdown `label` and pick `value`, with mouse clicks."""
    browser.click(labelled(label))
    browser.click(option(value))


@pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)
def test_browser_run_modes_and_recorder(tmp_path, monkeypatch):
    """In the page: "Show" -> depth, then accumulation (clicked) changes what is drawn; "Add keyframe" clicked
    twice from two browser cameras and "Save path" clicked write a JSON that `render --path` plays."""
    run_dir = _sphere_run(tmp_path, monkeypatch)
    viewer = view.serve(view.Config(target=run_dir, port=0, preview=96, refine=160))
    shots = {}
    try:
        with Browser(viewer.url, tmp_path / "profile") as browser:
            shots["rgb"] = browser.screenshot_when(_shows_sphere)
            for mode, good in (("depth", _shows_depth), ("accumulation", _shows_accumulation)):
                _choose(browser, "Show", mode)
                wait_until(lambda mode=mode: viewer.live.mode == mode, f"mode {mode}")
                shots[mode] = browser.screenshot_when(good)

            browser.click(button("Add keyframe (this view)"))
            wait_until(lambda: len(viewer.recorder.keyframes) == 1, "the first keyframe")
            (client,) = viewer.server.get_clients().values()
            first = client.camera.position
            client.camera.position = tuple(np.asarray(first) * 1.3)  # the browser's camera moves back
            wait_until(
                lambda: np.allclose(client.camera.position, np.asarray(first) * 1.3, atol=1e-3),
                "the browser to report its new camera",
            )
            browser.click(button("Add keyframe (this view)"))
            wait_until(lambda: len(viewer.recorder.keyframes) == 2, "the second keyframe")
            browser.type_into(labelled("Seconds"), "1")
            browser.type_into(labelled("FPS"), "4")
            browser.click(button("Save path"))
            wait_until(lambda: (run_dir / "camera_paths" / "camera_path.json").is_file(), "the saved camera path")
    finally:
        viewer.stop()
    for mode, shot in shots.items():
        iio.imwrite(tmp_path / f"{mode}.png", shot)
    assert _shows_sphere(shots["rgb"]), tmp_path / "rgb.png"
    assert _shows_depth(shots["depth"]), tmp_path / "depth.png"
    assert _shows_accumulation(shots["accumulation"]), tmp_path / "accumulation.png"
    keys = viewer.recorder.keyframes
    assert np.allclose(keys[1].world_from_cam[:3, 3], 1.3 * keys[0].world_from_cam[:3, 3], atol=1e-3)
    assert np.allclose(keys[1].world_from_cam[:3, :3], keys[0].world_from_cam[:3, :3], atol=1e-3)

    scene = viewer.scene_view.scene
    monkeypatch.setattr(render_stage, "load_trained", lambda run_dir, device: SphereRun(scene=scene))
    saved = run_dir / "camera_paths" / "camera_path.json"
    res = render_stage.run(
        render_stage.Config(run_dir=run_dir, out=tmp_path / "path.mp4", downscale=10.0, path=str(saved), device="cpu")
    )
    assert res.n_frames == 5 and res.size[0] == 48  # 1 s at 4 fps (typed in), 480 px high / 10


@pytest.fixture(scope="module")
def xray_run(tmp_path_factory) -> Path:
    """A seconds-long X-ray run on test_xray_stages' phantom (16^3, 12 views): only the viewer's input."""
    from nerfpipe.stages import xray_simulate, xray_train

    tmp = tmp_path_factory.mktemp("xray_view")
    np.save(tmp / "phantom.npy", phantom(16))
    xray_simulate.run(
        xray_simulate.Config(
            volume=tmp / "phantom.npy",
            out_dir=tmp / "scene",
            views=12,
            arc=360.0,
            test_views=2,
            voxel_size=1.0,
            dso=100.0,
            dsd=150.0,
        )
    )
    cfg = xray_train.Config(
        scene=tmp / "scene",
        run_dir=tmp / "run",
        max_steps=20,
        max_seconds=60.0,
        batch_rays=512,
        lr=0.1,
        eval_every=0.0,
        threads=1,
        device="cpu",
    )
    return xray_train.run(cfg).run_dir


def _panel_image(viewer) -> np.ndarray:
    return np.asarray(viewer.xray_view.handles["image"].image)


@pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)
def test_browser_xray_projection_and_slice(xray_run, tmp_path):
    """In the page: "Projection" -> MIP (clicked) replaces the DRR in the panel; the gantry angle and the slice
    axis / position (set server-side, as the page's sliders would) move the projection and the slice plane."""
    viewer = view.serve(view.Config(target=xray_run, port=0))
    xv = viewer.xray_view
    try:
        drr = _panel_image(viewer)
        assert drr.std() > 3, "blank DRR"
        with Browser(viewer.url, tmp_path / "profile") as browser:
            browser.click(labelled("Projection"))  # the page is up once its controls are
            browser.click(option("MIP"))
            wait_until(lambda: not np.array_equal(_panel_image(viewer), drr), "the MIP chosen in the page")
            mip = _panel_image(viewer)
            shot = browser.screenshot()
        assert mip.shape == drr.shape and mip.std() > 3 and np.abs(mip.astype(int) - drr).mean() > 2
        assert np.array_equal(mip, projection_image(xv.run, "MIP", 0.0, xv.volume))
        xv.handles["angle"].value = 90.0
        assert np.array_equal(_panel_image(viewer), projection_image(xv.run, "MIP", 90.0, xv.volume))
        assert not np.array_equal(_panel_image(viewer), mip)
        xv.handles["axis"].value = "x"
        xv.handles["where"].value = 0.25
        img, k = slice_image(xv.vol_np, "x", 0.25, xv.hi)
        assert k == 4 and np.array_equal(np.asarray(xv.handles["slice"].image), img)
        lo, hi = xv.box
        assert np.isclose(xv.handles["slice"].position[0], lo[0] + 4.5 * (hi[0] - lo[0]) / xv.vol_np.shape[0])
    finally:
        viewer.stop()
    iio.imwrite(tmp_path / "xray.png", shot)
    assert shot[..., :3].std() > 10, tmp_path / "xray.png"


def _red(img: np.ndarray) -> int:
    """Pixels of the rays' red (220, 30, 30)."""
    rgb = img[..., :3].astype(int)
    return int(((rgb[..., 0] > 150) & (rgb[..., 1] < 90) & (rgb[..., 2] < 90)).sum())


@pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)
def test_browser_scene_camera_click_and_rays(tmp_path):
    """A scene before training: every camera is a frustum with its image; a mouse click on camera 3's frustum in
    the 3-D view (the browser's camera set just behind it) shows its image and name in the panel; the rays
    checkbox, clicked, draws its rays and samples (red in the page) and, clicked again, removes them."""
    scene = sphere_scene(tmp_path / "scene", w=64, h=48)
    viewer = view.serve(view.Config(target=tmp_path / "scene", port=0))
    sv, i = viewer.scene_view, 3
    try:
        assert sorted(sv.frusta) == list(range(len(scene.frames)))
        assert all(np.asarray(f.image).shape == thumbnail(scene, k).shape for k, f in sv.frusta.items())
        with Browser(viewer.url, tmp_path / "profile") as browser:
            browser.click(labelled("Show its rays and samples"), seconds=BROWSER_SECONDS)  # the page is up:
            wait_until(lambda: sv.handles["rays"].value, "the rays checkbox ticked")  # (no camera chosen yet)
            assert "/scene/rays" not in sv.handles
            (client,) = viewer.server.get_clients().values()
            pose = scene.frames[i].world_from_cam
            forward, scale = -pose[:3, 2], 0.05 * sv.size
            client.camera.position = tuple(pose[:3, 3] - 3 * scale * forward)
            client.camera.look_at = tuple(pose[:3, 3] + scale * forward)
            wait_until(
                lambda: np.allclose(client.camera.position, pose[:3, 3] - 3 * scale * forward, atol=1e-3),
                "the browser to report its new camera",
            )
            before = browser.screenshot()
            browser.click_at(*browser.evaluate("[window.innerWidth / 2, window.innerHeight / 2]"))
            wait_until(lambda: sv.selected == i, f"camera {i} clicked in the 3-D view")
            wait_until(lambda: "/scene/rays" in sv.handles, "its rays drawn")
            name = scene.frames[i].file_path
            wait_until(lambda: name in browser.evaluate("document.body.innerText"), "its name in the panel")
            with_rays = browser.screenshot_when(lambda img: _red(img) > _red(before) + 200, seconds=10)
            browser.click(labelled("Show its rays and samples"))
            wait_until(lambda: "/scene/rays" not in sv.handles and "/scene/samples" not in sv.handles, "no rays")
        assert np.array_equal(np.asarray(sv.handles["image"].image), thumbnail(scene, i, 256))
    finally:
        viewer.stop()
    iio.imwrite(tmp_path / "rays.png", with_rays)
    assert _red(with_rays) > _red(before) + 200, tmp_path / "rays.png"
