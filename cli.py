"""nerfpipe command line: one command per stage, generated from the stage's `Config`.

Each command is one line in `STAGES` (module, one-line help, optional summary of the outputs). Its arguments
and options are read from the stage's frozen `Config` dataclass, so a default, a choice or a help text is
written once, in the Config:
- required fields (no default) are positional arguments, in declaration order; a required `tuple[X, ...]`
  is variadic (report: `RUN_DIR... OUT_DIR`);
- every other field is an option with the field's default; help is the first sentence of the field's
  docstring (read with `ast` from the class source);
- `Literal[...]` -> a choice; `bool` -> `--x/--no-x`; `X | None` -> optional (default None);
  `tuple[int, ...]`, `tuple[float, float]`, ... -> comma-separated text (`--downscales 2,4,8`);
  `D | None` with D a dataclass and a non-None default -> `--x/--no-x` (`--no-x` passes None: mesh cleanup);
- the few fields a rule cannot read from text use the stage's own parser (`PARSERS`);
- an options group nested in the Config and named in `GROUPS` (train's `fast` and `refine`) is spelt flat: its
  fields are options in its place, and the group is built back from them;
- anything else (callables, nested dataclasses) has no option and keeps its Config default.

Lazy commands (decision): importing a stage imports torch (seconds), so `nerfpipe --help` must not import any.
`_StageGroup` is a TyperGroup whose command table is a lazy mapping: a command is built (its stage module
imported, its Config read) only when it is invoked or asked for `--help`; the top-level listing uses the help
line in `STAGES`. Reading the Config with `ast` from its source instead would make `nerfpipe CMD --help` fast
too, but it means a second, partial evaluator of defaults (`1 << 18`, `field(default_factory=Cleanup)`) and
annotations that can drift from the class; importing the real class cannot.

Progress: the CLI owns the one live display, a `rich.progress.Progress(transient=True)` on stderr, created only
when stderr is a terminal (logs, pipes and tests get `progress=None`, i.e. silent stages); it is passed as
`progress=` to every stage `run` whose signature has that parameter.

Errors: a user error (`data.errors.UserError`: bad input, a full disk, a busy folder) prints one line `error: ...`
and exits 2 (a stage stopped cleanly by SIGINT/SIGTERM: `data.errors.Interrupted`, 130/143); any other failure
prints one line and exits 1; Ctrl-C prints one line and exits 130; `nerfpipe --debug ...` re-raises (traceback).
Usage errors (bad option, bad choice, missing argument) are typer's own `Error:` lines, exit 2.

Signals: for the whole command SIGTERM raises `data.stop.Terminated` (a KeyboardInterrupt) wherever the stage is,
so a stage stopped by a scheduler or `kill` unwinds as on Ctrl-C (no file that looks complete) and prints
`error: interrupted (SIGTERM)`, exit 143; train and xray-train keep their own handling (`data.stop.stop_on_signals`
replaces this handler inside their loop: they save a checkpoint first). Once the stage is imported the CLI takes
SIGTERM back (`data.stop.reclaim_sigterm`): importing pycolmap puts glog's stack-trace handler in its place.

Last guard (decision): RecursionError and MemoryError print one line and exit 2, as bad input. Readers that can
catch them at the source do (`data.camera_path`); but JSON is parsed in a dozen places (model/, data/transforms,
data/projections, the importers) and checkpoints are unpickled by torch, and a file nested 200000 deep makes any
of them raise RecursionError, a huge declared size MemoryError. A bug that recurses forever reads the same:
`--debug` shows the traceback.
"""

from __future__ import annotations

import ast
import contextlib
import copy
import dataclasses
import functools
import importlib
import inspect
import os
import re
import sys
import textwrap
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, get_args, get_origin

import typer
from typer.core import TyperCommand, TyperGroup

from nerfpipe.data.cpu_load import wait_policy
from nerfpipe.data.errors import UserError
from nerfpipe.data.stop import Terminated, reclaim_sigterm, sigterm_raises

