"""The poses stage's time budget (stages.poses.budget, issue 53: 22 photos of 4000 px took 590 s): the default
budget, the first attempt's working size capped by the probe's timing, retries predicted from the first attempt's
phases, shrunk to fit or left out, and never left out without a usable model. Pure functions, and the ladder with
its pycolmap steps stubbed (no COLMAP run)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from nerfpipe.stages.poses import budget
from nerfpipe.stages.poses.budget import AttemptCost, cap_working_size, fit_retry, predict, stage_budget
from nerfpipe.stages.poses.colmap import SfmSettings


def _settings(size: int = 3200, cap: int = 8192, **kw) -> SfmSettings:
    return SfmSettings(
        max_image_size=size,
        max_num_features=cap,
        camera_model="SIMPLE_RADIAL",
        single_camera=True,
        matcher="exhaustive",
        sequential_overlap=10,
        num_threads=2,
        seed=0,
        **kw,
    )


FIRST = AttemptCost(size=1000, cap=8192, features=1500.0, extraction=20.0, matching=10.0, mapping=5.0)
"""A first attempt at 1000 px: 1,500 features a photo, 20 s extraction, 10 s matching, 5 s mapping."""


def test_default_budget_follows_the_photo_count_not_their_size():
    assert stage_budget(None, 22) == pytest.approx(110.0) and stage_budget(None, 50) == pytest.approx(250.0)
    assert stage_budget(None, 5) == budget.MIN_SECONDS
    assert stage_budget(300.0, 22) == 300.0 and math.isinf(stage_budget(0.0, 22))


def test_first_working_size_is_capped_by_the_probe_timing():
    # 4000 px photos: 1000 px has too few features, 1600 enough; extracting 22 at 1600 (3 s a photo) = 66 s,
    # over a third of 110 s: 1000 px (1.2 s a photo, 26 s) instead
    size, why = cap_working_size(1600, {1000: 1.2, 1600: 3.0}, 22, 110.0, 4000)
    assert size == 1000 and "66 s" in why and "1000 px" in why
    assert cap_working_size(1600, {1000: 0.5, 1600: 1.2}, 22, 110.0, 4000) == (1600, None)  # 26 s: fits
    # 3200 px is taken without a count: predicted from 1600 x the pixels (4 x 1.0 s x 22 = 88 s > 37 s)
    assert cap_working_size(3200, {1000: 0.4, 1600: 1.0}, 22, 110.0, 4000)[0] == 1600
    assert cap_working_size(3200, {1000: 0.4, 1600: 1.0}, 22, math.inf, 4000) == (3200, None)  # unbounded
    assert cap_working_size(1000, {1000: 9.0}, 22, 110.0, 4000)[0] == 1000  # never under the smallest


def test_retry_costs_are_predicted_from_the_first_attempt():
    # 3200 px: 10.24 x the pixels; features min(8192, 1500 x 10.24) = 8192, 5.46 x: matching 29.8 x, mapping 5.46 x
    ratio = 8192 / 1500
    assert predict(FIRST, 3200, 8192, "nothing") == pytest.approx(20 * 10.24 + 10 * ratio**2 + 5 * ratio)
    assert predict(FIRST, 1000, 8192, "matches") == 10.0 and predict(FIRST, 1000, 8192, "neighbours") == 5.0
    assert predict(FIRST, 1000, 8192, "features") == 3 * 10.0 + 20 * 5.0  # guided: matching x 3, mapping x 20
    # wide-baseline features at the first attempt's size: extraction x 7.5, 4 x the features (6,000): matching
    # 16 x 1.3, mapping 4 x
    assert predict(FIRST, 1000, 8192, "nothing", wide=True) == pytest.approx(7.5 * 20 + 16 * 1.3 * 10 + 4 * 5)
    wide = _settings(1000, 8192, wide_baseline=True)
    assert fit_retry(wide, "nothing", FIRST, 400.0, 4000)[0] == wide
    assert fit_retry(wide, "nothing", FIRST, 300.0, 4000)[0] is None  # never shrunk: made at 1000 px already


def test_an_extraction_retry_is_shrunk_to_fit_or_left_out():
    settings = _settings(3200, 8192)
    kept, cost, why = fit_retry(settings, "nothing", FIRST, 10_000.0, 4000)
    assert kept == settings and "predicted" in why
    shrunk, cost, why = fit_retry(settings, "nothing", FIRST, 150.0, 4000)  # 3200 px does not fit; 1600 px does
    assert shrunk is not None and shrunk.max_image_size == 1600 and cost <= 150 and why.startswith("shrunk")
    assert shrunk.max_num_features in (8192, 4096)
    none, cost, why = fit_retry(settings, "nothing", FIRST, 30.0, 4000)  # 1600 px alone costs 51 s to extract
    assert none is None and why.startswith("left out")
    assert fit_retry(settings, "matches", FIRST, 9.0, 4000)[0] is None  # a relaxed mapping (10 s) over 9 s
    assert fit_retry(settings, "matches", FIRST, 11.0, 4000)[0] == settings


def _run_ladder(tmp_path: Path, monkeypatch, registered: list[int], first: AttemptCost, time_budget: float):
    """run_attempts over the 5-attempt plan (attempt 1 at 1000 px) with pycolmap stubbed; attempt k registers
    registered[k - 1] of 22 (cameras pass, no consistency check applies); the first attempt's cost is `first`."""
    from nerfpipe.data.rundir import MetricsLog
    from nerfpipe.stages.poses import attempts
    from nerfpipe.stages.poses import colmap as sfm
    from nerfpipe.stages.poses.report import PhaseTimer, RunState

    names = [f"{k}.jpg" for k in range(22)]
    stats = sfm.DatabaseStats(
        features=dict.fromkeys(names, 1500),
        matches=dict.fromkeys(names, 100),
        verified_pairs=dict.fromkeys(names, 3),
        camera_of=dict.fromkeys(names, 1),
    )
    models = iter([_model(n) for n in registered])
    monkeypatch.setattr(sfm, "extract", lambda db, *a: pycolmap.Database.open(db).close())
    monkeypatch.setattr(sfm, "match", lambda db, s: None)
    monkeypatch.setattr(sfm, "database_stats", lambda db: stats)
    monkeypatch.setattr(sfm, "reconstruct", lambda db, images, out, s: {0: next(models)})
    monkeypatch.setattr(attempts, "apply_focal_priors", lambda db, priors, weak=None: {1: {"prior_px": None}})
    monkeypatch.setattr(attempts, "consistency_checks", lambda rec, db, order: ([], None))
    monkeypatch.setattr(attempts, "attempt_cost", lambda *a: first)
    state = RunState(started=__import__("time").time())
    phase = PhaseTimer(
        state, MetricsLog(tmp_path / "metrics.csv", ["step", "seconds", "phase", "images", "registered"]), None
    )
    plan = attempts.ladder(_settings(1000, 8192), 5, long_side=4000)
    attempts.run_attempts(plan, tmp_path, tmp_path, [names], [4000], state, phase, budget=time_budget)
    return state


