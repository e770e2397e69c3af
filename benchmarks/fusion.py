"""Fusion throughput on the synthetic room (issue: fusion engine).

Fuses the room's pinhole RGB-D frames (640x480) at each voxel size and tile
size, each configuration in a fresh process so that peak RSS is its own, after
a warm-up that compiles (or loads) the kernels. Prints frames/s, voxel updates/s
(voxels a scan informs, free space included) and peak RSS.

    python benchmarks/fusion.py            # 100 frames at 2 cm and 1 cm, tiles 8/16/32
    python benchmarks/fusion.py --quick    # 10 frames at 4 cm (a smoke run)
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


def _child(cfg: dict) -> dict:
    from rangefuse.engine import FusionParams, GridSpec, NoiseModel, Volume
    from rangefuse.engine.synth import make_dataset

    data = make_dataset("room", views=cfg["frames"])
    scans = data.scans
    h = cfg["voxel"]
    params = FusionParams(NoiseModel(eps=2 * h, rho=0.05))
    grid = GridSpec(h, cfg["tile"], cfg["mode"], data.bounds if cfg["mode"] == "closed" else None)
    Volume(grid, params).add_many(scans[:1])  # compile or load the kernels
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    volume = Volume(grid, params)
    t0 = time.perf_counter()
    report = volume.add_many(scans)
    elapsed = time.perf_counter() - t0
    tiles = len(volume.tile_keys())
    return {
        **cfg,
        "seconds": elapsed,
        "fps": len(scans) / elapsed,
        "updates": report.voxel_updates,
        "ups": report.voxel_updates / elapsed,
        "tiles": tiles,
        "tile_mb": tiles * cfg["tile"] ** 3 * 8 / 2**20,
        "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "rss_before_mb": rss_before,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="10 frames at 4 cm")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--modes", default="mapping,closed")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(_child(json.loads(args.child))))
        return
    if args.quick:
        configs = [dict(frames=10, voxel=0.04, tile=16, mode=m) for m in args.modes.split(",")]
    else:
        configs = [
            dict(frames=100, voxel=v, tile=t, mode=m)
            for m in args.modes.split(",")
            for v in (0.02, 0.01)
            for t in (8, 16, 32)
        ]
    import numba
    from rangefuse.engine._threads import threading_layer

    # the children run with the same environment, hence the same layer
    print(f"{numba.get_num_threads()} numba threads, '{threading_layer()}' threading layer")
    header = (
        f"{'mode':8} {'voxel':>6} {'tile':>4} {'frames':>6} {'time s':>7} {'frames/s':>8} "
        f"{'Mupd/s':>7} {'tiles':>7} {'tiles MB':>8} {'peak RSS MB':>11}"
    )
    print(header)
    print("-" * len(header))
    for cfg in configs:
        out = subprocess.run(
            [sys.executable, __file__, "--child", json.dumps(cfg)],
            capture_output=True,
            text=True,
            check=True,
        )
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(
            f"{r['mode']:8} {r['voxel']:6.3f} {r['tile']:4d} {r['frames']:6d} "
            f"{r['seconds']:7.2f} {r['fps']:8.2f} {r['ups'] / 1e6:7.1f} {r['tiles']:7d} "
            f"{r['tile_mb']:8.1f} {r['rss_mb']:11.0f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
