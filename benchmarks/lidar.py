"""A long drive: the synthetic street mapped by a 64 x 1024 spherical LiDAR (issue 21).

One scan every 2 m (``rangefuse synth street --length L``; ``--scan-spacing`` for a sparser
or denser drive), 1 cm Gaussian range noise, mapping
mode with the command line's defaults at each voxel size. For each run (a fresh child
process, so peak RSS is its own): time per scan against the street's length, in memory (one
:meth:`~engine.Volume.add_many`, as ``rangefuse fuse``) and into a store (``--store``:
``store_scan`` each scan, then ``integrate_pending``, with a tile cache of ``--cache-mb``),
tiles, bytes on disk, the size of a dense float32 grid of the tiles' bounding box, and the
peak RSS (which includes the rendered scans themselves: the ``data MB`` column), and the
voxel updates per scan (``Mupd/scan``) with the time per update (``ns/upd``): a scan of a
street shorter than twice the sensor's reach sees less of it, so its time per scan is lower
for that alone, while the time per update shows what the map's size costs. A store run also
gives the share of its integration spent in the fusion kernel (``kernel``; the rest is
reading, staging and publishing chunks, planning and the catalog) and the tiles it wrote
per scan (``wr/scan``: a tile is written once per group of scans). In the same
run, OctoMap (``pyoctomap``, the ``bench`` extra: ``insertPointCloud`` with the sensor origin
and the sensor's max range; no-return pixels as points beyond it, so they carve free space
as in rangefuse) maps the first ``--octomap-scans`` scans of the shortest street at 10 cm and
5 cm, and rangefuse maps the same scans in memory for the ratio. Kernels are warmed on one
scan before each clock starts; the street is rendered before it too. ``--tilt R`` rolls and
pitches each pose by up to ``R`` radians (the synthetic street's poses are exactly level; a
vehicle's are not, and the kernel's level shortcut then does not apply).

    python benchmarks/lidar.py                    # the issue's table (tens of minutes)
    python benchmarks/lidar.py --quick            # 10 cm, 40 and 160 m, 4 OctoMap scans
    python benchmarks/lidar.py --voxels 0.1 --lengths 40,640 --no-store --octomap-scans 0
    python benchmarks/lidar.py --voxels 0.1 --lengths 160 --tilt 0.02 --tile-size 32
    python benchmarks/lidar.py --voxels 0.01 --lengths 1100 --scan-spacing 8 --no-memory \
        --tile-size 32 --octomap-scans 0 --store-max-length 2000   # a dense grid over 1 TB
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _children import run_child

#: Lengths run at each voxel size by default (metres); 1 cm runs into a store only.
DEFAULT_LENGTHS = {0.1: "40,160,640,2500", 0.05: "40,160,640", 0.01: "8,24"}
#: Longest street run into a store at each voxel size by default (the store's runs are slower).
STORE_MAX_LENGTH = {0.1: 640.0, 0.05: 160.0, 0.01: 24.0}
#: Metres driven between two scans by default (the synthetic street's own spacing).
SCAN_SPACING_M = 2.0
NOISE_M = 0.01
#: Voxel size of the warm-up (kernels loaded before the clock starts).
WARM_VOXEL_M = 0.1


def _max_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _street(
    length: float, n_scans: int | None = None, tilt: float = 0.0, spacing: float = SCAN_SPACING_M
) -> list:
    """The street's scans, one every ``spacing`` metres (at least one); with ``tilt`` (radians)
    each pose rolls and pitches by up to that much (a vehicle's sway: roll
    ``tilt sin(0.9 k + 0.3)``, pitch ``tilt cos(1.3 k)`` at scan ``k``) and the scans are
    rendered again from those poses, with the same noise model."""
    import numpy as np
    from rangefuse.engine import Scan
    from rangefuse.engine.synth import NoiseSpec, apply_noise, make_dataset, render

    noise = NoiseSpec(gaussian_m=NOISE_M)
    views = max(1, round(length / spacing))
    data = make_dataset("street", views=views, length_m=length, noise=noise)
    scans = data.scans if n_scans is None else data.scans[:n_scans]
    if tilt == 0.0:
        return scans
    rng = np.random.default_rng(0)
    tilted = []
    for k, (scan_id, scan) in enumerate(scans):
        roll, pitch = tilt * np.sin(0.9 * k + 0.3), tilt * np.cos(1.3 * k)
        cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
        R_x = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
        R_y = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
        T = scan.T_W_S.copy()
        T[:3, :3] = T[:3, :3] @ R_y @ R_x
        range_m = apply_noise(render(data.scene, data.sensor, T), noise, data.sensor, rng)
        tilted.append((scan_id, Scan(range_m=range_m, T_W_S=T, sensor=data.sensor)))
    return tilted


def _params(h: float):
    from rangefuse.engine import FusionParams, NoiseModel
    from rangefuse.engine.params import default_eps

    return FusionParams(NoiseModel(eps=default_eps(h)))


def _dense_gb(keys, T: int) -> float:
    if len(keys) == 0:
        return 0.0
    extent = (keys.max(axis=0) - keys.min(axis=0) + 1) * T
    return float(extent[0]) * float(extent[1]) * float(extent[2]) * 4 / 1e9


def _warm(scans: list, h: float) -> None:
    """Load (or compile) the kernels on one scan, outside the clock, on a grid of at least
    :data:`WARM_VOXEL_M` (the same kernels: numba specialises on types, not sizes; one 1 cm
    scan in memory took 1.9 GB, which the store runs' peak RSS reported as their own)."""
    from rangefuse.engine import GridSpec, Volume

    h = max(h, WARM_VOXEL_M)
    Volume(GridSpec(h, 16, "mapping"), _params(h)).add_many(scans[:1])


def _child_rangefuse(cfg: dict) -> dict:
    from rangefuse.engine import GridSpec, Volume

    h = cfg["voxel"]
    scans = _street(cfg["length"], cfg.get("n_scans"), cfg["tilt"], cfg["spacing"])
    data_mb = sum(s.range_m.nbytes for _, s in scans) / 2**20
    _warm(scans, h)
    grid = GridSpec(h, cfg["tile"], "mapping")
    params = _params(h)
    out: dict = dict.fromkeys(("disk_mb", "store_s", "integrate_s", "fuse_s", "written", "files"))
    t0 = time.perf_counter()
    if cfg["where"] == "memory":
        volume = Volume(grid, params)
        updates = volume.add_many(scans).voxel_updates
        seconds = time.perf_counter() - t0
        keys = volume.tile_keys()
    else:
        from rangefuse.storage import open_store

        tmp = tempfile.TemporaryDirectory(dir=cfg["tmp"])
        with tmp, open_store(Path(tmp.name) / "s", grid, params, cache_mb=cfg["cache_mb"]) as scene:
            for scan_id, scan in scans:
                scene.store_scan(scan_id, scan)
            stored = time.perf_counter()
            limits = {k: cfg[k] for k in ("group_scans", "group_pairs") if cfg.get(k)}
            report = scene.integrate_pending(**limits)
            updates = report.voxel_updates
            seconds = time.perf_counter() - t0
            out["fuse_s"], out["written"] = report.fuse_seconds, report.tiles_written
            out["store_s"] = stored - t0
            out["integrate_s"] = seconds - out["store_s"]
            keys = scene.tile_keys()
            out["disk_mb"] = scene.info()["bytes_on_disk"] / 2**20
            out["files"] = sum(len(f) for _, _, f in os.walk(scene.tiles.path / "c"))
    return {
        **cfg,
        **out,
        "tool": f"rangefuse {cfg['where']}",
        "scans": len(scans),
        "seconds": seconds,
        "tiles": len(keys),
        "dense_gb": _dense_gb(keys, cfg["tile"]),
        "rss_mb": _max_rss_mb(),
        "data_mb": data_mb,
        "updates": updates,
    }


def _world_points(scan) -> tuple:
    """A scan as OctoMap takes it: world points and the sensor origin; a no-return pixel as a
    point twice the max range away (OctoMap cuts a ray at its max range and marks it free)."""
    import numpy as np

    sensor = scan.sensor
    rng = np.asarray(scan.range_m, np.float64)
    rng = np.where(np.isposinf(rng), 2.0 * sensor.max_range, rng)
    v, u = np.nonzero(np.isfinite(rng))
    uvd = np.stack([u.astype(np.float64), v.astype(np.float64), rng[v, u]], axis=1)
    p_S = sensor.unproject(uvd[:, 0], uvd[:, 1], uvd[:, 2])
    T = scan.T_W_S
    p_W = p_S @ T[:3, :3].T + T[:3, 3]
    return np.ascontiguousarray(p_W), np.ascontiguousarray(T[:3, 3], np.float64)


def _child_octomap(cfg: dict) -> dict:
    import pyoctomap

    scans = _street(cfg["length"], cfg.get("n_scans"), cfg["tilt"], cfg["spacing"])
    clouds = [_world_points(s) for _, s in scans]
    data_mb = sum(s.range_m.nbytes for _, s in scans) / 2**20
    max_range = float(scans[0][1].sensor.max_range)
    tree = pyoctomap.OcTree(cfg["voxel"])
    t0 = time.perf_counter()
    for points, origin in clouds:
        tree.insertPointCloud(points, origin, max_range)
    seconds = time.perf_counter() - t0
    return {
        **cfg,
        "tool": "OctoMap",
        "scans": len(scans),
        "seconds": seconds,
        "tiles": None,
        "leaves": int(tree.getNumLeafNodes()),
        "dense_gb": None,
        "disk_mb": None,
        "store_s": None,
        "integrate_s": None,
        "rss_mb": _max_rss_mb(),
        "data_mb": data_mb,
    }


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _row(r: dict) -> str:
    per_scan = r["seconds"] / r["scans"]
    split = (
        f"{r['store_s']:.1f}+{r['integrate_s']:.1f}" if r["store_s"] is not None else "-"
    )  # fmt: skip
    tiles = r["tiles"] if r["tiles"] is not None else f"{r['leaves']}lv"
    return (
        f"{r['voxel']:6.2f} {r['length']:7.0f} {r['tool']:>18} {r['scans']:5d} "
        f"{r['seconds']:8.1f} {per_scan * 1000:8.0f} {1 / per_scan:7.2f} {split:>12} "
        f"{tiles!s:>9} {_fmt(r['disk_mb'], '8.1f'):>8} {_fmt(r['dense_gb'], '9.2f'):>9} "
        f"{r['rss_mb']:7.0f} {r['data_mb']:7.0f}{_per_update(r, per_scan)}{_io(r)}"
    )


def _io(r: dict) -> str:
    # a store run: the share of its integration spent in the fusion kernel (the rest is
    # reading, staging and publishing chunks, planning and the catalog) and the tiles it
    # wrote per scan (each tile once per group of scans: what the groups save)
    # and the files of its tile array (one per tile, or per shard of tiles: docs/storage.md)
    if r.get("fuse_s") is None:
        return f" {'-':>6} {'-':>7} {'-':>7}"
    share = 100 * r["fuse_s"] / max(r["integrate_s"], 1e-9)
    return f" {share:5.0f}% {r['written'] / r['scans']:7.0f} {r['files']:7d}"


def _per_update(r: dict, per_scan: float) -> str:
    # the voxel updates a scan makes (millions; a scan of a street shorter than twice the
    # sensor's reach sees less of it) and the time per update: what the map's size changes
    updates = r.get("updates")
    if updates is None:
        return f" {'-':>9} {'-':>6}"
    per = updates / r["scans"]
    return f" {per / 1e6:9.2f} {per_scan * 1e9 / max(per, 1):6.1f}"


def _lengths(text: str) -> list[float]:
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(f"--lengths: not a list of numbers: {text!r}") from None
    if not values or min(values) <= 0:
        raise SystemExit(f"--lengths: give positive lengths in metres, got {text!r}")
    return values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="10 cm, 40 and 160 m; 4 OctoMap scans")
    parser.add_argument("--voxels", default="0.1,0.05,0.01", help="voxel sizes in metres")
    parser.add_argument("--lengths", help="street lengths (default: per voxel size)")
    parser.add_argument("--no-memory", action="store_true", help="skip the in-memory runs")
    parser.add_argument("--no-store", action="store_true", help="skip the store runs")
    parser.add_argument("--store-max-length", type=float, help="longest street into a store")
    parser.add_argument("--octomap-scans", type=int, default=10, help="0: no OctoMap")
    parser.add_argument("--tile-size", type=int, default=16)
    parser.add_argument("--cache-mb", type=float, default=512.0)
    parser.add_argument(
        "--group-scans", type=int, help="most scans per checkpoint in the store runs "
        "(default: storage.groups.GROUP_SCANS, with its other bounds)"
    )  # fmt: skip
    parser.add_argument(
        "--group-pairs", type=int, help="most (scan, tile) pairs per store checkpoint"
    )
    parser.add_argument(
        "--tilt", type=float, default=0.0, help="roll and pitch each pose by up to this "
        "many radians (a vehicle's sway; 0: the level street)"
    )  # fmt: skip
    parser.add_argument(
        "--scan-spacing", type=float, default=SCAN_SPACING_M, help="metres driven between two "
        "scans (default 2: the synthetic street's)"
    )  # fmt: skip
    parser.add_argument("--tmp", default=None, help="folder for the stores (default: system)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        cfg = json.loads(args.child)
        result = _child_octomap(cfg) if cfg["where"] == "octomap" else _child_rangefuse(cfg)
        print(json.dumps(result))
        return
    try:
        voxels = [float(x) for x in args.voxels.split(",")]
    except ValueError:
        raise SystemExit(f"--voxels: not a list of numbers: {args.voxels!r}") from None
    if not 0.0 <= args.tilt <= 0.5:
        raise SystemExit(f"--tilt: give 0 to 0.5 radians, got {args.tilt}")
    if not 0.1 <= args.scan_spacing <= 100.0:
        raise SystemExit(f"--scan-spacing: give 0.1 to 100 metres, got {args.scan_spacing}")
    if args.group_scans is not None and args.group_scans < 1:
        raise SystemExit(f"--group-scans: give at least 1, got {args.group_scans}")
    if args.group_pairs is not None and args.group_pairs < 1:
        raise SystemExit(f"--group-pairs: give at least 1, got {args.group_pairs}")
    octomap_scans = args.octomap_scans
    if args.quick:
        voxels, octomap_scans = [0.1], min(octomap_scans, 4)
    if octomap_scans > 0 and importlib.util.find_spec("pyoctomap") is None:
        raise SystemExit("pyoctomap is not importable: pip install -e '.[bench]' (or give "
                         "--octomap-scans 0)")  # fmt: skip
    base = {"tile": args.tile_size, "cache_mb": args.cache_mb, "tmp": args.tmp,
            "group_scans": args.group_scans, "group_pairs": args.group_pairs, "tilt": args.tilt,
            "spacing": args.scan_spacing}  # fmt: skip
    configs: list[dict] = []
    for h in voxels:
        text = args.lengths or ("40,160" if args.quick else DEFAULT_LENGTHS.get(h, "40,160"))
        lengths = _lengths(text)
        store_max = args.store_max_length or STORE_MAX_LENGTH.get(h, max(lengths))
        for length in lengths:
            if not args.no_memory and h >= 0.05:
                configs.append(dict(base, voxel=h, length=length, where="memory"))
            if not args.no_store and length <= store_max:
                configs.append(dict(base, voxel=h, length=length, where="store"))
        if octomap_scans > 0 and h >= 0.05:
            same = {"voxel": h, "length": min(lengths), "n_scans": octomap_scans}
            configs.append(dict(base, **same, where="memory"))
            configs.append(dict(base, **same, where="octomap"))
    header = (
        f"{'voxel':>6} {'length':>7} {'tool':>18} {'scans':>5} {'time s':>8} {'ms/scan':>8} "
        f"{'scans/s':>7} {'store+fuse':>12} {'tiles':>9} {'disk MB':>8} {'dense GB':>9} "
        f"{'RSS MB':>7} {'data MB':>7} {'Mupd/scan':>9} {'ns/upd':>6} {'kernel':>6} "
        f"{'wr/scan':>7} {'files':>7}"
    )
    print(
        f"street, spherical LiDAR 64x1024 (max range 80 m), one scan per "
        f"{args.scan_spacing:g} m, gaussian noise "
        f"{NOISE_M} m, tiles {args.tile_size}^3, store cache {args.cache_mb:g} MB, "
        f"{os.cpu_count()} cores"
        + (f", {args.group_scans} scans per store checkpoint" if args.group_scans else "")
        + (f", {args.group_pairs} pairs per store checkpoint" if args.group_pairs else "")
        + (f", poses tilted by up to {args.tilt:g} rad" if args.tilt else ", level poses")
    )
    print(header)
    print("-" * len(header))
    results = []
    for cfg in configs:
        r = run_child(__file__, cfg)
        results.append(r)
        print(_row(r), flush=True)
    pairs = {}
    for r in results:
        if r.get("n_scans"):
            pairs.setdefault(r["voxel"], {})[r["tool"]] = r
    for h, pair in pairs.items():
        if "OctoMap" in pair and "rangefuse memory" in pair:
            ratio = pair["OctoMap"]["seconds"] / pair["rangefuse memory"]["seconds"]
            print(f"{h:g} m, the same {pair['OctoMap']['scans']} scans: rangefuse in memory is "
                  f"{ratio:.1f}x faster than OctoMap")  # fmt: skip


if __name__ == "__main__":
    main()
