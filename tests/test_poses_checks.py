"""Stage `poses` checks itself: camera and model checks (stages.poses.quality), the choice among retry attempts and
the ladder's stop (stages.poses.choice), the EXIF focal prior (stages.poses.exif) and upright copies of sideways
photos. Constructed pycolmap cameras / synthesized models and tiny generated photos; COLMAP runs only on single
images (SIFT extraction, well under a second)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2  # before pycolmap (imported by stages.poses): the other order crashes cv2's PNG writer
import numpy as np
import pycolmap
import pytest
from PIL import Image

from nerfpipe.data.checks import verdict
from nerfpipe.stages.poses import quality
from nerfpipe.stages.poses.choice import Candidate, candidate, choose, keepable, stop_reason
from nerfpipe.stages.poses.exif import FILM_DIAGONAL_MM, apply_focal_priors, exif_focal
from nerfpipe.stages.poses.images import write_upright
from nerfpipe.stages.poses.report import RunState, focal_prior_record

EXIF_F_PX = 7540.0  # the motivating capture: 4000 x 4000 px, EXIF focal ~7,540 px


def _camera(f: float, k1: float = 0.0, size: tuple[int, int] = (4000, 4000), pp: tuple[float, float] | None = None):
    w, h = size
    cx, cy = pp if pp is not None else (w / 2, h / 2)
    return pycolmap.Camera(model="SIMPLE_RADIAL", width=w, height=h, params=[f, cx, cy, k1])


def _by_name(checks) -> dict:
    return {c.name: c for c in checks}


# ---------------------------------------------------------------- camera checks


def test_sane_camera_passes():
    checks = _by_name(quality.camera_checks(_camera(EXIF_F_PX * 1.05, k1=-0.05), EXIF_F_PX))
    assert set(checks) == {"focal_vs_exif", "distortion", "principal_point"}  # with a prior: no FOV check
    assert all(c.ok for c in checks.values())
    assert checks["focal_vs_exif"].value == pytest.approx(5.0, abs=0.01)
    assert verdict(checks.values())["check"] == "ok"


def test_focal_off_the_exif_prior_is_suspect_with_its_figure():
    checks = quality.camera_checks(_camera(EXIF_F_PX * 1.4), EXIF_F_PX)
    result = verdict(checks)
    assert result["check"] == "suspect"
    (bad,) = [c for c in result["checks"] if not c["ok"]]
    assert bad["name"] == "focal_vs_exif" and bad["value"] == pytest.approx(40.0) and bad["limit"] == "<= 25 %"
    assert "10556 px" in bad["says"] and "7540 px" in bad["says"] and "+40%" in bad["says"]
    assert not _by_name(quality.camera_checks(_camera(EXIF_F_PX * 0.6), EXIF_F_PX))["focal_vs_exif"].ok


def test_strong_distortion_is_suspect():
    # f = long side, |k1| > 1: the corner (r^2 = 0.5 in normalised coordinates) moves by 60 %
    checks = _by_name(quality.camera_checks(_camera(4000, k1=-1.2), None))
    assert not checks["distortion"].ok and checks["distortion"].value == pytest.approx(60.0, rel=1e-3)
    assert "k = -1.2" in checks["distortion"].says and checks["field_of_view"].ok
    # the motivating case: f 10,450 px (+39 % on EXIF), k1 = -2.56 -> both the focal and the distortion fail
    case = _by_name(quality.camera_checks(_camera(10450, k1=-2.56), EXIF_F_PX))
    assert not case["focal_vs_exif"].ok and case["focal_vs_exif"].value == pytest.approx(38.6, abs=0.1)
    assert not case["distortion"].ok and case["distortion"].value == pytest.approx(18.75, abs=0.05)
    # the bound is on the image, not on k1: a long lens (r <= 0.07) with k1 = 0.5 bends its corners by 0.25 %
    assert _by_name(quality.camera_checks(_camera(20000, k1=0.5), None))["distortion"].ok


def test_distortion_measure_matches_the_closed_form():
    """SIMPLE_RADIAL, centred: the largest displacement is k1 r^2 at the corner, r = half diagonal / f."""
    for (w, h), f, k1 in [((4000, 4000), 10450, -2.56), ((600, 400), 500, 0.08), ((640, 480), 300, -0.2)]:
        r2 = (math.hypot(w, h) / 2 / f) ** 2
        assert quality.distortion_at_edges(_camera(f, k1, (w, h))) == pytest.approx(abs(k1) * r2, rel=1e-6)
    assert quality.distortion_at_edges(_camera(1000, 0.0, (600, 400))) == pytest.approx(0.0, abs=1e-12)


def test_principal_point_far_off_centre_is_suspect():
    checks = _by_name(quality.camera_checks(_camera(EXIF_F_PX, pp=(2800, 2000)), EXIF_F_PX))
    assert not checks["principal_point"].ok and checks["principal_point"].value == pytest.approx(20.0)
    assert _by_name(quality.camera_checks(_camera(EXIF_F_PX, pp=(2100, 1950)), EXIF_F_PX))["principal_point"].ok


def test_field_of_view_without_a_prior():
    fov = {f: _by_name(quality.camera_checks(_camera(f), None))["field_of_view"] for f in (300, 4800, 40000)}
    assert fov[4800].ok and fov[4800].value == pytest.approx(45.2, abs=0.1)  # COLMAP's start, 1.2 x long side
    assert not fov[300].ok and fov[300].value > 140  # f = 0.075 L: wider than any rectilinear lens
    assert not fov[40000].ok and fov[40000].value < 10  # a 360 mm lens equivalent


def test_opencv_camera_checks():
    def opencv(fx, fy, k1=0.0, k2=0.0, p1=0.0, p2=0.0):
        params = [fx, fy, 320, 240, k1, k2, p1, p2]
        return _by_name(
            quality.camera_checks(pycolmap.Camera(model="OPENCV", width=640, height=480, params=params), None)
        )

    sane = opencv(500, 501, k1=-0.1, k2=0.02, p1=1e-3, p2=-1e-3)
    assert all(c.ok for c in sane.values()) and "focal_aspect" in sane
    assert not opencv(500, 620)["focal_aspect"].ok
    assert not opencv(500, 500, k1=-0.4, k2=-0.3)["distortion"].ok
    assert not opencv(500, 500, p1=0.1)["distortion"].ok  # tangential terms count too


# ---------------------------------------------------------------- model checks and the choice


def _model(frames: int = 10, f: float = 1280.0, k1: float = 0.05) -> pycolmap.Reconstruction:
    """A synthesized, noise-free model: one 1024 x 768 SIMPLE_RADIAL camera, every point seen by every frame."""
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_cameras_per_rig, opts.num_frames_per_rig, opts.num_points3D = 1, 1, frames, 150
    opts.camera_params = [f, 512.0, 384.0, k1]
    pycolmap.set_random_seed(0)
    return pycolmap.synthesize_dataset(opts)


def test_model_checks_of_a_sane_model():
    rec = _model()
    (camera_id,) = rec.cameras
    checks = _by_name(quality.model_checks(rec, {camera_id: 1300.0}, total=10))
    assert set(checks) == {
        "focal_vs_exif",
        "distortion",
        "principal_point",
        "reprojection_error",
        "track_length",
        "registered_fraction",
    }
    assert all(c.ok for c in checks.values())
    assert checks["track_length"].value == 10 and checks["registered_fraction"].value == 100
    few = _by_name(quality.model_checks(rec, {}, total=20))  # 10 of 20; no prior: the FOV check instead
    assert not few["registered_fraction"].ok and "field_of_view" in few and "focal_vs_exif" not in few


def _degenerate_copy(rec: pycolmap.Reconstruction, focal_factor: float = 1.4, k1: float = -2.5):
    bad = pycolmap.Reconstruction(rec)
    for cam in bad.cameras.values():
        params = np.array(cam.params)
        params[cam.focal_length_idxs()] *= focal_factor
        params[cam.extra_params_idxs()[0]] = k1
        cam.params = params
    return bad


def _deregister(rec: pycolmap.Reconstruction, keep: int) -> pycolmap.Reconstruction:
    fewer = pycolmap.Reconstruction(rec)
    for frame_id in sorted(fewer.reg_frame_ids())[keep:]:
        fewer.deregister_frame(frame_id)
    return fewer


def test_choice_prefers_sane_cameras_over_more_images():
    good = _model(frames=10)
    (camera_id,) = good.cameras
    priors = {camera_id: 1280.0}
    sane = _deregister(good, keep=7)
    cands = [
        candidate("as configured", _degenerate_copy(good), priors, 10),
        candidate("more features", sane, priors, 10),
    ]
    assert cands[0].registered == 10 and cands[1].registered == 7 and not cands[0].sane and cands[1].sane
    chosen = choose(cands, total=10)
    assert chosen.index == 1 and chosen.warning is None
    assert "kept 'more features' (7/10 registered)" in chosen.sentence
    assert "'as configured' (10/10) failed focal_vs_exif = 40" in chosen.sentence and "distortion" in chosen.sentence
    # under 40 % registered the sane one is not usable: the most registered is kept, and said to be suspect
    cands[1] = candidate("more features", _deregister(good, keep=3), priors, 10)
    chosen = choose(cands, total=10)
    assert chosen.index == 0 and "focal_vs_exif = 40" in chosen.warning and "40%" in chosen.warning


def _cand(name: str, registered: int, ok: bool, points: int = 100) -> Candidate:
    focal = quality.camera_checks(_camera(EXIF_F_PX * (1.0 if ok else 1.5)), EXIF_F_PX)
    return Candidate(name=name, registered=registered, points=points, checks=tuple(focal))


def test_choice_when_every_attempt_fails_a_camera_check():
    chosen = choose([_cand("a", 18, False), _cand("b", 22, False), _cand("c", 22, False, points=50)], total=22)
    assert chosen.index == 1 and "focal_vs_exif = 50 (expected <= 25 %)" in chosen.warning
    assert "although its camera failed focal_vs_exif" in chosen.sentence
    same = choose([_cand("a", 20, True), _cand("b", 20, True)], total=22)  # a tie: the earlier (cheaper) one
    assert same.index == 0 and "the most registered" in same.sentence and same.warning is None
    only = choose([_cand("a", 20, True)], total=22)
    assert "the only attempt" in only.sentence
    with pytest.raises(ValueError):
        choose([], total=22)


def test_ladder_stops_on_a_good_attempt_not_on_a_bad_one_and_within_its_budget():
    total = 22
    assert stop_reason([_cand("as configured", 22, True)], total, 30.0, 110.0).startswith(
        "'as configured' registered 22/22"
    )
    # 80 %+ registered but a camera check failed: go on
    assert stop_reason([_cand("as configured", 22, False)], total, 30.0, 110.0) is None
    # a usable, sane model (15/22) and the stage past its time budget: stop; under it: go on
    tried = [_cand("as configured", 22, False), _cand("more features", 15, True)]
    assert stop_reason(tried, total, 100.0, 110.0) is None
    assert "time budget of 110 s" in stop_reason(tried, total, 120.0, 110.0)
    # without a usable, sane model the budget does not stop the ladder (the result would be failed or suspect)
    assert stop_reason([_cand("a", 22, False), _cand("b", 8, True)], total, 900.0, 110.0) is None
    assert keepable(tried, total).name == "more features" and keepable(tried[:1], total) is None


# ---------------------------------------------------------------- EXIF focal prior, sideways photos


def _photo(path: Path, size: tuple[int, int], orientation: int = 1, **tags) -> None:
    """A textured photo of `size` (w, h) as displayed, stored rotated for EXIF `orientation` 6 or 8."""
    rng = np.random.default_rng(0)
    w, h = size
    pixels = cv2.resize(rng.integers(0, 255, (h // 8, w // 8, 3), dtype=np.uint8), (w, h))
    im = Image.fromarray(pixels)
    exif = Image.Exif()
    if orientation != 1:
        exif[0x0112] = orientation
        # 6: displayed = stored rotated 90 deg clockwise; so stored = displayed rotated counter-clockwise
        im = im.transpose(Image.Transpose.ROTATE_90 if orientation == 6 else Image.Transpose.ROTATE_270)
    ifd = exif.get_ifd(0x8769)
    names = {"f35": 0xA405, "f_mm": 0x920A, "plane_res": 0xA20E, "plane_unit": 0xA210, "pixel_x": 0xA002}
    for key, value in tags.items():
        ifd[names[key]] = value
    fmt = "TIFF" if path.suffix == ".tif" else "JPEG"
    im.save(path, format=fmt, exif=exif.tobytes(), **({"quality": 95} if fmt == "JPEG" else {}))


def _colmap_camera(image_dir: Path, name: str, db: Path) -> pycolmap.Camera:
    pycolmap.extract_features(db, image_dir, image_names=[name], device=pycolmap.Device.cpu)
    database = pycolmap.Database.open(db)
    try:
        return database.read_all_cameras()[0]
    finally:
        database.close()


def test_exif_focal_prior_is_what_colmap_reads(tmp_path):
    """The 35 mm equivalent is by the diagonal (CIPA, as COLMAP): for 3:2 it is f35 / 36 mm x long side."""
    photos, copies = tmp_path / "photos", tmp_path / "copies"
    photos.mkdir(), copies.mkdir()
    _photo(photos / "wide.jpg", (600, 400), f35=50)
    _photo(photos / "phone.jpg", (640, 480), f35=26)
    _photo(photos / "plane.jpg", (600, 400), f_mm=20, plane_res=150, plane_unit=4, pixel_x=1200)
    _photo(photos / "none.jpg", (600, 400), f_mm=20)  # a focal length in mm without a sensor size: no prior
    assert exif_focal(photos / "wide.jpg").focal_px == pytest.approx(50 / 36 * 600, rel=1e-3)
    assert exif_focal(photos / "phone.jpg").focal_px == pytest.approx(26 / FILM_DIAGONAL_MM * 800)
    plane = exif_focal(photos / "plane.jpg")  # 20 mm x 150 px/mm = 3000 px at the sensor's 1200 px, half here
    assert plane.focal_px == pytest.approx(1500) and "scaled" in plane.source
    assert exif_focal(photos / "none.jpg") is None
    for name in ("wide.jpg", "phone.jpg"):
        copy, _ = write_upright(photos / name, copies, set())
        cam = _colmap_camera(copies, copy, tmp_path / f"{name}.db")
        assert cam.has_prior_focal_length
        assert cam.focal_length == pytest.approx(exif_focal(photos / name).focal_px, rel=1e-4)


@pytest.mark.parametrize("orientation", [6, 8])
def test_sideways_photo_gets_an_upright_copy_and_the_same_prior(tmp_path, orientation):
    photos, copies = tmp_path / "photos", tmp_path / "copies"
    photos.mkdir(), copies.mkdir()
    _photo(photos / "side.jpg", (300, 200), orientation=orientation, f35=35)
    _photo(photos / "flat.jpg", (300, 200), f35=35)
    with Image.open(photos / "side.jpg") as im:
        assert im.size == (200, 300)  # stored sideways
    name, grey = write_upright(photos / "side.jpg", copies, set())
    with Image.open(copies / name) as copy:
        assert copy.size == (300, 200) and copy.getexif().get(0x0112) == 1  # upright, orientation reset
    assert grey.shape == (200, 300)
    flat = np.asarray(Image.open(photos / "flat.jpg").convert("L"), np.float32)
    assert np.abs(np.asarray(Image.open(copies / name).convert("L"), np.float32) - flat).mean() < 6.0
    # the long side (and diagonal) is unchanged by the rotation: the same focal in pixels, before and after
    expected = 35 / FILM_DIAGONAL_MM * math.hypot(300, 200)
    assert exif_focal(photos / "side.jpg").focal_px == pytest.approx(expected)
    assert exif_focal(copies / name).focal_px == pytest.approx(expected)  # the re-encoded copy kept its EXIF
    cam = _colmap_camera(copies, name, tmp_path / "side.db")
    assert (cam.width, cam.height) == (300, 200) and cam.has_prior_focal_length
    assert cam.focal_length == pytest.approx(expected, rel=1e-4)


def test_prior_reaches_colmap_when_the_copy_lost_its_exif(tmp_path):
    """A TIFF becomes a PNG copy without EXIF: COLMAP reads no prior, `apply_focal_priors` sets it as COLMAP
    would (focal = prior, has_prior_focal_length); a camera whose photos have none says "absent"."""
    photos, copies = tmp_path / "photos", tmp_path / "copies"
    photos.mkdir(), copies.mkdir()
    _photo(photos / "scan.tif", (600, 400), f35=50)
    _photo(photos / "plain.jpg", (400, 300))
    prior = exif_focal(photos / "scan.tif")
    scan, _ = write_upright(photos / "scan.tif", copies, set())
    plain, _ = write_upright(photos / "plain.jpg", copies, set())
    assert scan == "scan.png" and exif_focal(copies / scan) is None
    db = tmp_path / "db.db"
    for group in ([scan], [plain]):
        pycolmap.extract_features(db, copies, image_names=group, device=pycolmap.Device.cpu)
    before = {c.camera_id: c for c in pycolmap.Database.open(db).read_all_cameras()}
    assert not any(c.has_prior_focal_length for c in before.values())
    info = apply_focal_priors(db, {scan: prior.focal_px})
    database = pycolmap.Database.open(db)
    try:
        cams = {im.name: database.read_camera(im.camera_id) for im in database.read_all_images()}
        ids = {im.name: im.camera_id for im in database.read_all_images()}
    finally:
        database.close()
    assert cams[scan].has_prior_focal_length and cams[scan].focal_length == pytest.approx(prior.focal_px)
    assert cams[scan].params[1:].tolist() == before[ids[scan]].params[1:].tolist()  # only the focal changed
    assert info[ids[scan]]["source"] == "EXIF of 1 of 1 photos" and info[ids[scan]]["colmap_read"] is None
    assert not cams[plain].has_prior_focal_length and info[ids[plain]]["source"] == "absent"
    state = RunState(
        started=0.0, names={scan: "scan.tif", plain: "plain.jpg"}, exif_focal={scan: prior}, focal_prior=info
    )
    record = focal_prior_record(state)
    assert record["exif"] == "1 of 2 photos" and json.dumps(record)
    assert focal_prior_record(RunState(started=0.0, names={plain: "plain.jpg"}))["exif"] == "absent"


# ---------------------------------------------------------------- the ladder, with its pycolmap steps stubbed


def _run_ladder(tmp_path: Path, monkeypatch, models: list[pycolmap.Reconstruction]) -> RunState:
    """`attempts.run_attempts` over the 4-attempt plan where attempt k's mapping returns models[k - 1] (10
    images, EXIF prior 1280 px); extraction, matching and statistics are stubs."""
    from nerfpipe.data.rundir import MetricsLog
    from nerfpipe.stages.poses import attempts
    from nerfpipe.stages.poses import colmap as sfm
    from nerfpipe.stages.poses.report import PhaseTimer

    names = [f"{k}.jpg" for k in range(10)]
    stats = sfm.DatabaseStats(
        features=dict.fromkeys(names, 500),
        matches=dict.fromkeys(names, 100),
        verified_pairs=dict.fromkeys(names, 3),
        camera_of=dict.fromkeys(names, 1),
    )
    made = iter(models)
    monkeypatch.setattr(sfm, "extract", lambda db, *a: pycolmap.Database.open(db).close())
    monkeypatch.setattr(sfm, "match", lambda db, s: None)
    monkeypatch.setattr(sfm, "database_stats", lambda db: stats)
    monkeypatch.setattr(sfm, "reconstruct", lambda db, images, out, s: {0: next(made)})
    monkeypatch.setattr(attempts, "apply_focal_priors", lambda db, priors, weak=None: {1: {"prior_px": 1280.0}})
    settings = sfm.SfmSettings(
        max_image_size=1000,
        max_num_features=2048,
        camera_model="SIMPLE_RADIAL",
        single_camera=True,
        matcher="exhaustive",
        sequential_overlap=10,
        num_threads=1,
        seed=0,
    )
    state = RunState(started=0.0)
    columns = ["step", "seconds", "phase", "images", "registered"]
    phase = PhaseTimer(state, MetricsLog(tmp_path / "metrics.csv", columns), None)
    plan = attempts.ladder(settings, 4, long_side=4000)
    attempts.run_attempts(plan, tmp_path, tmp_path, [names], [4000], state, phase)
    assert (tmp_path / "database.db").is_file() and not list(tmp_path.glob("database.*.db"))
    return state


def test_ladder_goes_on_past_a_full_model_with_a_bad_camera(tmp_path, monkeypatch):
    good = _model(frames=10)
    state = _run_ladder(tmp_path, monkeypatch, [_degenerate_copy(good), _deregister(good, keep=9), good, good])
    # attempt 1 registered 10/10 but its camera failed: not a stop; attempt 2 (9/10, sane) is: kept
    assert [a["registered"] for a in state.attempts] == [10, 9] and [a["kept"] for a in state.attempts] == [False, True]
    assert state.attempts[0]["check"] == "suspect" and not state.attempts[0]["cameras_pass"]
    assert {c["name"] for c in state.attempts[0]["checks"] if not c["ok"]} == {"focal_vs_exif", "distortion"}
    assert state.attempts[1]["check"] == "ok" and state.model.num_reg_images() == 9
    assert "kept 'more features' (9/10 registered)" in state.choice and "'as configured' (10/10)" in state.choice
    assert state.ladder["stopped"].startswith("'more features' registered 9/10") and not state.warnings


def test_ladder_keeps_a_suspect_model_only_when_every_attempt_fails(tmp_path, monkeypatch):
    bad = _degenerate_copy(_model(frames=10))
    state = _run_ladder(tmp_path, monkeypatch, [bad, _deregister(bad, keep=6), bad, bad])
    assert len(state.attempts) == 4 and state.ladder["stopped"].startswith("every attempt allowed was made")
    assert [a["kept"] for a in state.attempts] == [True, False, False, False]  # 10/10, the earliest of the ties
    assert len(state.warnings) == 1 and "focal_vs_exif = 40 (expected <= 25 %)" in state.warnings[0]


def test_summary_prints_one_warning_per_failed_check():
    from io import StringIO

    from rich.console import Console

    from nerfpipe.stages.poses.report import print_summary

    checks = quality.camera_checks(_camera(10450, k1=-2.56), EXIF_F_PX)
    report = {
        "registered": 22,
        "total": 22,
        "mean_reprojection_error_px": 0.8,
        "timings_s": {"mapping": 1.0},
        "attempts": [],
        "points3D": 5000,
        "warnings": [],
        **verdict(checks),
    }
    out = StringIO()
    print_summary(Console(file=out, width=400), report)
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("poses: 22/22 registered") and len(lines) == 3
    assert lines[1].startswith("warning: poses (colmap/sparse): focal_vs_exif = 38.59 (expected <= 25 %)")
    assert "f = 10450 px against the EXIF prior 7540 px (+39%)" in lines[1]
    assert lines[2].startswith("warning: poses (colmap/sparse): distortion = 18.75 (expected <= 15 %)")


# ---------------------------------------------------------------- EXIF priors of cropped photos (issue 53)


def test_a_square_crop_gets_its_frame_not_its_diagonal(tmp_path):
    """The shared head's EXIF: 4000 x 4000 px cut from a 6000 x 4000 px APS-C frame, FocalLength 31 mm,
    FocalLengthIn35mmFilm 46 mm. By the diagonal (COLMAP's rule) 6,014 px; its own cameras say ~7,540 px.
    As a crop keeping the short side of a 3:2 frame (crop factor 46 / 31 = 1.48 < 1.8): 46 / 43.27 x
    hypot(6000, 4000) = 7,666 px, +1.7 %. The prior says it is a guess. (Photos 400 px: the same rule in pixels.)"""
    _photo(tmp_path / "head.jpg", (400, 400), f_mm=31, f35=46)
    prior = exif_focal(tmp_path / "head.jpg")
    assert prior.focal_px * 10 == pytest.approx(46 / FILM_DIAGONAL_MM * math.hypot(6000, 4000), rel=1e-6)
    assert prior.focal_px * 10 == pytest.approx(7666, abs=1) and abs(prior.focal_px * 10 / 7540 - 1) < 0.02
    assert prior.focal_px * 10 != pytest.approx(6014, abs=50)  # the diagonal rule it replaces
    assert prior.weak is not None and "crop" in prior.weak and "3:2" in prior.weak and "1.48" in prior.weak
    # a phone's crop factor (~5) means a 4:3 frame; a 16:9 photo keeps the frame's long side
    _photo(tmp_path / "phone.jpg", (400, 400), f_mm=4.4, f35=26)
    assert exif_focal(tmp_path / "phone.jpg").focal_px == pytest.approx(26 / FILM_DIAGONAL_MM * 400 * 5 / 3)
    _photo(tmp_path / "wide.jpg", (640, 360), f35=30)
    assert exif_focal(tmp_path / "wide.jpg").focal_px == pytest.approx(
        30 / FILM_DIAGONAL_MM * math.hypot(640, 640 / 1.5)
    )
    # a frame's own aspect (3:2, 4:3) is the whole frame: the diagonal rule, a strong prior
    _photo(tmp_path / "frame.jpg", (600, 400), f_mm=31, f35=46)
    frame = exif_focal(tmp_path / "frame.jpg")
    assert frame.weak is None and frame.focal_px == pytest.approx(46 / FILM_DIAGONAL_MM * math.hypot(600, 400))


def test_exif_fields_that_disagree_make_a_weak_prior_from_the_pixel_pitch(tmp_path):
    # 3:2, f35 50 mm -> 833 px by the diagonal; FocalLength 20 mm x 60 px/mm = 1200 px: 44 % apart
    _photo(tmp_path / "odd.jpg", (600, 400), f35=50, f_mm=20, plane_res=60, plane_unit=4)
    prior = exif_focal(tmp_path / "odd.jpg")
    assert prior.focal_px == pytest.approx(1200) and "disagree" in prior.weak
    _photo(tmp_path / "even.jpg", (600, 400), f35=50, f_mm=20, plane_res=42, plane_unit=4)  # 840 px: agrees
    assert exif_focal(tmp_path / "even.jpg").weak is None


def test_a_weak_prior_never_decides_the_attempt_and_reaches_colmap_without_has_prior(tmp_path):
    """Issue 53's 4000 px head: an attempt registering 22/22 with f 30 % off a (wrong) prior was thrown away for
    one with 14/22. Against a weak prior the focal is reported (focal_vs_weak_exif, 50 %) but is no camera check:
    the 22/22 model is kept; a strong prior still decides."""
    cam = _camera(EXIF_F_PX * 1.3)
    weak = _by_name(quality.camera_checks(cam, EXIF_F_PX, weak="a crop, a guess"))
    assert set(weak) == {"focal_vs_weak_exif", "field_of_view", "distortion", "principal_point"}
    assert weak["focal_vs_weak_exif"].ok and weak["focal_vs_weak_exif"].value == pytest.approx(30.0)
    assert "weak EXIF prior" in weak["focal_vs_weak_exif"].says and "focal_vs_weak_exif" not in quality.CAMERA_CHECKS
    assert not _by_name(quality.camera_checks(_camera(EXIF_F_PX * 1.6), EXIF_F_PX, weak="guess"))[
        "focal_vs_weak_exif"
    ].ok
    full, partial = _model(frames=10, f=1280 * 1.3, k1=0.0), _deregister(_model(frames=10, f=1280, k1=0.0), keep=6)
    cands = [
        candidate("as configured", full, {1: 1280.0}, 10, {1: "a crop"}),
        candidate("more features", partial, {1: 1280.0}, 10, {1: "a crop"}),
    ]
    assert cands[0].sane and choose(cands, total=10).index == 0
    strong = [candidate("as configured", full, {1: 1280.0}, 10), candidate("more features", partial, {1: 1280.0}, 10)]
    assert not strong[0].sane and choose(strong, total=10).index == 1
    # COLMAP gets the value as its starting focal, without has_prior_focal_length
    _photo(tmp_path / "a.jpg", (300, 300), f_mm=31, f35=46)
    db = tmp_path / "db.db"
    pycolmap.extract_features(db, tmp_path, image_names=["a.jpg"], device=pycolmap.Device.cpu)
    prior = exif_focal(tmp_path / "a.jpg")
    info = apply_focal_priors(db, {"a.jpg": prior.focal_px}, {"a.jpg": prior.weak})
    database = pycolmap.Database.open(db)
    try:
        (cam,) = database.read_all_cameras()
    finally:
        database.close()
    assert not cam.has_prior_focal_length and cam.focal_length == pytest.approx(prior.focal_px)
    assert info[cam.camera_id]["weak"] == prior.weak
