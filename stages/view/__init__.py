"""Stage `view`: an interactive viewer (viser, in the browser) for a scene before training, a trained run or an
X-ray run.

    nerfpipe view SCENE_DIR|RUN_DIR [--port 7007] [--host 127.0.0.1] [--preview 256] [--refine 384]
        [--splats SPLATS.ply]

- SCENE_DIR (a folder with transforms.json): camera frusta with their images, sparse points (transforms.json's
  `sparse_points_path`), the scene box, the up axis; clicking a camera shows its image and name; a toggle draws
  a few of its rays and their sample points (`stages.view.scene_view`).
- RUN_DIR (`train`'s output): the field rendered live from the browser's camera, coarse while it moves and
  refined when it stops, as rgb / depth / accumulation; the training cameras; the test views' PSNR from the run's
  files (`stages.view.run_view`), and the camera-path recorder (`stages.view.recorder`), whose JSON
  `nerfpipe render RUN_DIR OUT.mp4 --path FILE.json` plays back. With splats made from the run (`--splats FILE.ply`,
  or RUN_DIR/splats.ply when it is there) the browser draws the Gaussians itself, in real time, and a `Draw`
  dropdown switches between them and the field's render (`stages.view.splat_view`).
- An X-ray run (`xray-train`'s output): DRR / MIP at any gantry angle and a movable slice plane
  (`stages.view.xray_view`).

The server listens on 127.0.0.1 (this machine only) unless `--host` says otherwise, which prints a warning.
It answers only its own page (`stages.view.gate`): a request must carry the token of the URL it prints
(`http://127.0.0.1:7007/?token=...`, a new one each time), name this machine in its Host header and, from a
browser, come from the viewer's own page (Origin); anything else gets 403. Ctrl-C (or SIGTERM) stops it: one
line, exit code 130 (143). `serve(config)` starts it and returns a `Viewer` (tests and scripts stop it with
`.stop()`); `run(config)` serves until Ctrl-C. The recorder saves new camera paths only, under `paths_dir`
(default: the folder viewed's `camera_paths/`), never over a file.
"""

from __future__ import annotations

import signal
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nerfpipe.data.confine import read_json
from nerfpipe.data.errors import Interrupted, UserError
from nerfpipe.data.transforms import read_scene
from nerfpipe.model import load_trained, resolve_device
from nerfpipe.model.methods import method_of_run
from nerfpipe.stages.view import server as viewer_server
from nerfpipe.stages.view.gate import Gate
from nerfpipe.stages.view.recorder import PathRecorder, add_recorder_gui
from nerfpipe.stages.view.run_view import MODES, LiveRender, psnr_summary
from nerfpipe.stages.view.scene_view import SceneView
from nerfpipe.stages.view.splat_view import SplatLayer, find_splats
from nerfpipe.stages.view.xray_view import XrayView

__all__ = ["Config", "Outputs", "Viewer", "kind_of", "serve", "run"]


@dataclass(frozen=True, kw_only=True)
class Config:
    target: Path
    """A scene folder (transforms.json), a train run directory or an xray-train run directory."""
    port: int = 7007
    """TCP port of the viewer (0: any free port)."""
    host: str = "127.0.0.1"
    """Address to listen on; 127.0.0.1 keeps the viewer to this machine, 0.0.0.0 opens it to the network."""
    preview: int = 256
    """Long side, in pixels, of the frames rendered while the camera moves (coarse)."""
    refine: int = 384
    """Long side, in pixels, of the frame rendered once the camera stops."""
    paths_dir: Path | None = None
    """The only folder the recorder writes to: new `NAME.json` camera paths, never over an existing file (default:
    `camera_paths/` in the folder viewed)."""
    splats: Path | None = None
    """A train run's Gaussian splats to draw in the browser beside the field's render: a .ply the splat stage made
    from this run (None: RUN_DIR/splats.ply when it is there)."""
    device: str = "auto"
    """torch device: auto (cuda if available, else cpu), cpu, cuda, cuda:1, ..."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    url: str
    """Where the viewer was served (without its token)."""
    kind: str
    """scene | run | xray."""


@dataclass
class Viewer:
    """A running viewer: its server, what it shows, and how to stop it."""

    server: object
    url: str
    """Where to open it: http://HOST:PORT/?token=..."""
    kind: str
    port: int
    gate: Gate
    live: LiveRender | None = None
    scene_view: SceneView | None = None
    recorder: PathRecorder | None = None
    xray_view: XrayView | None = None
    splats: SplatLayer | None = None
    stopped: threading.Event = field(default_factory=threading.Event)

    @property
    def address(self) -> str:
        """The URL without its token (for messages printed once it has stopped)."""
        return self.url.partition("?")[0]

    def stop(self) -> None:
        if self.live is not None:
            self.live.stop()
        if not self.stopped.is_set():
            self.stopped.set()
            viewer_server.stop_quietly(self.server)


