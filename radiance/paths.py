"""Camera paths for rendering, derived from the training cameras: a turntable orbit (or an arc of it), a smoothed
trajectory through the training cameras, and an LLFF-style spiral.

Conventions (see docs/DESIGN.md):
- Poses are `world_from_cam` [4, 4] float64 in the OpenGL camera convention (x right, y up, looking down -z),
  in the scene frame (up axis +z by contract). No file I/O here.
- The *focus* of a capture is the point closest, in the least-squares sense, to every camera's optical axis.
- Turntable: the camera orbits the focus around an `up` axis at a fixed `radius` (distance to the focus) and
  `elevation` (degrees above the plane through the focus perpendicular to `up`), always looking at the focus,
  its image up as close to `up` as the view allows.
- Azimuth coverage: the camera centres' azimuths about the orbit axis through the orbit centre; the largest gap
  between consecutive sorted azimuths (circularly) says whether the capture goes round the object (a phone walk
  half-way round leaves a gap of about 180 degrees). The covered arc starts just after the largest gap and runs
  counter-clockwise about `up` for `360 - gap` degrees.
- Trajectory: keyframes (training camera centres in path order) in cylindrical coordinates about the orbit axis,
  unrolled as (azimuth x median distance to the axis, distance to the axis, height) so that smoothing and the
  spline keep arcs round (Cartesian smoothing would pull an orbit in towards the object), are smoothed with a
  Gaussian along the sequence (odd reflection at the ends keeps the end points), joined by a centripetal
  Catmull-Rom spline, rolled back up and resampled at equal (Cartesian) arc length; every frame looks at the
  orbit centre with its image up towards `up`.
- Spiral (forward-facing captures, as LLFF's `render_path_spiral`): the camera circles the mean training pose
  in its image plane (radii from camera-position percentiles) while looking at a point ahead of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Orbit",
    "look_at",
    "camera_centres",
    "camera_forwards",
    "focus_point",
    "up_axis",
    "orbit_from_cameras",
    "turntable",
    "Coverage",
    "azimuth_coverage",
    "azimuth_order",
    "path_length",
    "smooth_polyline",
    "interpolate_polyline",
    "trajectory",
    "mean_pose",
    "spiral",
]

_SCENE_UP = np.array([0.0, 0.0, 1.0])


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-300)


def _check_poses(world_from_cams: np.ndarray) -> np.ndarray:
    m = np.asarray(world_from_cams, dtype=np.float64)
    if m.ndim != 3 or m.shape[1:] != (4, 4) or len(m) == 0:
        raise ValueError(f"expected world_from_cams [N>=1, 4, 4], got {m.shape}")
    return m


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenGL `world_from_cam` [4, 4] at `eye` looking at `target`, image up towards `up` (all [3]).

    When the view direction is parallel to `up`, a deterministic perpendicular replaces it.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = _unit(eye - target)  # camera +z points away from what it looks at
    if np.linalg.norm(back) == 0:
        raise ValueError("look_at: eye and target coincide")
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-9 * max(np.linalg.norm(up), 1e-300):
        # looking straight along up: use the world axis least aligned with the view
        right = np.cross(np.eye(3)[np.argmin(np.abs(back))], back)
    right = _unit(right)
    cam_up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, cam_up, back, eye
    return m


def camera_centres(world_from_cams: np.ndarray) -> np.ndarray:  # [N, 4, 4] -> [N, 3]
    return _check_poses(world_from_cams)[:, :3, 3]


def camera_forwards(world_from_cams: np.ndarray) -> np.ndarray:  # [N, 4, 4] -> [N, 3] unit
    return _unit(-_check_poses(world_from_cams)[:, :3, 2])  # OpenGL looks down -z


def focus_point(world_from_cams: np.ndarray) -> np.ndarray:
    """Least-squares intersection of the optical axes: argmin_p sum_i |(I - d_i d_i^T)(p - c_i)|^2 -> [3].

    Nearly parallel axes (forward-facing captures) make the system ill-conditioned; then the point on the mean
    axis (through the mean centre along the mean forward direction) closest to the axes is returned instead,
    found by 1-D least squares on the distance along that axis (deterministic; never random).
    """
    c = camera_centres(world_from_cams)
    d = camera_forwards(world_from_cams)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # [N, 3, 3]
    a = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, c)
    eig = np.linalg.eigvalsh(a)
    if eig[0] > 1e-3 * len(c):
        return np.linalg.solve(a, b)
    # degenerate: p = c0 + s * f with c0, f the mean centre and forward; minimise over s
    c0, f = c.mean(0), _unit(d.mean(0))
    pf = np.einsum("nij,j->ni", proj, f)  # [N, 3]
    r = np.einsum("nij,nj->ni", proj, c0[None] - c)  # [N, 3]
    denom = float((pf * pf).sum())
    s = -float((pf * r).sum()) / denom if denom > 1e-12 else 1.0
    if not math.isfinite(s) or s <= 0:
        s = float(np.median(np.linalg.norm(c - c0, axis=1))) or 1.0
    return c0 + s * f


def up_axis(world_from_cams: np.ndarray) -> tuple[np.ndarray, str]:
    """The orbit axis: the scene frame's +z (DESIGN: the scene frame is up +z) when the training cameras' mean
    image-up agrees with it within 60 degrees, otherwise the mean camera up. Returns (unit [3], reason)."""
    ups = _check_poses(world_from_cams)[:, :3, 1]
    mean_up = ups.mean(0)
    if np.linalg.norm(mean_up) < 1e-9:
        return _SCENE_UP.copy(), "scene +z (camera ups cancel out)"
    mean_up = _unit(mean_up)
    if float(mean_up @ _SCENE_UP) >= 0.5:
        return _SCENE_UP.copy(), "scene +z"
    return mean_up, "mean training camera up (differs from scene +z by more than 60 degrees)"


@dataclass(frozen=True, kw_only=True)
class Orbit:
    """A turntable orbit in the scene frame."""

    centre: np.ndarray
    """[3] the point looked at."""
    up: np.ndarray
    """[3] unit orbit axis."""
    radius: float
    """Distance from the camera to `centre`, scene units."""
    elevation_deg: float
    """Angle of the camera above the plane through `centre` perpendicular to `up`."""
    start_azimuth_deg: float
    """Azimuth of the first frame, measured in the basis of `_horizontal_basis(up)`."""


def _horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to `up` (x-ish first; deterministic)."""
    up = _unit(np.asarray(up, dtype=np.float64))
    seed = np.eye(3)[0] if abs(up[0]) < 0.9 else np.eye(3)[1]
    e1 = _unit(seed - (seed @ up) * up)
    return e1, np.cross(up, e1)


