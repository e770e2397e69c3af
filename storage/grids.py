"""The ``--grid-out`` volume file of FORMAT.md: the fused log-odds as a dense ``.npz``.

Keys: ``logodds`` (float32, X x Y x Z, NaN = unknown), ``origin`` (float64 [3], world
position of the centre of voxel [0, 0, 0]) and ``voxel_size`` (float64).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from engine import DenseGrid

from ._files import atomic_write
from .dataset import DatasetError

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
    """Read a grid written by :func:`write_grid` (or any tool following FORMAT.md)."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            logodds = npz["logodds"]
            origin = npz["origin"]
            voxel_size = float(npz["voxel_size"])
    except (KeyError, ValueError, OSError) as exc:
        raise DatasetError(f"{path}: not a grid file ({exc})") from None
    first = np.round(origin / voxel_size - 0.5).astype(np.int64)
    return DenseGrid(logodds=logodds, origin=origin, voxel_size=voxel_size, first_voxel=first)
