"""Writers of foreign scan formats, for the importer tests.

Each writer takes scans rendered from an analytic scene (``engine.synth``) and writes them
the way the format's own tools do: 16-bit depth PNGs (with storage's PNG writer), pose
text files, Velodyne ``.bin`` sweeps, Stanford range-grid PLYs with a ``.conf``. Nothing
here is copied from a real dataset.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from rangefuse.engine import PinholeSensor, Scan, SphericalSensor
from rangefuse.engine.synth import AnalyticScene, SceneBuilder, render
from rangefuse.storage.importers import write_png

from tests.scenes import look_at_cv, look_at_xfwd, pose

#: A small pinhole depth camera (about 67 x 53 degrees, like a Kinect's), z-depth.
CAMERA = PinholeSensor(
    width=80, height=64, fx=60.0, fy=60.0, cx=39.5, cy=31.5, range_convention="z",
    min_range=0.1, max_range=8.0,
)  # fmt: skip
#: A 16-beam LiDAR with unevenly spaced beams (denser near the horizon, as real ones).
LIDAR = SphericalSensor(
    width=360,
    height=16,
    az_min=-math.pi,
    az_max=math.pi,
    wrap=True,
    elevations=tuple(float(e) for e in np.radians(10.0 - 35.0 * np.linspace(0, 1, 16) ** 1.4)),
    max_range=30.0,
)


def room_scene() -> AnalyticScene:
    """A closed 6 x 5 x 2.8 m room (walls, floor, ceiling) with furniture: big planes."""
    b = SceneBuilder()
    hx, hy, h, t = 3.0, 2.5, 2.8, 0.1
    b.add_box((0.0, 0.0, -0.5 * t), (2 * hx + 2 * t, 2 * hy + 2 * t, t))  # floor
    b.add_box((0.0, 0.0, h + 0.5 * t), (2 * hx + 2 * t, 2 * hy + 2 * t, t))  # ceiling
    for s in (-1.0, 1.0):
        b.add_box((s * (hx + 0.5 * t), 0.0, 0.5 * h), (t, 2 * hy, h))
        b.add_box((0.0, s * (hy + 0.5 * t), 0.5 * h), (2 * hx, t, h))
    b.add_box((1.2, 0.8, 0.4), (1.0, 0.6, 0.8), 0.3)
    b.add_sphere((-1.0, -1.2, 0.5), 0.5)
    b.add_cylinder((-1.8, 1.4, 0.0), (-1.8, 1.4, 2.0), 0.2)
    return b.build()


def camera_poses(n: int) -> list[np.ndarray]:
    """A camera 1.3 m up, turning 12 degrees per frame while it walks a small circle."""
    out = []
    for k in range(n):
        a = math.radians(12.0 * k)
        eye = np.array([0.4 * math.cos(a), 0.4 * math.sin(a), 1.3])
        target = eye + np.array([math.cos(a + 0.6), math.sin(a + 0.6), -0.25])
        out.append(look_at_cv(eye, target))
    return out


def lidar_poses(n: int) -> list[np.ndarray]:
    """A LiDAR 1.2 m up, driving along x and turning slowly."""
    out = []
    for k in range(n):
        eye = np.array([-1.5 + 0.6 * k, 0.3 * math.sin(k), 1.2])
        yaw = 0.15 * k
        out.append(look_at_xfwd(eye, eye + np.array([math.cos(yaw), math.sin(yaw), 0.0])))
    return out


def render_scans(scene: AnalyticScene, sensor, poses: Sequence[np.ndarray]) -> list[Scan]:
    return [Scan(render(scene, sensor, T), T, sensor) for T in poses]


def depth_raw(range_m: np.ndarray, scale_m: float) -> np.ndarray:
    """16-bit depth in units of ``scale_m``; 0 where there is no finite measurement."""
    with np.errstate(invalid="ignore"):
        raw = np.where(np.isfinite(range_m), np.rint(range_m / scale_m), 0)
    return np.clip(raw, 0, 65534).astype(np.uint16)


def matrix_text(M: np.ndarray, digits: int = 17) -> str:
    return "\n".join(" ".join(f"{x:.{digits}g}" for x in row) for row in np.atleast_2d(M)) + "\n"


def quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (qx, qy, qz, qw) of a rotation matrix (Shepperd's method)."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    return np.array(q)


# --- RGB-D ------------------------------------------------------------------------------------


def write_7scenes(
    root: Path, scans: Sequence[Scan], scale_m: float = 0.001, poses: Sequence | None = None
) -> None:
    root.mkdir(parents=True, exist_ok=True)
    s = scans[0].sensor
    K = np.array([[s.fx, 0.0, s.cx], [0.0, s.fy, s.cy], [0.0, 0.0, 1.0]])
    (root / "camera-intrinsics.txt").write_text(matrix_text(K))
    for k, scan in enumerate(scans):
        write_png(root / f"frame-{k:06d}.depth.png", depth_raw(scan.range_m, scale_m))
        T = scan.T_W_S if poses is None else poses[k]
        (root / f"frame-{k:06d}.pose.txt").write_text(matrix_text(T))


def tum_stamps(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Depth timestamps at 30 Hz and ground-truth ones at 100 Hz, 3 ms off."""
    depth = 1305031102.0 + np.arange(n) / 30.0
    gt = np.arange(depth[0] - 0.05, depth[-1] + 0.05, 0.01) + 0.003
    return depth, gt


