"""The X-ray chain on a 24^3 phantom: xray-simulate -> xray-train (seconds) -> xray-eval -> xray-export, FDK,
load_xray_run, and the commands' --help. CPU, seconds."""

import json
import math

import numpy as np
import pytest
import torch

from nerfpipe import cli
from nerfpipe.data.errors import UserError
from nerfpipe.data.projections import read_projection_scene
from nerfpipe.model.xray import load_xray_run
from nerfpipe.radiance.ct_metrics import psnr_3d, ssim_3d
from nerfpipe.radiance.fdk import fdk, parker_weights
from nerfpipe.radiance.xray import VoxelGrid, XrayGeometry, project_views, shadow_detector
from nerfpipe.stages import xray_eval, xray_export, xray_simulate, xray_train

COMMANDS = ["xray-simulate", "xray-train", "xray-eval", "xray-export"]


def phantom(n: int = 24) -> np.ndarray:
    """A body (ellipsoid, mu 0.02/mm) with a dense insert and a hole, on an n^3 grid of 1 mm voxels."""
    c = (np.indices((n, n, n)).transpose(1, 2, 3, 0) + 0.5 - n / 2) / (n / 2)  # [-1, 1]
    vol = np.zeros((n, n, n), np.float32)
    vol[(c[..., 0] / 0.8) ** 2 + (c[..., 1] / 0.6) ** 2 + (c[..., 2] / 0.85) ** 2 < 1] = 0.02
    vol[np.linalg.norm(c - [0.3, 0.1, 0.0], axis=-1) < 0.2] = 0.05
    vol[np.linalg.norm(c - [-0.3, -0.1, 0.2], axis=-1) < 0.15] = 0.0
    return vol


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("xray")
    np.save(tmp / "phantom.npy", phantom())
    sim = xray_simulate.run(
        xray_simulate.Config(
            volume=tmp / "phantom.npy",
            out_dir=tmp / "scene",
            views=36,
            arc=360.0,
            test_views=4,
            voxel_size=1.0,
            dso=100.0,
            dsd=150.0,
        )
    )
    # 300 steps: about 5 s on an idle core (the time cap only guards a very busy machine)
    train = xray_train.run(
        xray_train.Config(
            scene=tmp / "scene",
            run_dir=tmp / "run",
            max_steps=300,
            max_seconds=60.0,
            batch_rays=512,
            lr=0.1,  # a 300-step run wants a larger step than the default's (tuned on 10-minute runs)
            eval_every=2.0,
            threads=1,
            device="cpu",
        )
    )
    return tmp, sim, train


def test_simulate_writes_a_scene(chain):
    tmp, sim, _ = chain
    scene = read_projection_scene(sim.out_dir)
    assert scene.geometry.n_views == 40 and scene.split("train") == tuple(range(36))
    assert scene.volume is not None and scene.grid.spacing == (1.0, 1.0, 1.0)
    assert (sim.out_dir / "manifest.json").is_file() and sim.max_line_integral > 0.2
    # the projections are the exact projector's
    direct = project_views(
        torch.from_numpy(scene.volume), scene.grid.spacing, scene.grid.center, scene.geometry.subset([0])
    )
    np.testing.assert_allclose(scene.projections[0], direct[0].numpy(), atol=1e-6)


def test_train_reconstructs_above_a_floor_in_seconds(chain):
    tmp, sim, train = chain
    scene = read_projection_scene(sim.out_dir)
    assert train.steps == 300
    assert train.psnr_3d > 29.0, train.psnr_3d  # 31.6 dB; FDK on the same 36 views: 27.9 dB
    assert train.test_proj_psnr > 30.0
    vol = np.load(train.volume)
    assert vol.shape == scene.grid.shape and vol.dtype == np.float32 and (vol >= 0).all()
    manifest = json.loads(train.manifest.read_text())
    assert {"colour", "view direction", "background"} <= set(manifest["left_out"])
    rows = train.metrics.read_text().splitlines()
    assert rows[0].startswith("step,seconds,") and any(r.split(",")[5] for r in rows[1:])  # psnr_3d logged
    run = load_xray_run(train.run_dir, "cpu")
    np.testing.assert_allclose(run.volume().numpy(), vol, atol=1e-6)
    drr, mip = run.drr(0.3), run.mip(0.3)
    assert drr.shape == mip.shape == scene.geometry.detector_shape and float(drr.max()) > 0.2
    assert float(mip.max()) <= float(run.volume().max()) + 1e-6
    # the field's own line integrals agree with the voxelised volume's on a training view
    from nerfpipe.radiance.xray import detector_rays

    o, d = detector_rays(scene.geometry, 0)
    p_field = run.line_integrals(o, d).reshape(drr.shape)
    assert float((p_field - torch.from_numpy(scene.projections[0])).abs().mean()) < 0.05


def test_eval_and_export(chain):
    tmp, _, train = chain
    ev = xray_eval.run(xray_eval.Config(run_dir=train.run_dir, out=tmp / "eval.json", threads=1, device="cpu"))
    doc = json.loads((tmp / "eval.json").read_text())
    assert doc["psnr_3d"] == pytest.approx(train.psnr_3d, abs=1e-3)
    assert 0 < doc["ssim_3d"] <= 1 and doc["proj_psnr"] > 30 and doc["fdk"]["psnr_3d"] > 15
    assert "gain_over_fdk_db" in doc and ev.manifest.is_file()
    ex = xray_export.run(
        xray_export.Config(run_dir=train.run_dir, out_dir=tmp / "export", frames=3, threads=1, device="cpu")
    )
    for name in (
        "slices.png",
        "slices_x.png",
        "slices_y.png",
        "slices_z.png",
        "drr_mip.mp4",
        "mesh.ply",
        "manifest.json",
    ):
        assert (tmp / "export" / name).is_file(), name
    import trimesh

    mesh = trimesh.load(tmp / "export" / "mesh.ply")
    assert ex.faces > 100 and ex.iso > 0
    lo, hi = mesh.bounds  # the body's surface, in mm around the rotation axis
    assert np.all(lo > -12.5) and np.all(hi < 12.5) and hi[0] - lo[0] > 15
    assert mesh.volume > 0  # wound counter-clockwise seen from outside


