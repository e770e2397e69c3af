"""Importers: range scans in the formats of common sensors and datasets, read into
:class:`engine.Scan` objects (and written as FORMAT.md dataset folders by
``rangefuse import``). See ``docs/importers.md``.

===========  ===================================================================
kind         source
===========  ===================================================================
stanford     a ``.conf`` with range-grid PLY scans (line-scan cylindrical sensor)
7scenes      ``frame-N.depth.png`` + ``frame-N.pose.txt`` + ``camera-intrinsics.txt``
tum          TUM RGB-D: ``depth.txt``, ``depth/*.png``, ``groundtruth.txt``
redwood      depth PNGs + an Open3D / Redwood ``.log`` trajectory
kitti        Velodyne ``.bin`` sweeps + ``poses.txt`` + ``calib.txt`` (spherical sensor)
===========  ===================================================================
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from rangefuse.engine import InvalidInputError

from ._png import decode_png, encode_png, read_png, write_png
from .checks import run_checks
from .errors import SourceError
from .kitti import estimate_beam_elevations, read_kitti
from .options import ImportOptions, ImportResult
from .poses import PoseFixes, snap_rotation
from .rgbd import read_7scenes, read_redwood, read_tum
from .stanford import read_stanford

__all__ = [
    "KINDS",
    "ImportOptions",
    "ImportResult",
    "PoseFixes",
    "SourceError",
    "decode_png",
    "encode_png",
    "estimate_beam_elevations",
    "read_7scenes",
    "read_kitti",
    "read_png",
    "read_redwood",
    "read_source",
    "read_stanford",
    "read_tum",
    "snap_rotation",
    "write_png",
]

_READERS: dict[str, Callable[[Path, ImportOptions], ImportResult]] = {
    "stanford": read_stanford,
    "7scenes": read_7scenes,
    "tum": read_tum,
    "redwood": read_redwood,
    "kitti": read_kitti,
}
#: The formats :func:`read_source` reads.
KINDS: tuple[str, ...] = tuple(_READERS)


def read_source(
    kind: str, src: str | os.PathLike[str], options: ImportOptions | None = None
) -> ImportResult:
    """Read scans in a foreign format.

    Parameters
    ----------
    kind : str
        One of :data:`KINDS`.
    src : path-like
        The source folder (Stanford: the ``.conf`` file or its folder).
    options : ImportOptions or None

    Returns
    -------
    ImportResult
        Scans with sensors and sensor-to-world poses, and warnings: what the readers noticed
        (snapped rotations, skipped frames) and, unless ``options.checks`` is off, what the
        sanity checks found (:mod:`storage.importers.checks`).

    Raises
    ------
    SourceError
        For a source that cannot be read; the message names the file (and line).
    engine.InvalidInputError
        For an unknown ``kind``.
    """
    if kind not in _READERS:
        raise InvalidInputError(
            "kind", f"unknown format {kind!r}; expected one of {', '.join(KINDS)}"
        )
    options = options if options is not None else ImportOptions()
    result = _READERS[kind](Path(src), options)
    if options.checks:
        result.warnings += run_checks(kind, result.items, result.extrinsics)
    return result