def write_tum(root: Path, scans: Sequence[Scan], depth_stamps: np.ndarray) -> None:
    """Depth frames, and ground truth at 100 Hz: the true pose at the ground-truth stamp
    nearest each depth frame, the same pose repeated at the other stamps nearby."""
    (root / "depth").mkdir(parents=True, exist_ok=True)
    lines = ["# depth maps", "# file: 'synthetic'", "# timestamp filename"]
    for stamp, scan in zip(depth_stamps, scans, strict=True):
        name = f"depth/{stamp:.6f}.png"
        write_png(root / name, depth_raw(scan.range_m, 1.0 / 5000.0))
        lines.append(f"{stamp:.6f} {name}")
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    _, gt_stamps = tum_stamps(len(scans))
    gt = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for stamp in gt_stamps:
        k = int(np.argmin(np.abs(depth_stamps - stamp)))
        T = scans[k].T_W_S
        q = quaternion_xyzw(T[:3, :3])
        gt.append(f"{stamp:.4f} " + " ".join(f"{x:.9f}" for x in (*T[:3, 3], *q)))
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")


def write_redwood(root: Path, scans: Sequence[Scan]) -> None:
    (root / "depth").mkdir(parents=True, exist_ok=True)
    log = []
    for k, scan in enumerate(scans):
        write_png(root / "depth" / f"{k:06d}.png", depth_raw(scan.range_m, 0.001))
        log.append(f"{k} {k} {k + 1}\n" + matrix_text(scan.T_W_S, 12))
    (root / "trajectory.log").write_text("".join(log))


# --- KITTI ------------------------------------------------------------------------------------

#: Velodyne-to-camera: the camera frame (x right, y down, z forward) of a forward-looking
#: Velodyne (x forward, y left, z up), slightly offset, as KITTI's calibration.
TR_VELO_TO_CAM = pose(
    np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]),
    np.array([-0.004, -0.076, -0.27]),
)


def write_kitti(root: Path, scans: Sequence[Scan], cam_poses: Sequence | None = None) -> None:
    """``velodyne/NNNNNN.bin`` from each scan's measured points, ``calib.txt`` with ``Tr``
    and ``poses.txt`` with the camera poses ``T_W_velo @ inv(Tr)``."""
    (root / "velodyne").mkdir(parents=True, exist_ok=True)
    lines = []
    for k, scan in enumerate(scans):
        v, u = np.nonzero(np.isfinite(scan.range_m))
        p = scan.sensor.unproject(u, v, scan.range_m[v, u])
        sweep = np.concatenate([p, np.full((len(p), 1), 0.5)], axis=1).astype("<f4")
        sweep.tofile(root / "velodyne" / f"{k:06d}.bin")
        T_cam = scan.T_W_S @ np.linalg.inv(TR_VELO_TO_CAM) if cam_poses is None else cam_poses[k]
        lines.append(" ".join(f"{x:.12e}" for x in T_cam[:3].ravel()))
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    P0 = "P0: 7.18e+02 0 6.07e+02 0 0 7.18e+02 1.85e+02 0 0 0 1 0"
    Tr = "Tr: " + " ".join(f"{x:.12e}" for x in TR_VELO_TO_CAM[:3].ravel())
    (root / "calib.txt").write_text(f"{P0}\n{Tr}\n")


# --- Stanford ---------------------------------------------------------------------------------

#: A line-scan grid like the Cyberware's, coarser: 2 mm column pitch with interlaced odd
#: rows, rows fanning out by 1.5 mrad (with a slight curvature, as measured on the bunny)
#: from an axis 1.37 m above the object.
AXIS_YZ = (0.1748, 1.3731)
PITCH = 0.002
COLS, ROWS = 48, 72


def row_angles(descending: bool = False) -> np.ndarray:
    """Angle of each row's ray about the axis, from the axis's -z direction towards +y."""
    r = np.arange(ROWS)
    theta = -0.165 + 0.0015 * r + 2e-7 * (r - ROWS / 2) ** 2
    return theta[::-1].copy() if descending else theta


