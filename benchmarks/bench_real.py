"""`make bench-real`: every real capture in ../shared/data through the commands a user types, one table.

Each capture runs as `make PHOTOS=... OUT=...` (photos) or `make POSED=... OUT=...` (posed datasets), the files as
distributed, with the budgets below (the issue's goals). The table, one row a capture:
registered images (and the pose error against the capture's own reference poses after a similarity alignment,
photos only), held-out PSNR / SSIM (`OUT/eval.json`), seconds per stage (each manifest's wall_seconds) and end to
end, the video's frames and size, the mesh's faces, and every stage's self-check (`check` in its manifest; the
failed checks named). Written to docs/BENCH_REAL.md with the commit it was measured at (and whether the tree
was clean) and the machine's load, and as JSON beside the runs.

    .venv/bin/python -m benchmarks.bench_real                       # all four (~1 h on 2 cores)
    .venv/bin/python -m benchmarks.bench_real --only fern,tiny      # some
    .venv/bin/python -m benchmarks.bench_real --table-only          # the table from runs already made

Noise: the same command twice on this 2-core machine differs by up to ~10 % in training steps (so ~0.2-0.3 dB
held-out on these captures: tiny npz 32.35 / 32.65 dB on one day, docs/BENCH_REAL.md lists repeats); a change to
a default lands only with this table re-measured and nothing worse than that.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from benchmarks.provenance import commit

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
sys.path.insert(0, str(ROOT))

from nerfpipe.pipelines.suspects import RECORDS  # noqa: E402

__all__ = ["CAPTURES", "main"]


@dataclass(frozen=True)
class Capture:
    name: str
    kind: str
    """What kind of capture it is (the defaults that apply: box, ndc, contract)."""
    make: tuple[str, ...]
    """make variables (besides OUT)."""
    goal: str
    reference: str | None = None
    """The capture's own poses, for the pose error of a photo capture: "transforms:<path>" (a transforms.json) or
    "llff:<folder>" (poses_bounds.npy in sorted image-name order)."""


CAPTURES = (
    Capture(
        "fern",
        "forward-facing (NDC)",
        (f"POSED={DATA}/fern", "CONVERT_ARGS=--images images_8", "TRAIN_ARGS=--max-seconds=300"),
        ">= 25.2 dB held-out (NeRF paper 25.17)",
    ),
    Capture(
        "tiny",
        "object on black (box)",
        (f"POSED={DATA}/lego_100/tiny_lego_100px.npz", "TRAIN_ARGS=--max-seconds=120"),
        ">= 32 dB",
    ),
    Capture(
        "fox",
        "phone photos, unbounded (contract)",
        (f"PHOTOS={DATA}/fox/images", "TRAIN_ARGS=--max-seconds=300"),
        ">= 26.9 dB, <= 13 min, 50/50 within 0.3 deg",
        reference=f"transforms:{DATA}/fox/transforms.json",
    ),
    Capture(
        "fox-sdf",
        "phone photos, unbounded (contract), `--method sdf`",
        (f"PHOTOS={DATA}/fox/images", "TRAIN_ARGS=--max-seconds=300 --method=sdf"),
        "one smooth surface for the head and plaque, <= 15 min (issue 48)",
        reference=f"transforms:{DATA}/fox/transforms.json",
    ),
    Capture(
        "head",
        "masked object, turntable (box)",
        (f"PHOTOS={DATA}/head/images", f"POSES_ARGS=--masks {DATA}/head/masks", "TRAIN_ARGS=--max-seconds=300"),
        ">= 25 dB held-out, 66/66 within 1 deg, no false suspect",
        reference=f"llff:{DATA}/head",
    ),
    Capture(
        "lego_400",
        "object RGBA (box)",
        (f"POSED={DATA}/lego_400", "TRAIN_ARGS=--max-seconds=900", "EVAL_ARGS=--views 25", "DEPTH_ARGS=--views train"),
        ">= 32.6 dB",
    ),
)
"""lego_400's test split has 200 views: eval scores 25 evenly spaced ones (as bench-train did) and depth maps the
100 training cameras at their size, so that the chain stays within an hour."""

NOTES = "<!-- notes: kept when the table is re-measured -->"

STAGE_FILES = {**dict(RECORDS), "poses": "scene/colmap/manifest.json"}
"""Each stage's record under OUT (`pipelines.suspects.RECORDS`), the poses stage's manifest (its wall seconds)
in place of its report, which `row` reads for the registered count."""


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _pose_error(out: Path, reference: str | None) -> str:
    """Median / largest rotation error (deg) of the registered cameras against the capture's own poses, after a
    similarity alignment ("given" for a posed dataset)."""
    from benchmarks.pose_reference import compare, from_llff, from_transforms

    sparse = out / "scene" / "colmap" / "sparse"
    if reference is None:
        return "given"
    if not sparse.is_dir():
        return "-"
    kind, path = reference.split(":", 1)
    ref = from_transforms(Path(path)) if kind == "transforms" else from_llff(Path(path))
    got = compare(sparse, ref, by_stem=True)
    if "rotation_deg" not in got:
        return "-"
    median, largest = got["rotation_deg"]
    return f"{median:.2f} / {largest:.2f} deg"


def row(capture: Capture, out: Path, wall: float | None) -> dict:
    """The table's row for a capture's run folder."""
    docs = {stage: _read(out / rel) for stage, rel in STAGE_FILES.items()}
    report = _read(out / "scene" / "poses_report.json")
    ev = _read(out / "eval.json") or {}
    train = docs["train"] or {}
    render = (docs["render"] or {}).get("used", {})
    mesh = docs["mesh"] or {}
    registered = "given"
    if report is not None:
        registered = f"{report.get('registered', '?')}/{report.get('total', '?')}"
    suspect = [
        f"{stage}: {c['name']} {c['value']}"
        for stage, d in docs.items()
        if d
        for c in d.get("checks", [])
        if not c["ok"]
    ]
    checks = {stage: d.get("check", "-") for stage, d in docs.items() if d}
    size = render.get("budget", {}).get("chosen", {}).get("size_hw")
    return {
        "capture": capture.name,
        "kind": capture.kind,
        "goal": capture.goal,
        "registered": registered,
        "pose_error": _pose_error(out, capture.reference),
        "psnr": ev.get("psnr"),
        "ssim": ev.get("ssim"),
        "steps": train.get("used", {}).get("steps"),
        "seconds": {stage: round(d["wall_seconds"]) for stage, d in docs.items() if d and "wall_seconds" in d},
        "end_to_end_s": None if wall is None else round(wall),
        "video": f"{render.get('frames', '?')} frames {size[1]}x{size[0]}" if size else "-",
        "mesh_faces": mesh.get("final", {}).get("faces"),
        "checks": checks,
        "suspect": suspect,
    }


def markdown(rows: list[dict], commit: str, load: str) -> str:
    lines = [
        "# Real captures: `make bench-real`",
        "",
        f"Measured at commit {commit}, {time.strftime('%Y-%m-%d')}, 2-core CPU machine, no GPU; load at the end "
        f"{load}. Command: `make bench-real` (`benchmarks/bench_real.py`), each capture through `make PHOTOS=` / "
        "`make POSED=` on the files as distributed.",
        "",
        "| capture | kind | registered | pose error (median / max) | held-out PSNR | SSIM | train steps | seconds "
        "per stage | end to end | video | mesh faces | self-checks | goal |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        secs = ", ".join(f"{k} {v}" for k, v in r["seconds"].items())
        checks = "all ok" if not r["suspect"] else "; ".join(r["suspect"])
        e2e = f"{r['end_to_end_s']} s" if r["end_to_end_s"] is not None else "-"
        psnr = f"{r['psnr']:.2f} dB" if r["psnr"] is not None else "-"
        ssim = f"{r['ssim']:.3f}" if r["ssim"] is not None else "-"
        lines.append(
            f"| {r['capture']} | {r['kind']} | {r['registered']} | {r['pose_error']} | {psnr} | "
            f"{ssim} | {r['steps']} | {secs} | {e2e} | {r['video']} | {r['mesh_faces']} | {checks} | "
            f"{r['goal']} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench" / "real")
    p.add_argument("--only", default=",".join(c.name for c in CAPTURES))
    p.add_argument("--table-only", action="store_true", help="no runs: the table from the run folders as they are")
    p.add_argument("--doc", type=Path, default=ROOT / "docs" / "BENCH_REAL.md")
    args = p.parse_args(argv)
    wanted = args.only.split(",")
    unknown = set(wanted) - {c.name for c in CAPTURES}
    if unknown:
        p.error(f"unknown captures {sorted(unknown)}; expected some of {[c.name for c in CAPTURES]}")
    walls = _read(args.out / "walls.json") or {}
    rows = []
    for capture in (c for c in CAPTURES if c.name in wanted):
        out = args.out / capture.name
        if not args.table_only:
            if not all((DATA / v.split("=", 1)[1].split()[0]).exists() for v in capture.make[:1]):
                print(f"{capture.name}: skipped, its data is not in {DATA}")
                continue
            shutil.rmtree(out, ignore_errors=True)  # measured afresh: make would keep an up-to-date chain
            t0 = time.perf_counter()
            cmd = ["make", "-C", str(ROOT), f"OUT={out}", *capture.make]
            print("$ " + " ".join(cmd), flush=True)
            subprocess.run(cmd, check=True)
            walls[capture.name] = time.perf_counter() - t0
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / "walls.json").write_text(json.dumps(walls))
        rows.append(row(capture, out, walls.get(capture.name)))
        print(json.dumps(rows[-1]), flush=True)
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    old = args.doc.read_text() if args.doc.is_file() else ""
    notes = old[old.index(NOTES) :] if NOTES in old else NOTES + "\n"
    args.doc.write_text(markdown(rows, commit(), load) + "\n" + notes)
    print(f"table -> {args.doc}")
    return rows


if __name__ == "__main__":
    main()
