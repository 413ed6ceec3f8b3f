"""Data-parallel train through torchrun (`model.distributed`): the rank split, the renderer's random draws a rank
takes, and real two-process runs on gloo (CPU): the same parameters as one process with the same global batch,
Ctrl-C to the torchrun group and --resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from nerfpipe.data.errors import UserError
from nerfpipe.model.distributed import SINGLE, DataParallel, World, world_from_env
from nerfpipe.model.methods.density import DensityOptions
from nerfpipe.stages import scene as scene_stage
from nerfpipe.stages import train
from tests.ports import free_port

ROOT = Path(__file__).resolve().parents[1]
OPTIONS = [
    "--device",
    "cpu",
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


def _torchrun(*args: str, **kw) -> subprocess.Popen:
    """`torchrun --standalone --nproc-per-node 2 -m nerfpipe.cli ARGS` (a free port; OMP_NUM_THREADS=1)."""
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        "2",
        "-m",
        "nerfpipe.cli",
        *map(str, args),
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def test_rank_split_covers_every_ray_once():
    for n in (0, 1, 5, 255, 256, 1023):
        for size in range(1, 9):
            parts = [World(rank=r, size=size).share(n) for r in range(size)]
            rays = [i for p in parts for i in range(n)[p]]
            assert rays == list(range(n)), (n, size)
            lengths = [len(range(n)[p]) for p in parts]
            assert max(lengths) - min(lengths) <= 1


def test_world_from_the_environment():
    assert world_from_env({}) is SINGLE and world_from_env({"WORLD_SIZE": "1", "RANK": "0"}) is SINGLE
    env = {"WORLD_SIZE": "4", "RANK": "3", "LOCAL_RANK": "1", "LOCAL_WORLD_SIZE": "2"}
    assert world_from_env(env) == World(rank=3, size=4, local_rank=1, local_size=2)
    assert world_from_env(env).writer is False and World(rank=0, size=4).writer
    with pytest.raises(UserError, match="expected whole numbers in RANK, WORLD_SIZE"):
        world_from_env({"WORLD_SIZE": "two"})
    with pytest.raises(UserError, match="RANK=2, WORLD_SIZE=2"):
        world_from_env({"WORLD_SIZE": "2", "RANK": "2"})


@pytest.mark.parametrize("total", [256, 255])
def test_each_rank_draws_its_share_of_the_one_process_jitter(total):
    """The fast field's march draws one jitter a ray from torch's global generator: inside `share_draws` rank r
    gets the one process's values for its rays, and leaves the generator where the one process would be."""
    torch.manual_seed(7)
    whole = torch.rand(total)
    after_one = torch.get_rng_state()
    got = []
    for rank in range(2):
        par = DataParallel(World(rank=rank, size=2), torch.device("cpu"), "gloo")
        torch.manual_seed(7)
        share = par.world.share(total)
        with par.share_draws(total, share):
            got.append(torch.rand(len(range(total)[share])))  # what the renderer draws for this rank's rays
        assert torch.equal(torch.get_rng_state(), after_one)
    assert torch.equal(torch.cat(got), whole)


def _tensors(state, prefix=""):
    """Every tensor of a checkpoint, by dotted name."""
    if isinstance(state, torch.Tensor):
        return {prefix: state}
    items = state.items() if isinstance(state, dict) else enumerate(state) if isinstance(state, list) else ()
    return {k: v for key, value in items for k, v in _tensors(value, f"{prefix}.{key}").items()}


def test_two_ranks_give_the_parameters_of_one_process(scene_dir, tmp_path):
    """70 steps (past the occupancy grid's warm-up, where its refresh draws from torch's global generator) of
    255 rays (127 + 128: the share weights) with pose refinement and appearance codes (their gradients are
    averaged too). Tolerance: the ranks' gradient is the one process's summed in another order (float32,
    ~1e-7 relative); Adam turns a relative gradient error e into about e x lr a step, so after 70 steps at
    lr <= 0.03 the parameters agree to ~1e-6 (measured: 9e-5 at most, the density lines); 5e-4 is a sixtieth of
    one Adam step, while a rank that took other rays or other jitter is off by ~0.1 (measured 0.16)."""
    fast = DensityOptions(resolution=(16, 24), occupancy_resolution=16, occupancy_every=4)
    common = dict(
        batch_rays=255,
        max_steps=70,
        options=fast,
        refine=train.RefineOptions(),
        appearance=True,
        eval_every=0,
        final_eval_views=1,
        device="cpu",
    )
    one = train.run(train.Config(scene_dir=scene_dir, run_dir=tmp_path / "one", threads=1, **common))
    proc = _torchrun(
        "train",
        scene_dir,
        tmp_path / "two",
        *OPTIONS,
        "--batch-rays",
        "255",
        "--max-steps",
        "70",
        "--occupancy-every",
        "4",
        "--refine-poses",
        "--appearance",
    )
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert out.count("70 steps in") == 1  # rank 0 reports (cli prints only RANK 0's summary); rc 0: both finished
    a = torch.load(one.checkpoint, weights_only=True)
    b = torch.load(tmp_path / "two" / "checkpoint.pt", weights_only=True)
    assert a["step"] == b["step"] == 70
    ta, tb = _tensors(a), _tensors(b)
    assert ta.keys() == tb.keys()
    for name, x in ta.items():
        if name == ".rng" or not x.dtype.is_floating_point:
            assert torch.equal(x, tb[name]) or name == ".occupancy.binary", name
        elif name.startswith(".occupancy.density"):
            torch.testing.assert_close(tb[name], x, rtol=1e-3, atol=1e-4, msg=name)
        elif not name.startswith(".optimizer") and not name.startswith(".camera_opt.optimizer"):
            torch.testing.assert_close(tb[name], x, rtol=0, atol=5e-4, msg=name)
    differ = (a["occupancy"]["binary"] != b["occupancy"]["binary"]).float().mean()
    assert differ <= 0.01  # a cell at the threshold may flip; measured: none
    manifest = json.loads((tmp_path / "two" / "manifest.json").read_text())
    assert manifest["used"]["world_size"] == 2 and manifest["used"]["data_parallel"]["backend"] == "gloo"
    assert json.loads(one.manifest.read_text())["used"]["world_size"] == 1