__all__ = ["GROUPS", "PARSERS", "STAGES", "Group", "Stage", "app", "config_from_args", "main", "skipped_fields"]


# ---------------------------------------------------------------------------------------------- summaries
def _pretrain(out: Any) -> str:
    return f"{out.steps} steps in {out.seconds:.1f} s, loss {out.loss_start:.4g} -> {out.loss_end:.4g} -> {out.weights}"


def _shapes(out: Any) -> str:
    return f"{out.examples} photos with their occupancy in {out.seconds:.1f} s -> {out.shapes}"


def _voxels(out: Any) -> str:
    return f"{out.photos} photo(s) -> {out.occupancy}, {out.mesh} ({out.occupied} cells >= {out.level})"


def _scene(out: Any) -> str:
    if out.scenes:
        return f"{len(out.scenes)} scenes of {len(out.images)} images, ground truth and manifests -> {out.out_dir}"
    return f"{len(out.images)} images, ground truth and manifest -> {out.out_dir}"


def _poses(out: Any) -> str:
    return (
        f"{out.registered}/{out.total} images registered, mean reprojection error "
        f"{out.mean_reprojection_error:.2f} px -> {out.sparse}"
    )


def _convert(out: Any) -> str:
    return f"{out.num_frames} frames ({out.kind}) -> {out.transforms}; splits {out.splits}"


def _train(out: Any) -> str:
    psnr = "n/a" if out.test_psnr is None else f"{out.test_psnr:.2f} dB ({out.test_scored})"
    return f"{out.steps} steps in {out.seconds:.1f} s, test PSNR {psnr} -> {out.run_dir}"


def _render(out: Any) -> str:
    return f"{out.n_frames} frames {out.size[0]}x{out.size[1]} -> {out.video}"


def _depth(out: Any) -> str:
    lo, hi = out.depth_range
    return f"{len(out.names)} depth maps (range {lo:.3g}..{hi:.3g}) -> {out.out_dir}"


def _eval(out: Any) -> str:
    return f"PSNR {out.result.get('psnr')}  SSIM {out.result.get('ssim')}  -> {out.out}"


def _report(out: Any) -> str:
    return f"report -> {out.markdown}, {out.plot}"


def _mesh(out: Any) -> str:
    how = f"level {out.threshold:.4g}" if out.threshold is not None else "poisson"  # method poisson: no level
    return f"{out.vertices} vertices, {out.faces} faces ({how}, watertight {out.watertight}) -> {out.mesh}"


def _export_points(out: Any) -> str:
    return f"{out.points} points ({out.outliers} outliers removed) from {out.rays} rays -> {out.out}"


def _fit_image(out: Any) -> str:
    scores = ", ".join(f"{m.label} {m.psnr:.1f} dB in {m.seconds:.0f} s" for m in out.models)
    return f"{scores} -> {out.montage}"


def _xray(out: Any) -> str:
    """The X-ray stages' success line: their headline figures, then the main output."""
    if hasattr(out, "max_line_integral"):  # xray-simulate
        return f"{out.n_views} training views on a {out.detector[0]}x{out.detector[1]} detector -> {out.scene}"
    if hasattr(out, "steps"):  # xray-train
        figs = f"3-D PSNR {out.psnr_3d:.2f} dB, SSIM {out.ssim_3d:.3f}" if out.psnr_3d is not None else "no GT"
        return f"{out.steps} steps in {out.seconds:.1f} s, {figs} -> {out.run_dir}"
    if hasattr(out, "result"):  # xray-eval
        r = out.result
        fdk = r.get("fdk", {}).get("psnr_3d")
        return f"PSNR 3-D {r.get('psnr_3d')}  SSIM 3-D {r.get('ssim_3d')}  FDK PSNR 3-D {fdk} -> {out.out}"
    return _done(out)


