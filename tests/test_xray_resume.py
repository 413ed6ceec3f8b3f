"""xray-train on the shared loop (`model.loop`): Ctrl-C saves a checkpoint and says so in one line, `--resume`
continues it to the very volume an uninterrupted run reaches, a rerun without --resume is refused, and a
non-finite loss restores the last good state at half the learning rate. A 16^3 phantom, CPU, seconds.

The interrupt is a real SIGINT sent to this process from inside a training step (where a Ctrl-C lands), so the
stage's own handler (`data.stop`) turns it into the stop request the loop polls."""

from __future__ import annotations

import json
import math
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import torch

import nerfpipe.stages.xray_train.loop as xray_loop
from nerfpipe import cli
from nerfpipe.data.errors import Interrupted, UserError
from nerfpipe.model.loop import TrainingDiverged
from nerfpipe.stages import xray_simulate, xray_train

STEPS = 40  # upsampling at steps 4 and 10 (upsample_at 0.1, 0.25)
OPTIONS = [
    "--max-steps",
    str(STEPS),
    "--max-seconds",
    "600",
    "--batch-rays",
    "256",
    "--eval-every",
    "0",
    "--eval-test-views",
    "1",
    "--threads",
    "1",
    "--device",
    "cpu",
]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("xray_resume")
    c = (np.indices((16, 16, 16)).transpose(1, 2, 3, 0) + 0.5 - 8) / 8
    vol = np.where(np.linalg.norm(c / [0.8, 0.6, 0.85], axis=-1) < 1, 0.02, 0.0).astype(np.float32)
    vol[np.linalg.norm(c - [0.3, 0.1, 0.0], axis=-1) < 0.3] = 0.05
    np.save(tmp / "phantom.npy", vol)
    out = tmp / "scene"
    xray_simulate.run(
        xray_simulate.Config(
            volume=tmp / "phantom.npy",
            out_dir=out,
            views=16,
            arc=360.0,
            test_views=2,
            voxel_size=1.0,
            dso=100.0,
            dsd=150.0,
        )
    )
    return out


@pytest.fixture(scope="module")
def straight(scene, tmp_path_factory) -> xray_train.Outputs:
    """The uninterrupted run."""
    return xray_train.run(_config(scene, tmp_path_factory.mktemp("straight") / "run"))


def _config(scene: Path, run_dir: Path, **kw) -> xray_train.Config:
    # no time budget: progress (and so the learning rate) is the step fraction alone, the same in every run
    base = dict(
        scene=scene,
        run_dir=run_dir,
        max_steps=STEPS,
        max_seconds=math.inf,
        batch_rays=256,
        eval_every=0.0,
        eval_test_views=1,
        threads=1,
        device="cpu",
    )
    base.update(kw)
    return xray_train.Config(**base)


def _ctrl_c_after(monkeypatch, step: int) -> None:
    """SIGINT to this process during training step `step` (counted from 1)."""
    real = xray_loop.XraySteps.train_step

    def train_step(self, lr):
        ok = real(self, lr)
        if self.step + 1 == step:
            os.kill(os.getpid(), signal.SIGINT)
        return ok

    monkeypatch.setattr(xray_loop.XraySteps, "train_step", train_step)


