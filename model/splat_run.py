"""What `render` and `eval` render: a trained run's field, or Gaussian splats made from a run (`nerfpipe splat`).

`open_input(path)` decides once: a folder is a run (its field, `model.load_trained`); a `.ply` file is a splat file
written by the splat stage, whose report next to it (`SPLATS.report.json`, `stages.splat`) names the run the
splats were made from (`config.run_dir`) and `out_from_scene`, the 4x4 from the run's scene frame to the file's
frame. `RenderInput.load(device, load_trained)` gives what the stages render: the run's `Trained`, or a `SplatRun`
(the run's scene, cameras, evaluation background and device, with the splats mapped back to the scene frame by the
inverse of `out_from_scene`).

A `SplatRun` is a run (`model.run.Run`) that renders whole cameras (capability `cameras`: rasterisation,
`radiance.splats.render`), not rays: `model.render_view` calls its `render_camera`. Returns what `render_view` returns
for a field, numpy float32: rgb [H, W, 3], acc [H, W] (1 - the final transmittance), and with `depth` the z-depth [H, W]
of the expected Gaussian depth (the same Gaussians composited with their camera z as colour over black, divided by acc:
a second pass) and depth_median = depth (splats have no per-ray weights to take a median of). Pinhole cameras only:
distortion coefficients are not applied (as in the splat stage's optimisation). Runs trained with --refine-poses keep
the run's field (`SplatRun.pose_run`) for eval's test-pose optimisation, so the splats are scored at the cameras the
field is scored at.

The run is found from the report: `run_from_splat` (the run folder relative to the splat file's folder) when the
report has it, else `config.run_dir` as recorded (absolute, or relative to where the splat stage ran).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nerfpipe.data.confine import read_json
from nerfpipe.data.errors import UserError
from nerfpipe.data.rundir import refuse_output_inside, sha256_file, sidecar
from nerfpipe.data.splat_ply import SplatData, read_ply
from nerfpipe.radiance import splats as sp
from nerfpipe.radiance.camera import Intrinsics

__all__ = ["SPLAT_SUFFIXES", "RenderInput", "SplatRun", "open_input", "load_splats", "splats_from_data"]

SPLAT_SUFFIXES = (".ply", ".splat")
"""A path with one of these suffixes is a splat file, not a run folder."""


@dataclass(frozen=True)
class RenderInput:
    """A run folder (`splat_file` None: its field) or a splat file made from a run (module doc)."""

    run_dir: Path
    splat_file: Path | None = None
    report: dict | None = None
    """The splat stage's report (SPLATS.report.json), None for a run."""

    @property
    def kind(self) -> str:
        """field | splats."""
        return "field" if self.splat_file is None else "splats"

    @property
    def report_path(self) -> Path | None:
        return None if self.splat_file is None else sidecar(self.splat_file, "report.json")

    @property
    def inputs(self) -> list[Path]:
        """The files rendered from, for the manifest (hashed there)."""
        run = [self.run_dir / "checkpoint.pt", self.run_dir / "config.json"]
        return run if self.splat_file is None else [self.splat_file, self.report_path, *run]

    @property
    def out_from_scene(self) -> np.ndarray:
        """[4, 4] from the run's scene frame to the splat file's frame (identity for a run)."""
        return np.eye(4) if self.report is None else np.asarray(self.report["out_from_scene"], dtype=np.float64)

    @property
    def train_psnr(self) -> tuple[float, str] | None:
        """Splats: the report's training PSNR after the optimisation and where it comes from (None for a run:
        eval reads the run's metrics.csv)."""
        value = (self.report or {}).get("psnr_train_final")
        if not isinstance(value, int | float) or not math.isfinite(value):
            return None
        views = len((self.report.get("used") or {}).get("scored_views") or [])
        return float(value), f"{self.report_path.name} psnr_train_final ({views} training views, optimised)"

    def record(self) -> dict[str, Any]:
        """What was rendered, for a manifest's `used` and eval's JSON: kind, run, and for splats the file's sha256,
        its Gaussians, the frame mapping and whether the run's checkpoint is still the one they were made from."""
        out: dict[str, Any] = {"kind": self.kind, "run_dir": str(self.run_dir)}
        if self.splat_file is None:
            return out
        made_from = next((v for k, v in (self.report.get("inputs") or {}).items() if k.endswith("checkpoint.pt")), None)
        ckpt = self.run_dir / "checkpoint.pt"
        now = sha256_file(ckpt) if ckpt.is_file() else None
        return {
            **out,
            "splat_file": str(self.splat_file),
            "splat_sha256": sha256_file(self.splat_file),
            "splat_report": str(self.report_path),
            "gaussians": self.report.get("gaussians"),
            "splat_frame": self.report.get("frame"),
            "scene_from_file": np.linalg.inv(self.out_from_scene).tolist(),
            "run_checkpoint": "the one the splats were made from"
            if made_from is not None and made_from == now
            else "changed since the splats were made (or not recorded)",
            "camera_model": "pinhole (distortion coefficients are not applied to splats)",
        }

    def refuse_output(self, out: str | Path, what: str) -> None:
        """UserError when a consumer's output `out` (with its OUT.metrics.csv and OUT.manifest.json) would damage what
        it reads: the run (`data.rundir.refuse_output_inside`) or, for splats, the splat file, its report or its
        metrics (`nerfpipe eval S.ply S.json` would write S.metrics.csv over the splat stage's)."""
        refuse_output_inside(out, self.run_dir, what)
        if self.splat_file is None:
            return
        own = {p.resolve(): p for p in (self.splat_file, self.report_path, sidecar(self.splat_file, "metrics.csv"))}
        for path in (Path(out), sidecar(out, "metrics.csv"), sidecar(out, "manifest.json")):
            if path.resolve() in own:
                raise UserError(
                    f"{out}: the {what} would write {path.name} over {own[path.resolve()]}, written with "
                    "the splats; expected another name"
                )

    def read_splats(self) -> sp.Splats:
        """The splat file's Gaussians in the run's scene frame (float64, CPU); UserError when the file does not hold
        what its report says."""
        if self.splat_file is None:
            raise ValueError("expected a splat input, got a run")
        splats = splats_from_data(read_ply(self.splat_file), self.out_from_scene, self.splat_file)
        if self.report.get("gaussians") not in (None, len(splats)):
            raise UserError(
                f"{self.splat_file}: holds {len(splats)} Gaussians, {self.report_path.name} says "
                f"{self.report['gaussians']}; expected the file the report was written with"
            )
        return splats

    def load(self, device: torch.device, load_trained: Callable[[Path, Any], Any]) -> Any:
        """The run's field (`load_trained(run_dir, device)`), or a `SplatRun` on that run."""
        trained = load_trained(self.run_dir, device)
        if self.splat_file is None:
            return trained
        moved = sp.Splats(*(p.to(trained.device, torch.float32) for p in self.read_splats().parameters()))
        return SplatRun.of(trained, moved, self)


