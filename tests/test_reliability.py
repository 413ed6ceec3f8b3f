"""Never lose a run (issue 19): interrupts, reruns, full disks, one writer per folder, checkpoint integrity, and
training views in bounded memory. Signals are sent to real `nerfpipe train` processes; faults are injected into
the one writer (`nerfpipe.data.atomic._write`) or come from a real file-size limit (RLIMIT_FSIZE).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

import nerfpipe.data.atomic
from nerfpipe import cli
from nerfpipe.data.atomic import write_json
from nerfpipe.data.errors import UserError, WriteFailed
from nerfpipe.data.lock import LOCK_NAME, FolderBusy, folder_lock
from nerfpipe.data.transforms import read_scene
from nerfpipe.model import load_trained
from nerfpipe.model.checkpoint import read_checkpoint
from nerfpipe.model.methods.density import DensityOptions
from nerfpipe.model.views import Views, load_views
from nerfpipe.radiance.camera import Intrinsics, generate_rays
from nerfpipe.stages import scene as scene_stage
from nerfpipe.stages import train

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "--device",
    "cpu",
    "--threads",
    "1",
    "--batch-rays",
    "256",
    "--resolution",
    "16,24",
    "--occupancy-resolution",
    "16",
    "--eval-every",
    "0",
    "--final-eval-views",
    "1",
]


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scene") / "rgba"
    scene_stage.run(scene_stage.Config(out_dir=out, kind="rgba", size=24, views=10, seed=0))
    return out


@pytest.fixture(scope="module")
def finished_run(scene_dir, tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("run") / "run"
    train.run(_config(scene_dir, run_dir))
    return run_dir


def _config(scene_dir: Path, run_dir: Path, **kw) -> train.Config:
    base = dict(
        scene_dir=scene_dir,
        run_dir=run_dir,
        max_steps=2,
        max_seconds=60.0,
        batch_rays=256,
        options=DensityOptions(resolution=(16, 24), occupancy_resolution=16),
        eval_every=0,
        final_eval_views=1,
        device="cpu",
        threads=1,
    )
    base.update(kw)
    if base.get("method", "density") != "density" and "options" not in kw:
        base["options"] = None  # another method: its own defaults
    return train.Config(**base)


def _copy(run_dir: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(run_dir, tmp_path / "run"))


def _cli(capsys, *args: str) -> tuple[int, str]:
    with pytest.raises(SystemExit) as e:
        cli.main([str(a) for a in args])
    return e.value.code, capsys.readouterr().err


def _spawn(*args: str, **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, str(ROOT / "cli.py"), *map(str, args)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 180.0) -> None:
    t0 = time.monotonic()
    while not path.exists():
        if proc.poll() is not None:
            raise AssertionError(f"process ended ({proc.returncode}) before {path.name}: {proc.stderr.read()}")
        if time.monotonic() - t0 > timeout:
            proc.kill()
            raise AssertionError(f"no {path.name} after {timeout} s")
        time.sleep(0.1)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ---------------------------------------------------------------------------------------------- interrupts
@pytest.mark.parametrize(("signum", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGKILL, -9)])
def test_signal_during_train_leaves_a_checkpoint_to_resume(scene_dir, tmp_path, signum, code):
    """Ctrl-C / SIGTERM save the current step and say so in one line; kill -9 loses at most checkpoint_seconds
    (here 0.3 s); each run then continues with --resume."""
    run_dir = tmp_path / "run"
    proc = _spawn(
        "train",
        scene_dir,
        run_dir,
        *TINY,
        "--max-steps",
        "100000",
        "--max-seconds",
        "600",
        "--checkpoint-seconds",
        "0.3",
    )
    _wait_for(run_dir / "checkpoint.pt", proc)  # written by the time budget: the loop is running
    time.sleep(0.5)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert state["step"] >= 1 and not (run_dir / "manifest.json").exists()
    if signum != signal.SIGKILL:  # (kill -9 during a write may leave a temporary: never a half checkpoint.pt)
        assert not list(run_dir.glob(".checkpoint.pt.*"))
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in err, err
        assert lines[0].startswith(f"error: interrupted ({signal.Signals(signum).name}) at step {state['step']} ")
        assert "continue with --resume" in lines[0]
    with pytest.raises(UserError, match="resume=True to continue it or overwrite=True"):
        train.run(_config(scene_dir, run_dir))  # an interrupted run is not silently replaced
    out = train.run(_config(scene_dir, run_dir, resume=True, max_steps=state["step"] + 2))
    assert out.steps == state["step"] + 2 and out.manifest.is_file()


def test_interrupted_consumers_leave_nothing_that_looks_complete(finished_run, tmp_path, monkeypatch):
    """render, depth, eval and mesh stopped midway (Ctrl-C inside the renderer or the density query) leave no
    final file and no manifest: their outputs are atomic and the manifest comes last."""
    from nerfpipe.model.trained import Trained
    from nerfpipe.radiance.fields import TensoRF
    from nerfpipe.stages import depth, eval, mesh, render

    calls = {"n": 0}
    real_render, real_density = Trained.render_rays, Trained.density

    def interrupt_later(real):
        def wrapped(self, *args, **kw):
            calls["n"] += 1
            if calls["n"] > 2:
                raise KeyboardInterrupt
            return real(self, *args, **kw)

        return wrapped

    monkeypatch.setattr(Trained, "render_rays", interrupt_later(real_render))
    monkeypatch.setattr(Trained, "density", interrupt_later(real_density))
    monkeypatch.setattr(TensoRF, "density", interrupt_later(TensoRF.density))  # mesh queries the field directly
    monkeypatch.setattr(TensoRF, "density_inference", interrupt_later(TensoRF.density_inference))  # the renderers
    runs = {
        "render": (
            lambda: render.run(render.Config(run_dir=finished_run, out=tmp_path / "v.mp4", frames=6, device="cpu")),
            [tmp_path / "v.mp4", tmp_path / "v.manifest.json"],
        ),
        "depth": (
            lambda: depth.run(depth.Config(run_dir=finished_run, out_dir=tmp_path / "d", device="cpu")),
            [tmp_path / "d" / "manifest.json"],
        ),
        "eval": (
            lambda: eval.run(eval.Config(run_dir=finished_run, out=tmp_path / "e.json", device="cpu")),
            [tmp_path / "e.json", tmp_path / "e.manifest.json"],
        ),
        "mesh": (
            lambda: mesh.run(mesh.Config(run_dir=finished_run, out=tmp_path / "m.ply", resolution=32, device="cpu")),
            [tmp_path / "m.ply", tmp_path / "m.report.json"],
        ),
    }
    for name, (run, outputs) in runs.items():
        calls["n"] = 0
        with pytest.raises(KeyboardInterrupt):
            run()
            print(f"{name} finished")
        assert calls["n"] > 2, f"{name} never reached the renderer"
        for path in outputs:
            assert not path.exists(), f"{name} left {path.name}"
        assert not [p for p in tmp_path.rglob(".*") if p.is_file()], f"{name} left a temporary file"


# ---------------------------------------------------------------------------------------------- reruns
def test_rerun_refuses_without_resume_or_overwrite(scene_dir, finished_run, tmp_path):
    run_dir = _copy(finished_run, tmp_path)
    before = _sha(run_dir / "checkpoint.pt")
    with pytest.raises(UserError, match=r"already holds an earlier output \(checkpoint.pt, manifest.json\)"):
        train.run(_config(scene_dir, run_dir))
    assert _sha(run_dir / "checkpoint.pt") == before
    with pytest.raises(UserError, match="either --resume"):
        train.run(_config(scene_dir, run_dir, resume=True, overwrite=True))
    out = train.run(_config(scene_dir, run_dir, overwrite=True, seed=1))
    assert out.steps == 2 and _sha(run_dir / "checkpoint.pt") != before
    assert not (tmp_path / "run.previous").exists()  # set aside during the run, deleted after its success
    assert not (run_dir / LOCK_NAME).exists()


def test_failed_overwrite_keeps_the_earlier_run(scene_dir, finished_run, tmp_path, monkeypatch):
    run_dir = _copy(finished_run, tmp_path)
    before = _sha(run_dir / "checkpoint.pt")
    _fail_writes(monkeypatch, "checkpoint.pt", errno.ENOSPC)
    with pytest.raises(
        WriteFailed,
        match=r"no space left on device writing .*checkpoint.pt \(the earlier output "
        r"is kept in .*run.previous\)",
    ):
        train.run(_config(scene_dir, run_dir, overwrite=True))
    assert _sha(tmp_path / "run.previous" / "checkpoint.pt") == before


def test_other_folder_stages_refuse_a_finished_output(finished_run, tmp_path):
    from nerfpipe.stages import depth

    out = tmp_path / "s"
    scene_stage.run(scene_stage.Config(out_dir=out, kind="rgba", size=16, views=4))
    with pytest.raises(UserError, match=r"already holds an earlier output \(manifest.json\); set overwrite=True"):
        scene_stage.run(scene_stage.Config(out_dir=out, kind="rgba", size=16, views=4))
    scene_stage.run(scene_stage.Config(out_dir=out, kind="rgba", size=16, views=5, overwrite=True))
    assert len(read_scene(out).frames) == 5 and not (tmp_path / "s.previous").exists()
    config = depth.Config(run_dir=finished_run, out_dir=tmp_path / "d", device="cpu")
    depth.run(config)
    with pytest.raises(UserError, match="already holds an earlier output"):
        depth.run(config)
    depth.run(depth.Config(run_dir=finished_run, out_dir=tmp_path / "d", device="cpu", overwrite=True))
    with pytest.raises(UserError, match="--views"):  # a failed stage leaves no empty folder behind
        depth.run(depth.Config(run_dir=finished_run, out_dir=tmp_path / "d2", views="nope"))
    assert not (tmp_path / "d2").exists()


# ---------------------------------------------------------------------------------------------- full disks, I/O
def _fail_writes(monkeypatch, name: str, code: int) -> None:
    """Writes of files called `name` (through data.atomic) fail with OSError(code); others go through."""
    real = nerfpipe.data.atomic._write

    def write(f, data):
        if Path(f.name).name.startswith(f".{name}."):
            raise OSError(code, os.strerror(code))
        real(f, data)

    monkeypatch.setattr(nerfpipe.data.atomic, "_write", write)


def test_full_disk_during_train_is_one_line_and_keeps_the_checkpoint(
    scene_dir, finished_run, tmp_path, capsys, monkeypatch
):
    run_dir = _copy(finished_run, tmp_path)
    before = _sha(run_dir / "checkpoint.pt")
    _fail_writes(monkeypatch, "checkpoint.pt", errno.ENOSPC)
    code, err = _cli(capsys, "train", scene_dir, run_dir, *TINY, "--resume", "--max-steps", "4")
    assert code == 2 and err == f"error: no space left on device writing {run_dir / 'checkpoint.pt'}\n"
    assert _sha(run_dir / "checkpoint.pt") == before and read_checkpoint(run_dir / "checkpoint.pt", "cpu")
    assert not list(run_dir.glob(".checkpoint.pt.*"))


@pytest.mark.parametrize(
    ("code", "cause"),
    [(errno.EIO, "input/output error"), (errno.EACCES, "permission denied"), (errno.ENOSPC, "no space left on device")],
)
def test_write_errors_name_the_file_and_cause(tmp_path, monkeypatch, code, cause):
    path = tmp_path / "m.json"
    write_json(path, {"old": 1})
    _fail_writes(monkeypatch, "m.json", code)
    with pytest.raises(WriteFailed) as e:
        write_json(path, {"new": 2})
    assert str(e.value) == f"{cause} writing {path}"
    assert json.loads(path.read_text()) == {"old": 1} and [p.name for p in tmp_path.iterdir()] == ["m.json"]


def test_a_real_file_size_limit_during_train(scene_dir, tmp_path):
    """No patching: the kernel refuses writes past RLIMIT_FSIZE (EFBIG) as a full disk would (ENOSPC); the
    checkpoint is the largest file train writes, so it is the one that fails."""
    limit = 64 * 1024  # config.json, metrics.csv fit; the tiny field's checkpoint (~300 KB) does not

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = _spawn("train", scene_dir, tmp_path / "run", *TINY, "--max-steps", "2", preexec_fn=cap)
    _, err = proc.communicate(timeout=180)
    assert proc.returncode == 2, err
    assert err == f"error: file too large writing {tmp_path / 'run' / 'checkpoint.pt'}\n"
    assert not (tmp_path / "run" / "checkpoint.pt").exists() and not (tmp_path / "run" / "manifest.json").exists()


# ---------------------------------------------------------------------------------------------- one writer
def test_second_writer_is_refused_and_a_dead_holder_is_taken_over(scene_dir, tmp_path, capsys):
    run_dir = tmp_path / "run"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from data.lock import folder_lock\n"
            "with folder_lock(sys.argv[1]):\n    print('held', flush=True); time.sleep(120)",
            str(run_dir),
        ],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        code, err = _cli(capsys, "train", scene_dir, run_dir, *TINY)
        assert code == 2 and f"(pid {holder.pid})" in err and err.count("\n") == 1, err
        assert not (run_dir / "config.json").exists()
    finally:
        holder.kill()
        holder.wait()
    assert (run_dir / LOCK_NAME).read_text().split()[0] == str(holder.pid)  # stale: its holder is dead
    out = train.run(_config(scene_dir, run_dir))
    assert out.manifest.is_file() and not (run_dir / LOCK_NAME).exists()


def test_lock_excludes_within_one_process_too(tmp_path):
    with folder_lock(tmp_path / "f"):
        with pytest.raises(FolderBusy, match=f"pid {os.getpid()}"):
            with folder_lock(tmp_path / "f"):
                pass
    with folder_lock(tmp_path / "f"):  # released
        pass


# ---------------------------------------------------------------------------------------------- integrity
def test_checkpoint_that_no_longer_matches_its_manifest_is_refused(finished_run, tmp_path):
    run_dir = _copy(finished_run, tmp_path)
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["checkpoint_sha256"] == _sha(run_dir / "checkpoint.pt")
    load_trained(run_dir, "cpu")
    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    state["step"] = 999  # a valid checkpoint, but not the one this run finished with
    torch.save(state, run_dir / "checkpoint.pt")
    with pytest.raises(UserError, match="does not match the sha256 recorded in manifest.json"):
        load_trained(run_dir, "cpu")


@pytest.mark.parametrize(
    ("state", "match"),
    [
        (
            {"format": "nerfpipe-xray-1", "nerfpipe_version": "0.9"},
            r"not a nerfpipe train checkpoint \(format 1\): found format 'nerfpipe-xray-1' written by nerfpipe 0.9",
        ),
        ({"format": 2, "nerfpipe_version": "9.0"}, "found format 2 written by nerfpipe 9.0, this is nerfpipe"),
        (
            {"format": 1, "field_config": {"kind": "gaussians"}},
            "written by no method nerfpipe knows \\(a field of kind 'gaussians'\\); expected one of density, nerf",
        ),
    ],
)
def test_foreign_checkpoints_are_refused_with_what_was_expected(tmp_path, state, match):
    torch.save(state, tmp_path / "checkpoint.pt")
    with pytest.raises(UserError, match=match):
        read_checkpoint(tmp_path / "checkpoint.pt", "cpu")


# ---------------------------------------------------------------------------------------------- bounded memory
def test_views_make_the_rays_whole_images_would(tmp_path):
    """Rays made per batch equal generate_rays over whole images (distorted cameras too); memory is the uint8
    images plus a camera per view."""
    import numpy as np

    from nerfpipe.data.transforms import Frame, Scene, write_scene
    from nerfpipe.data.video import write_png

    intr = Intrinsics(w=20, h=14, fx=18.0, fy=19.0, cx=9.7, cy=7.2, k1=-0.2, k2=0.05, p1=0.01, p2=-0.005)
    g = torch.Generator().manual_seed(0)
    frames = []
    for i in range(3):
        q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3], pose[:3, 3] = q * torch.sign(torch.det(q)), torch.randn(3, generator=g, dtype=torch.float64)
        write_png(tmp_path / f"{i}.png", (torch.rand(14, 20, 3, generator=g).numpy() * 255).astype("uint8"))
        frames.append(Frame(file_path=f"{i}.png", world_from_cam=pose.numpy()))
    scene = Scene(
        root=tmp_path,
        frames=tuple(frames),
        intrinsics=intr,
        applied_transform=np.eye(4)[:3],
        applied_scale=1.0,
        aabb=np.array([[-1.0] * 3, [1.0] * 3]),
        near=0.1,
        far=10.0,
        splits={"train": (0, 1, 2)},
        has_alpha=False,
        extra={},
    )
    write_scene(scene, tmp_path / "transforms.json")
    scene = read_scene(tmp_path)
    views = load_views(scene, (0, 1, 2))
    idx = torch.randperm(views.n_rays, generator=g)
    o, d, rgb, alpha = views.batch(idx, torch.device("cpu"))
    want_o, want_d = zip(*(generate_rays(intr, torch.as_tensor(f.world_from_cam)) for f in scene.frames), strict=True)
    torch.testing.assert_close(d, torch.cat(want_d).float()[idx], atol=2e-7, rtol=0)
    torch.testing.assert_close(o, torch.cat(want_o).float()[idx])
    assert views.view[idx].tolist() == (idx // (20 * 14)).tolist() and (alpha == 1).all()
    held = sum(t.numel() * t.element_size() for t in vars(views).values() if isinstance(t, torch.Tensor))
    assert held <= 4 * views.n_rays + 1024, held  # 4 bytes a pixel (RGBA) and a camera per view
    assert isinstance(views, Views)


def test_image_of_the_wrong_size_is_refused(scene_dir, tmp_path):
    import cv2

    scene = Path(shutil.copytree(scene_dir, tmp_path / "s"))
    image = scene / read_scene(scene).frames[0].file_path
    cv2.imwrite(str(image), cv2.resize(cv2.imread(str(image), cv2.IMREAD_UNCHANGED), (30, 24)))
    with pytest.raises(UserError, match=r"image is 30x24, transforms.json says 24x24"):
        train.run(_config(scene, tmp_path / "run"))
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


# ---------------------------------------------------------------------------------------------- the table
def test_reliability_doc_names_real_tests():
    """docs/RELIABILITY.md: at least 30 faults and bad inputs, each row naming a test that exists."""
    rows = [ln for ln in (ROOT / "docs" / "RELIABILITY.md").read_text().splitlines() if ln.startswith("| ")]
    rows = [r for r in rows if r.split("|")[1].strip().isdigit()]
    assert len(rows) >= 30, len(rows)
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert len(cells) == 7, row
        path, _, name = cells[-1].strip("`").partition("::")
        source = ROOT / path
        assert source.is_file() and f"def {name}(" in source.read_text(), f"row {cells[0]}: no test {cells[-1]}"
