"""Stage `report`: compare training runs: held-out PSNR against wall-clock seconds, and a summary table.

    nerfpipe report RUN_DIR... OUT_DIR

Reads each run's `metrics.csv` (step, seconds, ..., test_psnr: blank where not evaluated; train's last row is the
full-image evaluation) and `manifest.json` (`used.peak_cuda_mb`, `used.peak_rss_mb`, as train writes them).
Writes under OUT_DIR:
  psnr_vs_time.png   test PSNR (dB) vs training seconds, one line per run, dotted lines at the levels
  summary.md         one row per run: final test PSNR, steps, seconds, time to reach each level ("—" if never),
                     peak CUDA / RSS memory (MB)
  summary.csv        the same numbers, blank where a value does not exist
  manifest.json      written last
"Time to reach" is the wall-clock seconds of the first logged evaluation at or above the level (no interpolation).
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from nerfpipe.data.atomic import atomic_path, write_text
from nerfpipe.data.errors import UserError
from nerfpipe.data.rundir import config_to_json, output_folder, refuse_output_inside, write_manifest

__all__ = ["Config", "Outputs", "RunSummary", "read_run", "run"]

DASH = "—"


@dataclass(frozen=True, kw_only=True)
class Config:
    runs: tuple[Path, ...]
    """Training run directories (each with metrics.csv and manifest.json)."""
    out_dir: Path
    """Folder for psnr_vs_time.png, summary.md, summary.csv, manifest.json."""
    levels: tuple[float, ...] = (20.0, 25.0, 30.0)
    """PSNR levels (dB) whose time-to-reach the table reports."""
    labels: tuple[str, ...] | None = None
    """Names for the runs in the plot and table (default: the run folder names, made unique)."""
    overwrite: bool = False
    """Replace an earlier output in out_dir (set aside in OUT_DIR.previous/ until this one is written)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    plot: Path
    markdown: Path
    csv: Path
    manifest: Path
    runs: tuple[RunSummary, ...]


@dataclass(frozen=True, kw_only=True)
class RunSummary:
    label: str
    run_dir: Path
    seconds: tuple[float, ...]
    """Wall-clock seconds of each test-PSNR evaluation."""
    psnr: tuple[float, ...]
    """Test PSNR at those times, dB."""
    final_psnr: float | None
    steps: int | None
    total_seconds: float | None
    time_to: dict[float, float | None] = field(default_factory=dict)
    """PSNR level -> first seconds at or above it (None: never)."""
    peak_cuda_mb: float | None = None
    peak_rss_mb: float | None = None


