"""Peers the benchmarks compare against: Open3D's CPU TSDF (the optional ``bench`` extra)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from engine import PinholeSensor, Scan

#: Open3D's truncation distance in voxels and its depth cut-off (metres).
TRUNC_VOXELS = 4.0
DEPTH_MAX_M = 8.0


def import_open3d() -> Any:
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise SystemExit(
            f"open3d is not installed ({exc}); run `make bench` or "
            "`pip install -e '.[bench]'` (Debian needs libusb-1.0-0)"
        ) from None
    return o3d


class Open3DTSDF:
    """Open3D's ``VoxelBlockGrid`` TSDF integration of z-depth pinhole scans on the CPU."""

    def __init__(self, voxel_size_m: float, block_resolution: int = 8, blocks: int = 200_000):
        o3d = import_open3d()
        self._o3d = o3d
        self._o3c = o3d.core
        self.voxel_size_m = voxel_size_m
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"),
            attr_dtypes=(self._o3c.float32, self._o3c.float32),
            attr_channels=((1), (1)),
            voxel_size=voxel_size_m,
            block_resolution=block_resolution,
            block_count=blocks,
            device=self._o3c.Device("CPU:0"),
        )

    def _frame(self, scan: Scan) -> tuple[Any, Any, Any]:
        sensor = scan.sensor
        if not isinstance(sensor, PinholeSensor) or sensor.range_convention != "z":
            raise ValueError("Open3D's TSDF takes z-depth pinhole scans only")
        depth = np.where(np.isfinite(scan.range_m), scan.range_m, 0.0).astype(np.float32)
        K = np.array(
            [[sensor.fx, 0.0, sensor.cx], [0.0, sensor.fy, sensor.cy], [0.0, 0.0, 1.0]],
            np.float64,
        )
        extrinsic = np.linalg.inv(scan.T_W_S).astype(np.float64)
        o3c = self._o3c
        return (
            self._o3d.t.geometry.Image(o3c.Tensor(depth)),
            o3c.Tensor(K),
            o3c.Tensor(extrinsic),
        )

    def integrate(self, scans: Sequence[Scan]) -> float:
        """Integrate the scans; returns the seconds spent (image upload included)."""
        t0 = time.perf_counter()
        for scan in scans:
            depth, K, extrinsic = self._frame(scan)
            coords = self.vbg.compute_unique_block_coordinates(
                depth, K, extrinsic, 1.0, DEPTH_MAX_M, TRUNC_VOXELS
            )
            self.vbg.integrate(coords, depth, K, extrinsic, 1.0, DEPTH_MAX_M, TRUNC_VOXELS)
        return time.perf_counter() - t0

    #: Open3D meshes voxels of at least this weight (its default is 3; rangefuse meshes every
    #: informed voxel, so the comparison uses 1).
    weight_threshold = 1.0

    def extract_triangle_mesh(self) -> tuple[int, float]:
        """Marching cubes on the TSDF: (triangles, seconds)."""
        t0 = time.perf_counter()
        mesh = self.vbg.extract_triangle_mesh()
        seconds = time.perf_counter() - t0
        return int(mesh.triangle.indices.shape[0]), seconds
