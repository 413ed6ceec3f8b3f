"""Exports opened in clients nobody here wrote (issue 52): the Khronos glTF validator, three.js (a default scene:
GLTFLoader, PerspectiveCamera with its default up; PLYLoader) and gsplat.js (a splat viewer with its default camera),
each in Debian's headless Chromium (software WebGL) or node, from the npm packages `make js` installs into
tests/js/node_modules (nothing is downloaded by the tests; they skip, saying why, without node or the packages).

The files come from the stages with their defaults (frame "upright"), from analytic stand-ins whose colour says
which way is up: a ball coloured by its normal in the scene frame, 0.5 + 0.5 n, so its top (scene +z) is blue
(0.5, 0.5, 1) and its bottom yellow (0.5, 0.5, 0). Upright means the top of the object on the screen is blue:
`_top_minus_bottom_blue` (the mean blue of the upper third of the silhouette less the lower third's) is at least
BLUE_GAP (measured: see each test's print) in the default camera of each client, and negative for the same object
written upside down for that client: the GLB in the user's frame (tilted as COLMAP's frames are), the splats with
glTF's +Y up instead of the splat files' -Y.
"""

from __future__ import annotations

import base64
import functools
import http.server
import io
import json
import math
import shutil
import subprocess
import threading
from pathlib import Path

import imageio.v2 as iio
import numpy as np
import pytest
import torch
import trimesh

from benchmarks.standin import StandIn
from nerfpipe.data import splat_ply
from nerfpipe.data.export_frame import export_frame
from nerfpipe.radiance import splats as sp
from nerfpipe.stages import export_points, mesh
from nerfpipe.stages.splat import files as splat_files

try:  # the DevTools driver lives with the viewer's tests
    from test_view import BROWSER_SECONDS, CHROMIUM, NO_CHROMIUM, Browser, wait_until
except ImportError:  # tests/ imported as a package
    from tests.test_view import BROWSER_SECONDS, CHROMIUM, NO_CHROMIUM, Browser, wait_until

JS = Path(__file__).resolve().parent / "js"
MODULES = JS / "node_modules"
NODE = shutil.which("node")
NO_JS = "no node or no tests/js/node_modules: `make js` installs the npm clients (gltf-validator, three, gsplat)"
HAVE_JS = NODE is not None and all((MODULES / p).is_dir() for p in ("gltf-validator", "three", "gsplat"))
W, H, FOV = 320, 240, 40.0  # the page's canvas and three.js' vertical field of view (degrees)
BLUE_GAP = 0.15
"""Upright: the top third of the object on the screen is at least this much bluer than its bottom third."""


class _TiltedBall(StandIn):
    """A ball of radius 0.5 at the scene's origin, coloured by its normal; the user's frame is the scene's turned
    -120 degrees about x (and scaled by 4, shifted), as a COLMAP frame is turned from the gravity-aligned one: the
    scene's up is (0, -0.87, -0.5) there (the demo's, issue 52: (-0.004, -0.698, -0.716)), so a file in the user's
    frame opens upside down in a +Y-up client."""

    background = torch.zeros(3)

    def __init__(self, root):
        super().__init__(root, identity=True)
        c, s = math.cos(math.radians(-120)), math.sin(math.radians(-120))
        applied = np.array([[1.0, 0, 0, 0.1], [0, c, -s, -0.2], [0, s, c, 0.3]])
        self.scene = type(self.scene)(**{**self.scene.__dict__, "applied_transform": applied, "applied_scale": 0.25})

    def sdf(self, x):
        return torch.linalg.norm(x, dim=-1) - 0.5

    def color(self, x, d):
        return 0.5 + 0.5 * x / torch.linalg.norm(x, dim=-1, keepdim=True).clamp_min(1e-9)


