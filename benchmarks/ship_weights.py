"""Copy a pretrain-gnt or pretrain-voxels output's weights into the package, with their provenance (`make
pretrain-gnt`, `make pretrain-voxels`).

    python -m benchmarks.ship_weights PRETRAIN_OUT WEIGHTS_DIR --command "make pretrain-gnt ..."

Writes WEIGHTS_DIR/pretrained.pt (the weights file as the stage wrote it) and WEIGHTS_DIR/pretrained.json: the
command, the commit the code was at (and whether the tree had changes), the data recipe (gnt: each scene set's
scene manifest: subject, layout, kind, count, seeds, size, views; voxels: the shapes manifest), the last commit
that changed the code pretraining runs (`code_commit`), and the figures of the run (steps, seconds, loss at the
start and the end, parameters, the sha256 of the weights).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
from pathlib import Path

from nerfpipe.data.atomic import write_json
from nerfpipe.data.rundir import sha256_file

CODE = {
    "gnt": ("model", "stages/pretrain_gnt", "stages/scene", "data/synthetic", "radiance"),
    "voxels": ("model/voxels", "model/loop.py", "stages/pretrain_voxels", "stages/shapes", "data/synthetic"),
}
"""What pretraining runs: the last commit that changed it is `code_commit` (the weights' own commits left out)."""


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], capture_output=True, text=True, check=False).stdout.strip()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pretrain_out", type=Path)
    ap.add_argument("weights_dir", type=Path)
    ap.add_argument("--command", required=True)
    args = ap.parse_args(argv)
    manifest = json.loads((args.pretrain_out / "manifest.json").read_text())
    config = json.loads((args.pretrain_out / "config.json").read_text())
    kind = "voxels" if "shapes" in config else "gnt"
    recipe = []
    if kind == "voxels":
        shapes = Path(config["shapes"])
        doc = json.loads(((shapes if shapes.is_dir() else shapes.parent) / "manifest.json").read_text())
        recipe.append({"folder": str(shapes), **doc.get("used", {})})
    for m in sorted(Path(config.get("scenes", "/nonexistent")).glob("*/manifest.json")):
        doc = json.loads(m.read_text())
        cfg = doc.get("config", {})
        keep = ("subject", "layout", "kind", "count", "seed", "size", "views")
        recipe.append({"folder": m.parent.name, **{k: cfg.get(k) for k in keep}})
    code = ("--", *CODE[kind], ":!*/weights/*", ":!*.md")  # what pretraining runs, without the weights and docs
    provenance = {
        "command": args.command,
        "commit": _git("rev-parse", "HEAD"),
        "code_commit": _git("log", "-1", "--format=%H", *code),
        "pretrain_started": manifest.get("started"),
        "tree_changed": bool(_git("status", "--porcelain", "--untracked-files=no", *code)),  # that code uncommitted
    }
    args.weights_dir.mkdir(parents=True, exist_ok=True)
    target = args.weights_dir / "pretrained.pt"
    shipped = args.weights_dir / "pretrained.json"
    if config.get("init") == "pretrained" and shipped.is_file():  # continued the weights it replaces: keep their story
        before = json.loads(shipped.read_text())
        keep = ("command", "commit", "code_commit", "pretrain_started", "continued_from")
        provenance["continued_from"] = {k: before[k] for k in keep if k in before} | {
            "steps": before.get("figures", {}).get("steps"),
            "seconds": before.get("figures", {}).get("seconds"),
        }
    shutil.copyfile(args.pretrain_out / "weights.pt", target)
    write_json(
        args.weights_dir / "pretrained.json",
        {
            **provenance,
            "recipe": recipe,
            "pretrain_config": config,
            "figures": manifest.get("used", {}),
            "sha256": sha256_file(target),
        },
    )
    print(f"{target} ({target.stat().st_size / 1e6:.2f} MB) and pretrained.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
