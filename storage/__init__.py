"""rangefuse storage: bytes on disk (dataset folders, grid files; the Zarr volume and the
catalog come with the storage issue). Imports ``engine``, never ``service``."""

from .dataset import (
    Dataset,
    DatasetError,
    open_dataset,
    read_scan_file,
    write_dataset,
    write_scan_file,
)
from .grids import read_grid, write_grid

__all__ = [
    "Dataset",
    "DatasetError",
    "open_dataset",
    "read_grid",
    "read_scan_file",
    "write_dataset",
    "write_grid",
    "write_scan_file",
]
