"""rangefuse engine: numbers in, numbers out (numpy + numba; no files, no HTTP).

Certainty fusion of registered range images after Elsner, Whitaker & Abidi (1999);
see ``METHOD.md``.
"""

# first, before any kernel is defined: the kernels' cache keyed by every engine file
from . import _numba_cache  # noqa: F401
from .allocation import tiles_touched
from .certainty import NoiseModel, decode_count, decode_logodds
from .classify import tiles_in_view
from .errors import (
    InvalidGridError,
    InvalidInputError,
    InvalidNoiseError,
    InvalidScanError,
    InvalidSensorError,
    ScanNotFoundError,
)
from .filters import FILTERS, filter_range
from .fusion import IntegrationReport, Volume, integrate_tiles
from .grid import MODES, GridSpec
from .scans import NO_RETURN, FusionParams, PreparedScan, Scan, prepare_scan
from .sensors import (
    CylindricalSensor,
    OrthographicSensor,
    PinholeSensor,
    Sensor,
    SphericalSensor,
    sensor_from_dict,
)
from .volume import DenseGrid, MemoryTileStore, TileStore, dense_logodds

__all__ = [
    "FILTERS",
    "MODES",
    "NO_RETURN",
    "CylindricalSensor",
    "DenseGrid",
    "FusionParams",
    "GridSpec",
    "IntegrationReport",
    "InvalidGridError",
    "InvalidInputError",
    "InvalidNoiseError",
    "InvalidScanError",
    "InvalidSensorError",
    "MemoryTileStore",
    "NoiseModel",
    "OrthographicSensor",
    "PinholeSensor",
    "PreparedScan",
    "Scan",
    "ScanNotFoundError",
    "Sensor",
    "SphericalSensor",
    "TileStore",
    "Volume",
    "decode_count",
    "decode_logodds",
    "dense_logodds",
    "filter_range",
    "integrate_tiles",
    "prepare_scan",
    "sensor_from_dict",
    "tiles_in_view",
    "tiles_touched",
]