def _splat(out: Any) -> str:
    return (
        f"{out.gaussians} Gaussians, {out.steps} steps in {out.seconds:.1f} s ({out.backend}), training PSNR "
        f"{out.psnr_init:.2f} -> {out.psnr_final:.2f} dB -> {out.out}"
    )


def _view(out: Any) -> str:
    return f"viewer ({out.kind}) at {out.url} stopped"


def _done(out: Any) -> str:
    """Summary for a stage without its own: the first path among its outputs."""
    values = [getattr(out, f.name) for f in dataclasses.fields(out)] if dataclasses.is_dataclass(out) else []
    paths = [v for v in values if isinstance(v, Path)]
    return f"done -> {paths[0]}" if paths else "done"


# ---------------------------------------------------------------------------------------------- registry
@dataclasses.dataclass(frozen=True)
class Stage:
    """One command: the stage module (with `Config` and `run`), its one-line help, the success line."""

    module: str
    help: str
    summary: Callable[[Any], str] = _done


S = "nerfpipe.stages."
"""Where the stages live (a stage registered from elsewhere names its own module)."""
STAGES: dict[str, Stage] = {
    "scene": Stage(S + "scene", "A procedural textured scene with exact cameras, depth and mesh.", _scene),
    "poses": Stage(S + "poses", "Camera poses with COLMAP (pycolmap): features, matching, mapping.", _poses),
    "convert": Stage(S + "convert", "Convert a posed source into SCENE_DIR/transforms.json.", _convert),
    "train": Stage(S + "train", "Train a radiance field; logs held-out PSNR against wall-clock time.", _train),
    "render": Stage(S + "render", "Render a turntable, spiral or dataset-camera video of a run.", _render),
    "depth": Stage(S + "depth", "Depth maps in your units (.npy, 16-bit mm PNG), previews, opacity.", _depth),
    "eval": Stage(S + "eval", "PSNR, SSIM, render speed (and depth error) on test views, to JSON.", _eval),
    "report": Stage(S + "report", "Compare runs: held-out PSNR against wall-clock time, and a table.", _report),
    "mesh": Stage(S + "mesh", "Mesh the density field: marching cubes, cleanup, vertex colours.", _mesh),
    "export-points": Stage(S + "export_points", "Coloured point cloud with normals (PLY) from a run.", _export_points),
    "fit-image": Stage(S + "fit_image", "Fit one image with Fourier-feature MLPs and the fast grid.", _fit_image),
    "xray-simulate": Stage(S + "xray_simulate", "X-ray projections of a CT volume -> a projection scene.", _xray),
    "xray-train": Stage(S + "xray_train", "Fit an attenuation field to X-ray projections; 3-D PSNR vs time.", _xray),
    "xray-eval": Stage(S + "xray_eval", "3-D PSNR/SSIM, projection PSNR/SSIM, FDK baseline, to JSON.", _xray),
    "view": Stage(S + "view", "Browse a scene or a run in the browser (viser); record camera paths.", _view),
    "splat": Stage(S + "splat", "Gaussian splats from a run, optimised on its photos -> INRIA .ply / .splat.", _splat),
    "pretrain-gnt": Stage(
        S + "pretrain_gnt",
        "Train GNT across a folder of scenes (the weights train --method gnt --init uses).",
        _pretrain,
    ),
    "shapes": Stage(
        S + "shapes", "Photos of generated shapes with their exact occupancy (pretrain-voxels' data).", _shapes
    ),
    "pretrain-voxels": Stage(
        S + "pretrain_voxels", "Train the single-view voxel network on a shapes dataset.", _pretrain
    ),
    "voxels": Stage(
        S + "voxels", "One or more photos of an object (with masks) -> a 32^3 occupancy grid, a mesh.", _voxels
    ),
    "xray-export": Stage(S + "xray_export", "Slice montages, a rotating DRR/MIP video and an iso-surface mesh."),
}

