"""Projection scenes and CT volumes on disk (data.projections, data.volumes): round trips, the NAF / SAX-NeRF
pickle and R2-Gaussian readers on tiny fixtures written here, and bad input refused in one line naming the
field, with nothing written."""

import json
import math
import pickle
from dataclasses import replace

import numpy as np
import pytest

from nerfpipe.data.errors import UserError
from nerfpipe.data.projections import (
    ProjectionScene,
    read_any,
    read_naf_pickle,
    read_projection_scene,
    read_r2_gaussian,
    write_projection_scene,
)
from nerfpipe.data.volumes import read_volume
from nerfpipe.radiance.xray import VoxelGrid, XrayGeometry


def _scene(n_views=4, shape=(5, 6), with_volume=True) -> ProjectionScene:
    rng = np.random.default_rng(0)
    g = XrayGeometry(
        mode="cone",
        dso=100.0,
        dsd=150.0,
        detector_shape=shape,
        detector_pitch=(0.8, 0.9),
        detector_offset=(0.1, -0.2),
        angles=tuple(np.linspace(0, math.pi, n_views)),
    )
    grid = VoxelGrid(shape=(4, 5, 3), spacing=(1.0, 1.0, 2.0), center=(0.0, 0.5, 0.0))
    return ProjectionScene(
        geometry=g,
        projections=rng.random((n_views, *shape)).astype(np.float32),
        splits={"train": (0, 1, 2), "test": (3,)},
        grid=grid,
        volume=rng.random(grid.shape).astype(np.float32) if with_volume else None,
        noise={"model": "poisson", "i0": 1e5},
        extra={"source": {"note": "test"}},
    )


def test_projection_scene_round_trip(tmp_path):
    scene = _scene()
    write_projection_scene(scene, tmp_path / "s")
    back = read_projection_scene(tmp_path / "s")
    assert back.geometry == scene.geometry
    np.testing.assert_array_equal(back.projections, scene.projections)
    np.testing.assert_array_equal(back.volume, scene.volume)
    assert back.splits == scene.splits and back.grid == scene.grid and back.noise == scene.noise
    assert back.extra["source"] == {"note": "test"}
    doc = json.loads((tmp_path / "s" / "projections.json").read_text())
    assert doc["length_unit"] == "mm" and doc["projections"]["quantity"] == "line_integral"
    assert read_any(tmp_path / "s").geometry == scene.geometry


def test_scene_without_volume_round_trips(tmp_path):
    write_projection_scene(_scene(with_volume=False), tmp_path / "s")
    assert read_projection_scene(tmp_path / "s" / "projections.json").volume is None
    assert not (tmp_path / "s" / "volume.npy").exists()


@pytest.mark.parametrize(
    "change,field",
    [
        (lambda s: replace(s, geometry=replace(s.geometry, dsd=-50.0)), "geometry.dsd: the detector is behind"),
        (lambda s: replace(s, geometry=replace(s.geometry, dsd=80.0)), "geometry.dsd"),
        (lambda s: replace(s, geometry=replace(s.geometry, dso=0.0)), "geometry.dso"),
        (lambda s: replace(s, projections=s.projections[:3]), "projections: 3 projections but 4 angles"),
        (lambda s: replace(s, projections=s.projections[:, :4]), "geometry.detector_shape"),
        (
            lambda s: replace(s, projections=np.where(np.arange(30).reshape(5, 6) == 7, np.nan, s.projections)),
            "projections: 4 non-finite",
        ),
        (lambda s: replace(s, volume=-s.volume), "volume: negative attenuation"),
        (lambda s: replace(s, volume=np.full(s.grid.shape, np.inf, np.float32)), "volume: 60 non-finite"),
        (lambda s: replace(s, splits={"train": (0, 9)}), "splits.train: view index 9"),
        (lambda s: replace(s, geometry=replace(s.geometry, mode="fan")), "geometry.mode"),
    ],
)
def test_bad_scene_is_one_line_naming_the_field_and_writes_nothing(tmp_path, change, field):
    with pytest.raises(UserError) as e:
        write_projection_scene(change(_scene()), tmp_path / "s")
    msg = str(e.value)
    assert field in msg and "\n" not in msg, msg
    assert not (tmp_path / "s").exists() or not any((tmp_path / "s").iterdir())


