"""The command line: every command's options come from its stage Config; errors are one line and an exit code."""

import collections.abc
import dataclasses
import importlib
import subprocess
import sys
import textwrap
import types
import typing
from pathlib import Path
from types import SimpleNamespace

import pytest
import typer

from nerfpipe import cli
from nerfpipe.data.errors import UserError

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = [
    "scene",
    "poses",
    "convert",
    "train",
    "render",
    "depth",
    "eval",
    "report",
    "mesh",
    "fit-image",
    "export-points",
    "splat",
    "shapes",
    "pretrain-voxels",
    "voxels",
]
# Positional arguments that make each command parse (nothing is run by config_from_args).
ARGS = {
    "scene": ["s"],
    "poses": ["photos", "s"],
    "convert": ["src", "s"],
    "train": ["s", "r"],
    "render": ["r", "v.mp4"],
    "depth": ["r", "d"],
    "eval": ["r", "e.json"],
    "report": ["r1", "r2", "out"],
    "mesh": ["r", "m.ply"],
    "fit-image": ["image.png", "o"],
    "export-points": ["r", "c.ply"],
    "splat": ["r", "s.ply"],
    "shapes": ["o"],
    "pretrain-voxels": ["s", "o"],
    "voxels": ["a.png", "o"],
}


def _run(capsys, *args):
    with pytest.raises(SystemExit) as e:
        cli.main(list(args))
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def _command(name):
    return typer.main.get_command(cli.app).get_command(None, name)


def _config_cls(name):
    return importlib.import_module(cli.STAGES[name].module).Config


def _default(f):
    return f.default if f.default is not dataclasses.MISSING else f.default_factory()


def _has_default(f):
    return f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING


def _error_lines(err):
    """typer's usage errors: a Usage line, a hint, and exactly one `Error:` line; no traceback."""
    assert "Traceback" not in err
    return [ln for ln in err.splitlines() if ln.startswith("Error:")]


# ---------------------------------------------------------------------------------------------- help
def test_top_level_help_lists_every_command(capsys):
    code, out, _ = _run(capsys, "--help")
    assert code == 0
    for name in COMMANDS:
        assert name in out


def test_top_level_help_imports_no_stage():
    """`nerfpipe --help` stays fast: no stage module (and so no torch) is imported to list the commands."""
    code = textwrap.dedent("""
        import sys, cli
        try:
            cli.main(["--help"])
        except SystemExit:
            pass
        heavy = sorted(m for m in sys.modules if m == "torch" or m.startswith("nerfpipe.stages."))
        assert not heavy, heavy
    """)
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("name", COMMANDS)
def test_command_help(capsys, name):
    code, out, _ = _run(capsys, name, "--help")
    assert code == 0 and "Usage" in out
    skipped = set(cli.skipped_fields(name))
    for f in dataclasses.fields(_config_cls(name)):
        if _has_default(f) and f.name not in skipped:
            assert f"--{f.name.replace('_', '-')}" in out, f"{name}: no option for Config.{f.name}"


def test_version(capsys):
    code, out, _ = _run(capsys, "--version")
    assert code == 0 and out.startswith("nerfpipe ")


# ---------------------------------------------------------------------------------------------- generated from Config
@pytest.mark.parametrize("name", COMMANDS)
def test_option_defaults_are_the_config_defaults(name):
    """Each option's default (as shown in --help) is its Config field's default, written as one would type it."""
    cmd = _command(name)
    fields = {f.name: f for f in dataclasses.fields(_config_cls(name))}
    ctx = cmd.make_context(name, list(ARGS[name]), resilient_parsing=True)
    options = [p for p in cmd.params if p.name in fields and any(o.startswith("--") for o in p.opts)]
    assert options
    for p in options:
        default = _default(fields[p.name])
        if isinstance(default, tuple):
            shown = ",".join(str(v) for v in default)
        elif dataclasses.is_dataclass(default):
            shown = True  # --x/--no-x, on by default
        else:
            shown = default
        assert p.default == shown, f"{name} --{p.name}: {p.default!r} != Config default {default!r}"
        help_text = p.get_help_record(ctx)[1]
        if default is None:
            assert "[default:" not in help_text
        elif not isinstance(shown, bool) and shown != "":  # an empty tuple shows no default
            assert f"[default: {shown}]" in help_text, help_text