# (command, field) -> name of the stage module's `parse(text)` for fields no rule reads from text.
PARSERS: dict[tuple[str, str], tuple[str, str]] = {
    ("render", "outputs"): ("parse_outputs", "<name,...>"),
    ("render", "path"): ("parse_path", "<name|FILE.json>"),
    ("mesh", "threshold"): ("parse_threshold", "<auto|global|float>"),
    ("mesh", "bbox"): ("parse_bbox", "<auto|x0,y0,z0,x1,y1,z1>"),
    ("xray-export", "iso"): ("parse_iso", "<auto|float>"),
}


@dataclasses.dataclass(frozen=True)
class Group:
    """How an options dataclass nested in a stage's Config is spelt on the command line: each of its fields is an
    option in the group's place, named as the field (or as `names` says). With `switch`, the group is `X | None =
    None`: `--switch` (helped by the group field's docstring) builds it from its options, without it the group
    is None and giving one of its options is an error."""

    switch: str | None = None
    names: Mapping[str, str] = dataclasses.field(default_factory=dict)


# (command, Config field) -> how the options group in that field is spelt: train's flags stay flat (`--resolution`,
# `--refine-poses --refine-focal --camera-lr`) while its Config groups them by mode (`stages.train.config`).
GROUPS: dict[tuple[str, str], Group] = {
    ("train", "refine"): Group(switch="refine_poses", names={"focal": "refine_focal"}),
}
METHOD_GROUPS: dict[tuple[str, str], str] = {("train", "options"): "method"}
"""(command, Config field holding a method's options) -> the Config field naming the method. Every registered
method's options (`model.methods`: each `Method.Options`) are spelt flat in the group's place, one option per name
(two methods' options of one name share it; their types must agree); each defaults to None, "not given", so that
only the options given build the chosen method's group, and an option of another method is refused in one line."""


# ---------------------------------------------------------------------------------------------- Config -> params
_KEEP = object()  # a converted value meaning "leave the Config default"
_SCALARS = (int, float, str, bool, Path)
_NOUNS = {int: "integers", float: "numbers", str: "names", Path: "paths"}


@dataclasses.dataclass(frozen=True)
class _Param:
    """One typer parameter made from one Config field, and how its value becomes the field's."""

    name: str
    annotation: Any  # Annotated[type, typer.Option(...) | typer.Argument(...)]
    default: Any = inspect.Parameter.empty
    to_config: Callable[[Any], Any] = lambda value: value

    def parameter(self) -> inspect.Parameter:
        return inspect.Parameter(
            self.name, inspect.Parameter.KEYWORD_ONLY, default=self.default, annotation=self.annotation
        )


