"""3-D Gaussian splats: projection (EWA, local affine) and tile-based alpha compositing in torch, with its twin.

Conventions:
- Gaussians live in the scene frame (transforms.json's normalised frame) as `Splats`: `means` [N, 3],
  `log_scales` [N, 3] (natural log of the standard deviations along the Gaussian's own axes), `quats` [N, 4]
  (w, x, y, z; any length, normalised here), `opacity_logits` [N] (opacity = sigmoid), `sh` [N, K, 3] spherical
  harmonics coefficients per colour channel, K = (degree + 1)^2 for degree 0..3 (INRIA's basis and constants;
  colour = max(0, 0.5 + sum_k SH_k(d) sh_k), d the unit direction from the camera centre to the mean).
- Cameras as everywhere in nerfpipe (`radiance.camera`): `world_from_cam` [4, 4] OpenGL axes (x right, y up,
  looking down -z), pinhole `Intrinsics` in pixels (distortion is not applied: splats render a pinhole camera),
  pixel (col i, row j) has its centre at (i + 0.5, j + 0.5). Projection works in OpenCV camera axes
  (x right, y down, +z forward): u = fx x / z + cx, v = fy y / z + cy.
- 2-D covariance (EWA splatting, as 3DGS and gsplat): Sigma_2d = J W Sigma W^T J^T + eps2d I, W the camera
  rotation, J the Jacobian of (u, v) at the mean with x/z and y/z clamped to 1.3 x the half field of view
  (3DGS's guard for Gaussians far outside the view); eps2d = 0.3 px^2 is 3DGS's low-pass (viewers add it too).
- Compositing front to back in depth order (z of the mean): alpha_i = min(0.99, o_i exp(-0.5 d^T Sigma_2d^-1 d)),
  d = pixel centre - projected mean; an alpha below 1/255 is skipped; T_i = prod_{j<i} (1 - alpha_j), written as
  exp(exclusive cumsum of log1p(-alpha)); a pixel stops at the first Gaussian that would bring T below 1e-4
  (that one is left out, as 3DGS's kernel does); colour = sum_i alpha_i T_i c_i + T_final * background.
- Extent: a Gaussian's alpha reaches 1/255 exactly on the ellipse d^T Sigma_2d^-1 d = 2 ln(255 o), whose bounding
  box (half widths sqrt(2 ln(255 o) Sigma_xx), sqrt(2 ln(255 o) Sigma_yy)) decides the tiles it is binned in.
  Outside that box alpha < 1/255 is skipped anyway, so the tiles only skip work: the tiled render equals the
  per-pixel twin (`render_reference`, every Gaussian at every pixel) up to rounding.

Gradients flow by autograd through torch ops to every field of `Splats` (the binning, the depth order and the
stopping rule are piecewise constant, as in the CUDA rasterisers). Works on any device the tensors are on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from nerfpipe.radiance import splat_cpu
from nerfpipe.radiance.camera import OPENGL_FROM_OPENCV, Intrinsics

__all__ = [
    "ALPHA_MIN",
    "ALPHA_MAX",
    "T_MIN",
    "EPS2D",
    "SH_C0",
    "Splats",
    "Projected",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "transformed",
    "covariance",
    "sh_degree",
    "sh_basis",
    "sh_rotation",
    "sh_to_rgb",
    "rgb_to_sh0",
    "project",
    "resolve_kernel",
    "rasterize",
    "render",
    "render_reference",
]

ALPHA_MIN = 1.0 / 255.0
"""Alphas below this are skipped (3DGS, gsplat)."""
ALPHA_MAX = 0.99
"""Alphas are clamped to this (so 1 - alpha > 0 and log1p(-alpha) is finite)."""
T_MIN = 1e-4
"""A pixel stops before the Gaussian that would bring its transmittance below this."""
EPS2D = 0.3
"""Low-pass added to the 2-D covariance's diagonal, px^2 (3DGS)."""
TILE_NUMBA = 8
"""Default tile side of the numba kernel: smaller tiles mean shorter lists a pixel walks (fox, 300k Gaussians at
270x480: kernel 0.12 / 0.15 / 0.22 s forward at 4 / 8 / 16 px), more (tile, Gaussian) pairs to bin (0.085 / 0.040 /
0.028 s)."""
TILE_TORCH = 16
"""Default tile side of the torch path (a Python loop over tiles: fewer, larger tiles)."""
FOV_CLAMP = 1.3
"""x/z, y/z are clamped to this times the half field of view in the Jacobian (3DGS)."""
SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


