"""pipelines/Snakefile, run for real: `snakemake --cores 2` over two tiny posed captures builds every output and a
second run does nothing; the generic cluster executor, with a local stand-in for a scheduler's submit command,
submits every job with its resources, retries a failed one with attempt x memory, and re-enters where a failed
capture left off; each job's inputs are make's prerequisites of the same target and its command runs that one
recipe; `snakemake -n` and `--lint` are clean.

The tests run a copy of the checkout's workflow files (Makefile, pipelines/, and the code the stages depend on;
.venv linked): the jobs depend on the code files by their times, as make does, and other work in this checkout
must not make a second run rebuild. The code that runs is the checkout's (.venv's editable install)."""

import json
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from nerfpipe.stages import scene

ROOT = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent
SNAKEMAKE = VENV_BIN / "snakemake"
pytestmark = pytest.mark.skipif(
    shutil.which("make") is None or not SNAKEMAKE.is_file() or not (ROOT / ".venv" / ".installed").is_file(),
    reason="needs make, the project's .venv (make install) and snakemake in it (pip install -e '.[workflow]')",
)
STAGES = ("poses", "convert", "train", "render", "depth", "eval", "mesh")
TINY = """
args:
  train: >-
    --max-steps 40 --batch-rays 512 --resolution 16,24 --occupancy-resolution 16 --eval-every 0 --final-eval-views 1
  render: "--frames=2"
  mesh: "--resolution 32 --no-colors"
resources:
  poses: {threads: 1, mem_mb: 1000}
  convert: {threads: 1, mem_mb: 1000}
  train: {threads: 1, mem_mb: 2000}
  render: {threads: 1, mem_mb: 1000}
  depth: {threads: 1, mem_mb: 1000}
  eval: {threads: 1, mem_mb: 1000}
  mesh: {threads: 1, mem_mb: 1000}
"""
OUTPUTS = (
    "scene/transforms.json",
    "run/manifest.json",
    "run/checkpoint.pt",
    "video.mp4",
    "depth/manifest.json",
    "eval.json",
    "mesh.ply",
    "self_checks.txt",
)
CHECK_LINE = re.compile(
    r"^self-checks: all \d+ ok$|^(convert|train|render|depth|eval|mesh) \(.+\): \w+ = .+ \(expected "
)


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """A copy of the workflow and the code its jobs depend on, with the checkout's .venv linked."""
    copy = tmp_path_factory.mktemp("checkout")
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("Makefile", "pyproject.toml", "__init__.py", "cli.py"):
        shutil.copy2(ROOT / name, copy / name)
    for name in ("pipelines", "stages", "radiance", "data", "model"):
        shutil.copytree(ROOT / name, copy / name, ignore=ignore)
    (copy / ".venv").symlink_to(ROOT / ".venv")
    return copy


