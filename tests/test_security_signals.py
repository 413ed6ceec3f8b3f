"""Issue 32 (render and signals): a render that fails after its video is encoded leaves no OUT.mp4 (make's target);
SIGTERM stops every stage with one line and exit 143; camera paths that ask for absurd frames or are nested
200000 deep, and outputs that are folders, are one-line user errors; the CLI's last guard turns RecursionError and
MemoryError from a reader into one line.

Fast tests use the analytic sphere of test_render_stage (`sphere_run`) and call `cli.main` in-process; the signal
test sends SIGTERM to a real `nerfpipe render` process on a 2-step training run.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import nerfpipe.data.atomic
import nerfpipe.stages.render as render_stage
from nerfpipe import cli
from nerfpipe.data.camera_path import MAX_PIXELS, MAX_SIDE, read_camera_path
from nerfpipe.data.errors import UserError
from nerfpipe.data.stop import Terminated, sigterm_raises, stop_on_signals

try:  # the analytic stand-in lives with the render tests
    from test_render_stage import sphere_run, train_tiny_run  # noqa: F401  (fixture)
except ImportError:  # tests/ imported as a package
    from tests.test_render_stage import sphere_run, train_tiny_run  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]


def _cli(capsys, *args) -> tuple[int, str]:
    with pytest.raises(SystemExit) as e:
        cli.main([str(a) for a in args])
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return e.value.code, err.strip()


def _hidden(folder: Path) -> list[Path]:
    return [p for p in folder.rglob(".*") if p.is_file()]


# ---------------------------------------------------------------------------------------------- render's outputs
def test_full_disk_writing_the_manifest_leaves_no_video(sphere_run, tmp_path, monkeypatch, capsys):
    """The video is encoded under a hidden temporary name and renamed into place after the manifest: a disk that
    fills while the manifest is written leaves no OUT.mp4 (which `make` would take as done), no frames."""
    run_dir, _ = sphere_run
    real_write = nerfpipe.data.atomic._write

    def full_at_manifest(f, data):
        if "manifest" in Path(f.name).name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_write(f, data)

    monkeypatch.setattr(nerfpipe.data.atomic, "_write", full_at_manifest)
    out, frames = tmp_path / "out" / "v.mp4", tmp_path / "frames"
    code, err = _cli(capsys, "render", run_dir, out, "--frames", "3", "--frames-dir", frames)
    assert code == 2 and err == f"error: no space left on device writing {out.with_suffix('.manifest.json')}"
    assert not out.exists() and not out.with_suffix(".manifest.json").exists()
    assert not frames.exists(), "the PNG frames of a failed render are removed with the folder it made"
    assert not out.parent.exists(), "the video's folder, made by the failed render, is removed"
    assert not _hidden(tmp_path), "a temporary was left"


@pytest.mark.parametrize("fault", [KeyboardInterrupt, Terminated])
def test_interrupt_after_encoding_keeps_the_earlier_video(sphere_run, tmp_path, monkeypatch, fault):
    """A rerun stopped between encoding and the manifest keeps the earlier OUT.mp4 and its manifest byte for byte
    (and the frames folder it did not make), with no temporary."""
    run_dir, _ = sphere_run
    out, frames = tmp_path / "v.mp4", tmp_path / "frames"
    render_stage.run(render_stage.Config(run_dir=run_dir, out=out, frames=3, frames_dir=frames))
    before = {p: p.read_bytes() for p in (out, out.with_suffix(".manifest.json"))}
    (frames / "mine.txt").write_text("the user's")

    def stop(*args, **kw):
        raise fault

    monkeypatch.setattr(render_stage, "write_manifest", stop)
    with pytest.raises(fault):
        render_stage.run(render_stage.Config(run_dir=run_dir, out=out, frames=4, frames_dir=frames))
    assert {p: p.read_bytes() for p in before} == before
    assert sorted(p.name for p in frames.iterdir()) == ["mine.txt"], "the failed render's frames are removed"
    assert not _hidden(tmp_path)


@pytest.mark.parametrize("where", ["out", "frames_dir", "sidecar", "parent"])
def test_outputs_that_are_the_wrong_kind_of_file_are_one_line(sphere_run, tmp_path, capsys, where):
    run_dir, _ = sphere_run
    out, frames = tmp_path / "v.mp4", tmp_path / "frames"
    if where == "out":
        out.mkdir()
    elif where == "frames_dir":
        frames.write_text("a file")
    elif where == "sidecar":
        (tmp_path / "v.manifest.json").mkdir()
    else:
        (tmp_path / "file").write_text("a file")
        out = tmp_path / "file" / "v.mp4"
    code, err = _cli(capsys, "render", run_dir, out, "--frames", "2", "--frames-dir", frames)
    assert code == 2 and err.startswith("error: ") and "Error" not in err, err
    assert {
        "out": f"{out} is a folder",
        "frames_dir": f"{frames} is a file",
        "sidecar": "v.manifest.json is a folder",
        "parent": f"{tmp_path / 'file'} is a file",
    }[where] in err
    assert not _hidden(tmp_path)


# ---------------------------------------------------------------------------------------------- camera-path files
def _path_file(path: Path, *, width: int = 32, height: int = 24, frames: int = 2) -> Path:
    pose = np.eye(4)
    pose[2, 3] = 3.0
    cams = [{"camera_to_world": pose.reshape(-1).tolist(), "fov": 50.0}] * frames
    path.write_text(json.dumps({"camera_path": cams, "render_width": width, "render_height": height, "fps": 2}))
    return path


@pytest.mark.parametrize(
    ("width", "height", "field"),
    [(200000, 200000, "render_width"), (24, 20000, "render_height"), (16000, 16000, "render_width x render_height")],
)
def test_camera_path_asking_for_huge_frames_is_refused(sphere_run, tmp_path, capsys, width, height, field):
    """200000 x 200000 pixels once asked torch for 320 GB (exit 1); now one line naming the file and the field."""
    run_dir, _ = sphere_run
    f = _path_file(tmp_path / "huge.json", width=width, height=height)
    with pytest.raises(UserError, match=field):
        read_camera_path(f)
    code, err = _cli(capsys, "render", run_dir, tmp_path / "v.mp4", "--path", f)
    assert code == 2 and err.startswith(f"error: {f}: field") and field in err
    assert not (tmp_path / "v.mp4").exists()
    assert MAX_SIDE * 24 <= MAX_PIXELS  # a long strip at the side limit fits the pixel budget
    read_camera_path(_path_file(tmp_path / "ok.json", width=MAX_SIDE, height=24))


def test_camera_path_nested_200000_deep_is_one_line(sphere_run, tmp_path, capsys):
    run_dir, _ = sphere_run
    f = tmp_path / "deep.json"
    f.write_text("[" * 200_000 + "]" * 200_000)
    with pytest.raises(UserError, match="nested too deeply"):
        read_camera_path(f)
    code, err = _cli(capsys, "render", run_dir, tmp_path / "v.mp4", "--path", f)
    assert code == 2 and err.startswith(f"error: {f}: ") and "nested too deeply" in err


def test_a_downscale_that_asks_for_huge_frames_is_refused(sphere_run, tmp_path, capsys):
    """The same bound on a synthetic path blown up by --downscale (33 x 25 px training images / 1e-4)."""
    run_dir, _ = sphere_run
    code, err = _cli(capsys, "render", run_dir, tmp_path / "v.mp4", "--downscale", "0.0001", "--frames", "2")
    assert code == 2 and "downscale" in err and f"{MAX_SIDE}" in err, err


# ---------------------------------------------------------------------------------------------- the CLI's last guard
@pytest.mark.parametrize(
    ("exc", "line"),
    [
        (
            RecursionError("maximum recursion depth exceeded while decoding a JSON array from a unicode string"),
            "error: an input is nested too deeply to read (maximum recursion depth exceeded while decoding a JSON "
            "array from a unicode string); rerun with --debug for details",
        ),
        (
            MemoryError(),
            "error: out of memory (an input or an option asks for more than this machine has); rerun "
            "with --debug for details",
        ),
    ],
)
def test_recursion_and_memory_errors_from_a_reader_are_one_line(capsys, monkeypatch, exc, line):
    """Readers outside the stages (model/, data/transforms.py, torch.load, ...) parse JSON and pickles: a
    RecursionError or MemoryError they raise is the input's doing, not a bug: exit 2, one line."""
    import importlib

    def run(config, progress=None):
        raise exc

    monkeypatch.setattr(importlib.import_module("nerfpipe.stages.report"), "run", run)
    code, err = _cli(capsys, "report", "a", "b")
    assert code == 2 and err == line
    with pytest.raises(type(exc)):
        cli.main(["--debug", "report", "a", "b"])