def _model(registered: int) -> pycolmap.Reconstruction:
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_cameras_per_rig, opts.num_frames_per_rig, opts.num_points3D = 1, 1, 22, 100
    opts.camera_params = [1280.0, 512.0, 384.0, 0.0]
    pycolmap.set_random_seed(0)
    rec = pycolmap.synthesize_dataset(opts)
    for frame_id in sorted(rec.reg_frame_ids())[registered:]:
        rec.deregister_frame(frame_id)
    return rec


def test_ladder_leaves_out_retries_that_do_not_fit_once_a_usable_model_exists(tmp_path, monkeypatch):
    """Issue 53's 4000 px head: attempt 1 usable (13/22) but under 80 %; the budget (110 s) has no room for 3200 px
    and 8192 features (predicted ~430 s) nor for any shrunk extraction, nor for wide-baseline features (378 s) nor
    guided matching (predicted 130 s); the relaxed mapper (10 s) fits."""
    state = _run_ladder(tmp_path, monkeypatch, [13, 16], FIRST, 110.0)
    assert [a["name"] for a in state.attempts] == ["as configured", "relaxed mapper"]
    # attempt 1 found 1,500 features a photo: wide-baseline features were moved ahead of more features (and neither fit)
    assert state.ladder["left_out_for_time"] == ["wide-baseline features", "more features", "guided matching"]
    assert "moved before 'more features'" in state.ladder["reordered"]
    assert state.ladder["time_budget_s"] == 110.0
    assert "SIFT at 1000 px" in state.attempts[1]["settings"]  # the relaxed mapper re-maps attempt 1's matches
    assert [a["kept"] for a in state.attempts] == [False, True]
    assert any("'more features' left out" in w for w in state.warnings)
    assert state.ladder["stopped"].startswith("the retries that fit the time budget were made")