def _field_docs(cls: type) -> dict[str, str]:
    """Field name -> the docstring literal under it, read from the class source."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    body = tree.body[0].body
    docs = {}
    for node, doc in zip(body, body[1:], strict=False):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(doc, ast.Expr)
            and isinstance(doc.value, ast.Constant)
            and isinstance(doc.value.value, str)
        ):
            docs[node.target.id] = doc.value.value
    return docs


def _first_sentence(doc: str) -> str:
    """Up to the first '. ' outside parentheses (not after 'e.g'/'i.e'), whitespace collapsed."""
    text = " ".join(doc.split())
    depth = 0
    for i, ch in enumerate(text):
        depth += (ch == "(") - (ch == ")")
        if (
            ch == "."
            and depth == 0
            and text[i + 1 : i + 2] in ("", " ")
            and text[max(0, i - 3) : i] not in ("e.g", "i.e")
        ):
            return text[: i + 1]
    return text


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _unwrap_optional(hint: Any) -> tuple[Any, bool]:
    """`X | None` -> (X, True); other hints -> (hint, False)."""
    if get_origin(hint) in (typing.Union, types.UnionType):
        args = get_args(hint)
        rest = tuple(a for a in args if a is not type(None))
        if len(rest) < len(args):
            return (rest[0] if len(rest) == 1 else typing.Union[rest]), True  # noqa: UP007 - built at run time
    return hint, False


def _is_choice(hint: Any) -> bool:
    return get_origin(hint) is Literal


def _tuple_parser(hint: Any) -> tuple[Callable[[str], tuple], str] | None:
    """`tuple[T, ...]` or `tuple[T1, T2]` of scalars -> (parse comma-separated text, metavar); else None."""
    if get_origin(hint) is not tuple:
        return None
    args = get_args(hint)
    variadic = len(args) == 2 and args[1] is Ellipsis
    kinds = args[:1] if variadic else args
    if not kinds or not all(k in _NOUNS for k in kinds):
        return None
    noun = _NOUNS[kinds[0]] if len(set(kinds)) == 1 else "values"

    def parse(text: str) -> tuple:
        items = [s.strip() for s in text.split(",") if s.strip()]
        if not variadic and len(items) != len(kinds):
            raise typer.BadParameter(f"expected {len(kinds)} comma-separated {noun}, got {text!r}")
        try:
            return tuple(kind(s) for kind, s in zip(kinds * len(items) if variadic else kinds, items, strict=True))
        except ValueError:
            raise typer.BadParameter(f"expected comma-separated {noun}, got {text!r}") from None

    names = [k.__name__.lower() for k in kinds]
    return parse, "<" + (f"{names[0]},..." if variadic else ",".join(names)) + ">"


def _as_text(value: Any) -> Any:
    """A tuple default as the text one would type (`2,4,8`); other values unchanged."""
    return ",".join(str(v) for v in value) if isinstance(value, tuple) else value


def _usage_errors(parse: Callable[[str], Any]) -> Callable[[str], Any]:
    """A stage parser whose ValueError becomes typer's usage error with the parser's own message (click would
    otherwise drop the message and print only the value)."""

    def wrapped(text: str) -> Any:
        try:
            return parse(text)
        except ValueError as exc:
            raise typer.BadParameter(str(exc)) from None

    return wrapped


def _param(command: str, module: types.ModuleType, f: dataclasses.Field, hint: Any, doc: str) -> _Param | None:
    """The typer parameter for one Config field, or None for a field with no command-line form."""
    help_ = _first_sentence(doc)
    default = _default(f)
    base, optional = _unwrap_optional(hint)
    if default is dataclasses.MISSING:  # a positional argument
        if get_origin(base) is tuple and len(get_args(base)) == 2 and get_args(base)[1] is Ellipsis:
            return _Param(f.name, Annotated[list[get_args(base)[0]], typer.Argument(help=help_)], to_config=tuple)
        return _Param(f.name, Annotated[base, typer.Argument(help=help_)])
    if (command, f.name) in PARSERS:
        parser, metavar = PARSERS[command, f.name]
        option = typer.Option(help=help_, parser=_usage_errors(getattr(module, parser)), metavar=metavar)
        return _Param(f.name, Annotated[str | None, option], _as_text(default))
    if optional and dataclasses.is_dataclass(base) and default is not None:  # a nested config: on (default) / off
        return _Param(f.name, Annotated[bool, typer.Option(help=help_)], True, lambda on: _KEEP if on else None)
    if tuple_parser := _tuple_parser(base):
        parse, metavar = tuple_parser
        option = typer.Option(help=help_, parser=parse, metavar=metavar)
        return _Param(f.name, Annotated[str | None if optional else str, option], _as_text(default))
    if base in _SCALARS or _is_choice(base):
        return _Param(f.name, Annotated[base | None if optional else base, typer.Option(help=help_)], default)
    return None  # callables, nested dataclasses, unions: not settable from the command line


@functools.cache
def _stage_params(command: str) -> tuple[types.ModuleType, tuple[_Param, ...]]:
    """Import the stage and turn its Config fields into typer parameters (once per process)."""
    module = importlib.import_module(STAGES[command].module)
    config_cls = module.Config
    hints, docs = typing.get_type_hints(config_cls), _field_docs(config_cls)
    params = []
    for f in dataclasses.fields(config_cls):
        if (command, f.name) in METHOD_GROUPS:
            params += _method_params(command, module)
        elif (command, f.name) in GROUPS:
            params += _group_params(command, module, f, hints[f.name], docs.get(f.name, ""))
        elif f.init and (p := _param(command, module, f, hints[f.name], docs.get(f.name, ""))) is not None:
            params.append(p)
    return module, tuple(params)


def _group_params(command: str, module: types.ModuleType, f: dataclasses.Field, hint: Any, doc: str) -> list[_Param]:
    """The options of a group in `GROUPS`: its switch (if any), then one per field of the group's dataclass."""
    group, (cls, _) = GROUPS[command, f.name], _unwrap_optional(hint)
    hints, docs = typing.get_type_hints(cls), _field_docs(cls)
    params = []
    if group.switch is not None:
        params.append(_Param(group.switch, Annotated[bool, typer.Option(help=_first_sentence(doc))], False))
    for g in dataclasses.fields(cls):
        if (p := _param(command, module, g, hints[g.name], docs.get(g.name, ""))) is not None:
            params.append(dataclasses.replace(p, name=group.names.get(g.name, g.name)))
    return params


