"""Sanity checks on imported scans: the usual mistakes, found from the data.

Each check returns warnings (strings with the evidence), never raises, and stays silent
when the data give no clear sign:

- :func:`check_depth_scale`: the median range is implausible for the kind of sensor, and
  1000 times more or less would be plausible (millimetres read as metres, or the reverse).
- :func:`check_range_convention`: pinhole depth images read as z-depth and as ray range;
  a plane stays a plane only under the right one (under the wrong one it bends by up to
  ``sqrt(1 + x'^2 + y'^2) - 1``, 12 % at the edge of a 57 degree field of view), so the
  largest plane found by RANSAC holds clearly more pixels under the right reading.
- :func:`check_pose_direction`: points of one scan, moved into a neighbouring scan's frame
  with the relative pose, land on that scan's measured surface when the poses are right.
  Poses written world-to-sensor instead of sensor-to-world agree only under the inverse.

All sampling uses a fixed seed: the same data give the same warnings.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from rangefuse.engine import PinholeSensor, Scan

__all__ = [
    "PLAUSIBLE_RANGE_M",
    "check_depth_scale",
    "check_pose_direction",
    "check_range_convention",
    "run_checks",
]

#: Median measured range that is plausible for each format's sensor, metres.
PLAUSIBLE_RANGE_M = {
    "7scenes": (0.2, 15.0),
    "tum": (0.2, 15.0),
    "redwood": (0.2, 15.0),
    "kitti": (1.0, 200.0),
    "stanford": (0.05, 20.0),
}
_SENSOR_NAMES = {"kitti": "LiDAR", "stanford": "range scanner"}
#: Points sampled per scan or frame by the checks.
_SAMPLES = 4000
#: Plane test: inlier distance as a fraction of the point's range; RANSAC draws.
_PLANE_TOLERANCE = 0.01
_PLANE_DRAWS = 200
_PLANE_FRAMES = 6
#: A reading is reported when its largest plane holds at least this share of the pixels and
#: this many times the share under the declared reading.
_PLANE_MIN_SHARE = 0.2
_PLANE_RATIO = 1.5
#: Pose test: agreement within this fraction of the range; pairs compared; a pair's second
#: scan is the first one after it that moved by this angle or this share of the median
#: range (at most _PAIR_SPAN scans on).
_AGREE_TOLERANCE = 0.01
_PAIRS = 8
_PAIR_ANGLE_RAD = math.radians(3.0)
_PAIR_SHIFT = 0.03
_PAIR_SPAN = 30
#: Reported when the inverse poses agree on at least this share and this many times more.
_INVERSE_MIN_SHARE = 0.3
_INVERSE_RATIO = 2.0


def _finite_sample(scan: Scan, rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    v, u = np.nonzero(np.isfinite(scan.range_m))
    if len(u) > n:
        pick = rng.choice(len(u), n, replace=False)
        v, u = v[pick], u[pick]
    return u, v, scan.range_m[v, u].astype(np.float64)


def check_depth_scale(
    items: Sequence[tuple[str, Scan]], plausible_m: tuple[float, float], sensor_name: str
) -> list[str]:
    """Warn when the median range of all scans is outside ``plausible_m`` and 1000 times
    less (or more) would be inside: a depth scale off by 1000."""
    rng = np.random.default_rng(0)
    samples = [_finite_sample(scan, rng, _SAMPLES)[2] for _, scan in items]
    values = np.concatenate(samples) if samples else np.zeros(0)
    if values.size == 0:
        return []
    median = float(np.median(values))
    lo, hi = plausible_m
    if lo <= median <= hi:
        return []
    evidence = (
        f"the median measured range over {len(items)} scans is {median:.4g} m, implausible for "
        f"a {sensor_name} ({lo:g} to {hi:g} m)"
    )
    if lo <= median / 1000.0 <= hi:
        return [
            f"{evidence}: the depth scale looks 1000 times too large (millimetres read as "
            f"metres?); divide --depth-scale by 1000"
        ]
    if lo <= median * 1000.0 <= hi:
        return [
            f"{evidence}: the depth scale looks 1000 times too small (metres read as "
            f"millimetres?); multiply --depth-scale by 1000"
        ]
    return [f"{evidence}: check --depth-scale"]


def _largest_plane_share(points: np.ndarray, rng: np.random.Generator) -> float:
    """Share of ``points`` within _PLANE_TOLERANCE * range of the best RANSAC plane."""
    n = len(points)
    if n < 50:
        return 0.0
    draw = rng.integers(0, n, (_PLANE_DRAWS, 3))
    a, b, c = points[draw[:, 0]], points[draw[:, 1]], points[draw[:, 2]]
    normal = np.cross(b - a, c - a)
    length = np.linalg.norm(normal, axis=1)
    ok = length > 1e-12
    normal = normal[ok] / length[ok, None]
    offset = -np.einsum("ij,ij->i", normal, a[ok])
    tolerance = _PLANE_TOLERANCE * np.linalg.norm(points, axis=1)
    inliers = np.abs(points @ normal.T + offset) <= tolerance[:, None]
    return float(inliers.sum(axis=0).max() / n) if inliers.size else 0.0


def check_range_convention(items: Sequence[tuple[str, Scan]]) -> list[str]:
    """Warn when pinhole depth images look like ray range but are declared z-depth, or the
    reverse (see the module docstring)."""
    scans = [scan for _, scan in items if isinstance(scan.sensor, PinholeSensor)]
    if not scans:
        return []
    rng = np.random.default_rng(0)
    picks = np.unique(np.linspace(0, len(scans) - 1, min(len(scans), _PLANE_FRAMES)).astype(int))
    share = {"z": 0.0, "ray": 0.0}
    for i in picks:
        scan = scans[i]
        s = scan.sensor
        assert isinstance(s, PinholeSensor)
        u, v, d = _finite_sample(scan, rng, _SAMPLES)
        rays = np.stack([(u - s.cx) / s.fx, (v - s.cy) / s.fy, np.ones_like(d)], axis=1)
        as_z = rays * d[:, None]
        as_ray = as_z / np.linalg.norm(rays, axis=1, keepdims=True)
        share["z"] += _largest_plane_share(as_z, rng) / len(picks)
        share["ray"] += _largest_plane_share(as_ray, rng) / len(picks)
    declared = scans[0].sensor.range_convention
    other = "ray" if declared == "z" else "z"
    if share[other] >= _PLANE_MIN_SHARE and share[other] >= _PLANE_RATIO * share[declared]:
        names = {"z": "z-depth", "ray": "ray range (distance from the optical centre)"}
        return [
            f"the depth images look like {names[other]}, not {names[declared]}: the largest "
            f"plane in {len(picks)} frames holds {share[other]:.0%} of the pixels read as "
            f"{other} but {share[declared]:.0%} read as {declared}; if so, import with "
            f"--range-convention {other}"
        ]
    return []


def _bilinear(scan: Scan, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Range at continuous pixels (NaN outside or where a neighbour is not finite)."""
    H, W = scan.range_m.shape
    wrap = bool(getattr(scan.sensor, "wrap", False))
    ok = np.isfinite(u) & np.isfinite(v) & (v >= 0) & (v <= H - 1) & (u >= 0)
    ok &= u < W if wrap else u <= W - 1
    u = np.where(ok, u, 0.0)
    v = np.where(ok, v, 0.0)
    u0 = np.minimum(np.floor(u).astype(np.int64), W - 1 if wrap else W - 2)
    v0 = np.minimum(np.floor(v).astype(np.int64), H - 2)
    u1 = (u0 + 1) % W
    fu, fv = u - u0, v - v0
    r = scan.range_m.astype(np.float64)
    out = (
        r[v0, u0] * (1 - fu) * (1 - fv)
        + r[v0, u1] * fu * (1 - fv)
        + r[v0 + 1, u0] * (1 - fu) * fv
        + r[v0 + 1, u1] * fu * fv
    )
    return np.where(ok, out, np.nan)