@pytest.mark.parametrize("name", COMMANDS)
def test_no_options_gives_the_config_defaults(name):
    """What the CLI builds from the positional arguments alone equals the Config's own defaults."""
    config = cli.config_from_args(name, ARGS[name])
    for f in dataclasses.fields(config):
        if _has_default(f):
            assert getattr(config, f.name) == _default(f), f"{name}: Config.{f.name}"


@pytest.mark.parametrize("name", COMMANDS)
def test_only_fields_without_a_command_line_form_are_skipped(name):
    """Callables and nested dataclasses may be left out, and a method's options group (spelt flat through
    cli.METHOD_GROUPS); a field of any other type must become an option."""
    hints = typing.get_type_hints(_config_cls(name))
    for field_name in cli.skipped_fields(name):
        if (name, field_name) in cli.METHOD_GROUPS:
            continue
        hint = hints[field_name]
        members = [a for a in typing.get_args(hint) if a is not type(None)] if _is_union(hint) else [hint]
        assert len(members) == 1, f"{name}: Config.{field_name} ({hint}) has no option: add it to cli.PARSERS"
        base = members[0]
        no_cli_form = typing.get_origin(base) is collections.abc.Callable or dataclasses.is_dataclass(base)
        assert no_cli_form, f"{name}: Config.{field_name} ({hint}) has no option"


def _is_union(hint):
    return typing.get_origin(hint) in (typing.Union, types.UnionType)


def test_positional_arguments_are_the_required_fields():
    assert cli.config_from_args("train", ["scn", "run"]).scene_dir == Path("scn")
    assert cli.config_from_args("train", ["scn", "run"]).run_dir == Path("run")
    config = cli.config_from_args("report", ["a", "b", "c"])
    assert config.runs == (Path("a"), Path("b")) and config.out_dir == Path("c")


def test_options_reach_the_config():
    config = cli.config_from_args("train", ["s", "r", "--method", "nerf", "--lr", "0.01", "--no-view-dependent"])
    assert (config.method, config.lr, config.options.view_dependent) == ("nerf", 0.01, False)
    assert cli.config_from_args("convert", ["src", "s", "--downscales", "3,5", "--no-normalize"]).downscales == (3, 5)
    assert cli.config_from_args("convert", ["src", "s", "--downscales", ""]).downscales == ()
    assert cli.config_from_args("train", ["s", "r", "--resolution", "8, 16"]).options.resolution == (8, 16)
    assert cli.config_from_args("train", ["s", "r", "--rank", "16,4,4,48,12,12"]).options.rank == (16, 4, 4, 48, 12, 12)
    report = cli.config_from_args("report", ["a", "b", "o", "--levels", "21.5,30", "--labels", "x,y"])
    assert report.levels == (21.5, 30.0) and report.labels == ("x", "y")
    assert cli.config_from_args("render", ["r", "v.mp4", "--outputs", "rgb,depth"]).outputs == ("rgb", "depth")
    assert cli.config_from_args("render", ["r", "v.mp4", "--device", "cuda:1"]).device == "cuda:1"


def test_method_options_belong_to_the_method_named(capsys):
    """Every method's options are flags of `train`; one of another method is refused in one line, and an unknown
    method names the ones there are."""
    assert cli.config_from_args("train", ["s", "r"]).options is None  # the method's own defaults
    with pytest.raises(UserError, match="--tv: not an option of method nerf"):
        cli.config_from_args("train", ["s", "r", "--method", "nerf", "--tv", "0.1"])
    code, _, err = _run(capsys, "train", "s", "r", "--method", "bogus")
    assert code == 2 and err.strip().splitlines() == [
        "error: unknown method 'bogus': expected one of density, nerf, sdf, gnt"
    ]


