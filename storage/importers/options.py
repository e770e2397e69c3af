"""What an importer is told (:class:`ImportOptions`) and what it returns (:class:`ImportResult`)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rangefuse.engine import InvalidInputError, Scan, Sensor

__all__ = [
    "STANFORD_AXIS_YZ_M",
    "STANFORD_MAX_STEP_PITCHES",
    "ImportOptions",
    "ImportResult",
    "file_pose",
]

#: The Stanford bunny scanner's rotation axis (parallel to x) in each scan's frame, metres:
#: fitted over all 362k points of the ten scans (``../shared/data/stanford-bunny/README.md``).
STANFORD_AXIS_YZ_M = (0.1748, 1.3731)
#: Two neighbouring samples of a range grid are joined by interpolation only when their
#: ranges differ by at most this many column pitches: across a larger step (an occlusion
#: edge) no pixel is invented. 8 pitches (4 mm on the bunny's scanner) is a surface at 83
#: degrees to the line of sight.
STANFORD_MAX_STEP_PITCHES = 8.0
#: Velodyne HDL-64E (KITTI): beams and azimuth columns of one turn.
KITTI_BEAMS = 64
KITTI_COLUMNS = 2048
#: TUM's associate.py matches depth frames to poses within 20 ms.
TUM_TOLERANCE_S = 0.02


def _positive(name: str, value: Any, integer: bool = False) -> None:
    if value is None:
        return
    ok_type = (int,) if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, ok_type):
        raise InvalidInputError(
            name, f"must be a {'whole ' if integer else ''}number, got {value!r}"
        )
    if not (math.isfinite(value) and value > 0):
        raise InvalidInputError(name, f"must be positive, got {value!r}")


@dataclass(frozen=True)
class ImportOptions:
    """Options of the importers; ``None`` means the format's own default.

    Parameters
    ----------
    depth_scale_m : float or None
        Metres per stored depth unit (7-Scenes and Redwood 0.001, TUM 1/5000).
    intrinsics : (fx, fy, cx, cy) or None
        Pinhole intrinsics in pixels, replacing the source's (or the format's default).
    max_range_m : float or None
        The sensor's ``max_range`` (default per format).
    tolerance_s : float
        TUM: largest time difference between a depth frame and its pose.
    trajectory : Path or None
        The pose file when it is not where the format puts it (Redwood ``.log``, KITTI poses,
        TUM ground truth).
    every : int
        Take every n-th frame of a sequence.
    beams, columns : int
        KITTI: rows (laser beams) and azimuth columns of the spherical range images.
    axis_yz_m : (y, z)
        Stanford: the scanner's rotation axis in each scan's frame.
    max_step_m : float or None
        Stanford: largest range step bridged when resampling the range grid (default
        :data:`STANFORD_MAX_STEP_PITCHES` column pitches).
    range_convention : {"z", "ray"} or None
        RGB-D formats: what the depth images hold (default ``"z"``, z-depth).
    invert_poses : bool
        The source's poses are world-to-sensor: invert each (before composing it with a
        fixed extrinsic such as KITTI's ``Tr``).
    checks : bool
        Run the sanity checks of :mod:`storage.importers.checks` (warnings only).
    """

    depth_scale_m: float | None = None
    intrinsics: tuple[float, float, float, float] | None = None
    max_range_m: float | None = None
    tolerance_s: float = TUM_TOLERANCE_S
    trajectory: Path | None = None
    every: int = 1
    beams: int = KITTI_BEAMS
    columns: int = KITTI_COLUMNS
    axis_yz_m: tuple[float, float] = STANFORD_AXIS_YZ_M
    max_step_m: float | None = None
    range_convention: str | None = None
    invert_poses: bool = False
    checks: bool = True

    def __post_init__(self) -> None:
        _positive("depth_scale", self.depth_scale_m)
        _positive("max_range", self.max_range_m)
        _positive("tolerance", self.tolerance_s)
        _positive("every", self.every, integer=True)
        _positive("beams", self.beams, integer=True)
        _positive("columns", self.columns, integer=True)
        _positive("max_step", self.max_step_m)
        if self.beams < 2 or self.columns < 2:
            raise InvalidInputError("beams", "beams and columns must be at least 2")
        if self.intrinsics is not None:
            if len(self.intrinsics) != 4:
                raise InvalidInputError("intrinsics", "needs four numbers: fx fy cx cy")
            fx, fy, cx, cy = self.intrinsics
            _positive("intrinsics.fx", fx)
            _positive("intrinsics.fy", fy)
            if not (math.isfinite(cx) and math.isfinite(cy)):
                raise InvalidInputError("intrinsics", "cx and cy must be finite")
        if self.range_convention not in (None, "z", "ray"):
            raise InvalidInputError(
                "range_convention", f"must be 'z' or 'ray', got {self.range_convention!r}"
            )
        if len(self.axis_yz_m) != 2 or not all(math.isfinite(a) for a in self.axis_yz_m):
            raise InvalidInputError("axis", "needs two finite numbers: y z")


@dataclass
class ImportResult:
    """Scans read from a foreign format.

    Attributes
    ----------
    kind : str
        The format.
    source : Path
    sensor : Sensor
        The sensor shared by the scans (the first scan's when they differ: each scan carries
        its own, and ``write_dataset`` stores those that differ in the scan files).
    items : list of (str, Scan)
        Scans in order, named as in the source (frame number or file stem).
    extrinsics : list of arrays (4, 4) or None
        Each scan's sensor pose in the frame whose pose the source gives (KITTI's ``Tr``, a
        Stanford scanner in its scan frame); None when the source gives sensor poses.
    warnings : list of str
        What the sanity checks and the readers found (snapped rotations, skipped frames,
        a depth scale or range convention or pose direction that looks wrong), with evidence.
    """

    kind: str
    source: Path
    sensor: Sensor
    items: list[tuple[str, Scan]]
    warnings: list[str] = field(default_factory=list)
    extrinsics: list[np.ndarray] | None = None

    def scans(self) -> Iterator[tuple[str, Scan]]:
        """Yield ``(name, Scan)`` in order (the interface of :class:`storage.Dataset`)."""
        return iter(self.items)

    def __len__(self) -> int:
        return len(self.items)


def file_pose(T: np.ndarray, options: ImportOptions) -> np.ndarray:
    """A pose as read from a source file, inverted when ``options.invert_poses``."""
    return np.linalg.inv(T) if options.invert_poses else T
