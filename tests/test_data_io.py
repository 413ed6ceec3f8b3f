"""Atomic writes and run-directory files."""

import json
import time

import pytest

from nerfpipe.data.atomic import atomic_path, write_json
from nerfpipe.data.rundir import MetricsLog, write_config, write_manifest


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "out.json"
    write_json(target, {"a": 1})
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half written")
        raise RuntimeError("boom")
    assert json.loads(target.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]  # no temp files left behind


def test_json_refuses_nan(tmp_path):
    with pytest.raises(ValueError):
        write_json(tmp_path / "x.json", {"a": float("nan")})
    assert not list(tmp_path.iterdir())


def test_config_and_manifest(tmp_path):
    from dataclasses import dataclass
    from pathlib import Path

    @dataclass(frozen=True, kw_only=True)
    class Cfg:
        path: Path
        far: float = float("inf")

    write_config(tmp_path, Cfg(path=tmp_path / "a b"))
    assert json.loads((tmp_path / "config.json").read_text()) == {"path": str(tmp_path / "a b"), "far": "inf"}
    (tmp_path / "in.txt").write_text("x")
    write_manifest(
        tmp_path,
        stage="test",
        started=time.time() - 1,
        inputs=[tmp_path / "in.txt"],
        used={"field": "fast"},
        left_out={"ndc": "360-degree scene"},
    )
    m = json.loads((tmp_path / "manifest.json").read_text())
    assert m["stage"] == "test" and m["wall_seconds"] >= 1 and "torch" in m["versions"]
    assert len(m["inputs"][str(tmp_path / "in.txt")]) == 64 and m["left_out"] == {"ndc": "360-degree scene"}


def test_metrics_log_round_trip(tmp_path):
    log = MetricsLog(tmp_path / "metrics.csv", ["step", "seconds", "loss", "test_psnr"])
    log.append(step=1, seconds=0.5, loss=0.1)
    log.append(step=2, seconds=1.0, loss=0.05, test_psnr=21.0)
    log.save()
    again = MetricsLog(tmp_path / "metrics.csv", log.columns)
    again.load()
    assert again.rows == [
        {"step": "1", "seconds": "0.5", "loss": "0.1"},
        {"step": "2", "seconds": "1.0", "loss": "0.05", "test_psnr": "21.0"},
    ]
    with pytest.raises(ValueError, match="unknown metrics columns"):
        log.append(step=3, seconds=2, bogus=1)
    with pytest.raises(ValueError, match="start with step, seconds"):
        MetricsLog(tmp_path / "m.csv", ["loss"])