def _method_params(command: str, module: types.ModuleType) -> list[_Param]:
    """One option per name over every method's options group (`METHOD_GROUPS`), default None; its help says which
    methods have it and their defaults."""
    from nerfpipe.model.methods import methods

    found: dict[str, tuple[_Param, Any, list[str]]] = {}
    for method in methods():
        hints, docs = typing.get_type_hints(method.Options), _field_docs(method.Options)
        for g in dataclasses.fields(method.Options):
            base, _ = _unwrap_optional(hints[g.name])
            blank = copy.copy(g)  # the same field, "not given" by default
            blank.default, blank.default_factory = None, dataclasses.MISSING
            param = _param(command, module, blank, base | None, docs.get(g.name, ""))
            if param is None:
                continue
            default = _default(g)
            shown = f"{method.name}: {_as_text(default) if default is not None else 'automatic'}"
            if g.name in found:
                first, hint, owners = found[g.name]
                if hint != base:
                    raise TypeError(f"option {g.name}: methods {owners[0]} and {method.name} give it different types")
                owners.append(shown)
            else:
                found[g.name] = (param, base, [shown])
    params = []
    for param, _, owners in found.values():
        base, option = get_args(param.annotation)[:2]
        option.help = f"{option.help} [{'; '.join(owners)}]"
        params.append(param)
    return params


def skipped_fields(command: str) -> list[str]:
    """Config fields of `command` with no option or argument (they keep their Config default)."""
    module, params = _stage_params(command)
    return sorted({f.name for f in dataclasses.fields(module.Config) if f.init} - {p.name for p in params})


def _make_config(command: str, values: Mapping[str, Any]) -> Any:
    module, params = _stage_params(command)
    kwargs = {p.name: p.to_config(values[p.name]) for p in params}
    kwargs = {k: v for k, v in kwargs.items() if v is not _KEEP}
    hints = typing.get_type_hints(module.Config)
    for (cmd, name), group in GROUPS.items():
        if cmd == command:
            kwargs[name] = _make_group(group, _unwrap_optional(hints[name])[0], kwargs)
    for (cmd, name), chooser in METHOD_GROUPS.items():
        if cmd == command:
            kwargs[name] = _method_group(kwargs, chooser, _method_params(command, module))
    return module.Config(**kwargs)


def _method_group(kwargs: dict[str, Any], chooser: str, params: list[_Param]) -> Any:
    """The chosen method's options from the method options given (taken out of kwargs); None when none was given
    (the method's defaults); UserError naming an option the chosen method does not have."""
    from nerfpipe.model.methods import DEFAULT, method_named

    given = {p.name: kwargs.pop(p.name) for p in params if p.name in kwargs}
    given = {k: v for k, v in given.items() if v is not None}
    method = method_named(kwargs.get(chooser) or DEFAULT)
    own = {f.name for f in dataclasses.fields(method.Options)}
    foreign = [n for n in given if n not in own]
    if foreign:
        flags = ", ".join(f"--{n.replace('_', '-')}" for n in foreign)
        raise UserError(f"{flags}: not an option of method {method.name} (its options: train --method {method.name})")
    return method.Options(**given) if given else None


