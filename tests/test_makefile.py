"""The Makefile chain on a tiny posed scene: every output is built, a rerun has nothing to rebuild, and a change
re-runs exactly the stages whose code (their own, or the core packages) or inputs changed. The plan is printed
once, first; the video gets the training run's time as its budget; the self-check summary comes last, on every
`make all`."""

import json
import math
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from nerfpipe.pipelines import plan
from nerfpipe.stages import scene

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(
    shutil.which("make") is None or not (ROOT / ".venv" / ".installed").is_file(),
    reason="needs make and the project's .venv (make install)",
)


def _make(*args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MAKE")}
    return subprocess.run(
        ["make", "-C", str(ROOT), "--no-print-directory", *args], capture_output=True, text=True, env=env, timeout=600
    )


STAGES = ("poses", "convert", "train", "render", "depth", "eval", "mesh")
SUMMARY = re.compile(
    r"^self-checks: all \d+ ok$|^(poses|convert|train|render|depth|eval|mesh) \(.+\): \w+ = .+ \(expected "
)


def _stages_run(stdout: str) -> list[str]:
    """The stages whose command a make run printed (`-n`: would run)."""
    return [stage for stage in STAGES if f"nerfpipe {stage} " in stdout]


def test_posed_chain_builds_everything_then_nothing(tmp_path):
    src = tmp_path / "src"
    scene.run(scene.Config(out_dir=src, kind="posed", size=48, views=12, seed=0))
    out = tmp_path / "out"
    args = [
        f"POSED={src}",
        f"OUT={out}",
        "TRAIN_ARGS=--max-steps 150 --batch-rays 1024 --eval-every 0 --final-eval-views 1",
        "RENDER_ARGS=--frames=3",
        "MESH_ARGS=--resolution 48 --no-colors",
    ]
    first = _make("all", *args)
    assert first.returncode == 0, first.stderr[-2000:]
    assert first.stdout.count("nerfpipe plan:") == 1, first.stdout  # once, before the first stage
    assert first.stdout.index("nerfpipe plan:") < first.stdout.index("nerfpipe convert ")
    for line in ("convert", "train", "--max-steps 150", "render", "depth", "eval", "mesh", "total"):
        assert line in first.stdout, line
    assert (out / "plan.txt").read_text().count("nerfpipe plan:") == 1
    summary = first.stdout[first.stdout.index("pipelines/suspects.py") :].splitlines()[1:]  # after every stage
    assert first.stdout.index("nerfpipe mesh ") < first.stdout.index("pipelines/suspects.py")
    assert summary and all(SUMMARY.match(line) for line in summary), summary
    trained = json.loads((out / "run" / "manifest.json").read_text())["used"]["train_seconds"]
    budget = json.loads((out / "video.manifest.json").read_text())["used"]["budget"]
    assert budget["max_seconds"] == max(60, math.ceil(trained)), budget  # as long as training took
    for rel in (
        "scene/transforms.json",
        "run/manifest.json",
        "run/checkpoint.pt",
        "video.mp4",
        "depth/manifest.json",
        "eval.json",
        "mesh.ply",
    ):
        assert (out / rel).is_file(), rel
    again = _make("-n", "all", *args)  # nothing to rebuild: only the (phony) self-check summary would run
    assert again.returncode == 0 and _stages_run(again.stdout) == [], again.stdout
    assert again.stdout.strip().splitlines() == [f".venv/bin/python pipelines/suspects.py '{out}'"], again.stdout
    # each stage depends on the code it runs, nothing else; `-W FILE` (what if FILE changed) touches nothing
    core = _make("-n", "-W", "radiance/render.py", "all", *args)  # the core: every stage re-runs
    assert core.returncode == 0, core.stderr[-2000:]
    for stage in ("convert", "train", "render", "depth", "eval", "mesh"):
        assert f"nerfpipe {stage} " in core.stdout, (stage, core.stdout)
    own = _make("-n", "-W", "stages/mesh/grid.py", "all", *args)  # a stage package's own module: that stage
    assert "nerfpipe mesh " in own.stdout and "nerfpipe train " not in own.stdout, own.stdout
    helper = _make("-n", "-W", "benchmarks/standin.py", "all", *args)  # benchmark support: nothing
    assert helper.returncode == 0 and _stages_run(helper.stdout) == [], helper.stdout
    # a changed input re-runs the chain from convert on
    (src / "transforms.json").touch()
    stale = _make("-n", "all", *args)
    assert "nerfpipe convert" in stale.stdout and "nerfpipe train" in stale.stdout


def test_all_ends_with_the_self_check_summary_and_it_never_fails_the_build(tmp_path):
    """A chain whose outputs are all up to date (fabricated, newer than any code): `make all` runs only the
    summary, which prints the suspect check of a record and exits 0; once the record passes, "all N ok"."""
    src, out = tmp_path / "src", tmp_path / "out"
    src.mkdir()
    (src / "transforms.json").write_text("{}")
    later = time.time() + 3600  # newer than any code file, even one being edited now
    os.utime(src / "transforms.json", (later, later))
    records = {
        "scene/transforms.json": {},
        "run/manifest.json": {},
        "video.mp4": None,
        "eval.json": {},
        "depth/manifest.json": {},  # after eval.json: depth reads eval's renders
        "mesh.ply": None,
    }
    for k, (rel, doc) in enumerate(records.items(), start=1):
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(json.dumps(doc) if doc is not None else "")
        os.utime(out / rel, (later + k, later + k))
    slab = {"name": "box_fill", "ok": False, "value": 0.99, "limit": "<= 0.95", "says": "a slab, not an object"}
    report = out / "mesh.report.json"
    report.write_text(json.dumps({"stage": "mesh", "check": "suspect", "checks": [slab]}))
    args = [f"POSED={src}", f"OUT={out}"]
    run = _make("all", *args)
    assert run.returncode == 0 and _stages_run(run.stdout) == [], run.stdout + run.stderr[-2000:]
    assert run.stdout.strip().splitlines()[-1] == (
        f"mesh ({out}/mesh.report.json): box_fill = 0.99 (expected <= 0.95): a slab, not an object"
    )
    report.write_text(json.dumps({"stage": "mesh", "check": "ok", "checks": [{**slab, "ok": True, "value": 0.5}]}))
    run = _make("all", *args)
    assert run.returncode == 0 and run.stdout.strip().splitlines()[-1] == "self-checks: all 1 ok", run.stdout


def test_plan_reads_options_and_the_render_budget(tmp_path):
    assert plan.option("--max-steps 5 --max-seconds 120", "--max-seconds") == "120"
    assert plan.option("--max-seconds=30 --max-seconds 40", "--max-seconds") == "40"  # the last one wins
    assert plan.option("", "--max-seconds", "900") == "900"
    assert plan.render_seconds(tmp_path) == plan.RENDER_SHARE * plan.TRAIN_SECONDS  # no run yet: train's default
    (tmp_path / "manifest.json").write_text(json.dumps({"wall_seconds": 20, "used": {"train_seconds": 412.3}}))
    assert plan.render_seconds(tmp_path) == 207  # half the training time (issue 54), rounded up
    (tmp_path / "manifest.json").write_text(json.dumps({"wall_seconds": 20, "used": {"train_seconds": 2.0}}))
    assert plan.render_seconds(tmp_path) == plan.MIN_RENDER_SECONDS
    fox = plan.Facts(photos=50, size_wh=(1080, 1920), test_views=7, source="50 photos")
    args = {"poses": "", "train": "--max-seconds 300", "render": "", "depth": "", "mesh": ""}
    assert plan.estimate("train", fox, args)[0] == 300 and plan.estimate("render", fox, args)[:2] == (150, "<=")
    assert 40 < plan.estimate("eval", fox, args)[0] < 150  # 7 x 270 x 480 rays (train's downscale 4) at ~13k/s
