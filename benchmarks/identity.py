"""Outputs before and after a refactor (issue 28): the chain a user runs, hashed file by file.

Per scene space a tiny `nerfpipe scene` (posed, 40 px, 16 views; layout orbit -> box, forward -> ndc, room ->
contract), then `convert`, `train --max-steps STEPS --threads 1 --seed 0`, `render --path test`, `depth`, `eval` and
`mesh`, and a vanilla-field box run (a tenth of the steps, 64 rays a batch: its steps cost ~100x). Every file each
stage writes is hashed (sha256); JSON files are also kept whole so that a difference can be read, not only seen.
`--compare A.json` prints the files whose hash differs from an earlier run of this script, with the JSON keys that
differ.

Run:  .venv/bin/python -m benchmarks.identity --out runs/identity/before
      .venv/bin/python -m benchmarks.identity --out runs/identity/after --compare runs/identity/before/hashes.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
from pathlib import Path

CASES = {  # name: (layout, extra train options)
    "box": ("orbit", ""),
    "ndc": ("forward", ""),
    "contract": ("room", ""),
    "vanilla": ("orbit", "--method nerf --batch-rays 64"),  # 256 samples a ray through two MLPs: few, small steps
}
SKIP = {"manifest.json", "config.json", "train_log.jsonl", "plan.txt"}  # hashed, but also compared by key


def _run(args: str) -> None:
    cmd = [str(Path(sys.executable).parent / "nerfpipe"), *args.split()]
    print("$", " ".join(cmd[1:]), flush=True)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def chain(out: Path, name: str, steps: int) -> None:
    layout, extra = CASES[name]
    w = out / name
    _run(f"scene {w}/photos --kind posed --layout {layout} --size 40 --views 16 --seed 0 --overwrite")
    _run(f"convert {w}/photos {w}/scene")
    steps = steps if name != "vanilla" else max(1, steps // 10)
    _run(f"train {w}/scene {w}/run --max-steps {steps} --max-seconds 1e6 --threads 1 --seed 0 {extra}".strip())
    _run(f"render {w}/run {w}/video.mp4 --path test --frames-dir {w}/frames")
    _run(f"depth {w}/run {w}/depth")
    _run(f"eval {w}/run {w}/eval.json")
    if name in ("box", "vanilla"):
        _run(f"mesh {w}/run {w}/mesh.ply --resolution 48")


def hashes(out: Path) -> dict:
    res = {}
    for p in sorted(out.rglob("*")):
        if p.is_file() and p.name != "hashes.json":
            res[str(p.relative_to(out))] = hashlib.sha256(p.read_bytes()).hexdigest()[:16]
    return res


def _json_diff(a, b, path: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b)) for d in _json_diff(a.get(k), b.get(k), f"{path}.{k}")]
    return [] if a == b else [f"{path}: {json.dumps(a)[:80]} -> {json.dumps(b)[:80]}"]


def compare(before: Path, after: Path) -> None:
    a, b = json.loads(before.read_text()), json.loads((after / "hashes.json").read_text())
    for f in sorted(set(a) | set(b)):
        if a.get(f) == b.get(f):
            continue
        print(f"DIFF {f}: {a.get(f)} -> {b.get(f)}")
        if f.endswith(".json") and f in a and f in b:
            old = json.loads((before.parent / f).read_text())
            new = json.loads((after / f).read_text())
            for d in _json_diff(old, new)[:20]:
                print("   ", d)
    same = sum(a.get(f) == b.get(f) for f in b)
    print(f"{same}/{len(set(a) | set(b))} files identical")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--steps", type=int, default=120)
    p.add_argument("--cases", default=",".join(CASES))
    p.add_argument("--compare", type=Path, default=None)
    a = p.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    for name in a.cases.split(","):
        chain(a.out, name, a.steps)
    (a.out / "hashes.json").write_text(json.dumps(hashes(a.out), indent=1))
    if a.compare is not None:
        compare(a.compare, a.out)


if __name__ == "__main__":
    main()