class _Files(http.server.SimpleHTTPRequestHandler):
    """/node_modules/... from tests/js/node_modules, /files/... from the test's folder, /page/... from tests/js."""

    def __init__(self, *args, files: Path, **kw):
        self.files = files
        super().__init__(*args, directory=str(JS), **kw)

    def translate_path(self, path: str) -> str:
        path = path.split("?", 1)[0]
        if path.startswith("/files/"):
            return str(self.files / path[len("/files/") :])
        if path.startswith("/page/"):
            return str(JS / path[len("/page/") :])
        return super().translate_path(path)

    def log_message(self, *args) -> None:
        pass


def _serve(files: Path) -> tuple[http.server.ThreadingHTTPServer, str]:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Files, files=files))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}"


def _page_result(url: str, profile: Path) -> dict:
    with Browser(url, profile, size=(W, H)) as browser:
        wait_until(lambda: browser.evaluate("window.__result !== undefined"), f"{url} to draw", BROWSER_SECONDS)
        result = browser.evaluate("window.__result")
    assert "error" not in result, result
    png = base64.b64decode(result["png"].split(",", 1)[1])
    return {**result, "image": iio.imread(io.BytesIO(png))}


def _top_minus_bottom_blue(image: np.ndarray) -> float:
    """Mean blue (0..1) of the upper third of the opaque pixels' rows less the lower third's."""
    mask = image[..., 3] > 200
    rows = np.flatnonzero(mask.any(axis=1))
    assert len(rows) > 10, "the object is not on the screen"
    third = (rows[-1] - rows[0]) / 3
    blue = image[..., 2] / 255.0
    top = mask & (np.arange(len(mask))[:, None] < rows[0] + third)
    bottom = mask & (np.arange(len(mask))[:, None] > rows[-1] - third)
    return float(blue[top].mean() - blue[bottom].mean())


@pytest.fixture(scope="module")
def ball_files(tmp_path_factory):
    """The tilted ball meshed by the stage: a textured GLB, upright (the default) and in the user's frame, and a
    vertex-coloured GLB."""
    root = tmp_path_factory.mktemp("export_clients")
    s = _TiltedBall(root)
    kw = dict(run_dir=root, resolution=48, threshold=50.0, texture_views=0, target_faces=4000, threshold_rays=512)
    mesh.extract(s, mesh.Config(out=root / "upright.glb", texture=True, texture_size=256, **kw))
    mesh.extract(s, mesh.Config(out=root / "user.glb", texture=True, texture_size=256, frame="user", **kw))
    mesh.extract(s, mesh.Config(out=root / "coloured.glb", **kw))
    return root


