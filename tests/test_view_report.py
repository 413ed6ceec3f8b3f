"""train's per-image report (stages.train.report.per_view_report): every training view's PSNR, the worst listed,
a contact sheet of them; a photo that does not fit the others (here: colours inverted) comes out worst."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from nerfpipe.data.transforms import read_scene
from nerfpipe.model.methods.density import DensityOptions
from nerfpipe.stages import scene as scene_stage
from nerfpipe.stages import train
from nerfpipe.stages.train.report import WORST


@pytest.fixture(scope="module")
def bad_view_run(tmp_path_factory) -> tuple[Path, str]:
    root = tmp_path_factory.mktemp("view_report")
    scene_stage.run(scene_stage.Config(out_dir=root / "scene", kind="posed", size=32, views=12, seed=0))
    scene = read_scene(root / "scene")
    bad = scene.frames[scene.split("train")[3]].file_path
    path = root / "scene" / bad
    cv2.imwrite(str(path), 255 - cv2.imread(str(path)))  # a photo that no 3-D scene explains
    out = train.run(
        train.Config(
            scene_dir=root / "scene",
            run_dir=root / "run",
            max_steps=150,
            max_seconds=60.0,
            batch_rays=512,
            options=DensityOptions(resolution=(16, 32), occupancy_resolution=16),
            eval_every=0,
            final_eval_views=1,
            device="cpu",
            threads=1,
            scene_model="box",
        )
    )
    return out.run_dir, bad


def test_report_lists_every_view_worst_first(bad_view_run):
    run_dir, bad = bad_view_run
    doc = json.loads((run_dir / "per_view.json").read_text())
    scene = read_scene(json.loads((run_dir / "config.json").read_text())["scene_dir"])
    views = doc["views"]
    assert sorted(v["file"] for v in views) == sorted(scene.frames[i].file_path for i in scene.split("train"))
    psnrs = [v["psnr"] for v in views]
    assert psnrs == sorted(psnrs) and all(np.isfinite(psnrs))
    assert views[0]["file"] == bad  # the inverted photo is the worst
    assert bad in doc["suspect"] and len(doc["suspect"]) <= 2
    assert doc["sheet"][0] == bad and len(doc["sheet"]) == min(WORST, len(views))
    assert doc["median_psnr"] > psnrs[0] + 3


def test_contact_sheet_and_manifest(bad_view_run):
    run_dir, bad = bad_view_run
    sheet = cv2.imread(str(run_dir / "per_view_worst.png"))
    assert sheet is not None and sheet.shape[0] >= WORST * 128 and sheet.shape[1] >= 3 * 128
    manifest = json.loads((run_dir / "manifest.json").read_text())
    summary = manifest["used"]["per_view"]
    assert summary["worst"][0][0] == bad and summary["files"] == ["per_view.json", "per_view_worst.png"]
    assert {Path(p).name for p in manifest["outputs"]} >= {"per_view.json", "per_view_worst.png"}
    # budgeted: a few % of the training time (or the smallest renders), seconds not minutes
    assert summary["seconds"] < max(5.0, 3 * summary["budget_seconds"])