def test_a_run_config_nested_200000_deep_is_one_line(tmp_path, capsys):
    """A run's config.json nested too deep: model.trained reads it with data.confine.read_json, one line naming it."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_text("[" * 200_000 + "]" * 200_000)
    (run_dir / "checkpoint.pt").write_bytes(b"")
    code, err = _cli(capsys, "render", run_dir, tmp_path / "v.mp4")
    assert code == 2 and err == f"error: {run_dir / 'config.json'}: not valid JSON (nested too deeply)"


# ---------------------------------------------------------------------------------------------- SIGTERM
def test_sigterm_raises_inside_the_block_and_stop_on_signals_takes_over(capsys):
    """cli.main's SIGTERM handler raises `Terminated` (a KeyboardInterrupt: cleanups run); train's
    `stop_on_signals` replaces it inside its block and puts it back after; the original handler returns last."""
    original = signal.getsignal(signal.SIGTERM)
    with sigterm_raises():
        ours = signal.getsignal(signal.SIGTERM)
        assert ours is not original
        with stop_on_signals() as request:
            assert signal.getsignal(signal.SIGTERM) is not ours
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.01)
            assert request.signum == signal.SIGTERM  # a flag, no exception: train saves its step
            with pytest.raises(Terminated):  # a second one stops at once, and says SIGTERM (exit 143)
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(1)
        assert signal.getsignal(signal.SIGTERM) is ours
        with pytest.raises(Terminated):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # a second SIGTERM stops at once
    assert signal.getsignal(signal.SIGTERM) is original


def test_sigterm_in_a_stage_without_its_own_handling_is_one_line_143(capsys, monkeypatch):
    import importlib

    def run(config, progress=None):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)
        raise AssertionError("SIGTERM did not stop the stage")

    monkeypatch.setattr(importlib.import_module("nerfpipe.stages.report"), "run", run)
    code, err = _cli(capsys, "report", "a", "b")
    assert (code, err) == (143, "error: interrupted (SIGTERM)")


def test_an_ignored_sigterm_stays_ignored():
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        with sigterm_raises():
            assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_sigterm_after_importing_pycolmap_is_still_one_line(tmp_path):
    """Importing pycolmap (the poses stage) installs glog's C handler over Python's, behind its back: SIGTERM then
    printed a 35-line stack trace. The CLI takes SIGTERM back once the stage is imported (`reclaim_sigterm`)."""
    (tmp_path / "colmap_stage.py").write_text(
        textwrap.dedent('''
        import os, signal, time
        from dataclasses import dataclass
        from pathlib import Path
        import pycolmap  # noqa: F401

        @dataclass(frozen=True, kw_only=True)
        class Config:
            out: Path
            """Where to write."""

        def run(config):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(30)
    ''')
    )
    script = (
        f"import sys; sys.path.insert(0, {str(tmp_path)!r}); from nerfpipe import cli; "
        "cli.STAGES['colmap-stage'] = cli.Stage('colmap_stage', 'A stage that imports pycolmap.'); "
        "cli.main(['colmap-stage', 'o'])"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert (r.returncode, r.stderr.strip()) == (143, "error: interrupted (SIGTERM)")


def test_sigterm_during_render_is_one_line_and_leaves_nothing_complete(tmp_path):
    """A real `nerfpipe render` process (2-step training run, CPU) killed by SIGTERM while it writes frames: one
    line, exit 143, no OUT.mp4, no manifest, no frames, no temporary."""
    run_dir = train_tiny_run(tmp_path / "t")
    out, frames = tmp_path / "v.mp4", tmp_path / "frames"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [
            sys.executable,
            str(ROOT / "cli.py"),
            "render",
            str(run_dir),
            str(out),
            "--device",
            "cpu",
            "--frames",
            "100000",
            "--frames-dir",
            str(frames),
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    t0 = time.monotonic()
    while not (frames / "frame_00001.png").exists():
        assert proc.poll() is None, proc.communicate()[1]
        if time.monotonic() - t0 > 120:
            proc.kill()
            raise AssertionError("render wrote no frame in 120 s")
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert err.strip() == "error: interrupted (SIGTERM)"
    assert not out.exists() and not (tmp_path / "v.manifest.json").exists() and not frames.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "a temporary was left"
