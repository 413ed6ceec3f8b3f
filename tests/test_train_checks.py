"""train's self-check (stages.train.checks): each rule gives `suspect` with its reason and figure on a run that
breaks it, and `ok` on one that does not."""

from __future__ import annotations

import json

import pytest

from nerfpipe.data.checks import verdict
from nerfpipe.stages.train.checks import GAP_DB, HOLDOUT_FLOOR_DB, RISE_DB, train_checks


def _rows(final_train_psnr: float, rise: float = 0.0, n: int = 40) -> list[dict]:
    """metrics.csv rows over 100 s: training PSNR flat at the end, except a rise of `rise` dB over the last 20 %."""
    rows = []
    for k in range(n):
        s = 100.0 * (k + 1) / n
        p = final_train_psnr - (rise if s <= 80.0 else 0.0)
        rows.append({"step": str(k * 25), "seconds": f"{s:.1f}", "train_psnr": f"{p:.3f}"})
    return rows


def _failed(checks) -> dict:
    return {c.name: c for c in checks if not c.ok}


def test_a_sound_run_is_ok():
    checks = train_checks(
        rows=_rows(30.0),
        test_psnr=28.0,
        per_view={"suspect": [], "views_total": 20},
        occupied=0.1,
        object_box=True,
        pose=None,
    )
    assert verdict(checks)["check"] == "ok", [c for c in checks if not c.ok]
    assert {c.name for c in checks} >= {"holdout_psnr", "holdout_gap", "still_improving", "unexplained_views"}
    assert {"training_fit"} <= {c.name for c in checks} and "cause" not in {c.name for c in checks}


def test_held_out_far_under_train_is_suspect_with_the_gap():
    checks = train_checks(rows=_rows(31.0), test_psnr=20.0, per_view=None, occupied=None, object_box=False, pose=None)
    bad = _failed(checks)
    assert set(bad) == {"holdout_gap", "cause"}
    assert bad["holdout_gap"].value == pytest.approx(11.0) and bad["holdout_gap"].limit == f"<= {GAP_DB:g} dB"
    assert verdict(checks)["check"] == "suspect"
    assert bad["cause"].value == "generalisation" and "31.00 dB" in bad["cause"].says


def test_low_held_out_psnr_and_still_rising_loss_are_suspect():
    checks = train_checks(
        rows=_rows(16.0, rise=2.5), test_psnr=14.0, per_view=None, occupied=None, object_box=False, pose=None
    )
    bad = _failed(checks)
    assert bad["holdout_psnr"].value == pytest.approx(14.0) and f"{HOLDOUT_FLOOR_DB:g}" in bad["holdout_psnr"].limit
    assert bad["still_improving"].value == pytest.approx(2.5, abs=0.01) and RISE_DB < 2.5


def test_fog_in_the_box_and_an_empty_grid_and_unexplained_views_are_suspect():
    fog = train_checks(
        rows=_rows(30.0),
        test_psnr=28.0,
        per_view={"suspect": list("abcdef"), "views_total": 10},
        occupied=0.9,
        object_box=True,
        pose=None,
    )
    assert set(_failed(fog)) == {"occupied_share", "unexplained_views", "cause"}
    assert _failed(fog)["cause"].value == "background rule"
    empty = train_checks(rows=_rows(30.0), test_psnr=28.0, per_view=None, occupied=0.0, object_box=False, pose=None)
    assert set(_failed(empty)) == {"occupied_share_min", "cause"} and _failed(empty)["cause"].value == "empty field"
    room = train_checks(rows=_rows(30.0), test_psnr=28.0, per_view=None, occupied=0.9, object_box=False, pose=None)
    assert verdict(room)["check"] == "ok"  # a contracted room is full of surfaces: not fog


def test_checks_that_do_not_apply_are_left_out():
    checks = train_checks(
        rows=_rows(30.0)[:3], test_psnr=None, per_view=None, occupied=None, object_box=True, pose=None
    )
    assert checks == []


def test_a_run_shorter_than_one_logging_interval_leaves_the_gap_out():
    """No training PSNR logged (metrics.csv holds only the final held-out row): the gap cannot be read, so it is
    left out rather than reported as a NaN gap under the overfitting message; the held-out floor still applies."""
    rows = [{"step": "20", "seconds": "0.3", "train_psnr": "", "test_psnr": "8.5"}]
    checks = train_checks(rows=rows, test_psnr=8.5, per_view=None, occupied=None, object_box=False, pose=None)
    assert {c.name for c in checks} == {"holdout_psnr", "cause"}
    assert set(_failed(checks)) == {"holdout_psnr", "cause"}


# ---------------------------------------------------------------- the cause, one, from evidence (issue 53)


def _carton_rows() -> list[dict]:
    """A run like issue 53's folded carton: training PSNR flat near 17 dB (no rise at the end)."""
    return _rows(16.97)


