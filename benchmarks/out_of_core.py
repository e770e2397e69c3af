"""Out-of-core fusion of the synthetic street into a persistent store, in this process and on
Dask (issues: storage; jobs on Dask distributed).

A 64-beam spherical LiDAR drives along the street (one scan every 2 m); each run fuses all
scans into a new store (mapping mode, 1 cm voxels by default) with a tile cache of
``--cache-mb`` and reports, per street length: time, peak RSS of each process, tiles, bytes
on disk, how large a dense float32 grid of the tiles' bounding box would be, and a hash of
the fused tiles. Each run is a fresh child process, so peak RSS is its own. The largest length
runs again on the local cluster that ``--workers 2`` starts (a scheduler process and 2 worker
processes, children of the run) and on an external cluster (a ``dask scheduler`` and
2 ``dask worker`` processes started here), for the speed-up and to check that the tiles are the
same bits wherever the units ran. ``rangefuse warmup`` runs first, so that no timed run
compiles kernels.

    python benchmarks/out_of_core.py                  # 4, 8, 12 m at 1 cm, 512 MB cache
    python benchmarks/out_of_core.py --quick          # 6 m at 4 cm (a smoke run)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _children import run_child

BIN = Path(sys.executable).parent


def _max_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _tiles_hash(scene) -> str:
    """sha256 of the sorted tile keys and their voxel data, read back from the store."""
    keys = scene.tile_keys()
    digest = hashlib.sha256(keys.tobytes())
    for start in range(0, len(keys), 512):
        digest.update(scene.tile_store.read(keys[start : start + 512]).tobytes())
    return digest.hexdigest()[:16]


def _child(cfg: dict) -> dict:
    from rangefuse.engine import FusionParams, GridSpec, NoiseModel
    from rangefuse.engine.synth import make_dataset
    from rangefuse.service.cluster import Cluster
    from rangefuse.storage import open_store
    from rangefuse.storage.units import InProcess

    h = cfg["voxel"]
    data = make_dataset("street", length_m=cfg["length"])
    grid = GridSpec(h, cfg["tile"], "mapping")
    params = FusionParams(NoiseModel(eps=2 * h, rho=0.05))
    cluster = None
    if cfg["mode"] == "local":
        cluster = Cluster(workers=cfg["workers"], memory_limit="auto")
    elif cfg["mode"] == "external":
        cluster = Cluster(scheduler=cfg["scheduler"])
    runner = cluster.runner() if cluster else InProcess()
    if cluster:
        # the workers compile or load their kernels before the clock starts, as in a service
        while cluster.n_workers() < cfg["workers"]:
            time.sleep(0.1)
        cluster.client.run(_warm)
    try:
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
                tiles_hash = _tiles_hash(scene)
        workers_rss: list[float] = []
        scheduler_rss = None
        if cluster:
            workers_rss = sorted(cluster.client.run(_max_rss_mb).values())
            if cfg["mode"] == "external":
                scheduler_rss = cluster.client.run_on_scheduler(_max_rss_mb)
    finally:
        if cluster:
            cluster.close()
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
        "rss_mb": _max_rss_mb(),
        "workers_rss_mb": workers_rss,
        "scheduler_rss_mb": scheduler_rss,
        "hash": tiles_hash,
    }


def _warm() -> None:
    """Load the fusion kernels in a worker (from the numba cache when it is warm)."""
    import rangefuse.engine.fusion  # noqa: F401


class ExternalCluster:
    """A ``dask scheduler`` and ``workers`` ``dask worker`` processes on this machine."""

    def __init__(self, tmp: Path, workers: int) -> None:
        cores = os.cpu_count() or 1
        env = {**os.environ, "NUMBA_NUM_THREADS": str(max(1, cores // workers))}
        quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "env": env}
        file = tmp / "scheduler.json"
        self.procs = [
            subprocess.Popen(
                [str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", "0",
                 "--no-dashboard", "--scheduler-file", str(file)],
                **quiet,
            )
        ]  # fmt: skip
        deadline = time.time() + 60
        while not file.exists():
            if time.time() > deadline:
                self.close()
                raise SystemExit("dask scheduler did not start within 60 s")
            time.sleep(0.1)
        self.address = json.loads(file.read_text())["address"]
        for _ in range(workers):
            self.procs.append(
                subprocess.Popen(
                    [str(BIN / "dask"), "worker", self.address, "--nthreads", "1",
                     "--no-dashboard", "--preload", "rangefuse.service.worker"],
                    **quiet,
                )
            )  # fmt: skip

    def close(self) -> None:
        for proc in reversed(self.procs):
            proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="6 m of street at 4 cm")
    parser.add_argument("--lengths", default="4,8,12", help="street lengths in metres")
    parser.add_argument("--voxel", type=float, default=0.01)
    parser.add_argument("--tile-size", type=int, default=16)
    parser.add_argument("--cache-mb", type=float, default=512.0)
    parser.add_argument("--workers", type=int, default=2, help="Dask workers (default 2)")
    parser.add_argument("--tmp", default=None, help="folder for the stores (default: system)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(_child(json.loads(args.child))))
        return
    # kernels compile once per machine (into the numba cache), not inside a timed run
    t0 = time.perf_counter()
    subprocess.run([str(BIN / "rangefuse"), "warmup"], check=True, capture_output=True)
    print(f"rangefuse warmup: {time.perf_counter() - t0:.1f} s")
    lengths = [6.0] if args.quick else [float(x) for x in args.lengths.split(",")]
    voxel = 0.04 if args.quick else args.voxel
    base = dict(voxel=voxel, tile=args.tile_size, cache_mb=args.cache_mb, tmp=args.tmp)
    configs = [dict(base, length=n, mode="in-process", workers=1) for n in lengths]
    configs.append(dict(base, length=lengths[-1], mode="local", workers=args.workers))
    configs.append(dict(base, length=lengths[-1], mode="external", workers=args.workers))
    header = (
        f"{'length m':>8} {'scans':>5} {'runner':>10} {'workers':>7} {'time s':>7} "
        f"{'scans/s':>7} {'Mupd/s':>7} {'tiles':>8} {'disk MB':>8} {'dense GB':>9} "
        f"{'RSS MB':>7} {'workers RSS MB':>16} {'tiles sha256':>16}"
    )
    print(f"street, spherical LiDAR 64x1024, voxel {voxel} m, tiles {args.tile_size}^3, "
          f"cache {args.cache_mb:g} MB, mapping mode")  # fmt: skip
    print(header)
    print("-" * len(header))
    results = []
    for cfg in configs:
        if cfg["mode"] == "external":
            with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
                external = ExternalCluster(Path(tmp), args.workers)
                try:
                    r = run_child(__file__, dict(cfg, scheduler=external.address))
                finally:
                    external.close()
        else:
            r = run_child(__file__, cfg)
        results.append(r)
        workers_rss = "/".join(f"{x:.0f}" for x in r["workers_rss_mb"]) or "-"
        print(
            f"{r['length']:8.0f} {r['scans']:5d} {r['mode']:>10} {r['workers']:7d} "
            f"{r['seconds']:7.1f} {r['scans'] / r['seconds']:7.2f} "
            f"{r['updates'] / r['seconds'] / 1e6:7.1f} {r['tiles']:8d} {r['disk_mb']:8.1f} "
            f"{r['dense_gb']:9.1f} {r['rss_mb']:7.0f} {workers_rss:>16} {r['hash']:>16}",
            flush=True,
        )
    here, local, external = results[-3:]
    print(
        f"speed-up over in-process: local cluster of {args.workers} workers "
        f"{here['seconds'] / local['seconds']:.2f}x, external cluster of {args.workers} workers "
        f"{here['seconds'] / external['seconds']:.2f}x (scheduler peak RSS "
        f"{external['scheduler_rss_mb']:.0f} MB)"
    )
    same = here["hash"] == local["hash"] == external["hash"]
    print(f"same bits in-process, on the local cluster and on the external cluster: {same}")
    if not same:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
