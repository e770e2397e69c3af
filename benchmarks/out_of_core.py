"""Out-of-core fusion of the synthetic street into a persistent store (issue: storage).

A 64-beam spherical LiDAR drives along the street (one scan every 2 m); each run fuses all
scans into a new store (mapping mode, 1 cm voxels by default) with a tile cache of
``--cache-mb`` and reports, per street length: time, peak RSS of the process (and of its
worker processes), tiles, bytes on disk, and how large a dense float32 grid of the tiles'
bounding box would be. Each run is a fresh child process, so peak RSS is its own. The
largest length runs again with 2 worker processes for the speed-up.

    python benchmarks/out_of_core.py                  # 4, 8, 12 m at 1 cm, 512 MB cache
    python benchmarks/out_of_core.py --quick          # 6 m at 4 cm (a smoke run)
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _child(cfg: dict) -> dict:
    from rangefuse.engine import FusionParams, GridSpec, NoiseModel
    from rangefuse.engine.synth import make_dataset
    from rangefuse.service.runners import ProcessRunner
    from rangefuse.storage import open_store
    from rangefuse.storage.units import InProcess

    h = cfg["voxel"]
    data = make_dataset("street", length_m=cfg["length"])
    grid = GridSpec(h, cfg["tile"], "mapping")
    params = FusionParams(NoiseModel(eps=2 * h, rho=0.05))
    runner = ProcessRunner(cfg["workers"]) if cfg["workers"] > 1 else InProcess()
    with tempfile.TemporaryDirectory(dir=cfg["tmp"]) as tmp:
        t0 = time.perf_counter()
        with open_store(
            Path(tmp) / "store", grid, params, cache_mb=cfg["cache_mb"], runner=runner
        ) as scene:
            for scan_id, scan in data.scans:
                scene.store_scan(scan_id, scan)
            stored = time.perf_counter() - t0
            report = scene.integrate_pending()
            elapsed = time.perf_counter() - t0
            keys = scene.tile_keys()
            info = scene.info()
        if cfg["workers"] > 1:
            runner.close()  # type: ignore[attr-defined]
    T = cfg["tile"]
    extent = (keys.max(axis=0) - keys.min(axis=0) + 1) * T if len(keys) else [0, 0, 0]
    dense_gb = float(extent[0]) * float(extent[1]) * float(extent[2]) * 4 / 1e9
    return {
        **cfg,
        "scans": len(data.scans),
        "seconds": elapsed,
        "store_s": stored,
        "updates": report.voxel_updates,
        "tiles": len(keys),
        "disk_mb": info["bytes_on_disk"] / 2**20,
        "dense_gb": dense_gb,
        "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "child_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="6 m of street at 4 cm")
    parser.add_argument("--lengths", default="4,8,12", help="street lengths in metres")
    parser.add_argument("--voxel", type=float, default=0.01)
    parser.add_argument("--tile-size", type=int, default=16)
    parser.add_argument("--cache-mb", type=float, default=512.0)
    parser.add_argument("--tmp", default=None, help="folder for the stores (default: system)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(_child(json.loads(args.child))))
        return
    lengths = [6.0] if args.quick else [float(x) for x in args.lengths.split(",")]
    voxel = 0.04 if args.quick else args.voxel
    base = dict(voxel=voxel, tile=args.tile_size, cache_mb=args.cache_mb, tmp=args.tmp)
    configs = [dict(base, length=n, workers=1) for n in lengths]
    configs.append(dict(base, length=lengths[-1], workers=2))
    header = (
        f"{'length m':>8} {'scans':>5} {'workers':>7} {'time s':>7} {'scans/s':>7} "
        f"{'Mupd/s':>7} {'tiles':>8} {'disk MB':>8} {'dense GB':>9} {'RSS MB':>7} "
        f"{'workers RSS MB':>14}"
    )
    print(f"street, spherical LiDAR 64x1024, voxel {voxel} m, tiles {args.tile_size}^3, "
          f"cache {args.cache_mb:g} MB, mapping mode")  # fmt: skip
    print(header)
    print("-" * len(header))
    results = []
    for cfg in configs:
        out = subprocess.run(
            [sys.executable, __file__, "--child", json.dumps(cfg)],
            capture_output=True,
            text=True,
        )
        if out.returncode != 0:
            print(out.stderr[-2000:], file=sys.stderr)
            raise SystemExit(out.returncode)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        results.append(r)
        print(
            f"{r['length']:8.0f} {r['scans']:5d} {r['workers']:7d} {r['seconds']:7.1f} "
            f"{r['scans'] / r['seconds']:7.2f} {r['updates'] / r['seconds'] / 1e6:7.1f} "
            f"{r['tiles']:8d} {r['disk_mb']:8.1f} {r['dense_gb']:9.1f} {r['rss_mb']:7.0f} "
            f"{r['child_rss_mb']:14.0f}",
            flush=True,
        )
    one, two = results[-2], results[-1]
    print(f"speed-up from 1 to 2 worker processes: {one['seconds'] / two['seconds']:.2f}x")


if __name__ == "__main__":
    main()
