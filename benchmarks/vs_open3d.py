"""rangefuse against Open3D's CPU TSDF integration on the same synthetic room frames.

Both fuse the room's 640x480 z-depth frames (``engine.synth.make_dataset("room")``) at the
same voxel size, one after the other in this process, each after a warm-up of one frame
(numba compiles or loads its kernels; Open3D allocates its hash map). rangefuse runs as in
benchmarks/fusion.py: mapping mode, ``eps = 2 voxels``, ``rho = 0.05``. Open3D runs a
``VoxelBlockGrid`` (tsdf + weight, float32, 8^3 blocks) with a truncation of 4 voxels,
integrating each frame's frustum blocks. Prints seconds, frames/s, their ratio and the peak
resident memory of the process during each run (the frames themselves included, and what
earlier runs left mapped: the summary gives each one's smallest peak over the rounds).

The two run in rounds, alternating which goes first, and the summary gives the median of
the rounds' ratios: on a shared machine a single run says little (Open3D alone ran the same
100 frames at 107 to 236 frames/s at 2 cm on our 2-core CI machine), while the two runs of a
round see about the same machine.

    python benchmarks/vs_open3d.py             # 100 frames at 2 cm and 1 cm, 5 rounds
    python benchmarks/vs_open3d.py --rounds 9  # more rounds, a steadier median
    python benchmarks/vs_open3d.py --quick     # 10 frames at 4 cm, 1 round (a smoke run)

Needs the optional ``bench`` extra (``pip install -e '.[bench]'``: open3d, psutil).
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, PinholeSensor, Scan, Volume
from rangefuse.engine.synth import make_dataset

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _peers import (
    TRUNC_VOXELS,
    Open3DTSDF,
    depth_images,
    import_open3d,
    open3d_available,
)


class PeakRSS:
    """Samples the resident set size of this process in a thread; ``peak_mb`` after ``with``."""

    def __init__(self, interval_s: float = 0.01) -> None:
        import psutil

        self._process = psutil.Process(os.getpid())
        self._interval_s = interval_s
        self._stop = threading.Event()
        self.peak_mb = 0.0

    def _sample(self) -> None:
        self.peak_mb = max(self.peak_mb, self._process.memory_info().rss / 2**20)

    def _run(self) -> None:
        while not self._stop.wait(self._interval_s):
            self._sample()

    def __enter__(self) -> PeakRSS:
        self._sample()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()


def run_rangefuse(
    scans: Sequence[tuple[str, Scan]], voxel_m: float, tile_vox: int
) -> dict[str, float]:
    params = FusionParams(NoiseModel(eps=2 * voxel_m, rho=0.05))
    grid = GridSpec(voxel_m, tile_vox, "mapping")
    Volume(grid, params).add_many(list(scans[:1]))  # compile or load the kernels
    gc.collect()
    volume = Volume(grid, params)
    with PeakRSS() as rss:
        t0 = time.perf_counter()
        volume.add_many(list(scans))
        seconds = time.perf_counter() - t0
    tiles = len(volume.tile_keys())
    return {"seconds": seconds, "rss_mb": rss.peak_mb, "blocks": tiles}


def run_open3d(
    depths: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    sensor: PinholeSensor,
    voxel_m: float,
) -> dict[str, float]:
    warm = Open3DTSDF(voxel_m, sensor)
    warm.integrate(depths[0], warm.extrinsics(poses[:1])[0])  # allocate, warm up
    del warm
    gc.collect()
    tsdf = Open3DTSDF(voxel_m, sensor)
    extrinsics = tsdf.extrinsics(poses)
    with PeakRSS() as rss:
        seconds = tsdf.integrate_all(depths, extrinsics)
    blocks = tsdf.blocks
    del tsdf
    gc.collect()
    return {"seconds": seconds, "rss_mb": rss.peak_mb, "blocks": blocks}


def compare(
    frames: int, voxel_m: float, tile_vox: int, rounds: int, emit: Callable[[str], None]
) -> str:
    """Run both ``rounds`` times, alternating which goes first; emit a line per round and
    return the summary line."""
    data = make_dataset("room", views=frames)
    sensor = data.sensor
    if not isinstance(sensor, PinholeSensor):
        raise SystemExit(f"vs_open3d: the room's sensor is {sensor.model}, expected pinhole")
    depths = depth_images(data.scans)
    poses = [scan.T_W_S for _, scan in data.scans]
    ratios = []
    best = {"rf": 0.0, "o3d": 0.0}
    least_mb = {"rf": np.inf, "o3d": np.inf}
    for round_ in range(1, rounds + 1):
        runs = {}
        for peer in ("rf", "o3d") if round_ % 2 else ("o3d", "rf"):
            if peer == "rf":
                runs[peer] = run_rangefuse(data.scans, voxel_m, tile_vox)
            else:
                runs[peer] = run_open3d(depths, poses, sensor, voxel_m)
            gc.collect()
        rf, o3 = runs["rf"], runs["o3d"]
        rf_fps = frames / rf["seconds"]
        o3_fps = frames / o3["seconds"]
        ratios.append(rf_fps / o3_fps)
        best = {"rf": max(best["rf"], rf_fps), "o3d": max(best["o3d"], o3_fps)}
        least_mb = {peer: min(least_mb[peer], runs[peer]["rss_mb"]) for peer in runs}
        emit(
            f"{voxel_m:6.3f} {round_:5d} {frames:6d} {rf['seconds']:7.2f} {rf_fps:7.2f} "
            f"{o3['seconds']:7.2f} {o3_fps:7.2f} {rf_fps / o3_fps:6.2f} {rf['rss_mb']:7.0f} "
            f"{o3['rss_mb']:7.0f} {rf['blocks']:7.0f} {o3['blocks']:7.0f}"
        )
    return (
        f"{voxel_m:6.3f}: median ratio {float(np.median(ratios)):.2f} over {rounds} round(s) "
        f"(from {min(ratios):.2f} to {max(ratios):.2f}); best frames/s {best['rf']:.1f} / "
        f"{best['o3d']:.1f} = {best['rf'] / best['o3d']:.2f}; smallest peak RSS "
        f"{least_mb['rf']:.0f} / {least_mb['o3d']:.0f} MB"
    )


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="10 frames at 4 cm")
    parser.add_argument("--frames", type=int, default=None, help="frames (default 100)")
    parser.add_argument(
        "--voxel",
        type=float,
        action="append",
        default=None,
        metavar="M",
        help="voxel size in metres; repeat for several (default 0.02 and 0.01)",
    )
    parser.add_argument("--tile-size", type=int, default=16, help="rangefuse tile edge, voxels")
    parser.add_argument(
        "--rounds",
        type=int,
        default=None,
        help="runs of each, alternating which goes first (default 5; 1 with --quick)",
    )
    args = parser.parse_args(argv)
    rounds = args.rounds if args.rounds is not None else (1 if args.quick else 5)
    if rounds < 1:
        parser.error(f"--rounds must be at least 1, got {rounds}")
    frames = args.frames or (10 if args.quick else 100)
    voxels = args.voxel or ([0.04] if args.quick else [0.02, 0.01])
    if not open3d_available():
        import_open3d()  # exits with the install hint
    # numba picks its threading layer before Open3D loads its own TBB (else numba warns).
    import numba
    from rangefuse.engine._threads import threading_layer

    layer = threading_layer()
    print(
        f"room, 640x480 z-depth frames; rangefuse tiles {args.tile_size}^3, mapping mode, "
        f"eps 2 voxels; Open3D VoxelBlockGrid 8^3 blocks, trunc {TRUNC_VOXELS:g} voxels; "
        f"{numba.get_num_threads()} numba threads ('{layer}' layer), {os.cpu_count()} CPUs"
    )
    header = (
        f"{'voxel':>6} {'round':>5} {'frames':>6} {'rf s':>7} {'rf f/s':>7} {'o3d s':>7} "
        f"{'o3d f/s':>7} {'ratio':>6} {'rf MB':>7} {'o3d MB':>7} {'tiles':>7} {'blocks':>7}"
    )
    print(header)
    print("-" * len(header))
    summaries = [
        compare(frames, voxel_m, args.tile_size, rounds, lambda line: print(line, flush=True))
        for voxel_m in voxels
    ]
    print(
        "ratio = rangefuse frames/s / Open3D frames/s; MB = peak RSS of the process during "
        "that run (frames included)"
    )
    for line in summaries:
        print(line)


if __name__ == "__main__":
    main()