def test_a_folded_reconstruction_is_named_poses_from_the_poses_report(tmp_path):
    """The poses stage's report says the reconstruction folded: the cause is the poses, with the poses check's
    figure, not three possibilities."""
    report = {
        "check": "suspect",
        "checks": [
            {"name": "reprojection_error", "ok": True, "value": 0.75, "limit": "<= 2 px", "says": ""},
            {
                "name": "capture_order",
                "ok": False,
                "value": 2,
                "limit": "<= 0",
                "says": "folded where faces look alike",
            },
        ],
    }
    (tmp_path / "poses_report.json").write_text(json.dumps(report))
    checks = train_checks(
        rows=_carton_rows(),
        test_psnr=13.74,
        per_view=None,
        occupied=0.3,
        object_box=True,
        pose=None,
        scene_dir=tmp_path,
    )
    bad = _failed(checks)
    assert {"holdout_psnr", "training_fit", "cause"} <= set(bad)
    assert bad["cause"].value == "poses" and "capture_order = 2" in bad["cause"].says and "\n" not in bad["cause"].says
    assert "13.74 dB" in bad["cause"].says and "16.97 dB" in bad["cause"].says


def test_without_a_poses_verdict_a_flat_poor_fit_is_named_poses_and_a_rising_one_too_little_training(tmp_path):
    flat = _failed(
        train_checks(
            rows=_carton_rows(),
            test_psnr=13.7,
            per_view=None,
            occupied=None,
            object_box=False,
            pose=None,
            scene_dir=tmp_path,
        )
    )
    assert flat["cause"].value == "poses" and "cannot fit its own training photos" in flat["cause"].says
    rising = _failed(
        train_checks(
            rows=_rows(17.0, rise=2.0), test_psnr=13.7, per_view=None, occupied=None, object_box=False, pose=None
        )
    )
    assert rising["cause"].value == "too little training" and "2.0 dB" in rising["cause"].says
    some = _failed(
        train_checks(
            rows=_carton_rows(),
            test_psnr=13.7,
            per_view={"suspect": ["images/a.png", "images/b.png", "images/c.png"], "views_total": 10},
            occupied=None,
            object_box=False,
            pose=None,
        )
    )
    assert some["cause"].value == "poses of some views" and "a.png, b.png, c.png" in some["cause"].says


def test_a_poor_fit_under_a_background_that_contradicts_the_photos_is_named_the_background_rule(tmp_path):
    """make demo's white-backed photos trained with --background black: 2.0 dB, flat (named "poses" before)."""
    conflict = "the photos' border is one colour (1.00, 1.00, 1.00) in 97% of its pixels, but training put black"
    failed = _failed(
        train_checks(
            rows=_rows(2.0),
            test_psnr=2.1,
            per_view=None,
            occupied=0.05,
            object_box=True,
            pose=None,
            scene_dir=tmp_path,
            background_conflict=conflict,
        )
    )
    cause = failed["cause"]
    assert cause.value == "background rule" and conflict in cause.says and "--background auto" in cause.says
    fitted = train_checks(
        rows=_rows(31.0),
        test_psnr=30.0,
        per_view=None,
        occupied=0.1,
        object_box=True,
        pose=None,
        background_conflict=conflict,
    )
    assert verdict(fitted)["check"] == "ok"  # a conflict that did not stop the fit is no failure


def test_an_ok_poses_report_is_no_evidence_against_the_poses(tmp_path):
    (tmp_path / "poses_report.json").write_text(
        json.dumps(
            {"check": "ok", "checks": [{"name": "capture_order", "ok": True, "value": 0, "limit": "<= 0", "says": ""}]}
        )
    )
    bad = _failed(
        train_checks(
            rows=_rows(31.0),
            test_psnr=20.0,
            per_view=None,
            occupied=None,
            object_box=False,
            pose=None,
            scene_dir=tmp_path,
        )
    )
    assert bad["cause"].value == "generalisation"
    (tmp_path / "poses_report.json").write_text("{not json")  # unreadable: no evidence, no crash
    assert (
        _failed(
            train_checks(
                rows=_rows(31.0),
                test_psnr=20.0,
                per_view=None,
                occupied=None,
                object_box=False,
                pose=None,
                scene_dir=tmp_path,
            )
        )["cause"].value
        == "generalisation"
    )


def test_a_short_run_still_climbing_is_named_too_little_training_not_generalisation(tmp_path):
    """A run cut after 111 steps (the as-shot head on a loaded machine): 4 logged rows, training PSNR 7.9 -> 13.2
    dB, held-out 12.8. Too few rows for still_improving, but the trend says it was still learning; the poor fit
    of its own photos is no generalisation failure. Flat at the same level, it is named poses."""
    rows = [
        {"step": "25", "seconds": "20.8", "train_psnr": "7.850"},
        {"step": "50", "seconds": "47.8", "train_psnr": "10.997"},
        {"step": "75", "seconds": "75.9", "train_psnr": "12.602"},
        {"step": "100", "seconds": "106.4", "train_psnr": "13.192"},
        {"step": "111", "seconds": "120.2", "train_psnr": "", "test_psnr": "12.803"},
    ]
    bad = _failed(train_checks(rows=rows, test_psnr=12.8, per_view=None, occupied=None, object_box=False, pose=None))
    assert {"holdout_psnr", "training_fit", "cause"} <= set(bad) and "still_improving" not in bad
    assert bad["cause"].value == "too little training" and "2.2 dB" in bad["cause"].says
    flat = [dict(r, train_psnr="13.0") if r.get("train_psnr") else r for r in rows]
    bad = _failed(train_checks(rows=flat, test_psnr=12.8, per_view=None, occupied=None, object_box=False, pose=None))
    assert bad["cause"].value == "poses" and "cannot fit its own training photos" in bad["cause"].says