def _agreement(a: Scan, b: Scan, T_a_b: np.ndarray, rng: np.random.Generator) -> float:
    """Share of b's sampled points that land on a's measured surface under ``T_a_b``."""
    u, v, d = _finite_sample(b, rng, _SAMPLES)
    if d.size == 0:
        return 0.0
    p_b = b.sensor.unproject(u, v, d)
    p_a = p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]
    ua, va, da = a.sensor.project(p_a)
    measured = _bilinear(a, ua, va)
    with np.errstate(invalid="ignore"):
        agree = np.abs(da - measured) <= _AGREE_TOLERANCE * da
    return float(np.count_nonzero(agree) / d.size)


def _rotation_angle(R: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0)))


def _partner(
    given: Sequence[np.ndarray], inverted: Sequence[np.ndarray], i: int, shift_m: float
) -> int:
    """The first scan after ``i`` that moved enough (under either pose direction)."""
    last = min(len(given) - 1, i + _PAIR_SPAN)
    for j in range(i + 1, last + 1):
        for poses in (given, inverted):
            if _rotation_angle(poses[i][:3, :3].T @ poses[j][:3, :3]) >= _PAIR_ANGLE_RAD:
                return j
            if np.linalg.norm(poses[j][:3, 3] - poses[i][:3, 3]) >= shift_m:
                return j
    return last