def test_reader_names_the_file_and_field(tmp_path):
    write_projection_scene(_scene(), tmp_path / "s")
    doc = json.loads((tmp_path / "s" / "projections.json").read_text())
    doc["geometry"]["angles"] = doc["geometry"]["angles"][:2]
    (tmp_path / "s" / "projections.json").write_text(json.dumps(doc))
    with pytest.raises(UserError, match=r"projections.json: projections: 4 projections but 2 angles"):
        read_projection_scene(tmp_path / "s")


def test_array_files_named_outside_the_scene_are_refused(tmp_path):
    """projections.json's `projections.file` / `volume.file` stay inside the scene folder (data.confine)."""
    write_projection_scene(_scene(), tmp_path / "s")
    np.save(tmp_path / "outside.npy", np.zeros((4, 5, 6), np.float32))
    doc = json.loads((tmp_path / "s" / "projections.json").read_text())
    for key in ("projections", "volume"):
        bad = json.loads(json.dumps(doc))
        bad[key]["file"] = "../outside.npy"
        (tmp_path / "s" / "projections.json").write_text(json.dumps(bad))
        with pytest.raises(UserError, match=rf"{key}.file '../outside.npy' resolves outside the dataset folder"):
            read_projection_scene(tmp_path / "s")


def test_naf_pickle_reader(tmp_path):
    rng = np.random.default_rng(1)
    image = rng.random((4, 5, 3)).astype(np.float32)
    data = {
        "DSD": 1500.0,
        "DSO": 1000.0,
        "nDetector": [5, 6],
        "dDetector": [0.8, 0.9],
        "offDetector": [0.0, 0.0],
        "nVoxel": [4, 5, 3],
        "dVoxel": [2.0, 2.0, 2.0],
        "offOrigin": [0.0, 0.0, 0.0],
        "mode": "cone",
        "totalAngle": 180.0,
        "startAngle": 0.0,
        "accuracy": 0.5,
        "filter": None,
        "numTrain": 3,
        "numVal": 2,
        "image": image,
        "train": {"angles": np.linspace(0, np.pi, 3), "projections": rng.random((3, 5, 6)).astype(np.float32)},
        "val": {"angles": np.array([0.3, 1.0]), "projections": rng.random((2, 5, 6)).astype(np.float32)},
    }
    path = tmp_path / "chest_50.pickle"
    path.write_bytes(pickle.dumps(data))
    scene = read_any(path)
    assert scene.geometry.dso == 1000.0 and scene.geometry.dsd == 1500.0 and scene.geometry.mode == "cone"
    assert scene.geometry.detector_shape == (5, 6) and scene.geometry.detector_pitch == (0.8, 0.9)
    assert scene.splits == {"train": (0, 1, 2), "test": (3, 4)}
    np.testing.assert_allclose(scene.projections[3:], data["val"]["projections"])
    np.testing.assert_allclose(scene.volume, image / 1000.0, rtol=1e-6)  # 1/m -> 1/mm
    assert scene.grid.shape == (4, 5, 3) and scene.grid.spacing == (2.0, 2.0, 2.0)
    # and it writes out as our format
    write_projection_scene(scene, tmp_path / "ours")
    assert read_projection_scene(tmp_path / "ours").geometry == scene.geometry
    bad = dict(data, train={"angles": np.zeros(2), "projections": data["train"]["projections"]})
    path.write_bytes(pickle.dumps(bad))
    with pytest.raises(UserError, match="train.projections: 3 projections but 2 angles"):
        read_naf_pickle(path)


