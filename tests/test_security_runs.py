"""Issue 32, runs and folders: a planted lock file, outputs that would land inside the run they read, two poses
into one folder, poses stopped by SIGTERM or kill -9, stale temporaries, and `--resume` with other settings or
another scene. Each attack is tried for real (CLI or stage), then the one line and what is left on disk checked."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2  # noqa: F401  (before pycolmap, imported by stages.poses: the other order crashes cv2's PNG writer)
import numpy as np
import pytest
from PIL import Image

from nerfpipe import cli
from nerfpipe.data.errors import UserError
from nerfpipe.data.lock import LOCK_NAME, STALE_SECONDS, FolderBusy, folder_lock, sweep_stale
from nerfpipe.data.rundir import refuse_output_inside
from nerfpipe.model.methods.density import DensityOptions
from nerfpipe.stages import depth, eval, poses, report, train
from nerfpipe.stages import scene as scene_stage

ROOT = Path(__file__).resolve().parents[1]

try:  # the tiny scene, run and train settings of the reliability tests
    from test_reliability import TINY, _config, finished_run, scene_dir  # noqa: F401  (fixtures)
except ImportError:  # tests/ imported as a package
    from tests.test_reliability import TINY, _config, finished_run, scene_dir  # noqa: F401


def _cli(capsys, *args) -> tuple[int, str]:
    with pytest.raises(SystemExit) as e:
        cli.main([str(a) for a in args])
    return e.value.code, capsys.readouterr().err


def _copy(run_dir: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(run_dir, tmp_path / "run"))


def _hashes(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


# ---------------------------------------------------------------------------------------------- the lock file
def test_a_lock_planted_as_a_symlink_is_refused_and_its_target_untouched(scene_dir, finished_run, tmp_path, capsys):
    """`RUN/.nerfpipe.lock -> victim`: train --resume and depth used to truncate the victim and write
    "pid cmdline" into it (the lock was opened following symlinks)."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    run_dir = _copy(finished_run, tmp_path)
    (run_dir / LOCK_NAME).symlink_to(victim)
    before = _hashes(run_dir)
    code, err = _cli(capsys, "train", scene_dir, run_dir, *TINY, "--resume")
    assert code == 2 and err.count("\n") == 1, err
    assert (
        err == f"error: {run_dir / LOCK_NAME}: the lock file is a symbolic link; expected a regular file "
        f"(remove it if no nerfpipe process writes {run_dir})\n"
    )
    (tmp_path / "d2").mkdir()
    (tmp_path / "d2" / LOCK_NAME).symlink_to(victim)
    code, err = _cli(capsys, "depth", run_dir, tmp_path / "d2", "--device", "cpu")
    assert code == 2 and "the lock file is a symbolic link" in err and err.count("\n") == 1, err
    assert victim.read_text() == "precious\n" and _hashes(run_dir) == before


