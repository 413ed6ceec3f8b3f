"""`xray-train`'s plot: projection and volume PSNR against training seconds, SSIM on a second axis."""

from __future__ import annotations

from pathlib import Path

from nerfpipe.data.atomic import atomic_path

__all__ = ["plot_metrics"]


def _series(rows: list[dict], key: str) -> list[tuple[float, float]]:
    return [(float(r["seconds"]), float(r[key])) for r in rows if r.get(key) not in (None, "")]


def plot_metrics(rows: list[dict], path: Path) -> Path:
    """train / held-out projection PSNR and 3-D PSNR (left axis), 3-D SSIM (right axis) vs seconds, as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for key, style, label in (
        ("train_psnr", "-", "train projections PSNR"),
        ("test_proj_psnr", "s-", "held-out projections PSNR"),
        ("psnr_3d", "o-", "3-D PSNR"),
    ):
        pts = _series(rows, key)
        if pts:
            ax.plot(*zip(*pts, strict=True), style, label=label, markersize=3)
    ax.set_xlabel("training seconds")
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3)
    ssim = _series(rows, "ssim_3d")
    if ssim:
        ax2 = ax.twinx()
        ax2.plot(*zip(*ssim, strict=True), "^--", color="tab:red", label="3-D SSIM", markersize=3)
        ax2.set_ylabel("3-D SSIM")
        ax2.legend(loc="lower right")
    ax.legend(loc="upper left")
    ax.set_title("xray-train: error against run time")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return Path(path)
