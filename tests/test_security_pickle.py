"""No code from data (issue 32): a NAF / SAX-NeRF `*.pickle` is read by a restricted unpickler (data.safe_pickle)
that rebuilds only plain data and numpy arrays; a file naming any other global is refused in one line and its
payload never runs. `--trust-pickle` (xray-train only) unpickles a file the user vouches for. A run's config.json
names its scene: xray-eval, xray-export and view (model.xray.load_xray_run) read that path without trust.

Each payload writes a marker file when it runs; the tests check the marker is absent (and, with trust, present:
the payloads are live, so a test that passes is not passing because the payload is a dud)."""

from __future__ import annotations

import json
import os
import pickle
import pickletools
import shutil
from pathlib import Path

import numpy as np
import pytest

from nerfpipe import cli
from nerfpipe.data.errors import UserError
from nerfpipe.data.projections import read_any, read_naf_pickle
from nerfpipe.data.safe_pickle import PickleRefused, load_restricted
from nerfpipe.model.xray import load_xray_run
from nerfpipe.stages import xray_train

TINY = ["--device", "cpu", "--threads", "1", "--max-steps", "2", "--batch-rays", "64", "--eval-every", "0"]


class _System:
    """`os.system(cmd)` on unpickling."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


class _Exec:
    """`exec(code)` on unpickling: writes the marker from Python."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (exec, (f"open({str(self.marker)!r}, 'w').write('ran')",))


def naf_dict(seed: int = 0) -> dict:
    """A NAF-style scan laid out as NAF's generateData writes it (TIGRE geometry as numpy arrays and scalars,
    `train` / `val` dicts of angles and projections, `image` the volume in 1/m), tiny: 8^3 voxels, 4 + 2 views."""
    rng = np.random.default_rng(seed)
    return {
        "numTrain": 4,
        "numVal": 2,
        "DSD": np.float64(150.0),
        "DSO": np.float64(100.0),
        "nDetector": np.array([12, 12]),
        "dDetector": np.array([1.5, 1.5]),
        "sDetector": np.array([18.0, 18.0]),
        "nVoxel": np.array([8, 8, 8]),
        "dVoxel": np.array([1.0, 1.0, 1.0]),
        "sVoxel": np.array([8.0, 8.0, 8.0]),
        "offOrigin": np.array([0.0, 0.0, 0.0]),
        "offDetector": np.array([0.0, 0.0]),
        "accuracy": 0.5,
        "mode": "cone",
        "filter": None,
        "totalAngle": 180.0,
        "startAngle": 0.0,
        "randomAngle": False,
        "convert": True,
        "rescale_slope": 1.0,
        "rescale_intercept": 0.0,
        "normalize": True,
        "noise": 0,
        "tolerance": np.float32(1e-6),
        "image": (rng.random((8, 8, 8)) * 20.0).astype(np.float32),
        "train": {
            "angles": np.linspace(0.0, np.pi, 4, endpoint=False),
            "projections": rng.random((4, 12, 12)).astype(np.float32),
        },
        "val": {"angles": np.array([0.3, 1.9]), "projections": rng.random((2, 12, 12)).astype(np.float32)},
    }


def _as_numpy1(data: bytes) -> bytes:
    """The same pickle as numpy 1.x writes it: its helpers live in `numpy.core`, not `numpy._core` (protocols
    0-2 name globals as text lines, 4-5 as length-prefixed strings inside optional FRAMEs, dropped here)."""
    ops = [pos for op, _, pos in pickletools.genops(data) if op.name == "FRAME"]
    for pos in reversed(ops):
        data = data[:pos] + data[pos + 9 :]  # FRAME: opcode + 8-byte length
    for new, old in (
        (b"numpy.core.multiarray", b"numpy._core.multiarray"),
        (b"numpy.core.numeric", b"numpy._core.numeric"),
    ):
        data = data.replace(b"c" + old + b"\n", b"c" + new + b"\n")
        data = data.replace(b"\x8c" + bytes([len(old)]) + old, b"\x8c" + bytes([len(new)]) + new)
    return data