def linescan_grid(
    scene: AnalyticScene, T_W_scan: np.ndarray, interlaced: bool = True, descending: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast the scanner's rays into the scene: ``(points_scan (n, 3), rows, cols)``."""
    r, c = np.mgrid[0:ROWS, 0:COLS]
    x = PITCH * c + (0.5 * PITCH * (r % 2) if interlaced else 0.0) - 0.5 * PITCH * COLS
    theta = row_angles(descending)[r]
    ay, az = AXIS_YZ
    origins = np.stack([x, np.full_like(x, ay), np.full_like(x, az)], axis=-1).reshape(-1, 3)
    dirs = np.stack([np.zeros_like(theta), np.sin(theta), -np.cos(theta)], axis=-1).reshape(-1, 3)
    R, t = T_W_scan[:3, :3], T_W_scan[:3, 3]
    hit = scene.cast(origins @ R.T + t, dirs @ R.T)
    ok = np.isfinite(hit)
    points = origins[ok] + hit[ok, None] * dirs[ok]
    return points, r.ravel()[ok], c.ravel()[ok]


def write_range_ply(
    path: Path, points: np.ndarray, rows: np.ndarray, cols: np.ndarray, binary: bool,
    interlaced: bool = True,
) -> None:  # fmt: skip
    index = np.full(ROWS * COLS, -1)
    index[rows * COLS + cols] = np.arange(len(points))
    header = (
        "ply\n"
        + ("format binary_little_endian 1.0\n" if binary else "format ascii 1.0\n")
        + "obj_info is_cyberware_data 1\n"
        + f"obj_info is_interlaced {int(interlaced)}\n"
        + f"obj_info num_cols {COLS}\nobj_info num_rows {ROWS}\n"
        + f"element vertex {len(points)}\n"
        + "property float x\nproperty float y\nproperty float z\n"
        + f"element range_grid {ROWS * COLS}\n"
        + "property list uchar int vertex_indices\nend_header\n"
    )
    if binary:
        body = points.astype("<f4").tobytes()
        body += b"".join(
            b"\x00" if i < 0 else b"\x01" + np.int32(i).astype("<i4").tobytes() for i in index
        )
        path.write_bytes(header.encode() + body)
    else:
        lines = [f"{x:.7g} {y:.7g} {z:.7g}" for x, y, z in points]
        lines += ["0" if i < 0 else f"1 {i}" for i in index]
        path.write_text(header + "\n".join(lines) + "\n")


def stanford_poses() -> list[np.ndarray]:
    """Scan-to-world poses of views around the object (rotations about y, then a top view)."""
    out = []
    for k, yaw in enumerate((0.0, 40.0, 80.0, 120.0, 160.0, 200.0)):
        a = math.radians(yaw)
        R = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        out.append(pose(R, np.array([0.002 * k, -0.001 * k, 0.0015])))
    return out


def stanford_scene() -> AnalyticScene:
    """An object about 9 cm across near the origin of the scan frames, far from symmetric
    about the turntable axis (y), so that views rotated the wrong way do not agree."""
    return (
        SceneBuilder()
        .add_box((0.015, 0.0, -0.01), (0.05, 0.06, 0.025), 0.3)
        .add_sphere((-0.025, 0.01, 0.02), 0.022)
        .add_cylinder((-0.03, -0.035, -0.025), (0.03, -0.035, -0.025), 0.008)
        .build()
    )


def write_stanford(
    root: Path, poses: Sequence[np.ndarray], scene: AnalyticScene, binary: bool = False,
    conf_poses: Sequence[np.ndarray] | None = None, interlaced: bool = True,
    descending: bool = False,
) -> Path:  # fmt: skip
    """PLYs ``view{k}.ply`` and ``scans.conf`` with ``bmesh FILE t q``, where the rotation to
    apply is ``R(q)^T`` (so ``q`` is the quaternion of ``R^T``)."""
    root.mkdir(parents=True, exist_ok=True)
    lines = ["camera 0 0 0.5 0 0 0 1"]
    for k, T in enumerate(poses):
        points, rows, cols = linescan_grid(scene, T, interlaced, descending)
        write_range_ply(root / f"view{k}.ply", points, rows, cols, binary, interlaced)
        C = T if conf_poses is None else conf_poses[k]
        q = quaternion_xyzw(C[:3, :3].T)
        lines.append(f"bmesh view{k}.ply " + " ".join(f"{x:.10g}" for x in (*C[:3, 3], *q)))
    conf = root / "scans.conf"
    conf.write_text("\n".join(lines) + "\n")
    return conf
