"""`make bench-gpu`'s script at toy sizes (`--smoke`): every row runs through the commands a user types and lands in
one table; without CUDA and without --smoke it stops in one line (issue 51)."""

from __future__ import annotations

import json

import pytest
import torch

from benchmarks import bench_gpu


def test_smoke_runs_every_row_and_writes_one_table(tmp_path):
    rows = bench_gpu.main(["--smoke", "--out", str(tmp_path)])
    figures = [r.figure for r in rows]
    assert figures[0].startswith("lego_800 field") and any(f.startswith("fox, POSED chain") for f in figures)
    assert any(f.startswith("lego splats") for f in figures) and any(f.startswith("splats at 64x64") for f in figures)
    assert sum(f.startswith("viewer at 64x64") for f in figures) == 2
    assert all(r.met is None for r in rows), "toy sizes judge no goal"
    table = (tmp_path / "bench_gpu.md").read_text()
    assert "(smoke)" in table.splitlines()[0] and table.count("\n| ") == len(rows) + 1  # header + one line a row
    stored = json.loads((tmp_path / "bench_gpu.json").read_text())
    assert [r["figure"] for r in stored] == figures
    lego = json.loads((tmp_path / "lego" / "eval.json").read_text())
    assert lego["psnr"] > 15.0, "the smoke field learned something: the splat row starts from it"


@pytest.mark.skipif(torch.cuda.is_available(), reason="the refusal is for machines without CUDA")
def test_without_cuda_it_stops_in_one_line(tmp_path):
    with pytest.raises(SystemExit) as stop:
        bench_gpu.main(["--out", str(tmp_path)])
    assert "no CUDA device here" in str(stop.value) and "\n" not in str(stop.value)
    assert not any(tmp_path.iterdir()), "nothing written before the refusal"