@pytest.mark.skipif(not HAVE_JS, reason=NO_JS)
def test_the_khronos_validator_finds_no_error_in_the_glbs(ball_files):
    names = ["upright.glb", "user.glb", "coloured.glb"]
    out = subprocess.run(
        [NODE, str(JS / "validate.mjs"), *(str(ball_files / n) for n in names)],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    reports = [json.loads(line) for line in out.stdout.splitlines()]
    assert [Path(r["path"]).name for r in reports] == names
    for r in reports:
        print(Path(r["path"]).name, {k: r[k] for k in ("numErrors", "numWarnings", "numInfos")}, r["messages"][:3])
        assert r["numErrors"] == 0, r


@pytest.mark.skipif(not HAVE_JS or CHROMIUM is None, reason=NO_JS if not HAVE_JS else NO_CHROMIUM)
def test_the_glb_opens_upright_in_a_default_three_js_scene(ball_files, tmp_path):
    """The default GLB's ball shows its blue top at the top of three.js' default camera; the same ball written in
    the user's (tilted) frame does not. The frame also matches our own rasterisation of the file from the page's
    camera (silhouette IoU, colours), so three.js read the geometry and texture as written."""
    from benchmarks.bench_mesh_texture import rasterize_textured
    from nerfpipe.radiance.camera import Intrinsics

    server, base = _serve(ball_files)
    try:
        got = {
            name: _page_result(f"{base}/page/three_glb.html?file={name}&fov={FOV}&w={W}&h={H}", tmp_path / name)
            for name in ("upright.glb", "user.glb")
        }
    finally:
        server.shutdown()
    gaps = {name: _top_minus_bottom_blue(r["image"]) for name, r in got.items()}
    shot = got["upright.glb"]["image"]
    iio.imwrite(tmp_path / "three_upright.png", shot)
    m = trimesh.load(ball_files / "upright.glb", force="mesh", process=False)
    c2w = np.asarray(got["upright.glb"]["world_from_cam"], np.float64).reshape(4, 4).T  # three.js: column-major
    f = (H / 2) / math.tan(math.radians(FOV) / 2)
    intr = Intrinsics(w=W, h=H, fx=f, fy=f, cx=W / 2, cy=H / 2)
    image = np.asarray(m.visual.material.baseColorTexture.convert("RGB"))
    want, want_mask = rasterize_textured(
        np.asarray(m.vertices), np.asarray(m.faces), np.asarray(m.visual.uv), image, c2w, intr
    )
    mask = shot[..., 3] > 127
    iou = (mask & want_mask).sum() / (mask | want_mask).sum()
    both = mask & want_mask
    err = np.abs(shot[..., :3][both] / 255.0 - want[both]).mean()
    print(f"three.js: top-bottom blue {gaps}; against our rasterisation IoU {iou:.3f}, colour error {err:.3f}")
    assert gaps["upright.glb"] >= BLUE_GAP and gaps["user.glb"] <= -BLUE_GAP, gaps
    assert iou >= 0.97 and err <= 0.03, (iou, err, tmp_path)


@pytest.mark.skipif(not HAVE_JS or CHROMIUM is None, reason=NO_JS if not HAVE_JS else NO_CHROMIUM)
def test_vertex_coloured_glbs_show_their_colours_in_a_default_three_js_scene(ball_files, tmp_path):
    """A scene without lights (three.js' default): a ball of one colour comes out in that colour (COLOR_0 in linear
    light under an unlit material: glTF's default material drew it black, sRGB bytes read as linear washed it out),
    and the stage's vertex-coloured ball upright, as the textured GLB."""
    from nerfpipe.data.images import srgb_to_linear
    from nerfpipe.stages.mesh.texture_files import glb_vertex_coloured

    files = tmp_path / "files"
    files.mkdir()
    ball = trimesh.creation.icosphere(subdivisions=3)
    colour = np.array([200, 120, 40], np.uint8)
    (files / "uniform.glb").write_bytes(
        glb_vertex_coloured(ball.vertices, ball.faces, np.tile(colour, (len(ball.vertices), 1)))
    )
    (files / "coloured.glb").write_bytes((ball_files / "coloured.glb").read_bytes())
    server, base = _serve(files)
    try:
        shots = {
            name: _page_result(f"{base}/page/three_glb.html?file={name}&fov={FOV}&w={W}&h={H}", tmp_path / name)[
                "image"
            ]
            for name in ("uniform.glb", "coloured.glb")
        }
    finally:
        server.shutdown()
    uniform = shots["uniform.glb"]
    drawn = uniform[..., :3][uniform[..., 3] == 255].astype(np.float64)  # [P, 3] the ball's inner pixels
    spread = drawn.std(axis=0).round(2)
    print(f"one-colour GLB in three.js: drawn {drawn.mean(axis=0).round(1)} (spread {spread}), written {colour}")
    assert len(drawn) > 1000 and np.abs(drawn - colour).max() <= 2.0, (drawn.mean(axis=0), tmp_path)
    assert _top_minus_bottom_blue(shots["coloured.glb"]) >= BLUE_GAP
    (m,) = trimesh.load(files / "uniform.glb", process=False).geometry.values()  # trimesh reads them back, linear
    want = srgb_to_linear(colour / 255.0)
    np.testing.assert_allclose(np.asarray(m.visual.vertex_attributes["color"]), np.tile(want, (len(m.vertices), 1)))


def _ball_splats(n: int = 1500, radius: float = 0.15) -> sp.Splats:
    """Gaussians on a ball at the origin of `_TiltedBall`'s scene frame, coloured by the normal as it is (the radius
    smaller than the mesh tests' ball: 0.6 in the user's units, in view of the splat viewer's camera at 5)."""
    g = torch.Generator().manual_seed(0)
    normal = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return sp.Splats(
        means=radius * normal,
        log_scales=torch.full((n, 3), math.log(0.1 * radius)),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        opacity_logits=torch.full((n,), 4.0),
        sh=sp.rgb_to_sh0(0.5 + 0.5 * normal)[:, None, :],
    )


@pytest.mark.skipif(not HAVE_JS or CHROMIUM is None, reason=NO_JS if not HAVE_JS else NO_CHROMIUM)
def test_the_splat_ply_opens_upright_in_gsplat_js_default_camera(tmp_path):
    """The splat stage's export (`data.export_frame` "upright" for format splat, `stages.splat.files.to_file`,
    `data.splat_ply.write_ply`: what `stages.splat.run` writes its optimised Gaussians with) of Gaussians on the
    tilted ball: gsplat.js' default orbit camera shows the blue top at the top; written with glTF's +Y up instead,
    the same Gaussians show it at the bottom (the viewer's up is -Y, the 3DGS files' convention)."""
    s = _TiltedBall(tmp_path)
    splats = _ball_splats()
    for name, fmt in (("upright.ply", "splat"), ("gltf_up.ply", "gltf")):
        out_from_scene, _ = export_frame(s.scene.source_from_scene(), "upright", fmt)
        data, dropped = splat_files.to_file(splats, out_from_scene)
        assert dropped == 0
        splat_ply.write_ply(tmp_path / name, data)
    server, base = _serve(tmp_path)
    try:
        got = {
            name: _page_result(f"{base}/page/gsplat_ply.html?file={name}&w={W}&h={H}", tmp_path / f"p_{name}")
            for name in ("upright.ply", "gltf_up.ply")
        }
    finally:
        server.shutdown()
    for name, r in got.items():
        iio.imwrite(tmp_path / f"gsplat_{name}.png", r["image"])
    gaps = {name: _top_minus_bottom_blue(r["image"]) for name, r in got.items()}
    print(f"gsplat.js default camera at {got['upright.ply']['position']}: top-bottom blue {gaps} ({tmp_path})")
    assert gaps["upright.ply"] >= BLUE_GAP and gaps["gltf_up.ply"] <= -BLUE_GAP, gaps


@pytest.mark.skipif(not HAVE_JS, reason=NO_JS)
def test_the_point_cloud_is_read_by_three_js_plyloader_as_32_bit_floats(tmp_path):
    """export-points' PLY through three.js' PLYLoader in node: every point, as a Float32Array (what WebGL takes;
    a float64 attribute is refused at upload: "Unsupported buffer data format"), at the file's coordinates."""
    s = _TiltedBall(tmp_path)
    out = export_points.export(s, export_points.Config(run_dir=tmp_path, out=tmp_path / "p.ply", num_points=100))
    header = (tmp_path / "p.ply").read_bytes()[:400].decode("ascii", "replace")
    assert "property float x" in header and "double" not in header
    script = tmp_path / "read.mjs"
    script.write_text(
        "import { readFileSync } from 'node:fs';\n"
        f"import {{ PLYLoader }} from '{MODULES.as_uri()}/three/examples/jsm/loaders/PLYLoader.js';\n"
        "const buf = readFileSync(process.argv[2]);\n"
        "const g = new PLYLoader().parse(buf.buffer.slice(buf.byteOffset, buf.byteOffset + buf.byteLength));\n"
        "const p = g.getAttribute('position');\n"
        "console.log(JSON.stringify({ n: p.count, type: p.array.constructor.name,"
        " first: Array.from(p.array.slice(0, 3)),"
        " colour: g.hasAttribute('color'), normal: g.hasAttribute('normal') }));\n"
    )
    res = subprocess.run([NODE, str(script), str(out.out)], capture_output=True, text=True, check=True, timeout=60)
    got = json.loads(res.stdout)
    ours = np.asarray(trimesh.load(out.out, process=False).vertices)
    assert got["n"] == out.points and got["type"] == "Float32Array" and got["colour"] and got["normal"], got
    assert np.allclose(got["first"], ours[0], atol=1e-6)