def test_r2_gaussian_reader(tmp_path):
    rng = np.random.default_rng(2)
    folder = tmp_path / "0_chest_cone"
    (folder / "proj_train").mkdir(parents=True)
    (folder / "proj_test").mkdir()
    entries = {}
    for split, n in (("train", 3), ("test", 2)):
        entries[split] = []
        for i in range(n):
            rel = f"proj_{split}/proj_{split}_{i:04d}.npy"
            np.save(folder / rel, rng.random((5, 6)).astype(np.float32))
            entries[split].append({"file_path": rel, "angle": 0.4 * i})
    vol = rng.random((4, 4, 4)).astype(np.float32)
    np.save(folder / "vol_gt.npy", vol)
    scanner = {
        "mode": "parallel",
        "DSD": 7.0,
        "DSO": 5.0,
        "nDetector": [5, 6],
        "sDetector": [0.5, 0.6],
        "nVoxel": [4, 4, 4],
        "sVoxel": [0.4, 0.4, 0.4],
        "offOrigin": [0, 0, 0],
        "offDetector": [0, 0],
    }
    meta = {
        "scanner": scanner,
        "vol": "vol_gt.npy",
        "bbox": [[-1, -1, -1], [1, 1, 1]],
        "proj_train": entries["train"],
        "proj_test": entries["test"],
    }
    (folder / "meta_data.json").write_text(json.dumps(meta))
    scene = read_r2_gaussian(folder)
    assert scene.geometry.mode == "parallel" and scene.geometry.dso == pytest.approx(5000.0)  # m -> mm
    assert scene.geometry.detector_pitch == pytest.approx((100.0, 100.0))
    assert scene.grid.spacing == pytest.approx((100.0, 100.0, 100.0))
    assert scene.split("test") == (3, 4)
    np.testing.assert_allclose(scene.volume, vol / 1000.0, rtol=1e-6)
    assert read_any(folder / "meta_data.json").geometry == scene.geometry


def test_volume_readers(tmp_path):
    import nibabel
    import scipy.io

    vol = np.random.default_rng(3).random((4, 5, 6)).astype(np.float32)
    np.save(tmp_path / "v.npy", vol)
    scipy.io.savemat(tmp_path / "v.mat", {"img": vol})
    vol.reshape(-1, order="F").tofile(tmp_path / "v.raw")
    nibabel.save(nibabel.Nifti1Image(vol, np.diag([0.5, 0.6, 0.7, 1.0])), str(tmp_path / "v.nii.gz"))
    for name, kw in (("v.npy", {}), ("v.mat", {}), ("v.raw", {"shape": (4, 5, 6), "dtype": "float32"})):
        got = read_volume(tmp_path / name, spacing=2.0, **kw)
        np.testing.assert_array_equal(got.data, vol)
        assert got.spacing == (2.0, 2.0, 2.0)
    nii = read_volume(tmp_path / "v.nii.gz")
    np.testing.assert_array_equal(nii.data, vol)
    assert nii.spacing == pytest.approx((0.5, 0.6, 0.7))


@pytest.mark.parametrize(
    "setup,message",
    [
        (lambda p: np.save(p / "v.npy", -np.ones((3, 3, 3))), "negative attenuation"),
        (lambda p: np.save(p / "v.npy", np.full((3, 3, 3), np.nan)), "27 non-finite attenuation values"),
        (lambda p: np.save(p / "v.npy", np.ones((3, 3))), "expected a 3-D volume"),
        (lambda p: np.ones(10, np.float32).tofile(p / "v.raw"), "needs its shape and dtype"),
    ],
)
def test_bad_volumes(tmp_path, setup, message):
    setup(tmp_path)
    path = next(tmp_path.iterdir())
    with pytest.raises(UserError, match=message) as e:
        read_volume(path, spacing=1.0)
    assert "\n" not in str(e.value) and str(path) in str(e.value)