def test_a_lock_that_is_a_hard_link_a_folder_or_dangling_is_refused(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    hard = tmp_path / "hard"
    hard.mkdir()
    os.link(victim, hard / LOCK_NAME)
    with pytest.raises(UserError, match=r"the lock file is a hard link \(2 names\)"):
        with folder_lock(hard):
            pass
    assert victim.read_text() == "precious\n"
    (tmp_path / "dir" / LOCK_NAME).mkdir(parents=True)
    with pytest.raises(UserError, match="the lock file is not a regular file"):
        with folder_lock(tmp_path / "dir"):
            pass
    dangling = tmp_path / "dangling"
    dangling.mkdir()
    (dangling / LOCK_NAME).symlink_to(tmp_path / "created_by_us")
    with pytest.raises(UserError, match="symbolic link"):
        with folder_lock(dangling):
            pass
    assert not (tmp_path / "created_by_us").exists()
    with folder_lock(tmp_path / "fine") as path:  # an ordinary lock: a regular file, ours, one name
        assert path.read_text().split()[0] == str(os.getpid())


def test_taking_a_lock_sweeps_what_dead_writers_left(tmp_path):
    """poses' build folders (`.colmap.tmp-*`) at once; data.atomic's temporaries once STALE_SECONDS old (eval,
    render and mesh write into folders they do not lock, so a fresh one may be live); nothing else."""
    folder = tmp_path / "f"
    (folder / ".colmap.tmp-abc123de" / "images").mkdir(parents=True)
    (folder / ".colmap.tmp-abc123de" / "database.db").write_bytes(b"x" * 1000)
    old = [".checkpoint.pt.k2j3h4l5.pt", ".config.json.abcdefgh.json", ".x.abcdefgh.tmp", ".loss.png.zz_zz_zz.png"]
    fresh, keep = ".metrics.csv.q1w2e3r4.csv", [".hidden", ".notes.txt.abcdefgh.doc", "a.abcdefgh.json", "data.csv"]
    for name in [*old, fresh, *keep]:
        (folder / name).write_text("left")
    past = time.time() - STALE_SECONDS - 5
    for name in [*old, *keep]:
        os.utime(folder / name, (past, past))
    with folder_lock(folder):
        pass
    assert sorted(p.name for p in folder.iterdir()) == sorted([fresh, *keep])
    assert sweep_stale(folder, now=time.time() + STALE_SECONDS + 5) == [fresh]


# ---------------------------------------------------------------------------------------------- outputs
@pytest.mark.parametrize("name", ["manifest.json", "config.json"])
def test_eval_into_a_file_the_run_owns_is_refused(finished_run, tmp_path, capsys, name):
    run_dir = _copy(finished_run, tmp_path)
    before = _hashes(run_dir)
    code, err = _cli(capsys, "eval", run_dir, run_dir / name, "--device", "cpu")
    assert code == 2 and err == (
        f"error: {run_dir / name}: the run {run_dir} owns {name}; expected another name for the eval output\n"
    )
    assert _hashes(run_dir) == before


def test_depth_or_report_into_the_run_or_its_parent_is_refused(finished_run, tmp_path, capsys):
    """`depth RUN RUN --overwrite` moved the whole run to RUN.previous/; a parent folder would take the run with
    it the same way."""
    run_dir = _copy(finished_run, tmp_path)
    before = _hashes(run_dir)
    code, err = _cli(capsys, "depth", run_dir, run_dir, "--overwrite", "--device", "cpu")
    assert code == 2 and err == (
        f"error: {run_dir}: the depth output would be the run folder {run_dir} itself; expected a path outside it\n"
    )
    code, err = _cli(capsys, "depth", run_dir, tmp_path, "--overwrite", "--device", "cpu")
    assert code == 2 and "the depth output folder holds the run" in err and err.count("\n") == 1, err
    link = tmp_path.parent / f"{tmp_path.name}-link"
    link.symlink_to(run_dir)
    code, err = _cli(capsys, "report", run_dir, link, "--overwrite")
    assert code == 2 and "the report output would be the run folder" in err, err
    assert _hashes(run_dir) == before and not (tmp_path / "run.previous").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_a_new_name_inside_the_run_stays_allowed(finished_run, tmp_path):
    run_dir = _copy(finished_run, tmp_path)
    before = _hashes(run_dir)
    for out in (run_dir / "eval.json", run_dir / "depth", run_dir / "sub" / "manifest.json", tmp_path / "beside"):
        refuse_output_inside(out, run_dir)
    out = eval.run(eval.Config(run_dir=run_dir, out=run_dir / "eval.json", device="cpu", views=1))
    assert out.out.is_file() and {k: v for k, v in _hashes(run_dir).items() if k in before} == before
    depth.run(depth.Config(run_dir=run_dir, out_dir=run_dir / "depth", device="cpu"))
    report.run(report.Config(runs=(run_dir,), out_dir=run_dir / "report"))
    assert (run_dir / "depth" / "manifest.json").is_file() and (run_dir / "report" / "manifest.json").is_file()


# ---------------------------------------------------------------------------------------------- poses
def _photos(folder: Path, n: int = 3) -> Path:
    folder.mkdir(parents=True)
    for i in range(n):
        rng = np.random.default_rng(i)
        Image.fromarray(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(folder / f"p{i}.png")
    return folder


def test_two_poses_into_one_folder_the_second_is_refused(tmp_path):
    photos, out = _photos(tmp_path / "photos"), tmp_path / "scene"
    with folder_lock(out):  # the first poses (or any nerfpipe writer) holds the scene folder
        with pytest.raises(
            FolderBusy, match=f"{out} is being written by another nerfpipe process \\(pid {os.getpid()}"
        ):
            poses.run(poses.Config(input=photos, scene_dir=out, num_threads=1))
    assert list(out.iterdir()) == []  # no poses_report.json describing the other run's photos


@pytest.fixture(scope="module")
def poses_photos(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("poses_photos")
    scene_stage.run(scene_stage.Config(out_dir=root / "scene", kind="photos", size=192, views=16, seed=0))
    return root / "scene" / "images"


def _spawn_poses(photos: Path, out: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    args = [sys.executable, str(ROOT / "cli.py"), "poses", str(photos), str(out), "--num-threads", "1"]
    return subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_build(out: Path, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    t0 = time.monotonic()
    while not list(out.glob(".colmap.tmp-*/images/*")):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout, "no build folder"
        time.sleep(0.05)


def test_sigterm_during_poses_is_one_line_and_143(poses_photos, tmp_path):
    """pycolmap's import installs glog's failure-signal handler: SIGTERM printed a 35-line C++ stack trace."""
    out = tmp_path / "scene"
    proc = _spawn_poses(poses_photos, out)
    _wait_for_build(out, proc)
    time.sleep(1.0)  # inside pycolmap (extraction or matching)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and err == "error: interrupted (SIGTERM)\n", err
    assert not (out / "colmap").exists() and not list(out.glob(".colmap.tmp-*")) and not (out / LOCK_NAME).exists()
    assert json.loads((out / "poses_report.json").read_text())["status"] == "failed"


def test_kill_9_during_poses_leaves_a_build_folder_the_next_run_sweeps(poses_photos, tmp_path):
    out = tmp_path / "scene"
    proc = _spawn_poses(poses_photos, out)
    _wait_for_build(out, proc)
    proc.kill()
    proc.communicate(timeout=60)
    left = list(out.glob(".colmap.tmp-*"))
    assert len(left) == 1 and left[0].is_dir()
    with pytest.raises(UserError):  # the next run (here on a single photo: it fails at once) sweeps it first
        poses.run(poses.Config(input=_photos(tmp_path / "one", 1), scene_dir=out, num_threads=1))
    assert not list(out.glob(".colmap.tmp-*"))


# ---------------------------------------------------------------------------------------------- resume
def _resume_refused(scene_dir: Path, run_dir: Path, match: str, **kw) -> None:
    before = _hashes(run_dir)
    with pytest.raises(UserError, match=match) as e:
        train.run(_config(scene_dir, run_dir, resume=True, **kw))
    assert "\n" not in str(e.value) and str(e.value).startswith(f"{run_dir / 'config.json'}: resume continues")
    assert _hashes(run_dir) == before


def test_resume_with_other_settings_is_refused_naming_each(scene_dir, finished_run, tmp_path):
    run_dir = _copy(finished_run, tmp_path)
    _resume_refused(scene_dir, run_dir, r"downscale: 1\.0 -> 2\.0", downscale=2.0)
    _resume_refused(scene_dir, run_dir, "scene_model: auto -> contract", scene_model="contract")
    _resume_refused(scene_dir, run_dir, "seed: 0 -> 3, background: auto -> white", background="white", seed=3)
    _resume_refused(
        scene_dir,
        run_dir,
        r"options.resolution: \[16, 24\] -> \[16, 32\]",
        options=DensityOptions(resolution=(16, 32), occupancy_resolution=16),
    )
    _resume_refused(scene_dir, run_dir, "method: density -> nerf", method="nerf")
    (run_dir / "config.json").unlink()  # nothing to check the resumed run against
    with pytest.raises(UserError, match=r"config.json: missing; resume needs the config.json the run wrote"):
        train.run(_config(scene_dir, run_dir, resume=True))


def test_resume_with_another_scene_is_refused(scene_dir, finished_run, tmp_path):
    run_dir = _copy(finished_run, tmp_path)
    other = Path(shutil.copytree(scene_dir, tmp_path / "other"))
    doc = json.loads((other / "transforms.json").read_text())
    doc["frames"][0]["transform_matrix"][0][3] += 0.01  # another capture of the same layout
    (other / "transforms.json").write_text(json.dumps(doc))
    _resume_refused(other, run_dir, r"scene: .*rgba \(transforms.json sha256 [0-9a-f]{12}\) -> .*other \(sha256")
    # a run recorded before scene_sha256: the scene folder itself must be the one recorded
    stored = json.loads((run_dir / "config.json").read_text())
    del stored["scene_sha256"]
    (run_dir / "config.json").write_text(json.dumps(stored))
    _resume_refused(Path(shutil.copytree(scene_dir, tmp_path / "same_copy")), run_dir, "scene_dir: .* -> .*same_copy")


def test_resume_with_a_new_budget_goes_on_and_is_recorded(scene_dir, finished_run, tmp_path, capsys):
    run_dir = _copy(finished_run, tmp_path)
    moved = Path(shutil.copytree(scene_dir, tmp_path / "moved_scene"))  # the same scene elsewhere: the same content
    code, err = _cli(capsys, "train", moved, run_dir, *TINY, "--resume", "--max-steps", "4", "--max-seconds", "90")
    assert code == 0, err
    doc = json.loads((run_dir / "config.json").read_text())
    assert doc["max_steps"] == 4 and doc["max_seconds"] == 90.0 and doc["scene_dir"] == str(moved.resolve())
    (entry,) = doc["resumed"]
    assert (
        entry["step"] == 2
        and entry["changed"]["max_steps"] == [2, 4]
        and entry["changed"]["max_seconds"] == [60.0, 90.0]
        and entry["changed"]["scene_dir"][1] == str(moved.resolve())
    )
    assert set(entry["changed"]) == {"max_steps", "max_seconds", "scene_dir"}


def test_a_run_recorded_before_the_activation_and_width_options_resumes_as_it_was(scene_dir, finished_run, tmp_path):
    """config.json from before `--density-activation` and `--mlp-width` has no such keys: the run's density was
    softplus and its colour MLP 64 wide, so resume takes those (not the rule this version would choose), and a
    different value given is refused naming it."""
    run_dir = _copy(finished_run, tmp_path)
    stored = json.loads((run_dir / "config.json").read_text())
    assert stored["options"].pop("density_activation") == "softplus"  # an object scene: the box rule's
    assert stored["options"].pop("mlp_width") == 64
    (run_dir / "config.json").write_text(json.dumps(stored))
    fast = DensityOptions(resolution=(16, 24), occupancy_resolution=16, density_activation="relu")
    _resume_refused(scene_dir, run_dir, "options.density_activation: softplus -> relu", options=fast)
    fast = DensityOptions(resolution=(16, 24), occupancy_resolution=16, mlp_width=128)
    _resume_refused(scene_dir, run_dir, "options.mlp_width: 64 -> 128", options=fast)
    train.run(_config(scene_dir, run_dir, resume=True, max_steps=3))
    resumed = json.loads((run_dir / "config.json").read_text())["options"]
    assert resumed["density_activation"] == "softplus" and resumed["mlp_width"] == 64