def check_pose_direction(
    items: Sequence[tuple[str, Scan]], extrinsics: Sequence[np.ndarray] | None = None
) -> list[str]:
    """Warn when neighbouring scans agree far better under the inverse poses (see the module
    docstring).

    ``extrinsics[k]`` is scan k's sensor pose in the frame whose pose the source file gives
    (KITTI's Velodyne in ``cam0``, a Stanford scanner in its scan frame); the mistake
    inverts the file's pose, not the extrinsic. ``None``: identities.
    """
    if len(items) < 2:
        return []
    rng = np.random.default_rng(0)
    scans = [scan for _, scan in items]
    given = [scan.T_W_S for scan in scans]
    if extrinsics is None:
        inverted = [np.linalg.inv(T) for T in given]
    else:
        inverted = [
            np.linalg.inv(T @ np.linalg.inv(E)) @ E for T, E in zip(given, extrinsics, strict=True)
        ]
    some = scans[:: max(1, len(scans) // 20)]
    ranges = np.concatenate([_finite_sample(s, rng, 500)[2] for s in some])
    shift = _PAIR_SHIFT * float(np.median(ranges)) if ranges.size else 0.0
    starts = np.unique(np.linspace(0, len(scans) - 2, min(_PAIRS, len(scans) - 1)).astype(int))
    as_given = as_inverse = 0.0
    for i in starts:
        j = _partner(given, inverted, int(i), shift)
        for poses, total in ((given, "given"), (inverted, "inverse")):
            share = _agreement(scans[i], scans[j], np.linalg.inv(poses[i]) @ poses[j], rng)
            if total == "given":
                as_given += share / len(starts)
            else:
                as_inverse += share / len(starts)
    if as_inverse >= _INVERSE_MIN_SHARE and as_inverse >= _INVERSE_RATIO * as_given:
        return [
            f"the poses look inverted (world-to-sensor given as sensor-to-world): in "
            f"{len(starts)} pairs of neighbouring scans, {as_given:.0%} of the points of one "
            f"land on the other's surface with the poses as given, {as_inverse:.0%} with their "
            "inverses; if so, import with --invert-poses"
        ]
    return []


def run_checks(
    kind: str,
    items: Sequence[tuple[str, Scan]],
    extrinsics: Sequence[np.ndarray] | None = None,
) -> list[str]:
    """The checks that apply to a format: depth scale, range convention (pinhole formats),
    pose direction (``extrinsics`` as for :func:`check_pose_direction`)."""
    warnings = check_depth_scale(
        items, PLAUSIBLE_RANGE_M[kind], _SENSOR_NAMES.get(kind, "depth camera")
    )
    warnings += check_range_convention(items)
    warnings += check_pose_direction(items, extrinsics)
    return warnings
