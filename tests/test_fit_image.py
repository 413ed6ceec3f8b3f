"""fit-image stage: PSNR floor on a tiny procedural image, frequencies matter, every output, one-line user errors;
and smoke tests of the study's pieces (benchmarks/study.py)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from nerfpipe import cli
from nerfpipe.data.errors import UserError
from nerfpipe.data.video import write_png
from nerfpipe.stages import fit_image


@pytest.fixture
def fresh_cli():
    """cli caches each command's Config and typer command by name; tests/test_cli.py registers a fake module under
    "fit-image" (its one-registration test). Build the real command afresh, and leave no cached one behind."""
    cli._stage_params.cache_clear()
    cli._command.cache_clear()
    yield
    cli._stage_params.cache_clear()
    cli._command.cache_clear()


SMALL = dict(hidden=64, layers=3, steps=300, max_seconds=30.0, eval_every=50, device="cpu", threads=1)


def _png(path: Path, rgb: np.ndarray) -> Path:
    return write_png(path, (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8))


@pytest.fixture(scope="module")
def smooth_image(tmp_path_factory) -> Path:
    """32 x 32: two gentle sinusoids and a disc (low frequencies, one sharp edge)."""
    y, x = np.mgrid[0:32, 0:32] / 32.0
    disc = ((x - 0.5) ** 2 + (y - 0.5) ** 2 < 0.1).astype(float)
    rgb = np.stack([0.5 + 0.4 * np.sin(2 * np.pi * 1.5 * x), 0.5 + 0.4 * np.cos(2 * np.pi * y), 0.1 + 0.8 * disc], -1)
    return _png(tmp_path_factory.mktemp("img") / "smooth.png", rgb)


@pytest.fixture(scope="module")
def checker_image(tmp_path_factory) -> Path:
    """32 x 32 high-frequency pattern: cells of 2 x 3 pixels (no bare-coordinate MLP can fit it quickly)."""
    y, x = np.mgrid[0:32, 0:32] / 32.0
    cells = (np.sin(2 * np.pi * 8 * x) * np.sin(2 * np.pi * 6 * y) > 0).astype(float)
    return _png(tmp_path_factory.mktemp("img") / "checker.png", np.stack([cells, 1 - cells, 0.5 + 0 * cells], -1))


def test_fits_a_small_image_and_writes_every_output(smooth_image, tmp_path):
    out = fit_image.run(fit_image.Config(image=smooth_image, out_dir=tmp_path / "fit", freqs=6, **SMALL))
    by_name = {m.name: m for m in out.models}
    assert list(by_name) == ["fourier_L6", "grid_R32"]
    assert by_name["fourier_L6"].psnr > 22.0 and by_name["grid_R32"].psnr > 35.0, by_name  # 26, 54 dB here
    files = [
        out.montage,
        out.plot,
        out.metrics,
        out.summary,
        tmp_path / "fit" / "config.json",
        *(m.reconstruction for m in out.models),
    ]
    for f in files:
        assert f.is_file() and f.stat().st_size > 0, f
    assert all(out.manifest.stat().st_mtime_ns >= f.stat().st_mtime_ns for f in files)  # manifest last
    manifest = json.loads(out.manifest.read_text())
    assert manifest["stage"] == "fit-image" and str(smooth_image) in manifest["inputs"]
    with open(out.metrics, newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["step", "seconds", "model", "loss", "psnr"]
    assert {r["model"] for r in rows} == set(by_name) and rows[0]["step"] == "0"
    summary = json.loads(out.summary.read_text())
    assert (summary["width"], summary["height"]) == (32, 32)
    assert [m["psnr"] for m in summary["models"]] == [round(m.psnr, 3) for m in out.models]
    from nerfpipe.data.transforms import load_image

    assert load_image(out.montage).shape[1] > 3 * 32  # three panels side by side


def test_frequencies_matter_on_a_high_frequency_pattern(checker_image, tmp_path):
    out = fit_image.run(
        fit_image.Config(image=checker_image, out_dir=tmp_path / "fit", sweep=(0, 6), encoding="fourier", **SMALL)
    )
    psnr = {m.name: m.psnr for m in out.models}
    assert psnr["fourier_L0"] + 10.0 < psnr["fourier_L6"], psnr  # 8.0 and 27.4 dB here


def test_pixel_coords_are_pixel_centres():
    uv = fit_image.pixel_coords(2, 4)  # [8, 2], row-major
    assert uv[0].tolist() == [-0.75, -0.5] and uv[-1].tolist() == [0.75, 0.5]


def test_grid_model_is_the_fast_field_on_a_plane():
    model = fit_image.GridImage(8)
    rgb = model(torch.rand(5, 2) * 2 - 1)
    assert rgb.shape == (5, 3) and bool(((rgb > 0) & (rgb < 1)).all())
    groups = model.param_groups(0.02)
    assert [g["lr"] for g in groups] == [0.02, 0.001]  # grids at lr, basis and MLP at lr / 20 (as train)
    trained = {id(p) for g in groups for p in g["params"]}
    assert not trained & {id(p) for p in (*model.field.density_planes, *model.field.density_lines)}


@pytest.mark.parametrize(
    ("kw", "field"),
    [
        (dict(freqs=-1), "--freqs"),
        (dict(sweep=(2, 2)), "--sweep"),
        (dict(sweep=(0, 99)), "--sweep"),
        (dict(steps=0), "--steps"),
        (dict(max_seconds=0.0), "--max-seconds"),
        (dict(lr=-1.0), "--lr"),
        (dict(batch=0), "--batch"),
        (dict(encoding="hash"), "--encoding"),
        (dict(grid_resolution=1), "--grid-resolution"),
        (dict(device="tpu"), "device"),
        (dict(threads=0), "--threads"),
    ],
)
def test_bad_options_are_one_line_naming_the_field(smooth_image, tmp_path, kw, field):
    with pytest.raises(UserError) as e:
        fit_image.run(fit_image.Config(image=smooth_image, out_dir=tmp_path / "o", **kw))
    assert str(e.value).startswith(f"{field}:") and "\n" not in str(e.value)
    assert not (tmp_path / "o" / "manifest.json").exists()


def test_unreadable_image_is_one_user_error_line(tmp_path, capsys, fresh_cli):
    bad = tmp_path / "not_an_image.png"
    bad.write_text("hello")
    for path in (bad, tmp_path / "missing.png"):
        with pytest.raises(UserError, match=path.name):
            fit_image.run(fit_image.Config(image=path, out_dir=tmp_path / "o"))
    with pytest.raises(SystemExit) as e:
        cli.main(["fit-image", str(bad), str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and err.startswith("error: ") and bad.name in err


def test_cli_builds_the_config_and_runs(smooth_image, tmp_path, capsys, fresh_cli):
    args = [
        str(smooth_image),
        str(tmp_path / "o"),
        "--sweep",
        "0,2",
        "--encoding",
        "fourier",
        "--steps",
        "3",
        "--hidden",
        "16",
        "--device",
        "cpu",
        "--threads",
        "1",
    ]
    config = cli.config_from_args("fit-image", args)
    assert config.sweep == (0, 2) and config.encoding == "fourier" and config.lr is None and config.batch == 10000
    with pytest.raises(SystemExit) as e:
        cli.main(["fit-image", *args])
    assert e.value.code in (None, 0)
    out = capsys.readouterr().out
    assert "fourier L=0" in out and "fourier L=2" in out and "montage.png" in out


# ---------------------------------------------------------------------------------------------- the study's pieces
def test_study_compositing_and_stability_sections_make_a_page(tmp_path):
    """benchmarks/study.py on a tiny plan: convergence orders as theory says, the stiff sweep finite, a page whose
    images exist (make study-quick itself takes over a minute: the training and mesh sections are left out here)."""
    import dataclasses

    from benchmarks import study

    plan = dataclasses.replace(study.QUICK, samples=(4, 8, 16, 32, 64), rays=64)
    ctx = study.Context(out=tmp_path, plan=plan, threads=1, device="cpu")
    sections = [study.compositing(ctx), study.stability(ctx)]
    media = sections[0].data["media"]
    for name in ("slab", "sphere", "steps"):  # a density with jumps: first order
        assert 0.7 < -media[name]["order"]["opacity"] < 1.3, (name, media[name]["order"])
    assert 1.7 < -media["gaussian"]["order"]["depth"] < 2.3, media["gaussian"]["order"]  # smooth: second order
    summaries = sections[1].data["summaries"]
    assert [s["dtype"] for s in summaries] == ["float16", "bfloat16", "float32", "float64"]
    assert all(s["values_finite"] and s["gradients_finite"] and s["weights_sum_le_one"] for s in summaries)
    page = study.write_page(ctx, sections, study._machine(ctx), wall=1.0)
    text = page.read_text(encoding="utf-8")
    assert text.startswith("# nerfpipe study") and "## 2. Stiff and extreme inputs" in text
    for image in ("compositing.png", "stability.png"):
        assert f"]({image})" in text and (tmp_path / image).stat().st_size > 0
    results = json.loads((tmp_path / "results.json").read_text())
    assert set(results["sections"]) == {"compositing", "stability"}
