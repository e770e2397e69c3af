"""rangefuse storage: bytes on disk (dataset folders, grid and mesh files, persistent scenes:
Zarr tiles, the scan archive and the SQLite catalog). Imports ``engine``, never ``service``."""

from .archive import ArchiveError, ScanArchive
from .catalog import Catalog, CatalogError
from .dataset import (
    Dataset,
    DatasetError,
    open_dataset,
    read_scan_file,
    write_dataset,
    write_scan_file,
)
from .grids import read_grid, write_grid
from .scene import Scene, open_scene, open_store
from .store import (
    SceneConflictError,
    Store,
    StoreError,
    StoreLockedError,
    StoreVersionError,
)
from .tile_store import ZarrTileStore
from .zarr_tiles import TileArrayError, ZarrTiles

__all__ = [
    "ArchiveError",
    "Catalog",
    "CatalogError",
    "Dataset",
    "DatasetError",
    "ScanArchive",
    "Scene",
    "SceneConflictError",
    "Store",
    "StoreError",
    "StoreLockedError",
    "StoreVersionError",
    "TileArrayError",
    "ZarrTileStore",
    "ZarrTiles",
    "open_dataset",
    "open_scene",
    "open_store",
    "read_grid",
    "read_scan_file",
    "write_dataset",
    "write_grid",
    "write_scan_file",
]