def _cli(capsys, *args) -> tuple[int, str]:
    with pytest.raises(SystemExit) as e:
        cli.main([str(a) for a in args])
    return e.value.code, capsys.readouterr().err


def _evil_payloads(marker: Path) -> dict[str, object]:
    return {
        "os.system": {"train": _System(marker)},
        "builtins.exec": {"DSD": 150.0, "image": _Exec(marker)},
        "in an object array": {"train": {"angles": np.array([_Exec(marker)], dtype=object)}},
    }


@pytest.fixture(scope="module")
def genuine(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("naf") / "chest_50.pickle"
    path.write_bytes(pickle.dumps(naf_dict(), protocol=pickle.HIGHEST_PROTOCOL))
    return path


@pytest.fixture(scope="module")
def genuine_run(genuine, tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("run") / "run"
    xray_train.run(
        xray_train.Config(
            scene=genuine, run_dir=run_dir, max_steps=2, batch_rays=64, eval_every=0, device="cpu", threads=1
        )
    )
    return run_dir


@pytest.mark.parametrize("kind", ["os.system", "builtins.exec", "in an object array"])
def test_xray_train_refuses_a_pickle_with_a_payload(kind, tmp_path, capsys):
    """The attack of issue 32: before the restricted reader, `pickle.load` ran the payload (the marker was
    written) and only then was the dict found wanting."""
    marker = tmp_path / "PAYLOAD_RAN"
    evil = tmp_path / "evil.pickle"
    evil.write_bytes(pickle.dumps(_evil_payloads(marker)[kind]))
    code, err = _cli(capsys, "xray-train", evil, tmp_path / "run", *TINY)
    assert code == 2
    assert not marker.exists(), "the pickle's payload ran"
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {evil}: refused to unpickle global '")
    refused = "posix.system" if kind == "os.system" else "builtins.exec"
    assert f"'{refused}'" in lines[0] and lines[0].endswith("if you trust this file, set --trust-pickle")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("protocol", [2, 4, 5])
@pytest.mark.parametrize("numpy1", [False, True], ids=["numpy2", "numpy1"])
def test_a_genuine_naf_pickle_still_loads(protocol, numpy1, tmp_path):
    """Every global numpy's pickling uses (arrays, scalars, dtypes; `_codecs.encode` for bytes below protocol 3;
    `_frombuffer` at protocol 5; `numpy.core` as numpy 1.x names it) is allowed, and the scan reads whole."""
    data = naf_dict()
    raw = pickle.dumps(data, protocol=protocol)
    path = tmp_path / "scan.pickle"
    path.write_bytes(_as_numpy1(raw) if numpy1 else raw)
    if numpy1:
        assert b"numpy._core" not in path.read_bytes() and b"numpy.core" in path.read_bytes()
    loaded = load_restricted(path)
    assert loaded.keys() == data.keys() and loaded["filter"] is None and loaded["DSD"] == 150.0
    np.testing.assert_array_equal(loaded["image"], data["image"])
    scene = read_any(path)
    assert scene.geometry.dso == 100.0 and scene.geometry.detector_shape == (12, 12)
    assert scene.splits == {"train": (0, 1, 2, 3), "test": (4, 5)}
    np.testing.assert_allclose(scene.projections[4:], data["val"]["projections"])
    np.testing.assert_allclose(scene.volume, data["image"] / 1000.0, rtol=1e-6)


def test_other_globals_and_codecs_are_refused(tmp_path):
    """Only numpy's own helpers: a pickle of another numpy callable or a class is refused, and `_codecs.encode`
    takes latin-1 only."""
    path = tmp_path / "x.pickle"
    for obj, name in ((np.save, "numpy.save"), (Path("a"), "pathlib.PosixPath"), (np.int64, "numpy.int64")):
        path.write_bytes(pickle.dumps({"x": obj}))
        with pytest.raises(PickleRefused, match=f"refused to unpickle global '{name}'"):
            load_restricted(path)
    path.write_bytes(b"\x80\x02c_codecs\nencode\nX\x03\x00\x00\x00abcX\x05\x00\x00\x00rot13\x86R.")
    with pytest.raises(UserError, match="only latin-1"):
        load_restricted(path)
    path.write_bytes(b"not a pickle")
    with pytest.raises(UserError, match=r"x.pickle: cannot read pickle \(UnpicklingError"):
        read_naf_pickle(path)


def test_trust_pickle_loads_the_same_file(genuine, tmp_path, capsys):
    """--trust-pickle reads the genuine file to the same scene and trains from it; it is the plain unpickler
    (an evil file's payload does run with it, so the switch is only for files the user vouches for)."""
    assert read_any(genuine, trust_pickle=True).geometry == read_any(genuine).geometry
    code, err = _cli(capsys, "xray-train", genuine, tmp_path / "run", *TINY, "--trust-pickle")
    assert code == 0, err
    doc = json.loads((tmp_path / "run" / "config.json").read_text())
    assert doc["trust_pickle"] is True and (tmp_path / "run" / "manifest.json").is_file()
    marker = tmp_path / "PAYLOAD_RAN"
    evil = tmp_path / "evil.pickle"
    evil.write_bytes(pickle.dumps(_evil_payloads(marker)["builtins.exec"]))
    with pytest.raises(UserError):
        read_naf_pickle(evil, trust=True)  # not a scan; but the payload ran on the way
    assert marker.read_text() == "ran"


def _run_naming(run_dir: Path, tmp_path: Path, scene: Path) -> Path:
    """A copy of a finished X-ray run whose config.json names `scene` (as an edited or shared run would)."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    doc = json.loads((run / "config.json").read_text())
    doc.update(scene=str(scene), scene_abs=str(scene), scene_from_run=os.path.relpath(scene, run))
    (run / "config.json").write_text(json.dumps(doc))
    return run


def test_a_run_naming_an_evil_pickle_runs_no_code(genuine_run, tmp_path, capsys):
    """xray-eval, xray-export (and view, through load_xray_run) follow config.json to the scene: they read it
    with the restricted unpickler, never the trusting one, whatever the run's config.json says."""
    marker = tmp_path / "PAYLOAD_RAN"
    evil = tmp_path / "evil.pickle"
    evil.write_bytes(pickle.dumps(_evil_payloads(marker)["os.system"]))
    run = _run_naming(genuine_run, tmp_path, evil)
    doc = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**doc, "trust_pickle": True}))  # a run cannot vouch for a file
    expected = f"error: {run}/../evil.pickle: refused to unpickle global 'posix.system'"  # as the run names it
    code, err = _cli(capsys, "xray-eval", run, tmp_path / "eval.json", "--device", "cpu", "--threads", "1")
    assert code == 2 and err.startswith(expected) and len(err.strip().splitlines()) == 1
    assert f"(the scene named in {run / 'config.json'}; a run's scene is never unpickled with trust)" in err
    assert not (tmp_path / "eval.json").exists()
    code, err = _cli(capsys, "xray-export", run, tmp_path / "export", "--device", "cpu", "--threads", "1")
    assert code == 2 and err.startswith(expected) and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "export").exists()
    with pytest.raises(UserError, match="refused to unpickle global 'posix.system'.*never unpickled with trust"):
        load_xray_run(run, "cpu")
    pytest.importorskip("viser")
    from nerfpipe.stages import view

    with pytest.raises(UserError, match="refused to unpickle global 'posix.system'.*never unpickled with trust"):
        view.serve(view.Config(target=run, device="cpu", port=0))  # refused before any server starts
    assert not marker.exists(), "the pickle's payload ran"


def test_a_run_on_a_genuine_pickle_still_evaluates(genuine_run, tmp_path, capsys):
    """The restricted reader is no regression for a run trained on a real NAF pickle: xray-eval reads it."""
    code, err = _cli(
        capsys, "xray-eval", genuine_run, tmp_path / "eval.json", "--device", "cpu", "--threads", "1", "--no-baseline"
    )
    assert code == 0, err
    assert "psnr_3d" in json.loads((tmp_path / "eval.json").read_text())
