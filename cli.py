"""nerfpipe command line: one typer command per stage. Commands only build a stage's Config and call `run`.

Errors: a user error (`data.errors.UserError`) prints one line `error: ...` and exits 2; any other failure
prints one line and exits 1; `nerfpipe --debug ...` shows the traceback instead.
"""

from __future__ import annotations

import sys
from enum import Enum
from pathlib import Path
from typing import Annotated, Literal, get_args

import typer

from data.errors import UserError

app = typer.Typer(
    name="nerfpipe",
    help="Photos, video or posed datasets -> camera poses, a radiance field, turntable videos, depth maps, meshes.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version_callback(value: bool) -> None:
    if value:
        from importlib import metadata

        typer.echo(f"nerfpipe {metadata.version('nerfpipe')}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version_callback, is_eager=True, help="Print the version.")
    ] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show Python tracebacks on errors.")] = False,
) -> None:
    """nerfpipe: each command is one stage; stages talk only through files."""


def _choices(name: str, literal) -> type[Enum]:
    """A str Enum of a Literal's values, so typer shows and checks the choices."""
    return Enum(name, {v: v for v in get_args(literal)}, type=str)


def _csv_ints(text: str, option: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise UserError(f"{option}: expected comma-separated integers, got {text!r}") from None


Device = _choices("Device", Literal["auto", "cpu", "cuda"])
DeviceOpt = Annotated[Device, typer.Option(help="Where to run: auto uses CUDA when available.")]


# ---------------------------------------------------------------------------------------------- scene
SceneKind = _choices("SceneKind", Literal["photos", "posed", "rgba"])
SceneLayout = _choices("SceneLayout", Literal["orbit", "forward"])


@app.command()
def scene(
    out_dir: Annotated[Path, typer.Argument(help="Folder to write the synthetic scene into.")],
    kind: Annotated[SceneKind, typer.Option(help="photos: bare images; posed/rgba: with transforms.json.")] = "posed",
    size: Annotated[int, typer.Option(help="Image width and height in pixels.")] = 64,
    views: Annotated[int, typer.Option(help="Number of camera views.")] = 24,
    seed: Annotated[int, typer.Option(help="Random seed (the scene is deterministic for a seed).")] = 0,
    layout: Annotated[SceneLayout, typer.Option(help="orbit: 360-degree rig; forward: LLFF-style.")] = "orbit",
) -> None:
    """Generate a procedural, textured scene with exact cameras, depth and surface mesh."""
    from stages import scene as stage

    out = stage.run(stage.Config(out_dir=out_dir, kind=SceneKind(kind).value, size=size, views=views, seed=seed,
                                 layout=SceneLayout(layout).value))  # fmt: skip
    typer.echo(f"{len(out.images)} images, ground truth and manifest -> {out.out_dir}")


# ---------------------------------------------------------------------------------------------- poses
Matcher = _choices("Matcher", Literal["auto", "exhaustive", "sequential"])
CameraModel = _choices("CameraModel", Literal["SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE"])


@app.command()
def poses(
    input: Annotated[Path, typer.Argument(help="A folder of photos or a video file.")],
    scene_dir: Annotated[Path, typer.Argument(help="Output folder: colmap/ and poses_report.json.")],
    max_image_size: Annotated[int, typer.Option(help="Downscale images to this long side for features.")] = 1000,
    max_num_features: Annotated[int, typer.Option(help="SIFT features per image.")] = 2048,
    matcher: Annotated[Matcher, typer.Option(help="auto: exhaustive for photos, sequential for video.")] = "auto",
    single_camera: Annotated[bool, typer.Option(help="One shared camera per image size.")] = True,
    camera_model: Annotated[CameraModel, typer.Option(help="COLMAP camera model.")] = "SIMPLE_RADIAL",
    video_frames: Annotated[int, typer.Option(help="Frames to extract from a video (sharpest per window).")] = 150,
    drop_blurry: Annotated[float, typer.Option(help="Drop the blurriest images: a fraction (<1) or a count.")] = 0.0,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
) -> None:
    """Camera poses with COLMAP (in-process, pycolmap): features, matching, mapping; keeps the largest model."""
    from stages import poses as stage

    out = stage.run(
        stage.Config(
            input=input,
            scene_dir=scene_dir,
            max_image_size=max_image_size,
            max_num_features=max_num_features,
            matcher=Matcher(matcher).value,
            single_camera=single_camera,
            camera_model=CameraModel(camera_model).value,
            video_frames=video_frames,
            drop_blurry=drop_blurry,
            seed=seed,
        )  # fmt: skip
    )
    typer.echo(
        f"{out.registered}/{out.total} images registered, mean reprojection error "
        f"{out.mean_reprojection_error:.2f} px -> {out.sparse}"
    )


# ---------------------------------------------------------------------------------------------- convert
ConvertKind = _choices("ConvertKind", Literal["auto", "colmap", "blender", "llff", "npz", "transforms"])
UpAxis = _choices("UpAxis", Literal["auto", "keep", "cameras"])


@app.command()
def convert(
    source: Annotated[
        Path, typer.Argument(help="COLMAP model/folder, Blender folder, LLFF folder, .npz, or transforms.json.")
    ],
    scene_dir: Annotated[Path, typer.Argument(help="Output folder for transforms.json and images.")],
    kind: Annotated[ConvertKind, typer.Option(help="Source kind; auto looks at the files.")] = "auto",
    images: Annotated[Path | None, typer.Option(help="Image folder for COLMAP/LLFF sources (default: found).")] = None,
    downscales: Annotated[str, typer.Option(help="Factors for downscaled copies images_F, comma-separated.")] = "2,4,8",
    holdout_every: Annotated[int, typer.Option(help="Without the dataset's own split, every N-th frame is test.")] = 8,
    up: Annotated[UpAxis, typer.Option(help="Up axis: keep the source z, or the cameras' mean up.")] = "auto",
    normalize: Annotated[bool, typer.Option(help="Re-centre and scale the scene into [-1, 1]^3.")] = True,
) -> None:
    """Convert a posed source into SCENE_DIR/transforms.json (OpenGL, normalised, transform recorded)."""
    from stages import convert as stage

    out = stage.run(
        stage.Config(
            source=source,
            scene_dir=scene_dir,
            kind=ConvertKind(kind).value,
            images=images,
            downscales=_csv_ints(downscales, "--downscales"),
            holdout_every=holdout_every,
            up=UpAxis(up).value,
            normalize=normalize,
        )  # fmt: skip
    )
    typer.echo(f"{out.num_frames} frames ({out.kind}) -> {out.transforms}; splits {out.splits}")


# ---------------------------------------------------------------------------------------------- train
FieldKind = _choices("FieldKind", Literal["fast", "vanilla"])
SceneModel = _choices("SceneModel", Literal["auto", "box", "ndc"])


@app.command()
def train(
    scene_dir: Annotated[Path, typer.Argument(help="Folder with transforms.json.")],
    run_dir: Annotated[Path, typer.Argument(help="Run directory to write (config, checkpoint, metrics).")],
    field: Annotated[FieldKind, typer.Option(help="fast: factorised grid (default); vanilla: the NeRF paper.")] = (
        "fast"
    ),
    max_steps: Annotated[int, typer.Option(help="Stop after this many steps.")] = 30000,
    max_seconds: Annotated[float, typer.Option(help="Stop after this many seconds of training.")] = 900.0,
    device: DeviceOpt = "auto",
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    resume: Annotated[bool, typer.Option(help="Continue from RUN_DIR/checkpoint.pt.")] = False,
    batch_rays: Annotated[int | None, typer.Option(help="Rays per step (default: 1024 on CPU, 4096 on CUDA).")] = None,
    lr: Annotated[float | None, typer.Option(help="Base learning rate (default: per field).")] = None,
    eval_every: Annotated[int, typer.Option(help="Held-out PSNR every N steps (0: only at the end).")] = 250,
    view_dependent: Annotated[
        bool | None, typer.Option("--view-dependent/--no-view-dependent", help="Colour depends on view direction.")
    ] = None,
    final_eval_views: Annotated[
        int | None, typer.Option(help="Test views rendered in full at the end (evenly spaced; default all).")
    ] = None,
    scene_model: Annotated[
        SceneModel, typer.Option(help="box: the scene's aabb; ndc: forward-facing NDC; auto: from the cameras.")
    ] = "auto",
) -> None:
    """Train a radiance field; logs held-out PSNR against wall-clock seconds."""
    from stages import train as stage

    out = stage.run(
        stage.Config(
            scene_dir=scene_dir,
            run_dir=run_dir,
            field=FieldKind(field).value,
            max_steps=max_steps,
            max_seconds=max_seconds,
            device=Device(device).value,
            seed=seed,
            resume=resume,
            batch_rays=batch_rays,
            lr=lr,
            eval_every=eval_every,
            view_dependent=view_dependent,
            final_eval_views=final_eval_views,
            scene_model=SceneModel(scene_model).value,
        )  # fmt: skip
    )
    psnr = "n/a" if out.test_psnr is None else f"{out.test_psnr:.2f} dB"
    typer.echo(f"{out.steps} steps in {out.seconds:.1f} s, test PSNR {psnr} -> {out.run_dir}")


# ---------------------------------------------------------------------------------------------- render
RenderPath = _choices("RenderPath", Literal["auto", "turntable", "spiral", "test", "train"])


@app.command()
def render(
    run_dir: Annotated[Path, typer.Argument(help="A trained run directory.")],
    out: Annotated[Path, typer.Argument(help="Output video (.mp4, H.264).")],
    path: Annotated[RenderPath, typer.Option(help="auto: spiral if forward-facing, else turntable.")] = "auto",
    frames: Annotated[int, typer.Option(help="Frames for turntable/spiral.")] = 120,
    fps: Annotated[float, typer.Option(help="Frames per second.")] = 30.0,
    downscale: Annotated[float, typer.Option(help="Divide the training image size by this.")] = 1.0,
    elevation: Annotated[float | None, typer.Option(help="Turntable elevation in degrees (default: cameras').")] = None,
    radius: Annotated[float | None, typer.Option(help="Orbit radius in your units (default: cameras').")] = None,
    outputs: Annotated[str, typer.Option(help="Panels side by side: rgb,depth,accumulation.")] = "rgb",
    frames_dir: Annotated[Path | None, typer.Option(help="Also write PNG frames here.")] = None,
    device: DeviceOpt = "auto",
) -> None:
    """Render a turntable, spiral or dataset-camera video of a trained run."""
    from stages import render as stage

    out_ = stage.run(
        stage.Config(
            run_dir=run_dir,
            out=out,
            path=RenderPath(path).value,
            frames=frames,
            fps=fps,
            downscale=downscale,
            elevation=elevation,
            radius=radius,
            outputs=stage.parse_outputs(outputs),
            frames_dir=frames_dir,
            device=Device(device).value,
        )  # fmt: skip
    )
    typer.echo(f"{out_.n_frames} frames {out_.size[0]}x{out_.size[1]} -> {out_.video}")


# ---------------------------------------------------------------------------------------------- depth
DepthViews = _choices("DepthViews", Literal["test", "train", "turntable"])
DepthKind = _choices("DepthKind", Literal["expected", "median"])


@app.command()
def depth(
    run_dir: Annotated[Path, typer.Argument(help="A trained run directory.")],
    out_dir: Annotated[Path, typer.Argument(help="Output folder for depth maps.")],
    views: Annotated[DepthViews, typer.Option(help="Which cameras.")] = "test",
    kind: Annotated[DepthKind, typer.Option(help="Expected or median ray-termination depth.")] = "expected",
    frames: Annotated[int, typer.Option(help="Frames for --views turntable.")] = 120,
    downscale: Annotated[float, typer.Option(help="Divide the image size by this.")] = 1.0,
    video: Annotated[bool, typer.Option(help="Also write depth.mp4.")] = False,
    device: DeviceOpt = "auto",
) -> None:
    """Depth maps in your units (.npy), 16-bit millimetre PNGs, coloured previews and opacity."""
    from stages import depth as stage

    out = stage.run(
        stage.Config(
            run_dir=run_dir,
            out_dir=out_dir,
            views=DepthViews(views).value,
            kind=DepthKind(kind).value,
            frames=frames,
            downscale=downscale,
            video=video,
            device=Device(device).value,
        )  # fmt: skip
    )
    lo, hi = out.depth_range
    typer.echo(f"{len(out.names)} depth maps (range {lo:.3g}..{hi:.3g}) -> {out.out_dir}")


# ---------------------------------------------------------------------------------------------- eval
@app.command(name="eval")
def eval_(
    run_dir: Annotated[Path, typer.Argument(help="A trained run directory.")],
    out: Annotated[Path, typer.Argument(help="Output JSON.")],
    ground_truth: Annotated[Path | None, typer.Option(help="A synthetic scene's ground_truth/ folder.")] = None,
    device: DeviceOpt = "auto",
) -> None:
    """PSNR, SSIM, render speed (and depth error with ground truth) on the test views, to JSON."""
    from stages import eval as stage

    res = stage.run(stage.Config(run_dir=run_dir, out=out, ground_truth=ground_truth, device=Device(device).value))
    r = res.result
    typer.echo(f"PSNR {r.get('psnr')}  SSIM {r.get('ssim')}  -> {res.out}")


# ---------------------------------------------------------------------------------------------- report
@app.command()
def report(
    runs_and_out: Annotated[list[Path], typer.Argument(help="RUN_DIR... OUT_DIR")],
    levels: Annotated[str, typer.Option(help="PSNR levels (dB) for time-to-reach, comma-separated.")] = "20,25,30",
) -> None:
    """Compare runs: held-out PSNR against wall-clock seconds (PNG) and a table (markdown + CSV)."""
    from stages import report as stage

    if len(runs_and_out) < 2:
        raise UserError("report: expected at least one RUN_DIR and an OUT_DIR")
    try:
        lv = tuple(float(v) for v in levels.split(",") if v.strip())
    except ValueError:
        raise UserError(f"--levels: expected comma-separated numbers, got {levels!r}") from None
    out = stage.run(stage.Config(runs=tuple(runs_and_out[:-1]), out_dir=runs_and_out[-1], levels=lv))
    typer.echo(f"report -> {out.markdown}, {out.plot}")


# ---------------------------------------------------------------------------------------------- mesh
MeshFrame = _choices("MeshFrame", Literal["user", "normalized"])


@app.command()
def mesh(
    run_dir: Annotated[Path, typer.Argument(help="A trained run directory.")],
    out: Annotated[Path, typer.Argument(help="Output mesh: .ply, .obj or .glb.")],
    resolution: Annotated[int, typer.Option(help="Grid cells along the box's longest side.")] = 256,
    threshold: Annotated[str, typer.Option(help="Density iso-level, or auto (from training rays).")] = "auto",
    bbox: Annotated[str, typer.Option(help="auto, or x0,y0,z0,x1,y1,z1 in the chosen frame.")] = "auto",
    frame: Annotated[MeshFrame, typer.Option(help="user: your source frame and units; normalized: training.")] = (
        "user"
    ),
    target_faces: Annotated[int | None, typer.Option(help="Decimate to about this many faces.")] = None,
    cleanup: Annotated[bool, typer.Option(help="Remove floaters, repair, smooth (pymeshlab).")] = True,
    colors: Annotated[bool, typer.Option(help="Vertex colours from the field.")] = True,
    device: DeviceOpt = "auto",
) -> None:
    """Mesh the density field: marching cubes, cleanup, colours, exported in your coordinates."""
    from stages import mesh as stage

    kwargs = {} if cleanup else {"cleanup": None}
    out_ = stage.run(
        stage.Config(
            run_dir=run_dir,
            out=out,
            resolution=resolution,
            threshold=stage.parse_threshold(threshold),
            bbox=stage.parse_bbox(bbox),
            frame=MeshFrame(frame).value,
            target_faces=target_faces,
            colors=colors,
            device=Device(device).value,
            **kwargs,
        )  # fmt: skip
    )
    typer.echo(
        f"{out_.vertices} vertices, {out_.faces} faces (level {out_.threshold:.4g}, watertight {out_.watertight}) "
        f"-> {out_.mesh}"
    )


# ---------------------------------------------------------------------------------------------- entry
def _one_line(text: str) -> str:
    lines = [ln.strip() for ln in str(text).strip().splitlines() if ln.strip()]
    return lines[0] if lines else ""


def main(argv: list[str] | None = None) -> None:
    """Console entry point: runs the app and turns errors into one line and an exit code."""
    args = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in args
    try:
        app(args=args, prog_name="nerfpipe")  # standalone: --help, usage errors and typer.Exit end here
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        sys.exit(130)
    except UserError as e:
        if debug:
            raise
        print(f"error: {_one_line(str(e))}", file=sys.stderr)
        sys.exit(2)
    except Exception as e:  # noqa: BLE001 - the CLI boundary: one line, traceback only with --debug
        if debug:
            raise
        print(f"error: {type(e).__name__}: {_one_line(str(e))} (rerun with --debug for details)", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":  # `python cli.py ...` works as well as the `nerfpipe` console script
    main()