def orbit_from_cameras(world_from_cams: np.ndarray) -> Orbit:
    """Orbit through the training cameras: centre = focus point, radius and elevation = their medians,
    starting at the first camera's azimuth."""
    c = camera_centres(world_from_cams)
    centre = focus_point(world_from_cams)
    up, _ = up_axis(world_from_cams)
    e1, e2 = _horizontal_basis(up)
    rel = c - centre
    dist = np.linalg.norm(rel, axis=1)
    elev = np.degrees(np.arcsin(np.clip((rel @ up) / np.maximum(dist, 1e-300), -1.0, 1.0)))
    azim = np.degrees(np.arctan2(rel[0] @ e2, rel[0] @ e1))
    return Orbit(
        centre=centre,
        up=up,
        radius=float(np.median(dist)),
        elevation_deg=float(np.median(elev)),
        start_azimuth_deg=float(azim),
    )


def turntable(orbit: Orbit, n_frames: int, *, sweep_deg: float = 360.0) -> np.ndarray:
    """`n_frames` poses [N, 4, 4] evenly spaced over `sweep_deg` counter-clockwise about `up` from the orbit's
    start azimuth. A full turn (360) stops one step short of the first frame; a partial arc includes both ends."""
    if n_frames < 1:
        raise ValueError(f"expected n_frames >= 1, got {n_frames}")
    if not orbit.radius > 0:
        raise ValueError(f"expected radius > 0, got {orbit.radius}")
    if not 0 <= sweep_deg <= 360:
        raise ValueError(f"expected sweep_deg in [0, 360], got {sweep_deg}")
    e1, e2 = _horizontal_basis(orbit.up)
    el = math.radians(orbit.elevation_deg)
    sweep, steps = (2 * math.pi, n_frames) if sweep_deg >= 360 else (math.radians(sweep_deg), max(n_frames - 1, 1))
    out = np.empty((n_frames, 4, 4))
    for k in range(n_frames):
        az = math.radians(orbit.start_azimuth_deg) + sweep * k / steps
        direction = math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * orbit.up
        out[k] = look_at(orbit.centre + orbit.radius * direction, orbit.centre, orbit.up)
    return out


@dataclass(frozen=True, kw_only=True)
class Coverage:
    """How far round the orbit axis the cameras go (degrees, basis of `_horizontal_basis(up)`)."""

    azimuths_deg: np.ndarray
    """[N] azimuth of each camera centre about the orbit axis through the centre, in (-180, 180]."""
    largest_gap_deg: float
    """Largest angle between azimuth-neighbouring cameras, circularly (360 for a single camera)."""
    covered_deg: float
    """360 - largest_gap_deg: the arc the cameras span."""
    start_deg: float
    """Azimuth where the covered arc starts (the camera just after the largest gap, counter-clockwise)."""