def test_ctrl_c_saves_a_checkpoint_and_resume_reaches_the_uninterrupted_volume(scene, straight, tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    _ctrl_c_after(monkeypatch, 7)  # between the two upsamplings: the schedule's level must come back too
    with pytest.raises(Interrupted, match=r"^interrupted \(SIGINT\) at step 7 after .* s; continue with --resume") as e:
        xray_train.run(_config(scene, run_dir))
    assert e.value.exit_code == 130
    monkeypatch.undo()
    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert state["step"] == 7 and state["level"] == 1 and not (run_dir / "manifest.json").exists()
    refused = r"already holds an earlier output \(checkpoint.pt\); .*resume.* to continue it"
    with pytest.raises(UserError, match=refused):
        xray_train.run(_config(scene, run_dir))  # an interrupted run is not silently replaced
    out = xray_train.run(_config(scene, run_dir, resume=True))
    assert out.steps == straight.steps == STEPS and out.manifest.is_file()
    np.testing.assert_array_equal(np.load(out.volume), np.load(straight.volume))  # the same run, continued
    used = json.loads(out.manifest.read_text())["used"]
    assert used["resumed_from"]["step"] == 7 and used["steps"] == STEPS
    steps = [int(r.split(",")[0]) for r in out.metrics.read_text().splitlines()[1:]]
    assert steps == [25, STEPS]


def test_ctrl_c_from_the_command_line_is_one_line_and_resume_finishes(scene, tmp_path, capsys, monkeypatch):
    run_dir = tmp_path / "run"
    _ctrl_c_after(monkeypatch, 3)
    with pytest.raises(SystemExit) as e:
        cli.main(["xray-train", str(scene), str(run_dir), *OPTIONS])
    err = capsys.readouterr().err
    assert e.value.code == 130 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("error: interrupted (SIGINT) at step 3 ") and "continue with --resume" in err
    monkeypatch.undo()
    with pytest.raises(SystemExit) as e:
        cli.main(["xray-train", str(scene), str(run_dir), *OPTIONS, "--resume"])
    assert e.value.code in (0, None), capsys.readouterr().err
    assert json.loads((run_dir / "manifest.json").read_text())["used"]["steps"] == STEPS


def test_resume_refuses_another_field_and_a_missing_checkpoint(scene, straight, tmp_path):
    with pytest.raises(UserError, match="checkpoint holds a 'voxel' field, config asks for tensorf"):
        xray_train.run(_config(scene, straight.run_dir, resume=True, field="tensorf"))
    with pytest.raises(UserError, match="no checkpoint"):
        xray_train.run(_config(scene, tmp_path / "none", resume=True))
    assert not (tmp_path / "none").exists()
    with pytest.raises(UserError, match="either --resume"):
        xray_train.run(_config(scene, tmp_path / "x", resume=True, overwrite=True))


def _nan_renders(monkeypatch, calls: set[int]) -> None:
    """The field's line integrals are NaN on these training renders (counted from 1)."""
    real, count = xray_loop.field_line_integrals, [0]

    def render(*args, **kw):
        count[0] += 1
        out = real(*args, **kw)
        return out * float("nan") if count[0] in calls else out

    monkeypatch.setattr(xray_loop, "field_line_integrals", render)


def test_non_finite_loss_restores_and_halves_the_learning_rate(scene, tmp_path, monkeypatch, capsys):
    _nan_renders(monkeypatch, {12})
    out = xray_train.run(_config(scene, tmp_path / "run"))
    assert out.steps == STEPS and np.isfinite(out.psnr_3d)
    assert "xray-train: non-finite loss; restored step 10, learning rate x0.5" in capsys.readouterr().err
    assert torch.load(out.checkpoint, weights_only=True)["lr_factor"] == 0.5
    assert json.loads(out.manifest.read_text())["used"]["lr_factor"] == 0.5
    monkeypatch.undo()
    _nan_renders(monkeypatch, {5, 6, 7})
    with pytest.raises(TrainingDiverged, match=r"at step 4 after 3 restores .*; no checkpoint written to .*checkpoint"):
        xray_train.run(_config(scene, tmp_path / "diverged"))


def test_resume_flag_is_on_the_command():
    cfg = cli.config_from_args("xray-train", ["s", "r", "--resume", "--checkpoint-seconds", "5"])
    assert cfg.resume and cfg.checkpoint_seconds == 5.0


def test_a_run_moved_with_its_scene_loads_from_anywhere(scene, tmp_path, monkeypatch):
    """config.json records the scene relative to the run too: OUT/run and OUT/scene moved together still load
    from another working directory, with the recorded paths gone."""
    import shutil

    from nerfpipe.model.xray import load_xray_run

    out = tmp_path / "out"
    shutil.copytree(scene, out / "scene")
    xray_train.run(_config(out / "scene", out / "run", max_steps=3))
    assert json.loads((out / "run" / "config.json").read_text())["scene_from_run"] == "../scene"
    shutil.move(str(out), str(tmp_path / "moved"))
    monkeypatch.chdir(tmp_path / "moved" / "run")
    run = load_xray_run(tmp_path / "moved" / "run", "cpu")
    assert run.volume().shape == (16, 16, 16)
