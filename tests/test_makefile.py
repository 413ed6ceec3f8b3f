"""The Makefile chain on a tiny posed scene: every output is built, a rerun has nothing to rebuild, and a change
re-runs exactly the stages whose code (their own, or the core packages) or inputs changed."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from stages import scene

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(
    shutil.which("make") is None or not (ROOT / ".venv" / ".installed").is_file(),
    reason="needs make and the project's .venv (make install)",
)


def _make(*args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MAKE")}
    return subprocess.run(["make", "-C", str(ROOT), "--no-print-directory", *args], capture_output=True, text=True,
                          env=env, timeout=600)  # fmt: skip


def test_posed_chain_builds_everything_then_nothing(tmp_path):
    src = tmp_path / "src"
    scene.run(scene.Config(out_dir=src, kind="posed", size=48, views=12, seed=0))
    out = tmp_path / "out"
    args = [
        f"POSED={src}", f"OUT={out}",
        "TRAIN_ARGS=--max-steps 150 --batch-rays 1024 --eval-every 0 --final-eval-views 1",
        "RENDER_ARGS=--frames 3", "MESH_ARGS=--resolution 48 --no-colors",
    ]  # fmt: skip
    first = _make("all", *args)
    assert first.returncode == 0, first.stderr[-2000:]
    for rel in ("scene/transforms.json", "run/manifest.json", "run/checkpoint.pt", "video.mp4",
                "depth/manifest.json", "eval.json", "mesh.ply"):  # fmt: skip
        assert (out / rel).is_file(), rel
    again = _make("-n", "all", *args)
    assert again.returncode == 0 and "Nothing to be done" in again.stdout, again.stdout
    # each stage depends on the code it runs, nothing else; `-W FILE` (what if FILE changed) touches nothing
    core = _make("-n", "-W", "radiance/render.py", "all", *args)  # the core: every stage re-runs
    assert core.returncode == 0, core.stderr[-2000:]
    for stage in ("convert", "train", "render", "depth", "eval", "mesh"):
        assert f"nerfpipe {stage} " in core.stdout, (stage, core.stdout)
    own = _make("-n", "-W", "stages/mesh/grid.py", "all", *args)  # a stage package's own module: that stage
    assert "nerfpipe mesh " in own.stdout and "nerfpipe train " not in own.stdout, own.stdout
    helper = _make("-n", "-W", "benchmarks/standin.py", "all", *args)  # benchmark support: nothing
    assert helper.returncode == 0 and "Nothing to be done" in helper.stdout, helper.stdout
    # a changed input re-runs the chain from convert on
    (src / "transforms.json").touch()
    stale = _make("-n", "all", *args)
    assert "nerfpipe convert" in stale.stdout and "nerfpipe train" in stale.stdout