def azimuth_coverage(world_from_cams: np.ndarray, orbit: Orbit) -> Coverage:
    """Azimuths of the camera centres about `orbit.up` through `orbit.centre`, and the largest gap between them."""
    rel = camera_centres(world_from_cams) - orbit.centre
    e1, e2 = _horizontal_basis(orbit.up)
    az = np.degrees(np.arctan2(rel @ e2, rel @ e1))  # [N]
    srt = np.sort(az)
    gaps = np.diff(np.concatenate([srt, srt[:1] + 360.0]))  # gap after each sorted camera, the last wraps round
    k = int(np.argmax(gaps))
    gap = float(gaps[k]) if len(srt) > 1 else 360.0
    start = float(srt[(k + 1) % len(srt)])
    return Coverage(azimuths_deg=az, largest_gap_deg=gap, covered_deg=360.0 - gap, start_deg=start)


def azimuth_order(coverage: Coverage) -> np.ndarray:
    """Camera indices sorted counter-clockwise along the covered arc, starting after the largest gap -> [N]."""
    return np.argsort((coverage.azimuths_deg - coverage.start_deg) % 360.0, kind="stable")


def path_length(points: np.ndarray) -> float:
    """Length of the polyline through `points` [N, D] in order."""
    p = np.asarray(points, dtype=np.float64)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def smooth_polyline(points: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing along the sequence [N, D] -> [N, D], `sigma` in samples (0: unchanged).

    The ends are padded by odd reflection (p_{-k} = 2 p_0 - p_k), so a straight run stays put and the end
    points barely move; the kernel radius is 3 sigma, capped at N - 1.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2:
        raise ValueError(f"expected points [N, D], got {p.shape}")
    if not sigma >= 0:
        raise ValueError(f"expected sigma >= 0, got {sigma}")
    r = min(math.ceil(3 * sigma), len(p) - 1)
    if sigma == 0 or r < 1:
        return p.copy()
    padded = np.concatenate([2 * p[0] - p[r:0:-1], p, 2 * p[-1] - p[-2 : -r - 2 : -1]])
    x = np.arange(-r, r + 1)
    kernel = np.exp(-0.5 * (x / sigma) ** 2)
    kernel /= kernel.sum()
    return np.stack([np.convolve(padded[:, j], kernel, mode="valid") for j in range(p.shape[1])], axis=1)


def _catmull_rom(points: np.ndarray, samples_per_segment: int) -> np.ndarray:
    """Centripetal Catmull-Rom through `points` [K >= 2, D] (distinct consecutive points), densely sampled.
    End tangents come from mirrored phantom points. -> [(K - 1) * samples_per_segment + 1, D]."""
    p = np.concatenate([2 * points[:1] - points[1:2], points, 2 * points[-1:] - points[-2:-1]])
    knots = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1) ** 0.5)])
    out = [points[:1]]
    s = np.linspace(0.0, 1.0, samples_per_segment + 1)[1:, None]
    for i in range(1, len(p) - 2):  # the segment between p[i] and p[i + 1]
        t0, t1, t2, t3 = knots[i - 1 : i + 3]
        t = t1 + s * (t2 - t1)
        a1 = ((t1 - t) * p[i - 1] + (t - t0) * p[i]) / (t1 - t0)
        a2 = ((t2 - t) * p[i] + (t - t1) * p[i + 1]) / (t2 - t1)
        a3 = ((t3 - t) * p[i + 1] + (t - t2) * p[i + 2]) / (t3 - t2)
        b1 = ((t2 - t) * a1 + (t - t0) * a2) / (t2 - t0)
        b2 = ((t3 - t) * a2 + (t - t1) * a3) / (t3 - t1)
        out.append(((t2 - t) * b1 + (t - t1) * b2) / (t2 - t1))
    return np.concatenate(out)


def _dense_curve(points: np.ndarray, sigma: float, samples_per_segment: int = 32) -> np.ndarray:
    """Smoothed keyframes [K, D] joined by a centripetal Catmull-Rom spline, densely sampled -> [M, D]."""
    p = smooth_polyline(points, sigma)
    if len(p) == 0:
        raise ValueError("expected at least one keyframe")
    scale = max(float(np.abs(p).max()), 1.0)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9 * scale])
    p = p[keep]  # consecutive duplicates would make zero-length knot intervals
    return p if len(p) == 1 else _catmull_rom(p, samples_per_segment)


def _resample(dense: np.ndarray, n: int) -> np.ndarray:
    """`n` points at equal arc length along the polyline `dense` [M, D], both ends included -> [n, D]."""
    if n < 1:
        raise ValueError(f"expected n >= 1, got {n}")
    if len(dense) == 1:
        return np.repeat(dense, n, axis=0)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    at = np.linspace(0.0, arc[-1], n) if n > 1 else np.zeros(1)
    return np.stack([np.interp(at, arc, dense[:, j]) for j in range(dense.shape[1])], axis=1)