@dataclass
class Splats:
    """A set of 3-D Gaussians (scene frame; module doc)."""

    means: Tensor  # [N, 3]
    log_scales: Tensor  # [N, 3]
    quats: Tensor  # [N, 4] wxyz
    opacity_logits: Tensor  # [N]
    sh: Tensor  # [N, K, 3], K in (1, 4, 9, 16)

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        shapes = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,)}
        for name, shape in shapes.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"expected {name} {list(shape)}, got {list(got)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"expected sh [{n}, K, 3], got {list(self.sh.shape)}")
        sh_degree(self.sh.shape[1])

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def parameters(self) -> list[Tensor]:
        return [self.means, self.log_scales, self.quats, self.opacity_logits, self.sh]

    def subset(self, keep: Tensor) -> Splats:
        """The Gaussians selected by `keep` (bool [N] or indices)."""
        return Splats(*(p[keep] for p in self.parameters()))


@dataclass
class Projected:
    """Gaussians on the image plane (all N; `visible` marks the ones drawn)."""

    means2d: Tensor  # [N, 2] pixels
    conics: Tensor  # [N, 3] (a, b, c): Sigma_2d^-1 = [[a, b], [b, c]]
    depths: Tensor  # [N] z of the mean, camera frame
    extents: Tensor  # [N, 2] half widths of the alpha >= 1/255 box, pixels (no gradient)
    opacities: Tensor  # [N]
    rgb: Tensor  # [N, 3]
    visible: Tensor  # [N] bool


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] wxyz (any length > 0) -> [N, 3, 3] rotation matrices."""
    w, x, y, z = (quats / torch.linalg.norm(quats, dim=-1, keepdim=True)).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*quats.shape[:-1], 3, 3)


def rotmat_to_quat(rot: Tensor) -> Tensor:
    """[N, 3, 3] rotations -> [N, 4] unit quaternions wxyz with w >= 0 (Shepperd's method: the largest of 4w^2,
    4x^2, 4y^2, 4z^2 picks the stable formula)."""
    m = rot
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    t = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1)
    k = torch.argmax(t, dim=-1)
    s = torch.sqrt(t.gather(1, k[:, None]).clamp_min(torch.finfo(m.dtype).tiny))[:, 0] * 2  # 4 |q_k|
    d10, d01 = m[:, 1, 0], m[:, 0, 1]
    d20, d02 = m[:, 2, 0], m[:, 0, 2]
    d21, d12 = m[:, 2, 1], m[:, 1, 2]
    cands = torch.stack(
        [
            torch.stack([s / 4, (d21 - d12) / s, (d02 - d20) / s, (d10 - d01) / s], dim=-1),
            torch.stack([(d21 - d12) / s, s / 4, (d01 + d10) / s, (d02 + d20) / s], dim=-1),
            torch.stack([(d02 - d20) / s, (d01 + d10) / s, s / 4, (d12 + d21) / s], dim=-1),
            torch.stack([(d10 - d01) / s, (d02 + d20) / s, (d12 + d21) / s, s / 4], dim=-1),
        ],
        dim=1,
    )  # [N, 4 cases, 4]
    q = cands[torch.arange(m.shape[0], device=m.device), k]
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    return torch.where(q[:, :1] < 0, -q, q)


def transformed(splats: Splats, out_from_scene: Tensor) -> Splats:
    """The Gaussians under a similarity `out_from_scene` [4, 4] (A = s R, R orthogonal, a mirror allowed):
    means A x + t, scales times s, orientations R R_g (a mirror flips the Gaussian's third axis, which the
    Gaussian does not see), SH coefficients rotated with the directions (`sh_rotation`)."""
    m = torch.as_tensor(out_from_scene).to(splats.means)
    a, t = m[:3, :3], m[:3, 3]
    s = torch.abs(torch.linalg.det(a)) ** (1.0 / 3.0)
    rot = a / s
    if not torch.allclose(rot.T @ rot, torch.eye(3).to(rot), atol=1e-5):
        raise ValueError("expected a similarity (rotation, uniform scale, translation), got a shear or uneven scale")
    r_g = rot @ quat_to_rotmat(splats.quats)
    if torch.linalg.det(rot) < 0:
        r_g = r_g * torch.tensor([1.0, 1.0, -1.0]).to(r_g)  # flip the third column back to a rotation
    sh = splats.sh
    if sh.shape[1] > 1:
        sh = torch.einsum("jk,nkc->njc", sh_rotation(rot.detach().cpu(), sh_degree(sh.shape[1])).to(sh), sh)
    return Splats(
        means=splats.means @ a.T + t,
        log_scales=splats.log_scales + torch.log(s),
        quats=rotmat_to_quat(r_g),
        opacity_logits=splats.opacity_logits,
        sh=sh,
    )


def covariance(log_scales: Tensor, quats: Tensor) -> Tensor:
    """[N, 3], [N, 4] -> Sigma = R S S R^T [N, 3, 3]."""
    m = quat_to_rotmat(quats) * torch.exp(log_scales)[..., None, :]  # R S
    return m @ m.transpose(-1, -2)


def sh_degree(k: int) -> int:
    """SH coefficients per channel -> degree (1 -> 0, 4 -> 1, 9 -> 2, 16 -> 3)."""
    degree = {1: 0, 4: 1, 9: 2, 16: 3}.get(int(k))
    if degree is None:
        raise ValueError(f"expected 1, 4, 9 or 16 SH coefficients per channel (degree 0..3), got {k}")
    return degree


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """Colour in [0, 1] [..., 3] -> the degree-0 coefficient giving it [..., 3]."""
    return (rgb - 0.5) / SH_C0


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Unit dirs [N, 3] -> INRIA's real SH basis [N, (degree + 1)^2] (its constants and signs), degree 0..3."""
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"expected an SH degree 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree > 0:
        out += [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        c = _SH_C2
        out += [c[0] * xy, c[1] * yz, c[2] * (2 * zz - xx - yy), c[3] * xz, c[4] * (xx - yy)]
        if degree > 2:
            c = _SH_C3
            out += [
                c[0] * y * (3 * xx - yy),
                c[1] * xy * z,
                c[2] * y * (4 * zz - xx - yy),
                c[3] * z * (2 * zz - 3 * xx - 3 * yy),
                c[4] * x * (4 * zz - xx - yy),
                c[5] * z * (xx - yy),
                c[6] * x * (xx - 3 * yy),
            ]
    return torch.stack(out, dim=-1)


def sh_to_rgb(sh: Tensor, dirs: Tensor) -> Tensor:
    """sh [N, K, 3], unit dirs [N, 3] (camera centre -> mean) -> colour [N, 3] = max(0, 0.5 + SH), INRIA's basis."""
    basis = sh_basis(dirs, sh_degree(sh.shape[1])).to(sh.dtype)  # [N, K]
    return torch.clamp_min(torch.einsum("nk,nkc->nc", basis, sh) + 0.5, 0.0)


def _fibonacci_dirs(n: int, dtype: torch.dtype) -> Tensor:
    """n unit directions spread over the sphere (a Fibonacci lattice, deterministic)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = torch.sqrt(1.0 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1).to(dtype)


def sh_rotation(rot: Tensor, degree: int) -> Tensor:
    """The [K, K] matrix M (K = (degree + 1)^2) with sh_out = M @ sh for an orthogonal `rot` [3, 3] (a mirror too):
    sum_k sh_out_k Y_k(rot d) = sum_k sh_k Y_k(d) for every unit d. Each band is closed under rotations and mirrors
    (its functions are the harmonic polynomials of one degree), so M is block diagonal and each block is solved
    exactly from the basis at 64 spread directions (float64 least squares; band 0 is 1)."""
    rot = torch.as_tensor(rot, dtype=torch.float64)
    if rot.shape != (3, 3) or not torch.allclose(rot.T @ rot, torch.eye(3, dtype=torch.float64), atol=1e-6):
        raise ValueError(f"expected an orthogonal [3, 3] matrix, got {list(rot.shape)}: {rot.tolist()}")
    d = _fibonacci_dirs(64, torch.float64)
    y_in, y_out = sh_basis(d, degree), sh_basis(d @ rot.T, degree)  # [64, K]: Y(d) and Y(rot d)
    m = torch.zeros(y_in.shape[1], y_in.shape[1], dtype=torch.float64)
    m[0, 0] = 1.0
    for band in range(1, degree + 1):
        b = slice(band * band, (band + 1) * (band + 1))
        # Y_out[:, b] @ M_b = Y_in[:, b]  (sh_out = M_b sh for coefficient columns)
        m[b, b] = torch.linalg.lstsq(y_out[:, b], y_in[:, b]).solution
    return m


def _cam_from_world_cv(world_from_cam: Tensor, like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """OpenGL world_from_cam [4, 4] -> (R [3, 3], t [3]) of the OpenCV cam_from_world, and the centre [3]."""
    m = world_from_cam.to(like) @ OPENGL_FROM_OPENCV.to(like)  # OpenGL -> OpenCV camera axes
    rot = m[:3, :3].T  # rigid: the inverse rotation is the transpose
    centre = m[:3, 3]
    return rot, -rot @ centre, centre


def project(
    splats: Splats, world_from_cam: Tensor, intr: Intrinsics, *, near: float = 0.01, eps2d: float = EPS2D
) -> Projected:
    """Project every Gaussian (module doc). A Gaussian is visible when its mean is more than `near` in front of the
    camera, its opacity is at least 1/255 and its alpha >= 1/255 box meets the image."""
    means = splats.means
    rot, t, centre = _cam_from_world_cv(torch.as_tensor(world_from_cam), means)
    p = means @ rot.T + t  # [N, 3] OpenCV camera
    z = p[:, 2]
    front = z > near
    zs = torch.where(front, z, torch.ones_like(z))  # keeps culled ones finite (and their gradients zero)
    lim_x, lim_y = FOV_CLAMP * 0.5 * intr.w / intr.fx, FOV_CLAMP * 0.5 * intr.h / intr.fy
    tx = (p[:, 0] / zs).clamp(-lim_x, lim_x) * zs
    ty = (p[:, 1] / zs).clamp(-lim_y, lim_y) * zs
    zero = torch.zeros_like(zs)
    jac = torch.stack(
        [
            torch.stack([intr.fx / zs, zero, -intr.fx * tx / (zs * zs)], dim=-1),
            torch.stack([zero, intr.fy / zs, -intr.fy * ty / (zs * zs)], dim=-1),
        ],
        dim=-2,
    )  # [N, 2, 3]
    m = jac @ rot  # [N, 2, 3]: J W
    cov2d = m @ covariance(splats.log_scales, splats.quats) @ m.transpose(-1, -2)
    a, b, c = cov2d[:, 0, 0] + eps2d, cov2d[:, 0, 1], cov2d[:, 1, 1] + eps2d
    det = a * c - b * b
    ok = front & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)
    means2d = torch.stack([intr.fx * p[:, 0] / zs + intr.cx, intr.fy * p[:, 1] / zs + intr.cy], dim=-1)
    opacities = torch.sigmoid(splats.opacity_logits)
    with torch.no_grad():
        k = 2 * torch.log(torch.clamp_min(opacities * 255.0, 1.0))  # 0 when o <= 1/255: never reaches 1/255
        extents = torch.sqrt(torch.stack([k * a, k * c], dim=-1).clamp_min(0))
        extents = extents * (1 + 1e-4) + 1e-3  # a margin: binning a Gaussian into an extra tile changes nothing
        lo, hi = means2d - extents, means2d + extents
        inside = (hi[:, 0] > 0) & (lo[:, 0] < intr.w) & (hi[:, 1] > 0) & (lo[:, 1] < intr.h)
        visible = ok & (opacities >= ALPHA_MIN) & inside & torch.isfinite(means2d).all(-1) & (k > 0)
    dirs = means - centre
    dirs = dirs / torch.linalg.norm(dirs, dim=-1, keepdim=True).clamp_min(torch.finfo(dirs.dtype).tiny)
    rgb = sh_to_rgb(splats.sh, dirs)
    return Projected(
        means2d=means2d, conics=conics, depths=z, extents=extents, opacities=opacities, rgb=rgb, visible=visible
    )


def _tile_pairs(proj: Projected, order: Tensor, w: int, h: int, tile: int) -> tuple[Tensor, Tensor, int, int]:
    """Bin the depth-ordered visible Gaussians `order` [M] into tiles: (tile id per pair, Gaussian per pair) sorted by
    tile, each tile's Gaussians front to back; and the tile grid (nx, ny)."""
    nx, ny = -(-w // tile), -(-h // tile)
    mean, ext = proj.means2d.detach()[order], proj.extents[order]
    # pixel i has its centre at i + 0.5: the first and last pixel inside [mean - ext, mean + ext]
    p0 = torch.ceil(mean - ext - 0.5).clamp_min(0).long()
    p1 = torch.floor(mean + ext - 0.5).long()
    p1 = torch.minimum(p1, torch.tensor([w - 1, h - 1], device=p1.device))
    keep = (p1 >= p0).all(-1)
    order, p0, p1 = order[keep], p0[keep], p1[keep]
    t0, t1 = p0 // tile, p1 // tile  # [M, 2] first and last tile on each axis
    span = t1 - t0 + 1
    counts = span[:, 0] * span[:, 1]
    g = torch.repeat_interleave(torch.arange(order.shape[0], device=order.device), counts)
    first = torch.cumsum(counts, 0) - counts
    k = torch.arange(g.shape[0], device=order.device) - first[g]  # index within the Gaussian's tile block
    tx = t0[g, 0] + k % span[g, 0]
    ty = t0[g, 1] + k // span[g, 0]
    tile_id = ty * nx + tx
    by_tile = torch.sort(tile_id, stable=True).indices  # stable: keeps the depth order inside a tile
    return tile_id[by_tile], order[g[by_tile]], nx, ny


def _pair_coefficients(proj: Projected, tile_id: Tensor, gauss: Tensor, nx: int, tile: int) -> Tensor:
    """Per (tile, Gaussian) pair [M, 6]: log(o) - 0.5 d^T Sigma^-1 d, d = p - m, as a polynomial in the pixel's
    coordinates (x, y) about its tile's middle, coefficients of [x^2, y^2, xy, x, y, 1] (small coordinates: no
    cancellation worth a float32 digit)."""
    middle = torch.stack([tile_id % nx, tile_id // nx], dim=-1).to(proj.means2d.dtype) * tile + 0.5 * tile
    mx, my = (proj.means2d[gauss] - middle).unbind(-1)
    a, b, c = proj.conics[gauss].unbind(-1)
    quad = a * mx * mx + c * my * my
    return torch.stack(
        [
            -0.5 * a,
            -0.5 * c,
            -b,
            a * mx + b * my,
            c * my + b * mx,
            torch.log(proj.opacities[gauss]) - 0.5 * quad - b * mx * my,
        ],
        dim=-1,
    )


def _composite_tile(basis: Tensor, coeffs: Tensor, rgb: Tensor, chunk: int) -> tuple[Tensor, Tensor]:
    """One tile: pixels' `basis` [P, 6] ([x^2, y^2, xy, x, y, 1] about the tile's middle), its Gaussians front to back
    (`coeffs` [K, 6], `rgb` [K, 3]) -> (colour sum [P, 3], log T [P]), `chunk` Gaussians at a time; stops once every
    pixel is done."""
    log_t_min = math.log(T_MIN)
    n = basis.shape[0]
    color = basis.new_zeros(n, 3)
    log_t = basis.new_zeros(n)
    done = torch.zeros(n, dtype=torch.bool, device=basis.device)
    for i in range(0, coeffs.shape[0], chunk):
        e = torch.exp(basis @ coeffs[i : i + chunk].T)  # [P, k]: o exp(-0.5 d^T Sigma^-1 d)
        alpha = torch.where(e >= ALPHA_MIN, torch.clamp_max(e, ALPHA_MAX), torch.zeros_like(e))
        log1m = torch.log1p(-alpha)
        cum = log_t[:, None] + torch.cumsum(log1m, dim=1)  # log T after each Gaussian, [P, k]
        weights = alpha * torch.exp(cum - log1m)  # alpha T, T before the Gaussian
        stops = cum[:, -1] < log_t_min  # cum only decreases: the last column says whether a row stops here
        if bool(stops.any()) or bool(done.any()):
            use = (cum >= log_t_min) & ~done[:, None]  # a prefix of each row
            weights = torch.where(use, weights, torch.zeros_like(weights))
            log1m = torch.where(use, log1m, torch.zeros_like(log1m))
            done = done | stops
        color = color + weights @ rgb[i : i + chunk]
        log_t = log_t + log1m.sum(dim=1)
        if bool(done.all()):
            break
    return color, log_t


def resolve_kernel(kernel: str, device: torch.device | str) -> str:
    """`rasterize`'s `kernel` (auto | numba | torch) -> the one that runs on `device`: auto is numba on CPU when
    it imports (`radiance.splat_cpu.available`), else torch."""
    if kernel not in ("auto", "numba", "torch"):
        raise ValueError(f"expected kernel auto, numba or torch, got {kernel!r}")
    if kernel != "auto":
        return kernel
    return "numba" if torch.device(device).type == "cpu" and splat_cpu.available() else "torch"


def rasterize(
    proj: Projected,
    w: int,
    h: int,
    background: Tensor,
    *,
    tile: int | None = None,
    chunk: int = 256,
    kernel: str = "auto",
) -> dict[str, Tensor]:
    """Composite the visible Gaussians over `background` [3] -> dict(rgb [H, W, 3], alpha [H, W] = 1 - T_final).

    Tiles of `tile` x `tile` pixels each composite the Gaussians binned to them (module doc: the result does not
    depend on `tile`; None: TILE_NUMBA or TILE_TORCH, the faster for the kernel). `kernel`: numba
    (`radiance.splat_cpu`, CPU tensors: each pixel walks its Gaussians until it is opaque), torch (any device: every
    Gaussian of a tile at all its pixels, `chunk` Gaussians at a time, memory [tile^2, chunk]), or auto (numba on CPU
    when it imports, else torch). Both give the same values and gradients (tests/test_splats.py)."""
    like = proj.means2d
    fast = resolve_kernel(kernel, like.device) == "numba"
    background = torch.as_tensor(background).to(like).reshape(3)
    order = torch.nonzero(proj.visible).squeeze(1)
    order = order[torch.sort(proj.depths.detach()[order], stable=True).indices]
    tile = tile or (TILE_NUMBA if fast else TILE_TORCH)
    tile_id, gauss, nx, ny = _tile_pairs(proj, order, w, h, tile)
    starts = torch.searchsorted(tile_id, torch.arange(nx * ny + 1, device=tile_id.device))
    if fast:
        tiles = splat_cpu.Tiles(gauss=gauss, starts=starts, w=w, h=h, tile=tile, nx=nx)
        rgb, trans = splat_cpu.composite(
            proj.means2d,
            proj.conics,
            proj.opacities,
            proj.rgb,
            background,
            tiles,
            alpha_min=ALPHA_MIN,
            alpha_max=ALPHA_MAX,
            t_min=T_MIN,
        )
        return {"rgb": rgb, "alpha": 1 - trans}
    coeffs, rgb_pairs = _pair_coefficients(proj, tile_id, gauss, nx, tile), proj.rgb[gauss]
    starts = starts.tolist()
    ys, xs = torch.meshgrid(
        torch.arange(tile, device=like.device), torch.arange(tile, device=like.device), indexing="ij"
    )
    offsets = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)  # [tile^2, 2] (col, row)
    local = offsets.to(like.dtype) + 0.5 - 0.5 * tile  # pixel centres about the tile's middle
    full_basis = torch.stack(
        [
            local[:, 0] ** 2,
            local[:, 1] ** 2,
            local[:, 0] * local[:, 1],
            local[:, 0],
            local[:, 1],
            torch.ones_like(local[:, 0]),
        ],
        dim=-1,
    )  # [tile^2, 6]
    tiles_rgb, tiles_t, where = [], [], []
    for t in range(nx * ny):
        s0, s1 = starts[t], starts[t + 1]
        if s1 == s0:
            continue
        px = offsets + torch.tensor([(t % nx) * tile, (t // nx) * tile], device=like.device)
        inside = (px[:, 0] < w) & (px[:, 1] < h)
        basis = full_basis if bool(inside.all()) else full_basis[inside]
        color, log_t = _composite_tile(basis, coeffs[s0:s1], rgb_pairs[s0:s1], chunk)
        tiles_rgb.append(color)
        tiles_t.append(log_t)
        px = px[inside]
        where.append(px[:, 1] * w + px[:, 0])
    rgb = like.new_zeros(h * w, 3)
    trans = like.new_ones(h * w)
    if where:
        idx = torch.cat(where)
        rgb = rgb.index_put((idx,), torch.cat(tiles_rgb))
        trans = trans.index_put((idx,), torch.exp(torch.cat(tiles_t)))
    rgb = rgb + trans[:, None] * background
    return {"rgb": rgb.reshape(h, w, 3), "alpha": (1 - trans).reshape(h, w)}


def render(
    splats: Splats,
    world_from_cam: Tensor,
    intr: Intrinsics,
    background: Tensor,
    *,
    tile: int | None = None,
    near: float = 0.01,
    kernel: str = "auto",
) -> dict[str, Tensor]:
    """Project and rasterise: dict(rgb [H, W, 3], alpha [H, W]) for one camera (module doc; `kernel` as
    `rasterize`)."""
    proj = project(splats, world_from_cam, intr, near=near)
    return rasterize(proj, intr.w, intr.h, background, tile=tile, kernel=kernel)


# ---------------------------------------------------------------------------------------------- the plain twin
def _hamilton(p: Tensor, q: Tensor) -> Tensor:
    pw, px, py, pz = p.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    return torch.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def _twin_covariance(log_scale: Tensor, quat: Tensor) -> Tensor:
    """One Gaussian's Sigma [3, 3] with R's columns as q e_i q* (Hamilton products): not `quat_to_rotmat`'s formula."""
    q = quat / torch.linalg.norm(quat)
    conj = q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)
    cols = [_hamilton(_hamilton(q, torch.eye(4, dtype=q.dtype)[i + 1]), conj)[1:] for i in range(3)]
    rs = torch.stack(cols, dim=1) * torch.exp(log_scale)[None, :]
    return rs @ rs.T


def render_reference(
    splats: Splats, world_from_cam: Tensor, intr: Intrinsics, background: Tensor, *, near: float = 0.01
) -> dict[str, Tensor]:
    """`render`'s plain twin for tests (tiny images, a few Gaussians; CPU): J by autograd of the pinhole projection,
    R by quaternion products, and 3DGS's per-pixel loop over every Gaussian in depth order (no tiles, no extents)."""
    dt = splats.means.dtype
    wfc = torch.as_tensor(world_from_cam).to(dt) @ OPENGL_FROM_OPENCV.to(dt)
    rot = wfc[:3, :3].T
    centre = wfc[:3, 3]
    lim = (FOV_CLAMP * 0.5 * intr.w / intr.fx, FOV_CLAMP * 0.5 * intr.h / intr.fy)

    def pixel(pc: Tensor) -> Tensor:
        return torch.stack([intr.fx * pc[0] / pc[2] + intr.cx, intr.fy * pc[1] / pc[2] + intr.cy])

    items = []
    for i in range(len(splats)):
        pc = rot @ (splats.means[i] - centre)
        if not float(pc[2].detach()) > near:
            continue
        clamped = torch.stack(
            [(pc[0] / pc[2]).clamp(-lim[0], lim[0]) * pc[2], (pc[1] / pc[2]).clamp(-lim[1], lim[1]) * pc[2], pc[2]]
        )
        jac = torch.autograd.functional.jacobian(pixel, clamped, create_graph=True)  # [2, 3]
        cov = jac @ rot @ _twin_covariance(splats.log_scales[i], splats.quats[i]) @ rot.T @ jac.T
        cov = cov + EPS2D * torch.eye(2, dtype=dt)
        dirs = (splats.means[i] - centre) / torch.linalg.norm(splats.means[i] - centre)
        rgb = sh_to_rgb(splats.sh[i : i + 1], dirs[None])[0]
        items.append(
            (float(pc[2].detach()), pixel(pc), torch.linalg.inv(cov), torch.sigmoid(splats.opacity_logits[i]), rgb)
        )
    items.sort(key=lambda it: it[0])
    background = torch.as_tensor(background).to(dt)
    rows, alphas = [], []
    for j in range(intr.h):
        for i in range(intr.w):
            x = torch.tensor([i + 0.5, j + 0.5], dtype=dt)
            color, trans = torch.zeros(3, dtype=dt), torch.ones((), dtype=dt)
            for _, mean, inv, opacity, rgb in items:
                d = x - mean
                alpha = torch.clamp_max(opacity * torch.exp(-0.5 * d @ inv @ d), ALPHA_MAX)
                if float(alpha.detach()) < ALPHA_MIN:
                    continue
                test = trans * (1 - alpha)
                if float(test.detach()) < T_MIN:
                    break
                color = color + alpha * trans * rgb
                trans = test
            rows.append(color + trans * background)
            alphas.append(1 - trans)
    return {"rgb": torch.stack(rows).reshape(intr.h, intr.w, 3), "alpha": torch.stack(alphas).reshape(intr.h, intr.w)}
