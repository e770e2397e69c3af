"""Helpers shared by the tests of the synthetic scenes (tests/test_synth_*.py)."""

from __future__ import annotations

import numpy as np
from rangefuse.engine import Scan


def to_world(T: np.ndarray, p_S: np.ndarray) -> np.ndarray:
    return p_S @ T[:3, :3].T + T[:3, 3]


def surface_points(scan: Scan) -> np.ndarray:
    """World points of the finite pixels, unprojected in the sensor's range convention."""
    v, u = np.nonzero(np.isfinite(scan.range_m))
    p_S = scan.sensor.unproject(u, v, scan.range_m[v, u].astype(np.float64))
    return to_world(scan.T_W_S, p_S)
