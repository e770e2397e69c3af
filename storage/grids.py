"""The ``--grid-out`` volume file of FORMAT.md: the fused log-odds as a dense ``.npz``.

Keys: ``logodds`` (float32, X x Y x Z, NaN = unknown), ``origin`` (float64 [3], world
position of the centre of voxel [0, 0, 0]) and ``voxel_size`` (float64).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from rangefuse.engine import DenseGrid

from ._files import atomic_write
from .dataset import DatasetError, _read_npz

__all__ = ["read_grid", "write_grid"]


def write_grid(path: str | os.PathLike[str], grid: DenseGrid) -> Path:
    """Write a dense grid atomically (a temporary file renamed into place)."""
    path = Path(path)
    logodds = np.asarray(grid.logodds, np.float32)
    origin = np.asarray(grid.origin, np.float64)
    voxel_size = np.float64(grid.voxel_size)
    atomic_write(
        path, lambda fh: np.savez(fh, logodds=logodds, origin=origin, voxel_size=voxel_size)
    )
    return path


def read_grid(path: str | os.PathLike[str]) -> DenseGrid:
    """Read a grid written by :func:`write_grid` (or any tool following FORMAT.md).

    Raises
    ------
    DatasetError
        For a file that is not a readable ``.npz``, a missing key, or a key of the wrong
        dtype or shape; the message names the file and the key.
    """
    where = str(path)
    arrays = _read_npz(Path(path), where, ("logodds", "origin", "voxel_size"))
    logodds = arrays["logodds"]
    origin = arrays["origin"]
    voxel_size_arr = arrays["voxel_size"]
    if logodds.dtype.kind != "f" or logodds.ndim != 3:
        raise DatasetError(
            f"{where}: logodds: must be a 3-D float array, got dtype {logodds.dtype} "
            f"and shape {logodds.shape}"
        )
    if origin.dtype.kind not in "fiu" or origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise DatasetError(
            f"{where}: origin: must be 3 finite numbers, got dtype {origin.dtype} "
            f"and shape {origin.shape}"
        )
    if voxel_size_arr.dtype.kind not in "fiu" or voxel_size_arr.shape != ():
        raise DatasetError(f"{where}: voxel_size: must be a number, got {voxel_size_arr!r}")
    voxel_size = float(voxel_size_arr)
    if not (np.isfinite(voxel_size) and voxel_size > 0.0):
        raise DatasetError(f"{where}: voxel_size: must be positive, got {voxel_size}")
    origin = origin.astype(np.float64)
    first = np.round(origin / voxel_size - 0.5).astype(np.int64)
    return DenseGrid(logodds=logodds, origin=origin, voxel_size=voxel_size, first_voxel=first)
