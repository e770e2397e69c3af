"""RGB-D sequences: 7-Scenes, TUM RGB-D and Redwood (Open3D ``.log``) depth PNGs and poses.

All three store depth as 16-bit greyscale PNGs of z-depth (distance along the optical
axis) in integer units, 0 for no measurement; the camera is a pinhole in the OpenCV frame
(x right, y down, z forward), and poses are camera-to-world. They differ in the units, the
intrinsics and where the poses are:

==========  =========================  ============================  =========================
format      depth units (default)      intrinsics (default)          poses
==========  =========================  ============================  =========================
7scenes     1 mm, 65535 also invalid   ``camera-intrinsics.txt``     ``frame-N.pose.txt`` 4x4
tum         1/5000 m                   525 525 319.5 239.5 (ROS)     ``groundtruth.txt``,
                                                                     ``t q`` by nearest time
redwood     1 mm                       525 525 319.5 239.5 (Open3D)  ``*.log``, 4x4 per frame
==========  =========================  ============================  =========================
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from rangefuse.engine import PinholeSensor, Scan

from ._png import read_png
from .errors import SourceError
from .options import ImportOptions, ImportResult, file_pose
from .poses import PoseFixes, numeric_lines, parse_floats, pose_from_quaternion, rigid_pose

__all__ = [
    "DEFAULT_INTRINSICS",
    "read_7scenes",
    "read_redwood",
    "read_tum",
]

#: PrimeSense / Kinect v1 defaults that TUM (for depth) and Open3D (Redwood) document.
DEFAULT_INTRINSICS = (525.0, 525.0, 319.5, 239.5)
#: Depth units in metres.
SEVEN_SCENES_SCALE_M = 0.001
TUM_SCALE_M = 1.0 / 5000.0
REDWOOD_SCALE_M = 0.001
#: Stored value that also means "no measurement" (saturated 16-bit).
INVALID_RAW = 65535
#: Default ``max_range`` of a depth camera, metres (raised when the data reach farther).
RGBD_MAX_RANGE_M = 10.0


def _depth_scans(
    frames: Sequence[tuple[str, Path, np.ndarray]],
    scale_m: float,
    intrinsics: tuple[float, float, float, float],
    options: ImportOptions,
    src: Path,
) -> tuple[PinholeSensor, list[tuple[str, Scan]]]:
    """Scans from ``(name, png_path, T_W_S)``: raw units times ``scale_m``; 0 and 65535 NaN."""
    if not frames:
        raise SourceError(f"{src}: no depth frame with a usable pose")
    depths = []
    shape = None
    for _name, path, _T in frames:
        raw = read_png(path)
        if raw.dtype != np.uint16:
            raise SourceError(f"{path}: depth must be a 16-bit PNG, got 8 bits")
        if shape is None:
            shape = raw.shape
        elif raw.shape != shape:
            raise SourceError(
                f"{path}: size {raw.shape[1]}x{raw.shape[0]} differs from the first frame's "
                f"{shape[1]}x{shape[0]}"
            )
        depth = raw.astype(np.float32) * np.float32(scale_m)
        depth[(raw == 0) | (raw == INVALID_RAW)] = np.nan
        depths.append(depth)
    assert shape is not None
    finite_max = max((float(np.nanmax(d)) for d in depths if np.isfinite(d).any()), default=0.0)
    max_range = options.max_range_m or max(RGBD_MAX_RANGE_M, 1.05 * finite_max)
    fx, fy, cx, cy = intrinsics
    sensor = PinholeSensor(
        width=shape[1],
        height=shape[0],
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        range_convention=options.range_convention or "z",
        min_range=0.0,
        max_range=max_range,
    )
    items = [(name, Scan(d, T, sensor)) for (name, _p, T), d in zip(frames, depths, strict=True)]
    return sensor, items


def _folder(src: Path) -> Path:
    if not src.exists():
        raise SourceError(f"{src}: no such folder")
    if not src.is_dir():
        raise SourceError(f"{src}: not a folder")
    return src


def _matrix_file(path: Path, rows: int, what: str) -> np.ndarray:
    """A text file holding a ``rows`` x N matrix, one row per line."""
    lines = list(numeric_lines(path))
    if len(lines) != rows:
        raise SourceError(f"{path}: expected {rows} lines ({what}), got {len(lines)}")
    values = [parse_floats(tok, f"{path} line {n}", None, what) for n, tok in lines]
    if len({len(v) for v in values}) != 1:
        raise SourceError(f"{path}: rows of different lengths ({what})")
    return np.array(values)


def _intrinsics_file(path: Path) -> tuple[float, float, float, float]:
    K = _matrix_file(path, 3, "3x3 camera matrix")
    if K.shape != (3, 3):
        raise SourceError(f"{path}: expected a 3x3 camera matrix, got {K.shape[0]}x{K.shape[1]}")
    if abs(K[0, 1]) > 1e-6 * K[0, 0] or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise SourceError(
            f"{path}: expected [[fx 0 cx] [0 fy cy] [0 0 1]] (no skew), got {K.tolist()}"
        )
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def read_7scenes(src: Path, options: ImportOptions) -> ImportResult:
    """A 7-Scenes sequence folder: ``frame-NNNNNN.depth.png`` (16-bit millimetres, 0 and
    65535 invalid), ``frame-NNNNNN.pose.txt`` (4x4 camera-to-world) and
    ``camera-intrinsics.txt`` (3x3) unless ``options.intrinsics`` is given."""
    src = _folder(src)
    pngs = sorted(src.glob("frame-*.depth.png"))
    if not pngs:
        hint = " (7-Scenes keeps them in seq-NN/ folders)" if any(src.glob("seq-*")) else ""
        raise SourceError(f"{src}: no frame-*.depth.png files{hint}")
    intrinsics = options.intrinsics
    if intrinsics is None:
        path = src / "camera-intrinsics.txt"
        if not path.exists():
            raise SourceError(
                f"{path}: missing; give --intrinsics FX FY CX CY (the 7-Scenes Kinect: "
                "585 585 320 240)"
            )
        intrinsics = _intrinsics_file(path)
    warnings: list[str] = []
    fixes = PoseFixes()
    frames = []
    for png in pngs[:: options.every]:
        name = png.name[: -len(".depth.png")]
        pose_path = png.with_name(f"{name}.pose.txt")
        if not pose_path.exists():
            raise SourceError(f"{pose_path}: missing (the pose of {png.name})")
        M = _matrix_file(pose_path, 4, "4x4 camera-to-world pose")
        if not np.all(np.isfinite(M)):
            warnings.append(f"{pose_path}: pose is not finite (tracking lost?); frame skipped")
            continue
        frames.append((name, png, file_pose(rigid_pose(M, pose_path, 1, fixes), options)))
    scale = options.depth_scale_m or SEVEN_SCENES_SCALE_M
    sensor, items = _depth_scans(frames, scale, intrinsics, options, src)
    return ImportResult("7scenes", src, sensor, items, fixes.warnings() + warnings)


def _read_groundtruth(path: Path, fixes: PoseFixes) -> tuple[np.ndarray, list[np.ndarray]]:
    stamps = []
    poses = []
    for number, tokens in numeric_lines(path):
        where = f"{path} line {number}"
        values = parse_floats(tokens, where, 8, "timestamp tx ty tz qx qy qz qw")
        stamps.append(values[0])
        poses.append(pose_from_quaternion(values[1:4], values[4:8], path, number, fixes))
    if not stamps:
        raise SourceError(f"{path}: no poses")
    return np.array(stamps), poses


def read_tum(src: Path, options: ImportOptions) -> ImportResult:
    """A TUM RGB-D sequence folder: ``depth.txt`` (``timestamp filename`` per line),
    the depth PNGs it names (16-bit, 5000 units per metre), and ``groundtruth.txt``
    (``timestamp tx ty tz qx qy qz qw``, camera-to-world) or ``options.trajectory``.

    Each depth frame takes the pose with the nearest timestamp; frames with none within
    ``options.tolerance_s`` are skipped (with a warning that counts them).
    """
    src = _folder(src)
    gt_path = options.trajectory or src / "groundtruth.txt"
    fixes = PoseFixes()
    gt_stamps, gt_poses = _read_groundtruth(Path(gt_path), fixes)
    warnings = fixes.warnings()
    order = np.argsort(gt_stamps, kind="stable")
    gt_stamps = gt_stamps[order]
    depth_list = src / "depth.txt"
    entries = []
    for number, tokens in numeric_lines(depth_list):
        where = f"{depth_list} line {number}"
        if len(tokens) != 2:
            raise SourceError(f"{where}: expected 'timestamp filename', got {len(tokens)} fields")
        stamp = parse_floats(tokens[:1], where, 1, "timestamp")[0]
        entries.append((stamp, src / tokens[1], where))
    if not entries:
        raise SourceError(f"{depth_list}: no depth frames listed")
    frames = []
    skipped = []
    for stamp, png, _where in entries[:: options.every]:
        i = int(np.searchsorted(gt_stamps, stamp))
        candidates = [j for j in (i - 1, i) if 0 <= j < len(gt_stamps)]
        j = min(candidates, key=lambda c: abs(gt_stamps[c] - stamp))
        if abs(gt_stamps[j] - stamp) > options.tolerance_s:
            skipped.append((stamp, abs(gt_stamps[j] - stamp)))
            continue
        frames.append((png.stem, png, file_pose(gt_poses[int(order[j])], options)))
    if skipped:
        first, gap = skipped[0]
        warnings.append(
            f"{depth_list}: {len(skipped)} of {len(entries[:: options.every])} depth frames have "
            f"no pose in {gt_path} within {options.tolerance_s:g} s and were skipped (first: "
            f"{first:.6f}, nearest pose {gap:.3f} s away)"
        )
    if not frames:
        raise SourceError(
            f"{depth_list}: no depth frame has a pose within {options.tolerance_s:g} s "
            f"(give --tolerance S, or check that {gt_path} is this sequence's ground truth)"
        )
    scale = options.depth_scale_m or TUM_SCALE_M
    sensor, items = _depth_scans(
        frames, scale, options.intrinsics or DEFAULT_INTRINSICS, options, src
    )
    return ImportResult("tum", src, sensor, items, warnings)


def read_log(path: Path, fixes: PoseFixes) -> list[np.ndarray]:
    """Poses of an Open3D / Redwood ``.log`` trajectory: per frame a metadata line of three
    integers, then four rows of the 4x4 camera-to-world matrix."""
    lines = list(numeric_lines(path))
    if len(lines) % 5:
        raise SourceError(
            f"{path}: {len(lines)} lines, not a multiple of 5 (a metadata line and 4 matrix "
            "rows per frame)"
        )
    poses = []
    for start in range(0, len(lines), 5):
        number, meta = lines[start]
        if len(meta) != 3 or not all(tok.lstrip("-").isdigit() for tok in meta):
            raise SourceError(f"{path} line {number}: expected 3 integers (frame metadata)")
        rows = [
            parse_floats(tok, f"{path} line {n}", 4, "a row of the 4x4 pose")
            for n, tok in lines[start + 1 : start + 5]
        ]
        poses.append(rigid_pose(np.array(rows), path, lines[start + 1][0], fixes))
    if not poses:
        raise SourceError(f"{path}: no poses")
    return poses


def read_redwood(src: Path, options: ImportOptions) -> ImportResult:
    """A Redwood / Open3D RGB-D sequence: depth PNGs (16-bit millimetres) in ``SRC/depth/``
    (or ``SRC`` itself), in name order, and a ``.log`` trajectory in ``SRC`` (or
    ``options.trajectory``) with one pose per depth image, in the same order."""
    src = _folder(src)
    depth_dir = src / "depth" if (src / "depth").is_dir() else src
    pngs = sorted(depth_dir.glob("*.png"))
    if not pngs:
        raise SourceError(f"{depth_dir}: no depth .png files")
    log = options.trajectory
    if log is None:
        logs = sorted(src.glob("*.log"))
        if len(logs) != 1:
            found = ", ".join(p.name for p in logs) or "none"
            raise SourceError(
                f"{src}: expected one .log trajectory, found {found} (give --trajectory FILE)"
            )
        log = logs[0]
    fixes = PoseFixes()
    poses = read_log(Path(log), fixes)
    if len(poses) != len(pngs):
        raise SourceError(
            f"{log}: {len(poses)} poses for {len(pngs)} depth images in {depth_dir}; they are "
            "matched in order and must be as many"
        )
    frames = [(p.stem, p, file_pose(T, options)) for p, T in zip(pngs, poses, strict=True)][
        :: options.every
    ]
    scale = options.depth_scale_m or REDWOOD_SCALE_M
    sensor, items = _depth_scans(
        frames, scale, options.intrinsics or DEFAULT_INTRINSICS, options, src
    )
    return ImportResult("redwood", src, sensor, items, fixes.warnings())
