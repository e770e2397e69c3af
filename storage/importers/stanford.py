"""Stanford range scans: a ``.conf`` file and its range-grid PLY scans.

Each scan of the Stanford 3D Scanning Repository is the output of a line-scan
triangulation scanner (Cyberware 3030 MS): ``element range_grid`` has ``num_rows`` x
``num_cols`` cells that each list 0 or 1 vertex. Measured on the bunny
(``../shared/data/stanford-bunny/README.md``): the vertex of cell ``(row, col)`` has
``x = pitch * col + pitch/2 * (row mod 2) + x0`` exactly (the scanner moves along x; odd rows
are interlaced by half a step), and every row is a ray in the plane ``x = const`` from an
axis parallel to x through ``(y, z) = axis_yz`` (0.53 mrad per row); range is the distance
from that axis. This is :class:`engine.CylindricalSensor` with ``axial="linear"`` and
``range_convention="radial"``: sensor z along the scan's x (rows of the range image),
azimuth around it (columns).

The range image is built from the grid's samples, never by rendering a mesh
(``docs/importers.md`` explains the choices):

1. **Interlace**: the image has one row per half pitch (``2 * num_cols`` rows). A sample
   sits where its grid row's parity puts it; the other half of each grid row is filled by
   linear interpolation between the row's two samples either side (0.5 mm apart), so every
   pixel is a measurement or lies on the segment between two.
2. **Azimuth**: the measured angle of each row is not linear in the row number (up to
   0.25 mrad off a line, 0.3 mm at the object), so each image row is resampled at uniform
   azimuth steps (the mean row pitch) by linear interpolation between consecutive samples at
   their measured angles.

Neither step bridges two samples whose ranges differ by more than ``max_step_m`` (default 8
column pitches; an occlusion edge): no range is invented across a jump. Poses: ``bmesh FILE
tx ty tz qx qy qz qw`` means ``x_world = R(q)^T x_scan + t``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from rangefuse.engine import CylindricalSensor, Scan

from ._ply import read_ply
from .errors import SourceError
from .options import STANFORD_MAX_STEP_PITCHES, ImportOptions, ImportResult, file_pose
from .poses import PoseFixes, numeric_lines, parse_floats, pose_from_quaternion

__all__ = ["linescan_image", "read_conf", "read_stanford"]

#: A column pitch is accepted as linear when every vertex is within this fraction of the
#: pitch of the fitted line (the bunny's are exact to 1e-17 m).
_PITCH_TOLERANCE = 0.01
#: Largest angular gap between two consecutive samples that is interpolated, in row pitches.
_MAX_ROW_GAP = 3.0
#: The sensor's max_range: this factor times the largest measured range.
_MAX_RANGE_FACTOR = 1.25


def read_conf(path: Path, fixes: PoseFixes) -> list[tuple[int, Path, np.ndarray]]:
    """The scans of a Stanford ``.conf``: ``(line, ply_path, T_W_scan)`` per ``bmesh`` line.

    ``camera`` lines are ignored; ``mesh`` lines are read like ``bmesh``.

    Raises
    ------
    SourceError
        For an unknown keyword or a malformed line, naming the file and line.
    """
    scans = []
    for number, tokens in numeric_lines(path):
        where = f"{path} line {number}"
        if tokens[0] == "camera":
            continue
        if tokens[0] not in ("bmesh", "mesh"):
            raise SourceError(f"{where}: unknown keyword {tokens[0]!r} (expected bmesh or camera)")
        if len(tokens) != 9:
            raise SourceError(
                f"{where}: expected 'bmesh FILE tx ty tz qx qy qz qw', got {len(tokens)} fields"
            )
        values = parse_floats(tokens[2:], where, 7, "tx ty tz qx qy qz qw")
        T = pose_from_quaternion(values[:3], values[3:], path, number, fixes)
        T[:3, :3] = T[:3, :3].T.copy()  # the file's rotation is applied transposed
        scans.append((number, path.parent / tokens[1], T))
    if not scans:
        raise SourceError(f"{path}: no 'bmesh' lines")
    return scans


def _grid_samples(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, bool]:
    """Vertices of the grid cells and the grid: ``(points (n, 3), rows, cols, num_rows,
    num_cols, interlaced)``."""
    ply = read_ply(path)
    if "vertex" not in ply.elements or "range_grid" not in ply.elements:
        raise SourceError(f"{path}: not a range-grid PLY (needs 'vertex' and 'range_grid')")
    vertex = ply.elements["vertex"]
    grid = ply.elements["range_grid"]
    if vertex.data is None or not {"x", "y", "z"} <= set(vertex.data.dtype.names or ()):
        raise SourceError(f"{path}: element vertex needs properties x, y, z")
    if grid.counts is None or grid.items is None:
        raise SourceError(f"{path}: element range_grid must be a list of vertex indices")
    try:
        num_rows = int(ply.obj_info["num_rows"])
        num_cols = int(ply.obj_info["num_cols"])
    except (KeyError, ValueError):
        raise SourceError(f"{path}: needs 'obj_info num_rows' and 'obj_info num_cols'") from None
    if num_rows * num_cols != grid.count or num_rows < 2 or num_cols < 2:
        raise SourceError(
            f"{path}: range_grid has {grid.count} cells, not num_rows x num_cols = "
            f"{num_rows} x {num_cols}"
        )
    interlaced = ply.obj_info.get("is_interlaced", "0") not in ("0", "")
    first = np.concatenate([[0], np.cumsum(grid.counts)[:-1]])
    cells = np.flatnonzero(grid.counts > 0)
    index = grid.items[first[cells]].astype(np.int64)  # a cell listing several: its first
    if np.any(index < 0) or np.any(index >= vertex.count):
        raise SourceError(f"{path}: range_grid refers to vertices that do not exist")
    xyz = np.stack([vertex.data[c].astype(np.float64) for c in "xyz"], axis=1)
    return xyz[index], cells // num_cols, cells % num_cols, num_rows, num_cols, interlaced


def _interpolate_gaps(
    theta: np.ndarray, rho: np.ndarray, fill: np.ndarray, max_step: float
) -> None:
    """Fill ``fill``-marked cells of rows ``k`` from rows ``k - 1`` and ``k + 1`` (in place)."""
    t0, t1 = theta[:-2], theta[2:]
    r0, r1 = rho[:-2], rho[2:]
    ok = fill[1:-1] & np.isfinite(r0) & np.isfinite(r1) & (np.abs(r1 - r0) <= max_step)
    theta[1:-1][ok] = 0.5 * (t0 + t1)[ok]
    rho[1:-1][ok] = 0.5 * (r0 + r1)[ok]


def _resample_azimuth(
    theta: np.ndarray, rho: np.ndarray, az_min: float, daz: float, width: int, max_step: float
) -> np.ndarray:
    """Ranges at uniform azimuths ``az_min + j * daz`` of each row of ``(theta, rho)`` (K, R),
    linear between consecutive samples at their measured angles; NaN where none brackets."""
    out = np.full((theta.shape[0], width), np.nan)
    t0, t1 = theta[:, :-1], theta[:, 1:]
    r0, r1 = rho[:, :-1], rho[:, 1:]
    with np.errstate(invalid="ignore"):
        ok = (
            np.isfinite(r0)
            & np.isfinite(r1)
            & (t1 > t0)
            & (t1 - t0 <= _MAX_ROW_GAP * daz)
            & (np.abs(r1 - r0) <= max_step)
        )
    k, r = np.nonzero(ok)
    t0, t1, r0, r1 = t0[k, r], t1[k, r], r0[k, r], r1[k, r]
    j_lo = np.ceil((t0 - az_min) / daz).astype(np.int64)
    j_hi = np.floor((t1 - az_min) / daz).astype(np.int64)
    for step in range(int(math.ceil(_MAX_ROW_GAP)) + 1):
        j = j_lo + step
        m = (j <= j_hi) & (j >= 0) & (j < width)
        az = az_min + j[m] * daz
        w = (az - t0[m]) / (t1[m] - t0[m])
        out[k[m], j[m]] = r0[m] + w * (r1[m] - r0[m])
    return out


def _column_pitch(
    points: np.ndarray, rows: np.ndarray, cols: np.ndarray, where: str
) -> tuple[float, float, bool]:
    """The grid's column pitch and first x, measured from the points (x steps linearly with
    the column), and whether odd rows are shifted by half a pitch (interlaced)."""
    A = np.stack([cols, rows % 2, np.ones_like(cols)], axis=1).astype(np.float64)
    (pitch, shift, x0), *_ = np.linalg.lstsq(A, points[:, 0], rcond=None)
    residual = float(np.max(np.abs(A @ (pitch, shift, x0) - points[:, 0])))
    if not pitch > 0.0 or residual > _PITCH_TOLERANCE * pitch:
        raise SourceError(
            f"{where}: x does not step linearly with the grid column (pitch {pitch * 1e3:.4g} mm, "
            f"residual {residual * 1e3:.3g} mm): not a line-scan range grid"
        )
    if abs(shift - pitch / 2) <= _PITCH_TOLERANCE * pitch:
        return pitch, x0, True
    if abs(shift) <= _PITCH_TOLERANCE * pitch:
        return pitch, x0, False
    raise SourceError(
        f"{where}: odd rows are shifted by {shift * 1e3:.4g} mm, neither 0 nor half the "
        f"column pitch ({pitch * 1e3:.4g} mm)"
    )


def _fan(
    points: np.ndarray, rows: np.ndarray, ay: float, az: float, where: str
) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """Each point's angle about the axis and distance from it, the row angles' fit
    ``theta = alpha + beta * row``, and the sign that makes the angle grow with the row."""
    sign = 1.0
    x_S = az - points[:, 2]
    if np.median(x_S) <= 0.0:
        raise SourceError(
            f"{where}: the points are not in front of (below z = {az:g}) the scanner axis "
            f"(y, z) = ({ay:g}, {az:g}); wrong axis?"
        )
    theta = np.arctan2(points[:, 1] - ay, x_S)
    rho = np.hypot(points[:, 1] - ay, x_S)
    alpha, beta = np.polynomial.polynomial.polyfit(rows.astype(np.float64), theta, 1)
    if beta < 0.0:  # turn the sensor frame half a turn about its x axis: azimuth grows
        sign = -1.0
        theta, alpha, beta = -theta, -alpha, -beta
    if not beta > 0.0:
        raise SourceError(f"{where}: the rows do not fan out around the axis")
    return theta, rho, float(alpha), float(beta), sign


def linescan_image(
    points: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    num_rows: int,
    num_cols: int,
    axis_yz_m: tuple[float, float],
    max_step_m: float | None,
    where: str,
) -> tuple[CylindricalSensor, np.ndarray, np.ndarray, bool]:
    """The range image of one line-scan range grid.

    Parameters
    ----------
    points : array (n, 3)
        Scan-frame vertices of the grid cells, metres.
    rows, cols : int arrays (n,)
        Their grid cells.
    num_rows, num_cols : int
        Grid size.
    axis_yz_m : (y, z)
        Rotation axis of the scanner (parallel to x) in the scan frame.
    max_step_m : float or None
        Largest range step bridged by interpolation; None for
        :data:`~storage.importers.options.STANFORD_MAX_STEP_PITCHES` column pitches.
    where : str
        File name for messages.

    Returns
    -------
    sensor : CylindricalSensor
        ``axial="linear"``, ``range_convention="radial"``; one image row per half pitch when
        interlaced (else per pitch), one column per mean row pitch of azimuth.
    range_m : float32 array (H, W)
        Distance from the axis; NaN where no sample lies.
    T_scan_S : array (4, 4)
        The sensor's pose in the scan frame.
    interlaced : bool
        Whether the grid's odd rows are shifted by half a pitch (measured from the data).
    """
    if len(points) < 3:
        raise SourceError(f"{where}: fewer than 3 samples in the range grid")
    pitch, x0, interlaced = _column_pitch(points, rows, cols, where)
    step = pitch / 2 if interlaced else pitch
    k = 2 * cols + rows % 2 if interlaced else cols
    n_fine = 2 * num_cols if interlaced else num_cols
    if max_step_m is None:
        max_step_m = STANFORD_MAX_STEP_PITCHES * pitch
    ay, az = axis_yz_m
    theta, rho, alpha, beta, sign = _fan(points, rows, ay, az, where)
    theta_grid = np.full((n_fine, num_rows), np.nan)
    rho_grid = np.full((n_fine, num_rows), np.nan)
    theta_grid[k, rows] = theta
    rho_grid[k, rows] = rho
    if interlaced:
        kk, rr = np.mgrid[0:n_fine, 0:num_rows]
        _interpolate_gaps(theta_grid, rho_grid, (kk % 2) != (rr % 2), max_step_m)
    u0 = math.floor((np.nanmin(theta_grid) - alpha) / beta)
    u1 = math.ceil((np.nanmax(theta_grid) - alpha) / beta)
    width = max(u1 - u0 + 1, 2)
    az_min = alpha + u0 * beta
    image = _resample_azimuth(theta_grid, rho_grid, az_min, beta, width, max_step_m)
    # image row v = cy - fy * z_S with fy = 1 / step and z_S = sign * (x0 + step * k)
    if sign > 0:
        image = image[::-1]
        cy = n_fine - 1 + x0 / step
    else:
        cy = -x0 / step
    sensor = CylindricalSensor(
        width=width,
        height=n_fine,
        az_min=float(az_min),
        az_max=float(az_min + beta * (width - 1)),
        wrap=False,
        fy=float(1.0 / step),
        cy=float(cy),
        axial="linear",
        range_convention="radial",
        min_range=0.0,
        max_range=float(_MAX_RANGE_FACTOR * np.max(rho)),
    )
    T_scan_S = np.eye(4)
    T_scan_S[:3, 0] = (0.0, 0.0, -1.0)
    T_scan_S[:3, 1] = (0.0, sign, 0.0)
    T_scan_S[:3, 2] = (sign, 0.0, 0.0)
    T_scan_S[:3, 3] = (0.0, ay, az)
    return sensor, image.astype(np.float32), T_scan_S, interlaced


def _find_conf(src: Path) -> Path:
    if src.is_file():
        return src
    if not src.exists():
        raise SourceError(f"{src}: no such file or folder")
    confs = sorted(src.glob("*.conf"))
    if len(confs) != 1:
        found = ", ".join(p.name for p in confs) or "none"
        raise SourceError(f"{src}: expected one .conf file in the folder, found {found}")
    return confs[0]


def read_stanford(src: Path, options: ImportOptions) -> ImportResult:
    """Read a Stanford ``.conf`` (or a folder holding one) and its range-grid PLY scans.

    Returns
    -------
    ImportResult
        One :class:`engine.Scan` per ``bmesh`` line, named by the PLY file's stem, each with
        its own line-scan :class:`engine.CylindricalSensor` (see :func:`linescan_image`) and
        pose ``T_W_S = T_W_scan @ T_scan_S``.
    """
    conf = _find_conf(Path(src))
    fixes = PoseFixes()
    scans = read_conf(conf, fixes)
    warnings = fixes.warnings()
    items = []
    extrinsics = []
    for _line, ply_path, T_W_scan in scans[:: options.every]:
        points, rows, cols, num_rows, num_cols, header_interlaced = _grid_samples(ply_path)
        sensor, image, T_scan_S, interlaced = linescan_image(
            points,
            rows,
            cols,
            num_rows,
            num_cols,
            options.axis_yz_m,
            options.max_step_m,
            str(ply_path),
        )
        if interlaced != header_interlaced:
            warnings.append(
                f"{ply_path}: the header says is_interlaced {int(header_interlaced)}, the "
                f"vertices say {int(interlaced)}; following the vertices"
            )
        T_W_S = file_pose(T_W_scan, options) @ T_scan_S
        items.append((ply_path.stem, Scan(image, T_W_S, sensor)))
        extrinsics.append(T_scan_S)
    return ImportResult("stanford", conf, items[0][1].sensor, items, warnings, extrinsics)