def _float(value: Any) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def read_run(run_dir: Path, label: str, levels: tuple[float, ...]) -> RunSummary:
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UserError(f"{run_dir}: run directory not found")
    metrics = run_dir / "metrics.csv"
    if not metrics.is_file():
        raise UserError(f"{run_dir}: no metrics.csv (not a training run?)")
    with open(metrics, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        columns = reader.fieldnames or []
        rows = list(reader)
    missing = [c for c in ("step", "seconds", "test_psnr") if c not in columns]
    if missing:
        raise UserError(f"{metrics}: missing column(s) {', '.join(missing)} (have {', '.join(columns) or 'none'})")
    points = [
        (s, p)
        for s, p in ((_float(r["seconds"]), _float(r["test_psnr"])) for r in rows)
        if s is not None and p is not None
    ]
    steps = [v for v in (_float(r["step"]) for r in rows) if v is not None]
    secs = [v for v in (_float(r["seconds"]) for r in rows) if v is not None]
    used: dict[str, Any] = {}
    manifest = run_dir / "manifest.json"
    if manifest.is_file():
        try:
            doc = json.loads(manifest.read_text(encoding="utf-8"))
            used = {**doc, **(doc.get("used") or {})} if isinstance(doc, dict) else {}
        except json.JSONDecodeError:
            raise UserError(f"{manifest}: not valid JSON") from None
    time_to = {lvl: next((s for s, p in points if p >= lvl), None) for lvl in levels}
    return RunSummary(
        label=label,
        run_dir=run_dir,
        seconds=tuple(s for s, _ in points),
        psnr=tuple(p for _, p in points),
        final_psnr=points[-1][1] if points else None,
        steps=int(max(steps)) if steps else None,
        total_seconds=max(secs) if secs else None,
        time_to=time_to,
        peak_cuda_mb=_float(used.get("peak_cuda_mb")),
        peak_rss_mb=_float(used.get("peak_rss_mb")),
    )


def _labels(runs: tuple[Path, ...], labels: tuple[str, ...] | None) -> list[str]:
    if labels is not None:
        if len(labels) != len(runs):
            raise UserError(f"--labels: got {len(labels)} label(s) for {len(runs)} run(s)")
        return list(labels)
    names = [Path(r).name or str(r) for r in runs]
    if len(set(names)) < len(names):
        names = [f"{Path(r).parent.name}/{Path(r).name}" for r in runs]
    if len(set(names)) < len(names):
        names = [str(r) for r in runs]
    return names


def _fmt(v: float | None, digits: int, dash: str) -> str:
    return dash if v is None else f"{v:.{digits}f}"


def _table(runs: list[RunSummary], levels: tuple[float, ...], dash: str) -> tuple[list[str], list[list[str]]]:
    header = [
        "run",
        "final test PSNR (dB)",
        "steps",
        "seconds",
        *(f"time to {lvl:g} dB (s)" for lvl in levels),
        "peak CUDA (MB)",
        "peak RSS (MB)",
    ]
    body = []
    for r in runs:
        steps = dash if r.steps is None else str(r.steps)
        times = [_fmt(r.time_to[lvl], 1, dash) for lvl in levels]
        body.append(
            [
                r.label,
                _fmt(r.final_psnr, 2, dash),
                steps,
                _fmt(r.total_seconds, 1, dash),
                *times,
                _fmt(r.peak_cuda_mb, 1, dash),
                _fmt(r.peak_rss_mb, 1, dash),
            ]
        )
    return header, body


def _plot(path: Path, runs: list[RunSummary], levels: tuple[float, ...]) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    try:
        for r in runs:
            if r.psnr:
                ax.plot(r.seconds, r.psnr, "o-", ms=3, label=r.label)
        for lvl in levels:
            ax.axhline(lvl, color="grey", lw=0.6, ls=":")
        ax.set_xlabel("training wall-clock (s)")
        ax.set_ylabel("held-out PSNR (dB)")
        ax.set_title("test PSNR vs time")
        ax.grid(alpha=0.3)
        if any(r.psnr for r in runs):
            ax.legend(fontsize=8)
        fig.tight_layout()
        with atomic_path(path, suffix=".png") as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)


def run(config: Config, progress: Any | None = None) -> Outputs:
    """Hold out_dir (one writer; an earlier output needs --overwrite) and run the stage (`_run`)."""
    for run_dir in config.runs:
        refuse_output_inside(config.out_dir, run_dir, "report output")
    with output_folder(config.out_dir, overwrite=config.overwrite):
        return _run(config, progress)


def _run(config: Config, progress: Any | None = None) -> Outputs:
    started = time.time()
    runs_in = tuple(Path(r) for r in config.runs)
    if not runs_in:
        raise UserError("report: give at least one run directory")
    levels = tuple(float(v) for v in config.levels)
    labels = _labels(runs_in, config.labels)
    runs = [read_run(r, label, levels) for r, label in zip(runs_in, labels, strict=True)]
    out_dir = Path(config.out_dir)
    plot = out_dir / "psnr_vs_time.png"
    _plot(plot, runs, levels)

    header, body = _table(runs, levels, DASH)
    md = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    md += ["| " + " | ".join(row) + " |" for row in body]
    notes = (
        "Time to reach a level: seconds of the first logged test evaluation at or above it; "
        f"{DASH} = never reached (or not logged)."
    )
    markdown = write_text(out_dir / "summary.md", "\n".join(md) + "\n\n" + notes + "\n")
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(_table(runs, levels, "")[1])
    csv_path = write_text(out_dir / "summary.csv", buf.getvalue())

    left_out = {r.label: "no test_psnr values in metrics.csv" for r in runs if not r.psnr}
    manifest = write_manifest(
        out_dir,
        stage="report",
        started=started,
        inputs=[p for r in runs_in for p in (r / "metrics.csv", r / "manifest.json") if p.is_file()],
        outputs=[plot, markdown, csv_path],
        used={"levels_db": list(levels), "labels": labels},
        left_out=left_out,
        config=config_to_json(config),
    )
    return Outputs(plot=plot, markdown=markdown, csv=csv_path, manifest=manifest, runs=tuple(runs))
