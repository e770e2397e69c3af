"""Peers the benchmarks compare against: Open3D's CPU TSDF (the optional ``bench`` extra)."""

from __future__ import annotations

import importlib.util
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from rangefuse.engine import PinholeSensor, Scan

#: Open3D's truncation distance in voxels and its depth cut-off (metres).
TRUNC_VOXELS = 4.0
DEPTH_MAX_M = 8.0
#: Hash-map blocks Open3D allocates up front: enough for the room at 1 cm.
BLOCKS_AT_1CM = 100_000


def open3d_available() -> bool:
    """Whether open3d can be imported (without importing it: numba warns after it)."""
    return importlib.util.find_spec("open3d") is not None


def import_open3d() -> Any:
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise SystemExit(
            f"open3d is not importable ({exc}); run `make bench` or "
            "`pip install -e '.[bench]'` (the wheel also needs libusb-1.0-0 from apt)"
        ) from None
    return o3d


def depth_images(scans: Sequence[tuple[str, Scan]]) -> list[np.ndarray]:
    """z-depth maps in metres, float32, 0 where a pixel has no measurement (Open3D's invalid)."""
    out = []
    for _, scan in scans:
        sensor = scan.sensor
        if not isinstance(sensor, PinholeSensor):
            raise SystemExit(f"Open3D's TSDF needs a pinhole sensor, got {sensor.model}")
        depth = scan.range_m.astype(np.float32)
        if sensor.range_convention == "ray":  # |p| -> p_z along each pixel's ray
            v, u = np.mgrid[0 : sensor.height, 0 : sensor.width]
            x = (u - sensor.cx) / sensor.fx
            y = (v - sensor.cy) / sensor.fy
            depth = (depth / np.sqrt(x * x + y * y + 1.0)).astype(np.float32)
        depth[~np.isfinite(depth)] = 0.0
        out.append(np.ascontiguousarray(depth))
    return out


class Open3DTSDF:
    """Open3D's ``VoxelBlockGrid`` (tsdf + weight, float32, 8^3 blocks) on the CPU."""

    #: Open3D meshes voxels of at least this weight (its default is 3; rangefuse meshes every
    #: informed voxel, so the comparison uses 1).
    weight_threshold = 1.0

    def __init__(self, voxel_size: float, sensor: PinholeSensor) -> None:
        o3d = import_open3d()
        self._o3d = o3d
        o3c = o3d.core
        self._o3c = o3c
        self.intrinsic = o3c.Tensor(
            np.array([[sensor.fx, 0.0, sensor.cx], [0.0, sensor.fy, sensor.cy], [0.0, 0.0, 1.0]]),
            o3c.float64,
        )
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"),
            attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1), (1)),
            voxel_size=voxel_size,
            block_resolution=8,
            block_count=max(10_000, int(BLOCKS_AT_1CM * (0.01 / voxel_size) ** 2)),
            device=o3c.Device("CPU:0"),
        )

    def extrinsics(self, poses: Sequence[np.ndarray]) -> list[Any]:
        return [self._o3c.Tensor(np.linalg.inv(T_W_S), self._o3c.float64) for T_W_S in poses]

    def integrate(self, depth_np: np.ndarray, extrinsic: Any) -> None:
        depth = self._o3d.t.geometry.Image(self._o3c.Tensor(depth_np))
        kwargs: dict[str, Any] = {
            "depth_scale": 1.0,
            "depth_max": DEPTH_MAX_M,
            "trunc_voxel_multiplier": TRUNC_VOXELS,
        }
        frustum = self.vbg.compute_unique_block_coordinates(
            depth, self.intrinsic, extrinsic, **kwargs
        )
        self.vbg.integrate(frustum, depth, self.intrinsic, extrinsic, **kwargs)

    def integrate_all(self, depths: Sequence[np.ndarray], extrinsics: Sequence[Any]) -> float:
        """Integrate prepared frames; returns the seconds spent."""
        t0 = time.perf_counter()
        for depth_np, extrinsic in zip(depths, extrinsics, strict=True):
            self.integrate(depth_np, extrinsic)
        return time.perf_counter() - t0

    @property
    def blocks(self) -> int:
        return int(self.vbg.hashmap().size())

    def extract_triangle_mesh(self) -> tuple[int, float]:
        """Marching cubes on the TSDF: (triangles, seconds)."""
        t0 = time.perf_counter()
        mesh = self.vbg.extract_triangle_mesh(weight_threshold=self.weight_threshold)
        seconds = time.perf_counter() - t0
        return int(mesh.triangle.indices.shape[0]), seconds