def test_fdk_reconstructs_a_ball_and_parker_weights_pair_up():
    grid = VoxelGrid(shape=(32, 32, 32), spacing=(1.0, 1.0, 1.0))
    c = grid.centers(dtype=torch.float64)
    vol = 0.02 * (c.norm(dim=-1) < 10).double()
    shape, pitch = shadow_detector(grid.box, "cone", 200.0, 300.0, 1.5)
    for arc in (2 * math.pi, math.pi + 0.4):  # full scan; short scan with Parker weights
        g = XrayGeometry(
            mode="cone",
            dso=200.0,
            dsd=300.0,
            detector_shape=shape,
            detector_pitch=pitch,
            angles=tuple(np.arange(72) * arc / 72),
        )
        rec = fdk(project_views(vol.float(), grid.spacing, grid.center, g), g, grid)
        inner = c.norm(dim=-1) < 7
        assert float(rec[inner].mean()) == pytest.approx(0.02, rel=0.03)
        assert psnr_3d(rec.numpy(), vol.numpy()) > 25 and ssim_3d(rec.numpy(), vol.numpy()) > 0.6
    beta = torch.rand(1000, dtype=torch.float64) * (math.pi + 0.4)
    gamma = (torch.rand(1000, dtype=torch.float64) - 0.5) * 0.3
    conj = beta + math.pi + 2 * gamma
    ok = conj <= math.pi + 0.4
    total = parker_weights(beta, gamma, 0.2) + parker_weights(conj, -gamma, 0.2)
    torch.testing.assert_close(total[ok], torch.ones_like(total[ok]))


def test_simulate_refuses_bad_input_and_writes_nothing(tmp_path):
    vol = phantom(8)
    vol[0, 0, 0] = -1.0
    np.save(tmp_path / "neg.npy", vol)
    with pytest.raises(UserError, match="negative attenuation"):
        xray_simulate.run(xray_simulate.Config(volume=tmp_path / "neg.npy", out_dir=tmp_path / "a"))
    np.save(tmp_path / "ok.npy", phantom(8))
    with pytest.raises(UserError, match="dsd: the detector is behind the source"):
        xray_simulate.run(xray_simulate.Config(volume=tmp_path / "ok.npy", out_dir=tmp_path / "b", dsd=-10.0))
    with pytest.raises(UserError, match="dso"):
        xray_simulate.run(
            xray_simulate.Config(volume=tmp_path / "ok.npy", out_dir=tmp_path / "c", dso=2.0, dsd=3.0, voxel_size=1.0)
        )
    assert not any((tmp_path / d).exists() for d in "abc")


@pytest.mark.parametrize("name", COMMANDS)
def test_help_and_every_field_has_an_option(name, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main([name, "--help"])
    assert e.value.code == 0
    assert "Usage" in capsys.readouterr().out
    assert cli.skipped_fields(name) == []


def test_cli_parses_options():
    cfg = cli.config_from_args(
        "xray-simulate",
        ["v.mat", "out", "--views", "25", "--detector", "64,80", "--noise", "1e5", "--mode", "parallel"],
    )
    assert cfg.views == 25 and cfg.detector == (64, 80) and cfg.noise == 1e5 and cfg.mode == "parallel"
    assert cli.config_from_args("xray-export", ["r", "o", "--iso", "auto"]).iso is None
    assert cli.config_from_args("xray-export", ["r", "o", "--iso", "0.015"]).iso == 0.015


def test_sart_optimizer_and_its_guard(chain, tmp_path):
    tmp, sim, _ = chain
    out = xray_train.run(
        xray_train.Config(
            scene=sim.out_dir,
            run_dir=tmp_path / "sart",
            optimizer="sart",
            max_steps=100,
            max_seconds=60.0,
            batch_rays=512,
            eval_every=0,
            threads=1,
            device="cpu",
        )
    )
    assert out.steps == 100 and out.psnr_3d > 22.0, out.psnr_3d
    with pytest.raises(UserError, match="optimizer: sart needs the grid field"):
        xray_train.run(xray_train.Config(scene=sim.out_dir, run_dir=tmp_path / "x", optimizer="sart", field="tensorf"))
    assert not (tmp_path / "x").exists()


def test_tensorf_field_trains_and_loads(chain, tmp_path):
    _, sim, _ = chain
    out = xray_train.run(
        xray_train.Config(
            scene=sim.out_dir,
            run_dir=tmp_path / "tf",
            field="tensorf",
            rank=4,
            max_steps=40,
            max_seconds=60.0,
            batch_rays=256,
            eval_every=0,
            threads=1,
            device="cpu",
        )
    )
    assert out.steps == 40 and np.isfinite(out.psnr_3d)
    run = load_xray_run(out.run_dir, "cpu")
    assert not run.field.has_color and run.volume().shape == (24, 24, 24)
