"""Stage `report`: plot + markdown + CSV from fake runs; time-to-level and peak memory; user errors."""

from __future__ import annotations

import csv
import json

import imageio.v2 as iio
import pytest

import nerfpipe.stages.report as report
from nerfpipe.data.errors import UserError

HEADER = "step,seconds,loss,train_psnr,test_psnr,lr,samples_per_ray,skip_fraction\n"


def _fake_run(folder, rows, used):
    folder.mkdir(parents=True)
    lines = [f"{step},{sec},0.01,20.0,{'' if p is None else p},0.01,10,0.5" for step, sec, p in rows]
    (folder / "metrics.csv").write_text(HEADER + "\n".join(lines) + "\n")
    (folder / "manifest.json").write_text(json.dumps({"stage": "train", "used": used}))
    return folder


@pytest.fixture
def two_runs(tmp_path):
    fast = _fake_run(
        tmp_path / "a" / "fast",
        [(0, 0.5, None), (100, 10.0, 21.0), (200, 20.0, 26.5), (200, 20.5, 26.9)],
        {"peak_cuda_mb": 812.25, "peak_rss_mb": 900.0},
    )
    slow = _fake_run(
        tmp_path / "b" / "vanilla",
        [(0, 1.0, None), (100, 60.0, 18.0), (200, 120.0, 22.0)],
        {"peak_cuda_mb": None, "peak_rss_mb": 1500.5},
    )
    return fast, slow


def test_report_writes_plot_markdown_and_csv(two_runs, tmp_path):
    out = report.run(report.Config(runs=two_runs, out_dir=tmp_path / "rep"))
    img = iio.imread(out.plot)
    assert img.ndim == 3 and img.shape[0] > 100
    md = out.markdown.read_text()
    assert md.count("\n| ") >= 2 and "| fast | 26.90 | 200 | 20.5 | 10.0 | 20.0 | — | 812.2 | 900.0 |" in md
    assert "| vanilla | 22.00 | 200 | 120.0 | 120.0 | — | — | — | 1500.5 |" in md
    with open(out.csv, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["run"] for r in rows] == ["fast", "vanilla"]
    assert rows[0]["time to 25 dB (s)"] == "20.0" and rows[1]["time to 25 dB (s)"] == ""
    assert rows[1]["peak CUDA (MB)"] == "" and rows[1]["peak RSS (MB)"] == "1500.5"
    assert json.loads(out.manifest.read_text())["stage"] == "report"


def test_time_to_level_is_the_first_crossing(two_runs):
    summary = report.read_run(two_runs[0], "fast", (20.0, 26.0, 40.0))
    assert summary.time_to == {20.0: 10.0, 26.0: 20.0, 40.0: None}
    assert summary.psnr == (21.0, 26.5, 26.9) and summary.final_psnr == 26.9


def test_duplicate_names_get_parent_prefix_and_labels_override(tmp_path):
    a = _fake_run(tmp_path / "x" / "run", [(1, 1.0, 10.0)], {})
    b = _fake_run(tmp_path / "y" / "run", [(1, 1.0, 12.0)], {})
    out = report.run(report.Config(runs=(a, b), out_dir=tmp_path / "r"))
    assert [r.label for r in out.runs] == ["x/run", "y/run"]
    out = report.run(report.Config(runs=(a, b), out_dir=tmp_path / "r", labels=("one", "two"), overwrite=True))
    assert [r.label for r in out.runs] == ["one", "two"]


def test_run_without_test_psnr_is_reported_not_fatal(tmp_path):
    a = _fake_run(tmp_path / "a", [(1, 1.0, None)], {})
    out = report.run(report.Config(runs=(a,), out_dir=tmp_path / "r"))
    assert "| a | — |" in out.markdown.read_text()
    assert "a" in json.loads(out.manifest.read_text())["left_out"]


def test_user_errors(tmp_path, two_runs):
    bad_csv = tmp_path / "bad"
    bad_csv.mkdir()
    (bad_csv / "metrics.csv").write_text("step,loss\n1,0.1\n")
    cases = [
        ((tmp_path / "missing",), "not found"),
        ((tmp_path,), "metrics.csv"),
        ((bad_csv,), "missing column"),
        ((), "at least one run"),
    ]
    for runs, match in cases:
        with pytest.raises(UserError, match=match) as e:
            report.run(report.Config(runs=runs, out_dir=tmp_path / "r"))
        assert "\n" not in str(e.value)
    with pytest.raises(UserError, match="labels"):
        report.run(report.Config(runs=two_runs, out_dir=tmp_path / "r", labels=("one",)))