def test_wide_baseline_features_stay_late_when_attempt_1_found_few_features(tmp_path, monkeypatch):
    few = dataclasses.replace(FIRST, features=600.0)  # under ENOUGH_FEATURES: more of them comes first
    state = _run_ladder(tmp_path, monkeypatch, [13, 16], few, 110.0)
    assert "reordered" not in state.ladder
    assert state.ladder["left_out_for_time"][:2] == ["more features", "wide-baseline features"]


def test_without_a_usable_model_the_budget_leaves_nothing_out(tmp_path, monkeypatch):
    # 5/22 is under 40 %: not usable; the wide-baseline retry (predicted 378 s, moved ahead) runs all the same
    state = _run_ladder(tmp_path, monkeypatch, [5, 20], FIRST, 110.0)
    assert [a["name"] for a in state.attempts] == ["as configured", "wide-baseline features"]
    assert state.ladder["left_out_for_time"] == [] and "budget" not in state.attempts[1]


# ---------------------------------------------------------------- working copies of large photos


def test_working_copies_give_colmaps_own_database(tmp_path):
    """Photos of 512 px at a 200 px working size (>= 2x: copies): the database after `to_full_resolution` is the
    one COLMAP makes from the full photos itself, up to the resize filter: cameras of the photos' size, keypoints in
    their pixels, on the same image features (most within 1.5 full-size px of one COLMAP finds)."""
    from scipy.spatial import cKDTree

    from nerfpipe.stages import scene
    from nerfpipe.stages.poses import colmap as sfm
    from nerfpipe.stages.poses.working import worth_copying

    scene.run(scene.Config(out_dir=tmp_path / "s", kind="photos", size=512, views=2, seed=0))
    images = tmp_path / "s" / "images"
    names = sorted(p.name for p in images.iterdir())
    settings = _settings(200, 2048)
    assert worth_copying(512, 200) and not worth_copying(1920, 1000)  # the fox keeps COLMAP's own path
    sfm.extract(tmp_path / "own.db", images, [names], [512], settings)
    sfm.extract(tmp_path / "copied.db", images, [names], [512], settings, tmp_path / "work")
    assert sorted(p.name for p in (tmp_path / "work" / "200" / "images").iterdir()) == names
    own, copied = pycolmap.Database.open(tmp_path / "own.db"), pycolmap.Database.open(tmp_path / "copied.db")
    try:
        (cam_own,), (cam_copied,) = own.read_all_cameras(), copied.read_all_cameras()
        assert (cam_copied.width, cam_copied.height) == (cam_own.width, cam_own.height) == (512, 512)
        assert cam_copied.principal_point_x == pytest.approx(256) and cam_copied.focal_length == pytest.approx(
            cam_own.focal_length
        )
        for image in own.read_all_images():
            a = own.read_keypoints(image.image_id)
            b = copied.read_keypoints(copied.read_image_with_name(image.name).image_id)
            assert 0.7 < len(b) / len(a) < 1.4 and b[:, :2].min() >= 0 and b[:, :2].max() <= 512
            distance, _ = cKDTree(a[:, :2]).query(b[:, :2])
            assert np.median(distance) < 1.5
            scale_own, scale_copied = np.hypot(a[:, 2], a[:, 4]), np.hypot(b[:, 2], b[:, 4])  # sqrt(a11^2 + a21^2)
            assert np.median(scale_copied) == pytest.approx(np.median(scale_own), rel=0.25)
    finally:
        own.close()
        copied.close()
