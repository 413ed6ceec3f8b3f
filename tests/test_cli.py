"""Every command: --help works; a bad path gives one line on stderr and a non-zero exit."""

import subprocess
import sys
from pathlib import Path

import pytest

import cli

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = ["scene", "poses", "convert", "train", "render", "depth", "eval", "report", "mesh"]


def _run(capsys, *args):
    with pytest.raises(SystemExit) as e:
        cli.main(list(args))
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def test_top_level_help_lists_every_command(capsys):
    code, out, _ = _run(capsys, "--help")
    assert code == 0
    for name in COMMANDS:
        assert name in out


@pytest.mark.parametrize("name", COMMANDS)
def test_command_help(capsys, name):
    code, out, _ = _run(capsys, name, "--help")
    assert code == 0 and "Usage" in out


def test_version(capsys):
    code, out, _ = _run(capsys, "--version")
    assert code == 0 and out.startswith("nerfpipe ")


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
    }


@pytest.mark.parametrize("name", [c for c in COMMANDS if c != "scene"])
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


def test_python_cli_py_entry_point():
    r = subprocess.run([sys.executable, "cli.py", "--version"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith("nerfpipe ")