def _make_group(group: Group, cls: type, kwargs: dict[str, Any]) -> Any:
    """The group's dataclass from its options (taken out of kwargs); None when its switch is off, UserError when
    one of its options was given then."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    values = {n: kwargs.pop(group.names.get(n, n)) for n in fields if group.names.get(n, n) in kwargs}
    if group.switch is None or kwargs.pop(group.switch):
        return cls(**values)
    given = [group.names.get(n, n) for n, v in values.items() if v != _default(fields[n])]
    if given:
        flags = ", ".join(f"--{n.replace('_', '-')}" for n in given)
        raise UserError(f"{flags} {'needs' if len(given) == 1 else 'need'} --{group.switch.replace('_', '-')}")
    return None


# ---------------------------------------------------------------------------------------------- running a stage
@contextlib.contextmanager
def _progress() -> Iterator[Any]:
    """The one live progress display, on stderr; None (silent stages) when stderr is not a terminal."""
    if not sys.stderr.isatty():
        yield None
        return
    from rich.console import Console
    from rich.progress import Progress, TimeElapsedColumn

    with Progress(
        *Progress.get_default_columns(), TimeElapsedColumn(), console=Console(stderr=True), transient=True
    ) as p:
        yield p


def _run_stage(command: str, values: Mapping[str, Any]) -> None:
    module, _ = _stage_params(command)
    reclaim_sigterm()  # importing the stage may have put a C handler in its place (pycolmap's glog)
    config = _make_config(command, values)
    takes_progress = "progress" in inspect.signature(module.run).parameters
    with _progress() as progress:
        out = module.run(config, **({"progress": progress} if takes_progress else {}))
    if os.environ.get("RANK", "0") == "0":  # under torchrun only rank 0 reports (every rank returns the outputs)
        typer.echo(STAGES[command].summary(out))
    for line in _suspect_lines(command, out):
        typer.echo(line, err=True)


def _suspect_lines(command: str, out: Any) -> list[str]:
    """One line per failed self-check (`data.checks`) in the manifest or report the stage wrote, if any."""
    from nerfpipe.data.checks import read_failed

    lines = []
    for name in ("manifest", "report"):
        path = getattr(out, name, None)
        if isinstance(path, Path) and path.suffix == ".json" and path.is_file():
            with contextlib.suppress(OSError, ValueError, KeyError, TypeError, AttributeError):
                lines += [f"suspect: {line}" for line in read_failed(command, path, path.name)[0]]
    return lines


@functools.cache
def _command(command: str) -> TyperCommand:
    """The typer command for a stage: a callback whose signature is made from the Config."""
    _, params = _stage_params(command)

    def callback(**values: Any) -> None:
        _run_stage(command, values)

    callback.__signature__ = inspect.Signature([p.parameter() for p in params])  # what typer reads
    single = typer.Typer(add_completion=False, rich_markup_mode=None, pretty_exceptions_enable=False)
    single.command(name=command, help=STAGES[command].help)(callback)
    return typer.main.get_command(single)


def config_from_args(command: str, args: list[str]) -> Any:
    """The stage Config that `nerfpipe COMMAND ARGS...` would run with (parsing errors raise)."""
    ctx = _command(command).make_context(command, list(args))
    return _make_config(command, ctx.params)


# ---------------------------------------------------------------------------------------------- the app
class _LazyCommands(Mapping[str, TyperCommand]):
    """STAGES as a command table: a command is built on first lookup."""

    def __getitem__(self, name: str) -> TyperCommand:
        if name not in STAGES:
            raise KeyError(name)
        return _command(name)

    def __iter__(self) -> Iterator[str]:
        return iter(STAGES)

    def __len__(self) -> int:
        return len(STAGES)


class _Interrupted(Exception):
    """Ctrl-C inside a command, carried past typer (which would turn it into a silent exit 130)."""


class _StageGroup(TyperGroup):
    """The top-level group: commands from STAGES, imported only when used."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.commands = _LazyCommands()

    def list_commands(self, ctx: Any) -> list[str]:
        return list(STAGES)

    def format_commands(self, ctx: Any, formatter: Any) -> None:
        with formatter.section("Commands"):  # from STAGES: listing the commands imports no stage
            formatter.write_dl([(name, stage.help) for name, stage in STAGES.items()])

    def invoke(self, ctx: Any) -> Any:
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as e:
            raise _Interrupted() from e