def _snakemake(root: Path, work: Path, *args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MAKE")}
    env["PATH"] = f"{VENV_BIN}{os.pathsep}{env.get('PATH', '')}"
    cmd = [str(SNAKEMAKE), "-s", str(root / "pipelines" / "Snakefile"), "--configfile", "tiny.yaml", *args]
    return subprocess.run(cmd, cwd=work, capture_output=True, text=True, env=env, timeout=timeout)


def _posed(work: Path, name: str, seed: int) -> None:
    scene.run(scene.Config(out_dir=work / "posed" / name, kind="posed", size=32, views=10, seed=seed))


def _jobs(stdout: str) -> dict[str, int]:
    """The job counts of snakemake's 'Job stats' table."""
    table = stdout[stdout.index("Job stats:") :].splitlines()[3:]
    counts = {}
    for line in table:
        words = line.split()
        if len(words) != 2 or words[0] == "total":
            break
        counts[words[0]] = int(words[1])
    return counts


def _dry_jobs(stdout: str) -> list[tuple[str, str, str, str]]:
    """(rule, its input line, its output line, its shell command) of each job `snakemake -n -p` lists."""
    jobs = []
    for block in re.split(r"\n\s*\n", stdout):
        rule = re.search(r"^(?:local)?rule (\w+):$", block, flags=re.M)
        if rule:
            field = {k: v for k, v in re.findall(r"^\s*(input|output): (.*)$", block, flags=re.M)}
            shell = re.search(r"^Shell command: (.*)$", block, flags=re.M)
            jobs.append(
                (rule.group(1), field.get("input", ""), field.get("output", ""), shell.group(1) if shell else "")
            )
    return jobs


def _assert_built(out: Path) -> None:
    for rel in OUTPUTS:
        assert (out / rel).is_file(), out / rel
    lines = (out / "self_checks.txt").read_text().splitlines()
    assert lines and all(CHECK_LINE.match(line) for line in lines), lines


def _make_prerequisites(root: Path, variables: list[str], target: str) -> set[str]:
    """What make's database says `target` depends on (normal prerequisites, absolute paths)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MAKE")}
    res = subprocess.run(
        ["make", "-pq", "--no-print-directory", "-C", str(root), *variables, target],
        capture_output=True,
        text=True,
        env=env,
    )
    line = next(line for line in res.stdout.splitlines() if line.startswith(f"{target}: "))
    normal = line[len(target) + 2 :].split("|")[0].split()
    return {p if p.startswith("/") else str(root / p) for p in normal}


def test_jobs_read_what_make_reads_and_run_only_their_recipe(root, tmp_path):
    """Photos, a video and a posed dataset: every stage job's inputs are exactly make's prerequisites of the same
    target, and its command, dry-run by make (-n), runs that stage's nerfpipe command and no other."""
    work = tmp_path
    (work / "tiny.yaml").write_text(TINY)
    scene.run(scene.Config(out_dir=work / "captures" / "mug", kind="photos", size=16, views=3, seed=0))
    (work / "captures" / "walk").mkdir()
    (work / "captures" / "walk" / "walk.mp4").write_bytes(b"a video; only a dry run reads this folder")
    scene.run(scene.Config(out_dir=work / "posed" / "box", kind="posed", size=16, views=3, seed=0))
    sources = {
        "mug": f"PHOTOS={work}/captures/mug/images",
        "walk": f"PHOTOS={work}/captures/walk/walk.mp4",
        "box": f"POSED={work}/posed/box",
    }
    dry = _snakemake(root, work, "-n", "-p")
    assert dry.returncode == 0, dry.stderr[-3000:]
    seen = []
    for rule, inputs, output, shellcmd in _dry_jobs(dry.stdout):
        if rule not in STAGES:
            continue
        name = output.split("/")[1]
        target = str(work / output)
        mine = {p if p.startswith("/") else str(work / p) for p in inputs.split(", ")}
        assert mine == _make_prerequisites(root, [f"OUT={work}/runs/{name}", sources[name]], target), output
        command = shellcmd.split(" > ")[0].replace("make -C", "make -n -C", 1)
        assert command.startswith("make -n -C") and f' "$PWD"/{output} ' in command  # no absolute path: a moved
        plan = subprocess.run(
            ["bash", "-c", command],
            capture_output=True,
            text=True,
            cwd=work,  # folder re-runs
            env={k: v for k, v in os.environ.items() if not k.startswith("MAKE")},
        )
        assert plan.returncode == 0, plan.stderr[-2000:]
        ran = re.findall(r"(?:^|/)nerfpipe (\w+) ", plan.stdout, flags=re.M)
        assert ran == [rule], (output, plan.stdout)
        seen.append((name, rule))
    expected = {(n, s) for n in ("mug", "walk") for s in STAGES} | {("box", s) for s in STAGES if s != "poses"}
    assert set(seen) == expected and len(seen) == len(expected)
    poses = next(job[3] for job in _dry_jobs(dry.stdout) if job[0] == "poses" and job[2].startswith("runs/walk/"))
    assert 'POSES_ARGS="--num-threads 1 "' in poses and 'PHOTOS="$PWD"/captures/walk/walk.mp4' in poses


def test_dry_run_lint_and_profiles_are_clean(root, tmp_path):
    work = tmp_path
    (work / "tiny.yaml").write_text(TINY)
    _posed(work, "a", 0)
    _posed(work, "b", 1)
    dry = _snakemake(root, work, "-n")
    assert dry.returncode == 0, dry.stderr[-3000:]
    assert "This was a dry-run (flag -n)." in dry.stdout
    assert "warning" not in (dry.stdout + dry.stderr).lower()
    assert _jobs(dry.stdout) == {
        "convert": 2,
        "train": 2,
        "depth": 2,
        "eval": 2,
        "mesh": 2,
        "render": 2,
        "self_checks": 2,
        "all": 1,
    }
    lint = _snakemake(root, work, "--lint")
    assert lint.returncode == 0 and "Lints for" not in lint.stdout + lint.stderr, lint.stdout + lint.stderr
    assert "Congratulations, your workflow is in a good condition!" in lint.stdout + lint.stderr
    # the profiles: every key is an option snakemake takes (the SLURM plugin is not installed here: its executor
    # line is checked by name and left out of the dry run)
    for profile, executor in (("slurm", "slurm"), ("cluster-generic", "cluster-generic")):
        text = (root / "pipelines" / "snakemake" / "profiles" / profile / "config.yaml").read_text()
        assert f"\nexecutor: {executor}\n" in text
        copy = tmp_path / "profiles" / profile
        copy.mkdir(parents=True)
        (copy / "config.yaml").write_text(text.replace(f"\nexecutor: {executor}\n", "\n"))
        run = _snakemake(root, work, "-n", "--profile", str(copy))
        assert run.returncode == 0 and "This was a dry-run" in run.stdout, (profile, run.stderr[-2000:])


def test_local_cores_build_every_output_then_nothing(root, tmp_path):
    work = tmp_path / "project"
    work.mkdir()
    (work / "tiny.yaml").write_text(TINY)
    _posed(work, "a", 0)
    _posed(work, "b", 1)
    first = _snakemake(root, work, "--cores", "2")
    assert first.returncode == 0, first.stderr[-4000:]
    for name in ("a", "b"):
        out = work / "runs" / name
        _assert_built(out)
        assert "nerfpipe train " in (out / "logs" / "train.log").read_text()
        # render's budget came from make (the training run's time, at least 60 s), as in a `make` run
        trained = json.loads((out / "run" / "manifest.json").read_text())["used"]["train_seconds"]
        budget = json.loads((out / "video.manifest.json").read_text())["used"]["budget"]
        assert budget["max_seconds"] == max(60, math.ceil(trained)), budget
    assert re.search(r"^a: (self-checks|\w+ \()", first.stdout, flags=re.M), first.stdout[-2000:]  # onsuccess
    moved = work.parent / f"{work.name}-moved"  # the project folder moved: its commands name no absolute path
    work.rename(moved)
    again = _snakemake(root, moved, "--cores", "2")
    assert again.returncode == 0, again.stderr[-2000:]
    assert "Nothing to be done (all requested files are present and up to date)." in again.stderr
    assert "rule " not in again.stderr and "Job stats" not in again.stderr


SUBMIT = """#!/bin/bash
# A stand-in for a scheduler's submit command: records what the job asked for, runs the job script in the
# background (the jobs run at once, as on a cluster) and prints a job id.
set -eu
jobscript="${@: -1}"
echo "$*" >> "$(dirname "$0")/submitted.log"
nohup bash "$jobscript" > "$jobscript.out" 2>&1 &
echo "local-$!"
"""


def test_cluster_executor_submits_jobs_with_resources_retries_and_reenters(root, tmp_path):
    """The generic profile with a local submit command. A capture whose mesh options are wrong: every job is
    submitted with its rule's resources; mesh fails, is retried once with twice the memory (the profile's
    retries: 1), and the run fails with the rest built (--keep-going). Once the options are fixed, a second run
    submits mesh alone (the trained run is kept); a third submits nothing."""
    work = tmp_path
    (work / "tiny.yaml").write_text(TINY + 'capture_args:\n  cap: {mesh: "--resolution not-a-number"}\n')
    _posed(work, "cap", 0)
    submit = work / "submit.sh"
    submit.write_text(SUBMIT)
    submit.chmod(0o755)
    log = work / "submitted.log"
    command = (
        f"{submit} --rule {{rule}} --threads {{threads}} --mem {{resources.mem_mb}} "
        "--runtime {resources.runtime} --gpu {resources.gpu}"
    )
    profile = [
        "--profile",
        str(root / "pipelines" / "snakemake" / "profiles" / "cluster-generic"),
        "--cluster-generic-submit-cmd",
        command,
        "--jobs",
        "2",
        "--latency-wait",
        "5",
        "--keep-going",
        "--seconds-between-status-checks",
        "1",
    ]
    out = work / "runs" / "cap"

    first = _snakemake(root, work, *profile)
    assert first.returncode != 0, first.stderr[-3000:]
    assert "--resolution" in (out / "logs" / "mesh.log").read_text()  # typer's line naming the bad option
    assert not (out / "mesh.ply").exists() and not (out / "self_checks.txt").exists()
    for rel in ("scene/transforms.json", "run/manifest.json", "video.mp4", "depth/manifest.json", "eval.json"):
        assert (out / rel).is_file(), rel
    jobs = [shlex.split(line) for line in log.read_text().splitlines()]
    assert all(Path(words[-1]).name.startswith("snakejob.") and words[-1].endswith(".sh") for words in jobs)
    asked = [dict(zip(words[0:10:2], words[1:10:2], strict=True)) for words in jobs]
    rules = sorted(a["--rule"] for a in asked)
    assert rules == sorted(["convert", "train", "render", "depth", "eval", "mesh", "mesh"]), rules
    train = next(a for a in asked if a["--rule"] == "train")
    # as config says: train's memory and threads, no GPU, minutes from the plan (900 s budget: 2 x 15 + 10)
    assert (train["--mem"], train["--threads"], train["--gpu"], train["--runtime"]) == ("2000", "1", "0", "40")
    assert [int(a["--mem"]) for a in asked if a["--rule"] == "mesh"] == [1000, 2000]  # attempt 2: twice the memory
    trained = (out / "run" / "manifest.json").stat().st_mtime_ns

    (work / "tiny.yaml").write_text(TINY)
    log.unlink()
    second = _snakemake(root, work, *profile)
    assert second.returncode == 0, second.stderr[-3000:]
    _assert_built(out)
    assert [shlex.split(line)[1] for line in log.read_text().splitlines()] == ["mesh"]
    assert (out / "run" / "manifest.json").stat().st_mtime_ns == trained

    log.unlink()
    third = _snakemake(root, work, *profile)
    assert third.returncode == 0 and "Nothing to be done" in third.stderr, third.stderr[-2000:]
    assert not log.exists()