def _report(path: Path) -> dict:
    """The splat stage's report next to `path`, checked (UserError naming the report)."""
    report = sidecar(path, "report.json")
    if not report.is_file():
        raise UserError(
            f"{path}: no {report.name} next to it; expected a splat file written by the splat stage (its "
            "report names the run the splats were made from and their frame)"
        )
    doc = read_json(report)
    if not isinstance(doc, dict) or doc.get("stage") != "splat":
        raise UserError(f'{report}: not a splat stage report (expected "stage": "splat")')
    m = np.asarray(doc.get("out_from_scene", []), dtype=object)
    try:
        m = m.astype(np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != (4, 4) or not np.isfinite(m).all() or abs(np.linalg.det(m)) < 1e-12:
        raise UserError(f"{report}: out_from_scene is not an invertible 4x4 matrix of numbers")
    if not isinstance((doc.get("config") or {}).get("run_dir"), str):
        raise UserError(f"{report}: names no run (config.run_dir)")
    return doc


def _run_of(path: Path, doc: dict) -> Path:
    """The run folder the report names (module doc): tried in order, the first that is a folder."""
    tried = []
    if isinstance(doc.get("run_from_splat"), str):
        tried.append(path.parent / doc["run_from_splat"])
    tried.append(Path(doc["config"]["run_dir"]))
    found = next((p for p in tried if p.is_dir()), None)
    if found is None:
        raise UserError(
            f"{sidecar(path, 'report.json')}: the run the splats were made from is not found (looked in "
            f"{', '.join(map(str, tried))}); expected the run folder the splat stage read"
        )
    return found


def open_input(path: str | Path) -> RenderInput:
    """A run folder, or a splat file (.ply) with its report (module doc); UserError naming what is wrong."""
    path = Path(path)
    if path.suffix.lower() not in SPLAT_SUFFIXES or path.is_dir():
        return RenderInput(run_dir=path)  # load_trained says what is wrong with a run folder
    if not path.is_file():
        raise UserError(f"{path}: splat file not found (expected a run directory or a .ply from the splat stage)")
    if path.suffix.lower() == ".splat":
        raise UserError(
            f"{path}: a .splat file (a web viewers' layout, colours in 8 bits); expected the .ply the "
            "splat stage writes (INRIA's layout) to render or evaluate splats"
        )
    doc = _report(path)
    return RenderInput(run_dir=_run_of(path, doc), splat_file=path, report=doc)


def splats_from_data(data: SplatData, out_from_scene: np.ndarray, path: Path | str = "splats") -> sp.Splats:
    """A splat file's Gaussians (file frame) -> `radiance.splats.Splats` in the scene frame, float64 CPU: SH
    [N, K, 3] from f_dc and the channel-major f_rest, then the inverse of `out_from_scene`."""
    if len(data) == 0:
        raise UserError(f"{path}: holds no Gaussians")
    sh = np.concatenate([data.f_dc[:, None, :], np.transpose(data.f_rest, (0, 2, 1))], axis=1)
    splats = sp.Splats(
        *(
            torch.from_numpy(np.asarray(a, dtype=np.float64))
            for a in (data.means, data.scales, data.quats, data.opacity, sh)
        )
    )
    scene_from_out = np.linalg.inv(np.asarray(out_from_scene, dtype=np.float64))
    if np.allclose(scene_from_out, np.eye(4)):
        return splats
    try:
        return sp.transformed(splats, torch.from_numpy(scene_from_out))
    except ValueError as exc:
        raise UserError(f"{path}: cannot map the splats back to the run's scene frame ({exc})") from None


@dataclass
class SplatRun:
    """Splats rendered as their run would be (module doc): a `model.run.Run` with the run's scene, background,
    device and downscale, that rasterises whole cameras (capability `cameras`); where the run it was made from can
    place a test camera (`pose_opt`: --refine-poses runs), it keeps that run for eval's test-pose optimisation."""

    splats: sp.Splats
    """Scene frame, on the run's device, float32."""
    source: RenderInput
    scene: Any
    background: torch.Tensor
    device: torch.device
    downscale: float
    pose_refinement: dict | None = None
    pose_run: Any = None
    """The run the splats were made from, kept where it can place test cameras (`pose_opt`), else None."""
    method: str = "splats"
    far: float = math.inf
    """Splats draw whatever lies in front of a camera: no far bound."""
    appearance: None = None
    """Splats have no per-image appearance codes."""

    @classmethod
    def of(cls, run: Any, splats: sp.Splats, source: RenderInput) -> SplatRun:
        """Splats made from `run` (a `model.run.Run`, or a test stand-in)."""
        return cls(
            splats=splats,
            source=source,
            scene=run.scene,
            background=run.background,
            device=run.device,
            downscale=float(getattr(run, "downscale", 1.0)),
            pose_refinement=run.pose_refinement,
            pose_run=run if "pose_opt" in getattr(run, "capabilities", ()) else None,
        )

    @property
    def capabilities(self) -> frozenset[str]:
        return frozenset({"cameras"} | ({"pose_opt"} if self.pose_run is not None else set()))

    def render_differentiable(self, o: torch.Tensor, d: torch.Tensor, background: torch.Tensor) -> dict:
        """The run's differentiable render (eval places a test camera with the run's field, as for the field)."""
        return self.pose_run.render_differentiable(o, d, background)

    def parameters(self):
        return self.pose_run.parameters()

    @torch.no_grad()
    def render_camera(self, intr: Intrinsics, world_from_cam: np.ndarray, *, depth: bool = True) -> dict:
        """One camera (scene frame, OpenGL axes) -> numpy float32 rgb [H, W, 3], acc [H, W], and with `depth`
        depth [H, W] (z-depth, scene units) and depth_median [H, W] (the same; module doc)."""
        pose = torch.as_tensor(np.asarray(world_from_cam, dtype=np.float64))
        bg = self.background.to(self.splats.means).reshape(3)
        proj = sp.project(self.splats, pose, intr)
        out = sp.rasterize(proj, intr.w, intr.h, bg)
        acc = out["alpha"]
        view = {"rgb": out["rgb"].float().cpu().numpy(), "acc": acc.float().cpu().numpy()}
        if depth:
            as_colour = dataclasses.replace(proj, rgb=proj.depths[:, None].expand(-1, 3))
            z_sum = sp.rasterize(as_colour, intr.w, intr.h, torch.zeros_like(bg))["rgb"][..., 0]
            z = (z_sum / acc.clamp_min(torch.finfo(acc.dtype).eps)).float().cpu().numpy()
            view.update(depth=z, depth_median=z.copy())
        return view


def load_splats(path: str | Path, device: str | torch.device = "auto") -> SplatRun:
    """A splat file made by the splat stage, ready to render (its run loaded with `model.load_trained`)."""
    from nerfpipe.model.device import resolve_device
    from nerfpipe.model.run import load_trained

    source = open_input(path)
    if source.splat_file is None:
        raise UserError(f"{path}: expected a splat file (.ply) from the splat stage")
    return source.load(resolve_device(device), load_trained)