def interpolate_polyline(points: np.ndarray, n: int, *, sigma: float = 0.0) -> np.ndarray:
    """`n` points [n, D] at equal arc length along a smooth curve through `points` [K, D] (in order).

    The keyframes are smoothed (`smooth_polyline(points, sigma)`), joined by a centripetal Catmull-Rom spline
    (it passes through each smoothed keyframe and makes no cusps or loops within a segment), and resampled at
    equal arc length, both ends included. A single keyframe (or keyframes that coincide) gives `n` copies.
    """
    if n < 1:
        raise ValueError(f"expected n >= 1, got {n}")
    return _resample(_dense_curve(np.asarray(points, dtype=np.float64), sigma), n)


def trajectory(
    world_from_cams: np.ndarray,
    n_frames: int,
    *,
    centre: np.ndarray,
    up: np.ndarray,
    sigma: float = 2.0,
) -> np.ndarray:
    """Poses [n_frames, 4, 4] along the cameras' path, given in path order: their centres, unrolled about the axis
    `up` through `centre`, smoothed (`sigma` in keyframes), splined, rolled back up and resampled at equal arc
    length; each frame looks at `centre` with its image up towards `up`."""
    if n_frames < 1:
        raise ValueError(f"expected n_frames >= 1, got {n_frames}")
    centre, up = np.asarray(centre, dtype=np.float64), _unit(np.asarray(up, dtype=np.float64))
    e1, e2 = _horizontal_basis(up)
    rel = camera_centres(world_from_cams) - centre
    x, y, height = rel @ e1, rel @ e2, rel @ up
    rho = np.hypot(x, y)
    r0 = float(np.median(rho)) or 1.0
    azimuth = np.unwrap(np.arctan2(y, x))  # continuous along the sequence
    dense = _dense_curve(np.stack([azimuth * r0, rho, height], axis=1), sigma)
    az = dense[:, :1] / r0
    xyz = centre + dense[:, 1:2] * (np.cos(az) * e1 + np.sin(az) * e2) + dense[:, 2:3] * up
    return np.stack([look_at(eye, centre, up) for eye in _resample(xyz, n_frames)])


def mean_pose(world_from_cams: np.ndarray) -> np.ndarray:
    """LLFF's `poses_avg`: mean centre, mean back (+z) axis, mean up re-orthogonalised -> [4, 4]."""
    m = _check_poses(world_from_cams)
    back_sum = m[:, :3, 2].sum(0)
    if np.linalg.norm(back_sum) < 1e-3 * len(m):
        raise ValueError("the cameras look in all directions (no mean viewing direction): not a forward-facing capture")
    back = _unit(back_sum)
    up = m[:, :3, 1].sum(0)
    right = _unit(np.cross(up, back))
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = right, np.cross(back, right), back, m[:, :3, 3].mean(0)
    return out


def spiral(
    world_from_cams: np.ndarray,
    n_frames: int,
    *,
    focus_distance: float | None = None,
    rotations: float = 2.0,
    percentile: float = 90.0,
    z_rate: float = 0.5,
) -> np.ndarray:
    """LLFF-style spiral around the mean pose -> [N, 4, 4].

    Radii along the mean pose's right/up/back axes are the `percentile` of the cameras' absolute offsets from
    the mean centre in that pose's frame (a small floor keeps a single camera moving); the camera looks at the
    point `focus_distance` ahead of the mean pose (default: the focus point's depth along the mean axis).
    """
    if n_frames < 1:
        raise ValueError(f"expected n_frames >= 1, got {n_frames}")
    m = _check_poses(world_from_cams)
    avg = mean_pose(m)
    if focus_distance is None:
        focus_distance = float((focus_point(m) - avg[:3, 3]) @ -avg[:3, 2])
        if not focus_distance > 0:
            focus_distance = float(np.median(np.linalg.norm(m[:, :3, 3] - avg[:3, 3], axis=1))) or 1.0
    offsets = (m[:, :3, 3] - avg[:3, 3]) @ avg[:3, :3]  # [N, 3] in the mean pose's axes
    radii = np.percentile(np.abs(offsets), percentile, axis=0)
    radii = np.maximum(radii, 0.05 * focus_distance * np.array([1.0, 1.0, 0.0]))
    target = avg[:3, 3] - focus_distance * avg[:3, 2]
    up = avg[:3, 1]
    out = np.empty((n_frames, 4, 4))
    for k in range(n_frames):
        theta = 2 * math.pi * rotations * k / n_frames
        local = np.array([math.cos(theta), -math.sin(theta), -math.sin(theta * z_rate)]) * radii
        eye = avg[:3, :3] @ local + avg[:3, 3]
        out[k] = look_at(eye, target, up)
    return out