def test_mesh_special_fields():
    default = cli.config_from_args("mesh", ["r", "m.ply"])
    assert default.cleanup is not None and default.threshold == "auto" and default.bbox is None
    assert cli.config_from_args("mesh", ["r", "m.ply", "--no-cleanup"]).cleanup is None
    assert cli.config_from_args("mesh", ["r", "m.ply", "--cleanup"]).cleanup == default.cleanup
    assert cli.config_from_args("mesh", ["r", "m.ply", "--threshold", "0.5"]).threshold == 0.5
    bbox = cli.config_from_args("mesh", ["r", "m.ply", "--bbox", "0,0,0,1,1,2"]).bbox
    assert bbox == (0.0, 0.0, 0.0, 1.0, 1.0, 2.0)
    assert cli.config_from_args("mesh", ["r", "m.ply", "--bbox", "auto"]).bbox is None


@pytest.mark.parametrize(
    "name, option, good",
    [
        ("train", "--scene-model", "ndc"),
        ("convert", "--kind", "llff"),
        ("render", "--path", "spiral"),
        ("depth", "--views", "turntable"),
        ("poses", "--camera-model", "OPENCV"),
    ],
)
def test_choices_are_enforced(capsys, monkeypatch, name, option, good):
    module = importlib.import_module(cli.STAGES[name].module)
    monkeypatch.setattr(module, "run", lambda *a, **k: pytest.fail("a bad choice must not run the stage"))
    code, _, err = _run(capsys, name, *ARGS[name], option, "bogus")
    assert code == 2
    [line] = _error_lines(err)
    assert option in line and "bogus" in line
    assert good in err  # the error lists the choices
    attr = option[2:].replace("-", "_")
    assert getattr(cli.config_from_args(name, [*ARGS[name], option, good]), attr) == good


@pytest.mark.parametrize(
    "name, option, bad",
    [
        ("convert", "--downscales", "2,x"),
        ("train", "--resolution", "1,2,3"),
        ("train", "--upsample-at", "0.1,a"),
        ("report", "--levels", "20,high"),
    ],
)
def test_tuple_option_parse_error_is_one_line(capsys, name, option, bad):
    code, _, err = _run(capsys, name, *ARGS[name], option, bad)
    assert code == 2
    [line] = _error_lines(err)
    assert option in line and bad in line


def test_stage_parser_error_is_one_line(capsys):
    code, _, err = _run(capsys, "render", "r", "v.mp4", "--outputs", "rgb,normals")
    assert code == 2
    assert err.strip().splitlines() == [err.strip()] and err.startswith("error: --outputs")


# ---------------------------------------------------------------------------------------------- errors and --debug
def _bad_path_args(tmp_path):
    missing = tmp_path / "does not exist"
    return {
        "scene": None,  # scene creates its output folder: a bad option instead
        "poses": [str(missing), str(tmp_path / "out")],
        "convert": [str(missing), str(tmp_path / "out")],
        "train": [str(missing), str(tmp_path / "run")],
        "render": [str(missing), str(tmp_path / "o.mp4")],
        "depth": [str(missing), str(tmp_path / "d")],
        "eval": [str(missing), str(tmp_path / "e.json")],
        "report": [str(missing), str(tmp_path / "r")],
        "mesh": [str(missing), str(tmp_path / "m.ply")],
        "fit-image": [str(missing), str(tmp_path / "o")],
        "export-points": [str(missing), str(tmp_path / "c.ply")],
        "splat": [str(missing), str(tmp_path / "s.ply")],
        "shapes": None,  # shapes creates its output folder
        "pretrain-voxels": [str(missing), str(tmp_path / "w")],
        "voxels": [str(missing), str(tmp_path / "v")],
    }


@pytest.mark.parametrize("name", [c for c in COMMANDS if c not in ("scene", "shapes")])
def test_bad_path_one_line_nonzero(capsys, tmp_path, name):
    code, _, err = _run(capsys, name, *_bad_path_args(tmp_path)[name])
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "does not exist" in lines[0], "the message should name the bad path"
    assert not (tmp_path / "out" / "transforms.json").exists()


def test_scene_bad_option_one_line(capsys, tmp_path):
    code, _, err = _run(capsys, "scene", str(tmp_path / "s"), "--size", "0")
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err


def test_usage_error_exit_code(capsys):
    code, _, err = _run(capsys, "train")
    assert code == 2 and "Missing argument" in err


