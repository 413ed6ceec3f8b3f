"""Where the poses stage writes: an earlier colmap/ set aside, the kept model with names.json, metrics.csv,
poses_report.json and manifest.json written into the build folder and renamed into place as SCENE_DIR/colmap, the
report of a failed run, and the `Outputs` of a successful one."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import pycolmap

from nerfpipe.data.atomic import write_json
from nerfpipe.data.checks import verdict
from nerfpipe.data.rundir import MetricsLog, config_to_json, write_manifest
from nerfpipe.stages.poses.config import Config, Outputs
from nerfpipe.stages.poses.report import RunState, build_report

__all__ = ["VERSION", "set_aside", "write_model", "write_failed_report", "outputs"]

VERSION = "2"


def set_aside(colmap_dir: Path, report_path: Path) -> Path | None:
    """Move an earlier run's colmap/ (and its report, into it) to colmap.previous/; returns that folder, or
    None when there was no earlier colmap/ (an older colmap.previous/ is then left as it is)."""
    previous = colmap_dir.with_name("colmap.previous")
    if not colmap_dir.exists():
        report_path.unlink(missing_ok=True)  # a failed run's report: this run writes its own
        return previous if previous.exists() else None
    shutil.rmtree(previous, ignore_errors=True)
    os.replace(colmap_dir, previous)
    if report_path.exists():
        os.replace(report_path, previous / report_path.name)
    return previous


def write_model(
    config: Config,
    state: RunState,
    build: Path,
    colmap_dir: Path,
    report_path: Path,
    metrics: MetricsLog,
    matcher: str,
    groups: list[list[str]],
) -> dict[str, Any]:
    """Write the kept model (`state.model`), names.json, metrics.csv, the report and the manifest into `build`,
    then rename `build` to `colmap_dir`; returns the report."""
    masked = config.masks is not None
    (build / "sparse").mkdir()
    state.model.write_binary(str(build / "sparse"))
    shutil.rmtree(build / "models")
    shutil.rmtree(build / "working", ignore_errors=True)  # working copies of large photos (`working`)
    report = build_report(config, state, "ok", None)
    write_json(build / "names.json", state.names)
    metrics.save()
    write_json(report_path, report)
    write_manifest(
        build,
        stage="poses",
        started=state.started,
        inputs=[config.input],
        outputs=[
            "images/",
            *(["masks/"] if masked else []),
            "names.json",
            "database.db",
            "sparse/",
            "metrics.csv",
            "../poses_report.json",
        ],
        used={
            "matcher": matcher,
            "principal_point": state.principal_point,
            "radial_term": report["radial_term"],
            "camera_groups": [len(g) for g in groups],
            "pycolmap": pycolmap.__version__,
            "working_size": state.working_size,
            "masks": str(config.masks) if masked else None,
            "stationary_matches": state.stationary,
            "focal_prior": report["focal_prior"],
            "attempts": [
                {k: a[k] for k in ("name", "registered", "total", "kept", "check", "settings")} for a in state.attempts
            ],
            "choice": state.choice,
            "consistency": state.consistency[1],
            "ladder": state.ladder,
        },
        left_out={**state.skipped, **report["not_registered"]},
        version=VERSION,
        config=config_to_json(config),
        **verdict(state.checks),
    )
    os.replace(build, colmap_dir)
    return report


def write_failed_report(config: Config, state: RunState, report_path: Path, error: Exception) -> None:
    """poses_report.json with status "failed" and the error's first line; never raises (the report must never
    hide the original error)."""
    try:
        write_json(report_path, build_report(config, state, "failed", str(error).splitlines()[0] if str(error) else ""))
    except Exception:  # the report must never hide the original error
        pass


def outputs(colmap_dir: Path, report_path: Path, report: dict[str, Any], state: RunState) -> Outputs:
    """The `Outputs` of a successful run, from its report and state."""
    return Outputs(
        colmap_dir=colmap_dir,
        sparse=colmap_dir / "sparse",
        images=colmap_dir / "images",
        database=colmap_dir / "database.db",
        report=report_path,
        registered=report["registered"],
        total=report["total"],
        mean_reprojection_error=float(report["mean_reprojection_error_px"]),
        working_size=state.working_size["size"],
        check=report["check"],
        attempts=tuple(
            f"{a['name']}: {a['registered']}/{a['total']} registered{' (kept)' if a['kept'] else ''}; {a['settings']}"
            for a in state.attempts
        ),
    )
