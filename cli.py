"""nerfpipe command line: one typer command per stage. Commands only build a stage's Config and call `run`.

Errors: a user error (`data.errors.UserError`) prints one line `error: ...` and exits 2; any other failure
prints one line and exits 1; `nerfpipe --debug ...` shows the traceback instead.
"""

from __future__ import annotations

import sys
from enum import Enum
from pathlib import Path
from typing import Annotated

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


# ---------------------------------------------------------------------------------------------- scene
class SceneKind(str, Enum):
    photos = "photos"
    posed = "posed"
    rgba = "rgba"


@app.command()
def scene(
    out_dir: Annotated[Path, typer.Argument(help="Folder to write the synthetic scene into.")],
    kind: Annotated[SceneKind, typer.Option(help="photos: bare images; posed/rgba: with transforms.json.")] = (
        SceneKind.posed
    ),
    size: Annotated[int, typer.Option(help="Image width and height in pixels.")] = 64,
    views: Annotated[int, typer.Option(help="Number of camera views.")] = 24,
    seed: Annotated[int, typer.Option(help="Random seed (the scene is deterministic for a seed).")] = 0,
) -> None:
    """Generate a procedural, textured scene with exact cameras, depth and surface mesh."""
    from stages import scene as stage

    out = stage.run(stage.Config(out_dir=out_dir, kind=kind.value, size=size, views=views, seed=seed))
    typer.echo(f"scene written to {out_dir} ({out})")


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