def test_ctrl_c_to_torchrun_checkpoints_every_rank_at_one_step_and_resume_continues(scene_dir, tmp_path):
    """Ctrl-C reaches torchrun (the terminal's process group), which passes SIGINT to each rank: the ranks
    agree on the step, rank 0 writes the checkpoint and each says so in one line; --resume under torchrun
    continues the run to its end."""
    run_dir = tmp_path / "run"
    proc = _torchrun(
        "train",
        scene_dir,
        run_dir,
        *OPTIONS,
        "--batch-rays",
        "256",
        "--max-steps",
        "100000",
        "--max-seconds",
        "600",
        "--checkpoint-seconds",
        "0.3",
        start_new_session=True,
    )
    t0 = time.monotonic()
    while not (run_dir / "checkpoint.pt").exists():  # written by the time budget: the loop is running
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() - t0 < 180, "no checkpoint after 180 s"
        time.sleep(0.1)
    time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    lines = [ln for ln in err.splitlines() if ln.startswith("error: ")]
    assert len(lines) == 2 and len(set(lines)) == 1, err  # one line a rank, the same step on both
    assert lines[0].startswith(f"error: interrupted (SIGINT) at step {state['step']} ") and "--resume" in lines[0]
    assert not (run_dir / "manifest.json").exists() and not list(run_dir.glob(".checkpoint.pt.*"))
    proc = _torchrun(
        "train",
        scene_dir,
        run_dir,
        *OPTIONS,
        "--batch-rays",
        "256",
        "--max-steps",
        state["step"] + 3,
        "--max-seconds",
        "600",
        "--resume",
    )
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["used"]["steps"] == state["step"] + 3 and manifest["used"]["world_size"] == 2
    resumed = json.loads((run_dir / "config.json").read_text())["resumed"]
    assert [r["step"] for r in resumed] == [state["step"]]


_RANK_SCRIPT = """
import sys, time
from pathlib import Path
import torch
from nerfpipe.data.errors import UserError
from nerfpipe.model.distributed import joined, world_from_env
out, mode = Path(sys.argv[1]), sys.argv[2]
try:
    with joined(world_from_env(), torch.device("cpu")) as par:
        if par.writer:
            time.sleep(1.0)  # rank 0's final evaluation and writes
            if mode == "fail":
                raise ValueError("rank 0 failed while writing")
            (out / "written").write_text("done")
except UserError as exc:
    print(f"error: {exc}", flush=True)
    sys.exit(1)
print("left; rank 0 had written:", (out / "written").exists(), flush=True)
"""


def _two_ranks(tmp_path: Path, mode: str) -> list[tuple[int, str]]:
    """The script above as ranks 0 and 1 of a gloo group on a free local port -> (exit code, stdout) of each."""
    (tmp_path / "rank.py").write_text(_RANK_SCRIPT)
    env = {
        **os.environ,
        "MASTER_ADDR": "127.0.0.1",
        "MASTER_PORT": str(free_port()),
        "WORLD_SIZE": "2",
        "OMP_NUM_THREADS": "1",
    }
    procs = [
        subprocess.Popen(
            [sys.executable, str(tmp_path / "rank.py"), str(tmp_path), mode],
            cwd=ROOT,
            env={**env, "RANK": str(r), "LOCAL_RANK": str(r)},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for r in range(2)
    ]
    results = []
    for p in procs:
        out, _ = p.communicate(timeout=120)
        results.append((p.returncode, out))
    return results


def test_every_rank_leaves_the_group_after_rank_0_has_written_and_says_when_it_did_not(tmp_path):
    """`joined` ends at a barrier: rank 1, done training, waits for rank 0's writes before it leaves (before, it
    left at once, and a rank that ended badly on its way out made torchrun stop rank 0 mid-write). When rank 0
    fails after training, rank 1 stops with one line pointing at rank 0's message."""
    ok = _two_ranks(tmp_path, "ok")
    assert ok == [(0, "left; rank 0 had written: True\n")] * 2, ok
    (tmp_path / "written").unlink()
    (rc0, _), (rc1, out1) = _two_ranks(tmp_path, "fail")
    assert rc0 != 0 and rc1 == 1, (rc0, rc1, out1)
    assert out1.startswith("error: rank 1: another rank stopped before the end of the run (its message says why")
