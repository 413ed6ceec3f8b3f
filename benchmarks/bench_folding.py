"""`make bench-folding`: objects whose faces look alike, photographed all round on white, through `nerfpipe poses`
(issue 53: a reconstruction can fold onto itself and still reproject well).

Each case is a `nerfpipe scene --kind photos --subject S` (exact poses) posed by `nerfpipe poses` as a user would;
the model is compared with the truth (`pose_reference.compare`: rotation error after a similarity alignment, and
the difference of the rotation between every two cameras, which needs no alignment). Goal: poses within 1 deg, or
flagged (`check: suspect`) with the right cause. The verdict column says which:
  right        every registered camera within 1 deg of the truth (after alignment);
  flagged      wrong, and the poses report is suspect with a consistency check (capture_order, look_alike_matches)
               failed: the right cause;
  WRONG        wrong and not flagged (the failure this benchmark exists to catch).
Cases: carton (one print on front and back, another on both sides: a 2-fold look-alike), cube (one print on all
four sides: 4-fold), objects (the default five-object scene: the control), and the carton with its photos renamed
in a random order (no capture order to go by).

    .venv/bin/python -m benchmarks.bench_folding                      # all (~20-40 min on 2 cores)
    .venv/bin/python -m benchmarks.bench_folding --only carton,cube   # some

Writes docs/BENCH_FOLDING.md (the table, the commit, the load) and OUT/results.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.pose_reference import compare, from_ground_truth  # noqa: E402

NERFPIPE = ROOT / ".venv" / "bin" / "nerfpipe"
CASES = {
    "carton": {"subject": "carton", "shuffle": False},
    "cube": {"subject": "cube", "shuffle": False},
    "objects": {"subject": "objects", "shuffle": False},
    "carton-unordered": {"subject": "carton", "shuffle": True},
}
RIGHT_DEG = 1.0
CONSISTENCY = ("capture_order", "look_alike_matches")


def _run(cmd: list[str]) -> tuple[int, float]:
    print("$ " + " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    rc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True).returncode
    return rc, time.perf_counter() - t0


def case(name: str, out: Path, size: int, views: int, seed: int, threads: int) -> dict:
    spec = CASES[name]
    scene_dir, photos, posed = out / name / "scene", out / name / "photos", out / name / "posed"
    shutil.rmtree(out / name, ignore_errors=True)
    scene_args = ["--kind", "photos", "--subject", spec["subject"], "--size", str(size), "--views", str(views)]
    _run([str(NERFPIPE), "scene", str(scene_dir), *scene_args, "--seed", str(seed)])
    truth = from_ground_truth(scene_dir)
    photos.mkdir(parents=True)
    renamed = {}
    order = np.random.default_rng(seed).permutation(views) if spec["shuffle"] else np.arange(views)
    for k, src in enumerate(sorted((scene_dir / "images").iterdir())):
        dst = f"shot_{order[k]:04d}.png" if spec["shuffle"] else src.name
        shutil.copyfile(src, photos / dst)
        renamed[dst] = truth[src.name]
    rc, seconds = _run([str(NERFPIPE), "poses", str(photos), str(posed), "--num-threads", str(threads)])
    report = json.loads((posed / "poses_report.json").read_text())
    row = {
        "case": name,
        "photos": views,
        "size": size,
        "seconds": round(seconds),
        "registered": f"{report.get('registered')}/{report.get('total')}",
        "check": report.get("check"),
        "failed": [f"{c['name']} {c['value']}" for c in report.get("checks", []) if not c["ok"]],
        "attempts": [f"{a['name']} {a['registered']}/{a['total']} {a['check']}" for a in report.get("attempts", [])],
        "kept": next((a["name"] for a in report.get("attempts", []) if a["kept"]), None),
        "choice": report.get("choice"),
    }
    if rc == 0:
        row.update(compare(posed / "colmap" / "sparse", renamed))
        right = row["rotation_deg"][1] <= RIGHT_DEG
        flagged = report["check"] == "suspect" and any(f.split()[0] in CONSISTENCY for f in row["failed"])
        row["verdict"] = "right" if right else "flagged" if flagged else "WRONG"
    else:
        row["verdict"] = f"failed (exit {rc})"
    print(json.dumps(row), flush=True)
    return row


def _git() -> str:
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    return head.strip() + (" (with uncommitted changes)" if dirty else "")


def markdown(rows: list[dict], commit: str, load: str, args: argparse.Namespace) -> str:
    lines = [
        "# Objects whose faces look alike: `make bench-folding`",
        "",
        f"Measured at commit {commit}, {time.strftime('%Y-%m-%d')}, 2-core CPU machine; load average at the end "
        f"{load} (shared with other jobs: seconds are wall-clock under that load). Command: `python -m "
        f"benchmarks.bench_folding --size {args.size} --views {args.views} --seed {args.seed}`.",
        "",
        "| case | registered | rotation error after alignment (median / max) | rotation between two cameras, "
        "difference (median / max) | check | failed checks | attempts | verdict | seconds |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        rot = "/".join(f"{v:.2f}" for v in r.get("rotation_deg", [])) or "-"
        pair = "/".join(f"{v:.2f}" for v in r.get("pairwise_deg", [])) or "-"
        lines.append(
            f"| {r['case']} | {r['registered']} | {rot} deg | {pair} deg | {r['check']} | "
            f"{'; '.join(r['failed']) or '-'} | {'; '.join(r['attempts'])} (kept: {r['kept']}) | {r['verdict']} | "
            f"{r['seconds']} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench" / "folding")
    p.add_argument("--only", default=",".join(CASES))
    p.add_argument("--size", type=int, default=640)
    p.add_argument("--views", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--doc", type=Path, default=ROOT / "docs" / "BENCH_FOLDING.md")
    args = p.parse_args(argv)
    wanted = args.only.split(",")
    if set(wanted) - set(CASES):
        p.error(f"unknown cases {sorted(set(wanted) - set(CASES))}; expected some of {list(CASES)}")
    rows = [case(n, args.out, args.size, args.views, args.seed, args.threads) for n in wanted]
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    old = args.doc.read_text() if args.doc.is_file() else ""
    notes = old[old.index("<!-- notes") :] if "<!-- notes" in old else "<!-- notes: kept when re-measured -->\n"
    args.doc.write_text(markdown(rows, _git(), load, args) + "\n" + notes)
    print(f"table -> {args.doc}")
    return rows


if __name__ == "__main__":
    main()
