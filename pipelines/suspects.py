"""`make`'s last word on a chain: the self-checks every stage recorded under OUT, one line per failed check.

    python pipelines/suspects.py OUT

Reads the records the chain writes (`RECORDS`, paths under OUT; a missing one is skipped: a chain from a posed
dataset has no poses report, a stage not run yet has no record), each one's `checks` (`data.checks`), and prints
`data.checks.check_line` for every failed check, or the one line `self-checks: all N ok` (`self-checks: no record
under OUT holds any` when none has checks). Exit status 0 either way: a suspect result is reported, not an error
(the outputs are built; the lines say which to look at and why). A record that cannot be read gets a line saying
so. Called by the root Makefile's `all` recipe (`SUSPECTS` in pipelines/common.mk), after every output of the chain
is built.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nerfpipe.data.checks import read_failed

__all__ = ["RECORDS", "summary", "main"]

RECORDS = (
    ("poses", "scene/poses_report.json"),
    ("convert", "scene/convert_manifest.json"),
    ("train", "run/manifest.json"),
    ("render", "video.manifest.json"),
    ("depth", "depth/manifest.json"),
    ("eval", "eval.manifest.json"),
    ("mesh", "mesh.report.json"),
)
"""(stage, record path under OUT), in the chain's order."""


def summary(out: str | Path) -> list[str]:
    """The lines to print for the chain under `out` (module doc)."""
    lines, n_checks = [], 0
    for stage, rel in RECORDS:
        path = Path(out) / rel
        if not path.is_file():
            continue
        try:
            failed, n = read_failed(stage, path)
        except (OSError, ValueError, AttributeError, TypeError, KeyError) as exc:
            lines.append(f"{stage} ({path}): cannot read its self-checks ({type(exc).__name__}: {exc})")
            continue
        n_checks += n
        lines += failed
    if lines:
        return lines
    return [f"self-checks: all {n_checks} ok" if n_checks else f"self-checks: no record under {out} holds any"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pipelines/suspects.py", description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the chain's OUT folder")
    a = parser.parse_args(argv)
    print("\n".join(summary(a.out)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