app = typer.Typer(
    name="nerfpipe",
    cls=_StageGroup,
    help="Photos, video or posed datasets -> camera poses, a radiance field, turntable videos, depth maps, meshes.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)
_debug = False  # --debug, set while the arguments are parsed (before a stage is imported); read by main()


def _debug_callback(value: bool) -> None:
    global _debug
    _debug = value


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
    debug: Annotated[
        bool, typer.Option("--debug", callback=_debug_callback, is_eager=True, help="Show Python tracebacks on errors.")
    ] = False,
) -> None:
    """nerfpipe: each command is one stage; stages talk only through files."""


def _one_line(text: str) -> str:
    lines = [ln.strip() for ln in str(text).strip().splitlines() if ln.strip()]
    return lines[0] if lines else ""


_SWITCH = re.compile(r"(?<![\w.-])([a-z][a-z0-9_]*)=True\b")


def _as_flags(text: str) -> str:
    """A library message's switches in the CLI's words: "set resume=True" -> "set --resume" (the library names
    config fields; flags belong here)."""
    return _SWITCH.sub(lambda m: "--" + m.group(1).replace("_", "-"), text)


def main(argv: list[str] | None = None) -> None:
    """Console entry point: runs the app and turns errors into one line and an exit code."""
    global _debug
    _debug = False
    args = list(sys.argv[1:] if argv is None else argv)
    if args and not args[0].startswith("-") and "--help" not in args:  # a stage will run: before torch loads
        wait_policy(os.environ, torch_loaded="torch" in sys.modules)  # data.cpu_load: busy CPU -> passive waits
    try:
        with sigterm_raises():  # SIGTERM -> Terminated (a KeyboardInterrupt) -> _Interrupted, below
            app(args=args, prog_name="nerfpipe")  # usage errors end here
    except _Interrupted as e:
        if _debug:
            raise e.__cause__ from None
        term = isinstance(e.__cause__, Terminated)
        print(f"error: interrupted{' (SIGTERM)' if term else ''}", file=sys.stderr)
        sys.exit(128 + Terminated.signum if term else 130)
    except UserError as e:
        if _debug:
            raise
        print(f"error: {_as_flags(_one_line(str(e)))}", file=sys.stderr)
        sys.exit(e.exit_code)  # 2; 130/143 for a stage stopped cleanly by SIGINT/SIGTERM (data.errors.Interrupted)
    except (RecursionError, MemoryError) as e:  # the last guard (module doc): a reader's input, exit 2
        if _debug:
            raise
        what = (
            f"an input is nested too deeply to read ({_one_line(str(e))})"
            if isinstance(e, RecursionError)
            else "out of memory (an input or an option asks for more than this machine has)"
        )
        print(f"error: {what}; rerun with --debug for details", file=sys.stderr)
        sys.exit(2)
    except Exception as e:  # noqa: BLE001 - the CLI boundary: one line, traceback only with --debug
        if _debug:
            raise
        print(f"error: {type(e).__name__}: {_one_line(str(e))} (rerun with --debug for details)", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":  # `python cli.py ...` works as well as the `nerfpipe` console script
    main()
