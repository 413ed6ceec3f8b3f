"""Field throughput on this machine: samples/s for forward + backward (density + colour).

Run: .venv/bin/python -m benchmarks.bench_fields [threads]   (benchmarks are not tests; prints a table)
"""

from __future__ import annotations

import time

import torch

from nerfpipe.radiance.fields import NeRFMLP, TensoRF

__all__ = ["measure", "main"]


def measure(field, n: int, repeats: int = 3, color_fraction: float = 1.0) -> float:
    """Samples per second for sigma (all n) + rgb (first color_fraction * n) forward and backward."""
    x = torch.rand(n, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    n_c = max(1, int(n * color_fraction))

    def step() -> None:
        sigma = field.density(x)
        loss = sigma.mean()
        if field.has_color:
            loss = loss + field.color(x[:n_c], d[:n_c] if field.view_dependent else None).mean()
        loss.backward()

    step()  # warm-up
    t0 = time.perf_counter()
    for _ in range(repeats):
        step()
    return n * repeats / (time.perf_counter() - t0)


def main(threads: int | None = None) -> None:
    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(0)
    aabb = [[-1.0] * 3, [1.0] * 3]
    rows = [
        ("vanilla MLP (one network)", NeRFMLP(), 4096, 1.0),
        ("fast res128, colour at all samples", TensoRF(aabb=aabb, resolution=128), 65536, 1.0),
        ("fast res128, colour at 20% of samples", TensoRF(aabb=aabb, resolution=128), 65536, 0.2),
        ("fast res256, colour at 20% of samples", TensoRF(aabb=aabb, resolution=256), 65536, 0.2),
        ("fast density-only res128", TensoRF(aabb=aabb, resolution=128, has_color=False), 65536, 1.0),
    ]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    for name, field, n, frac in rows:
        print(f"{name:40s} {measure(field, n, color_fraction=frac) / 1e6:8.3f} M samples/s")


if __name__ == "__main__":
    import sys

    main(int(sys.argv[1]) if len(sys.argv) > 1 else None)
