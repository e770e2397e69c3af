"""KITTI odometry: Velodyne ``.bin`` sweeps, ``poses.txt`` and ``calib.txt``.

A sweep is ``float32 (n, 4)``: x, y, z (metres, Velodyne frame: x forward, y left, z up)
and reflectance. ``poses.txt`` holds one 3x4 pose per line, frame ``i`` on line ``i``, of
the left grey camera (``cam0``) in the frame of the sequence's first ``cam0``;
``calib.txt``'s ``Tr`` line is the Velodyne-to-``cam0`` transform, so the scan pose is
``T_W_velo = T_W_cam0 @ Tr``.

Each sweep becomes a spherical range image: one column per ``360 / columns`` degrees of
azimuth (a full turn, ``wrap``) and one row per laser beam. The beams of a real LiDAR are not
evenly spaced (the HDL-64E has two blocks of 32 with different spacing), so the beam
elevations are estimated from the data (:func:`estimate_beam_elevations`) and written as
the sensor's ``elevations`` table. A point goes to its azimuth's column and the beam
nearest its elevation; when several land in one pixel the nearest wins; empty pixels are
NaN (invalid: an empty pixel may be a dropout as well as open sky).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from rangefuse.engine import Scan, SphericalSensor

from .errors import SourceError
from .options import ImportOptions, ImportResult, file_pose
from .poses import PoseFixes, numeric_lines, parse_floats, rigid_pose

__all__ = ["estimate_beam_elevations", "read_kitti", "spherical_image"]

#: Points closer than this are left out of the beam estimate: the lasers of a HDL-64E sit
#: centimetres apart, so a near point's elevation seen from the sensor origin is off (its
#: lowest beam still meets flat ground 3.7 m away).
BEAM_MIN_RANGE_M = 2.0
#: Histogram bin for the elevation estimate, radians (0.006 degrees).
_BEAM_BIN_RAD = 1e-4
#: Bins holding less than this fraction of the points are ignored as strays.
_BEAM_STRAY_FRACTION = 2e-5
#: At most this many sweeps are pooled for the beam estimate.
_BEAM_SWEEPS = 20
#: The HDL-64E reaches 120 m.
KITTI_MAX_RANGE_M = 120.0


def estimate_beam_elevations(elevation_rad: np.ndarray, beams: int, where: str) -> np.ndarray:
    """Elevations of ``beams`` laser beams from point elevations (radians), top beam first.

    The points of one beam cluster tightly around its elevation; the clusters are separated
    by gaps. The sorted elevations are binned (0.006 degree bins, bins with a negligible share
    of the points ignored as strays) and cut at the ``beams - 1`` widest gaps between occupied
    bins; each beam's elevation is the median of its cluster.

    Raises
    ------
    SourceError
        When the data do not show ``beams`` clusters (fewer occupied groups, or the cut is
        ambiguous: the widest gap not cut is nearly as wide as the narrowest one cut).
    """
    el = np.sort(np.asarray(elevation_rad, np.float64))
    if el.size < beams:
        raise SourceError(f"{where}: {el.size} points cannot show {beams} beams")
    bins = np.floor((el - el[0]) / _BEAM_BIN_RAD).astype(np.int64)
    ids, counts = np.unique(bins, return_counts=True)
    occupied = ids[counts >= max(1.0, _BEAM_STRAY_FRACTION * el.size)]
    if occupied.size < beams:
        raise SourceError(
            f"{where}: the point elevations form fewer than {beams} groups; is --beams right?"
        )
    gaps = np.diff(occupied)
    order = np.argsort(gaps, kind="stable")[::-1]
    cut = np.sort(order[: beams - 1])
    narrowest_cut = gaps[order[beams - 2]] if beams > 1 else np.inf
    widest_uncut = gaps[order[beams - 1]] if gaps.size >= beams else 0
    if widest_uncut > 0.5 * narrowest_cut:
        raise SourceError(
            f"{where}: cannot separate {beams} beams in the point elevations (a gap of "
            f"{math.degrees(widest_uncut * _BEAM_BIN_RAD):.3f} deg within a beam against "
            f"{math.degrees(narrowest_cut * _BEAM_BIN_RAD):.3f} deg between beams); "
            "is --beams right?"
        )
    # boundaries halfway between the cut bins, as elevations
    lower = el[0] + (occupied[cut] + 1) * _BEAM_BIN_RAD
    upper = el[0] + occupied[cut + 1] * _BEAM_BIN_RAD
    edges = 0.5 * (lower + upper)
    labels = np.searchsorted(edges, el)
    centres = np.array([np.median(el[labels == b]) for b in range(beams)])
    return centres[::-1].copy()


def spherical_image(points: np.ndarray, sensor: SphericalSensor) -> np.ndarray:
    """Range image (H, W) float32 of sensor-frame points: nearest point per pixel, NaN empty."""
    assert sensor.elevations is not None
    table = np.asarray(sensor.elevations)
    rng = np.linalg.norm(points, axis=1)
    keep = rng > 0.0
    p, rng = points[keep], rng[keep]
    az = np.arctan2(p[:, 1], p[:, 0])
    el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    daz = (sensor.az_max - sensor.az_min) / sensor.width
    col = np.rint(((az - sensor.az_min) % (2.0 * math.pi)) / daz).astype(np.int64) % sensor.width
    ascending = table[::-1]
    mid = 0.5 * (ascending[1:] + ascending[:-1])
    row = sensor.height - 1 - np.searchsorted(mid, el)
    half_gap = 0.5 * np.abs(np.diff(table))
    inside = (el <= table[0] + half_gap[0]) & (el >= table[-1] - half_gap[-1])
    image = np.full(sensor.shape, np.inf)
    np.minimum.at(image, (row[inside], col[inside]), rng[inside])
    image[np.isinf(image)] = np.nan
    return image.astype(np.float32)


def _read_sweep(path: Path, scale: float) -> np.ndarray:
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise SourceError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if len(blob) % 16:
        raise SourceError(
            f"{path}: {len(blob)} bytes is not a whole number of points (16 bytes each: "
            "x y z reflectance float32)"
        )
    xyz = np.frombuffer(blob, "<f4").reshape(-1, 4)[:, :3].astype(np.float64) * scale
    return xyz[np.all(np.isfinite(xyz), axis=1)]


def _read_calib(path: Path, fixes: PoseFixes) -> np.ndarray:
    for number, tokens in numeric_lines(path):
        if tokens[0] == "Tr:":
            where = f"{path} line {number}"
            values = parse_floats(tokens[1:], where, 12, "Tr: 3x4 Velodyne-to-camera")
            return rigid_pose(values.reshape(3, 4), path, number, fixes)
    raise SourceError(f"{path}: no 'Tr:' line (the Velodyne-to-camera transform)")


def _read_poses(path: Path, fixes: PoseFixes) -> list[np.ndarray]:
    poses = []
    for number, tokens in numeric_lines(path):
        where = f"{path} line {number}"
        values = parse_floats(tokens, where, 12, "a 3x4 pose, row-major")
        poses.append(rigid_pose(values.reshape(3, 4), path, number, fixes))
    if not poses:
        raise SourceError(f"{path}: no poses")
    return poses


def read_kitti(src: Path, options: ImportOptions) -> ImportResult:
    """A KITTI odometry sequence folder: ``velodyne/NNNNNN.bin``, ``calib.txt`` and
    ``poses.txt`` (or ``options.trajectory``, e.g. ``poses/00.txt``). Sweep ``NNNNNN`` takes
    the pose on line ``NNNNNN + 1``."""
    if not src.is_dir():
        raise SourceError(f"{src}: no such folder")
    velo = src / "velodyne" if (src / "velodyne").is_dir() else src
    bins = sorted(velo.glob("*.bin"))
    if not bins:
        raise SourceError(f"{velo}: no .bin Velodyne sweeps")
    fixes = PoseFixes()
    Tr = _read_calib(src / "calib.txt", fixes)
    pose_path = Path(options.trajectory or src / "poses.txt")
    poses = _read_poses(pose_path, fixes)
    scale = options.depth_scale_m or 1.0
    frames = []
    for k, path in enumerate(bins[:: options.every]):
        index = int(path.stem) if path.stem.isdigit() else k * options.every
        if index >= len(poses):
            raise SourceError(
                f"{pose_path}: has {len(poses)} poses, none for sweep {path.name} (line "
                f"{index + 1})"
            )
        frames.append((path.stem, path, file_pose(poses[index], options) @ Tr))
    sweeps = [_read_sweep(path, scale) for _, path, _ in frames]
    pick = np.unique(np.linspace(0, len(sweeps) - 1, min(len(sweeps), _BEAM_SWEEPS)).astype(int))
    pooled = np.concatenate([sweeps[i] for i in pick])
    far = pooled[np.linalg.norm(pooled, axis=1) >= BEAM_MIN_RANGE_M]
    if len(far) < options.beams * 10:  # a small or scaled scene: use every point
        far = pooled
    elevations = estimate_beam_elevations(
        np.arctan2(far[:, 2], np.hypot(far[:, 0], far[:, 1])), options.beams, str(velo)
    )
    max_seen = max((float(np.linalg.norm(s, axis=1).max()) for s in sweeps if len(s)), default=0)
    sensor = SphericalSensor(
        width=options.columns,
        height=options.beams,
        az_min=-math.pi,
        az_max=math.pi,
        wrap=True,
        elevations=tuple(float(e) for e in elevations),
        min_range=0.0,
        max_range=options.max_range_m or max(KITTI_MAX_RANGE_M, 1.05 * max_seen),
    )
    items = [
        (name, Scan(spherical_image(points, sensor), T, sensor))
        for (name, _, T), points in zip(frames, sweeps, strict=True)
    ]
    return ImportResult("kitti", src, sensor, items, fixes.warnings(), [Tr] * len(items))