def test_debug_reraises_user_error(capsys, tmp_path):
    with pytest.raises(UserError):
        cli.main(["--debug", "train", str(tmp_path / "missing"), str(tmp_path / "run")])
    code, _, err = _run(capsys, "train", str(tmp_path / "missing"), str(tmp_path / "run"))  # no --debug: not sticky
    assert code == 2 and err.startswith("error: ") and len(err.strip().splitlines()) == 1


def _fake_report_run(monkeypatch, exc):
    def run(config, progress=None):
        raise exc

    monkeypatch.setattr(importlib.import_module("nerfpipe.stages.report"), "run", run)


def test_unexpected_error_one_line_exit_1(capsys, monkeypatch):
    _fake_report_run(monkeypatch, RuntimeError("boom\nsecond line"))
    code, _, err = _run(capsys, "report", "a", "b")
    assert code == 1
    assert err.strip() == "error: RuntimeError: boom (rerun with --debug for details)"
    with pytest.raises(RuntimeError, match="boom"):
        cli.main(["--debug", "report", "a", "b"])


def test_keyboard_interrupt_exits_130(capsys, monkeypatch):
    _fake_report_run(monkeypatch, KeyboardInterrupt())
    code, _, err = _run(capsys, "report", "a", "b")
    assert code == 130 and err.strip() == "error: interrupted"
    with pytest.raises(KeyboardInterrupt):
        cli.main(["--debug", "report", "a", "b"])


# ---------------------------------------------------------------------------------------------- running a stage
def test_progress_passed_to_run_when_stderr_is_a_terminal(capsys, monkeypatch):
    seen = []

    def run(config, progress=None):
        seen.append(progress)
        return SimpleNamespace(markdown=config.out_dir / "summary.md", plot=config.out_dir / "psnr_vs_time.png")

    monkeypatch.setattr(importlib.import_module("nerfpipe.stages.report"), "run", run)
    code, out, _ = _run(capsys, "report", "a", "o")  # captured stderr is not a terminal: silent stage
    assert code == 0 and seen == [None]
    assert out.strip() == "report -> o/summary.md, o/psnr_vs_time.png"
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    code, _, _ = _run(capsys, "report", "a", "o")
    assert code == 0 and hasattr(seen[1], "add_task") and hasattr(seen[1], "advance")


def test_new_stage_is_one_registration(capsys, monkeypatch, tmp_path):
    """A stage module with a Config and `run(config)` (no progress parameter) becomes a command from one entry."""
    (tmp_path / "fake_fit_image.py").write_text(
        textwrap.dedent('''
            from dataclasses import dataclass
            from pathlib import Path
            from typing import Literal

            @dataclass(frozen=True, kw_only=True)
            class Config:
                out: Path
                """Where to write."""
                mode: Literal["grid", "mlp"] = "grid"
                """Which field."""
                steps: tuple[int, ...] = (1, 2)
                """Steps."""

            def run(config):
                return config
        ''')
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(cli.STAGES, "fake-stage", cli.Stage("fake_fit_image", "Fit one image."))
    code, out, _ = _run(capsys, "fake-stage", "--help")
    assert code == 0 and "--mode <grid|mlp>" in out and "[default: 1,2]" in out
    code, out, _ = _run(capsys, "fake-stage", "o", "--mode", "mlp")
    assert code == 0 and out.strip() == "done -> o"


def test_python_cli_py_entry_point():
    r = subprocess.run([sys.executable, "cli.py", "--version"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith("nerfpipe ")


def test_library_switches_are_said_as_flags(capsys, tmp_path):
    """A library error names config fields ("set overwrite=True"); the command line says the flag instead."""
    assert (
        cli._as_flags("set resume=True to continue it or overwrite=True")
        == "set --resume to continue it or --overwrite"
    )
    assert cli._as_flags("refine_poses=True, a.b=True, x=Truest") == "--refine-poses, a.b=True, x=Truest"
    args = ("scene", str(tmp_path / "s"), "--kind", "rgba", "--size", "16", "--views", "4")
    assert _run(capsys, *args)[0] == 0
    code, _, err = _run(capsys, *args)
    assert code == 2 and "set --overwrite to replace it" in err and "=True" not in err