def kind_of(target: Path) -> str:
    """'scene' (transforms.json), 'run' (a train run: its config.json names its method, `model.methods`) or 'xray'
    (an xray-train run: anything else with a config.json and a checkpoint, which the X-ray loader then checks)."""
    target = Path(target)
    if not target.exists():
        raise UserError(f"{target}: not found (expected a scene folder or a run directory)")
    if (target / "transforms.json").is_file() or (target.is_file() and target.name.endswith(".json")):
        return "scene"
    cfg = target / "config.json"
    if cfg.is_file() and (target / "checkpoint.pt").is_file():
        doc = read_json(cfg)
        try:
            method_of_run(doc if isinstance(doc, dict) else {}, str(cfg))
            return "run"
        except UserError:
            return "xray"
    raise UserError(
        f"{target}: neither a scene folder (transforms.json) nor a finished run (config.json, checkpoint.pt)"
    )


def _look_from_first_camera(server, scene, centre: np.ndarray, pull_back: float = 1.0) -> None:
    """The browser starts at the first training camera (`pull_back` times as far from the centre), looking at
    the centre."""
    train = scene.split("train") or tuple(range(len(scene.frames)))
    pose = scene.frames[train[0]].world_from_cam
    server.initial_camera.position = tuple(centre + pull_back * (pose[:3, 3] - centre))
    server.initial_camera.look_at = tuple(centre)
    server.initial_camera.up = (0.0, 0.0, 1.0)


def serve(config: Config) -> Viewer:
    """Start the viewer for `config.target` and return at once."""
    if config.preview < 8 or config.refine < 8:
        raise UserError(f"--preview/--refine: expected >= 8 pixels, got {config.preview}, {config.refine}")
    kind = kind_of(config.target)
    target = Path(config.target)
    folder = target if target.is_dir() else target.parent
    paths_dir = Path(config.paths_dir) if config.paths_dir is not None else folder / "camera_paths"
    if paths_dir.exists() and not paths_dir.is_dir():
        raise UserError(f"{paths_dir}: paths_dir is not a folder (the recorder saves camera paths in it)")
    if config.splats is not None and kind != "run":
        raise UserError(f"{target}: splats: only a train run's viewer draws splats, this is a {kind} folder")
    splats = find_splats(target, config.splats) if kind == "run" else None
    device = resolve_device(config.device)
    loaded = load_trained(target, device) if kind == "run" else None
    if kind == "xray":
        from nerfpipe.model.xray import load_xray_run

        xray = load_xray_run(target, device)
    gate = Gate(bind_host=config.host, port=config.port)
    server = viewer_server.start(config.host, config.port, gate)
    port = server.get_port()
    viewer = Viewer(server=server, url=viewer_server.url(config.host, port, gate), kind=kind, port=port, gate=gate)
    try:
        if kind == "xray":
            viewer.xray_view = XrayView(server, xray)
            viewer.xray_view.draw()
            return viewer
        scene = loaded.scene if loaded is not None else read_scene(target)
        view = SceneView(server, scene)
        centre = np.asarray(scene.aabb, dtype=np.float64).reshape(2, 3).mean(axis=0)
        # a scene: from behind the rig, every camera in view; a run: from its first camera, whose frustum (drawn
        # without its image: the live render is the picture) then lies round the view's edges
        _look_from_first_camera(server, scene, centre, pull_back=2.0 if loaded is None else 1.0)
        if loaded is None:
            view.draw()
        else:
            _draw_run(server, viewer, loaded, target, config, splats)
            train = scene.split("train") or tuple(range(len(scene.frames)))
            view.draw(train, label="Training cameras", images=False)
        viewer.scene_view = view
        viewer.recorder = add_recorder_gui(server, paths_dir, size=view.size)
    except BaseException:
        viewer.stop()
        raise
    return viewer


def _draw_run(server, viewer: Viewer, trained, run_dir: Path, config: Config, splats) -> None:
    live = LiveRender(server, trained, preview=config.preview, refine=config.refine)
    viewer.live = live
    with server.gui.add_folder("Render"):
        if splats is not None:
            viewer.splats = SplatLayer.add(server, splats, live)
        mode = server.gui.add_dropdown("Show", MODES, initial_value="rgb")
        server.gui.add_markdown(psnr_summary(run_dir))

    @mode.on_update
    def _(_event) -> None:
        live.mode = mode.value
        live.refresh()


def run(config: Config) -> Outputs:
    """Serve until Ctrl-C / SIGTERM (Interrupted: one line, exit 130 / 143) or until `Viewer.stop()`."""
    viewer = serve(config)
    try:
        signum = viewer_server.wait(viewer.stopped, f"nerfpipe view: {viewer.kind} at {viewer.url} (Ctrl-C stops)")
    finally:
        viewer.stop()
    if signum is not None:
        name = signal.Signals(signum).name
        raise Interrupted(f"interrupted ({name}): the viewer at {viewer.address} stopped", signum)
    return Outputs(url=viewer.address, kind=viewer.kind)
