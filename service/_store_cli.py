"""Command-line verbs on a persistent store (``docs/storage.md``).

``rangefuse fuse DATASET --store DIR`` creates or reopens the store's scene and fuses every
scan of the dataset it does not hold yet (named by file stem), so re-running after a crash
resumes; ``add``, ``remove``, ``extract`` and ``info`` work on an existing store.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

from rangefuse.engine import FusionParams, GridSpec, Scan
from rangefuse.engine.budget import Limits, check_scans
from rangefuse.engine.meshing import Mesh
from rangefuse.storage import open_dataset
from rangefuse.storage.dataset import read_scan_file
from rangefuse.storage.scene import Scene, open_store
from rangefuse.storage.store import CACHE_MB
from rangefuse.storage.units import InProcess, Runner

from ._cliutil import (
    CommandError,
    add_budget_options,
    add_far_ranges_option,
    add_output_options,
    budget_limits,
    check_outputs,
    far_ranges_note,
    finite_float,
    positive_float,
    positive_int,
    scan_read_options,
    write_outputs,
)
from ._progress import ProgressBar

__all__ = [
    "add_arguments",
    "cache_option",
    "extract_arguments",
    "fuse_into_store",
    "info_arguments",
    "remove_arguments",
    "workers_option",
]


def _announce_recovery(scene: Scene) -> None:
    r = scene.recovered
    if any(r.get(k) for k in ("discarded", "published", "rebuilt_tiles", "orphan_scans",
                               "removals_resumed", "temporaries")):  # fmt: skip
        print(
            f"recovered an interrupted run: discarded {r['discarded']} tiles staged by an "
            f"unfinished group, published {r['published']} of a finished one, rebuilt "
            f"{r['rebuilt_tiles']} tiles, removed {r['orphan_scans']} unacknowledged scans, "
            f"resumed {r['removals_resumed']} removals"
        )


def _store_and_integrate(
    scene: Scene, items: Iterable[tuple[str, Scan]], quiet: bool, label: str
) -> None:
    t0 = time.perf_counter()
    stored = 0
    for scan_id, scan in items:
        if scan_id in scene:
            continue
        scene.store_scan(scan_id, scan, name=scan_id)
        stored += 1
        # the acknowledgement: durable from here on
        print(f"stored {scan_id}{far_ranges_note(scan)}", flush=True)
    pending = len(scene.scan_rows(("stored",)))
    bar = ProgressBar(label, enabled=not quiet)
    try:
        report = scene.integrate_pending(progress=bar)
    finally:
        bar.close()
    info = scene.catalog.n_tiles(scene.scene_id)
    print(
        f"{stored} new scans stored; fused {pending} into {info} tiles of "
        f"{scene.grid.tile_size}^3 voxels ({report.voxel_updates:,} voxel updates, "
        f"{report.tiles_written} tiles written) in {time.perf_counter() - t0:.2f} s"
    )


def _write_scene_outputs(args: argparse.Namespace, scene: Scene) -> None:
    def mesh(refine: bool, bounds: Sequence[float] | None) -> Mesh:
        result, counts = scene.extract_mesh(refine=refine, bounds=bounds)
        print(
            f"meshed {counts['meshed']} tiles, reused {counts['reused']} cached tile meshes "
            f"of {counts['tiles']}"
        )
        return result

    write_outputs(args, scene.to_dense, mesh)


def fuse_into_store(
    args: argparse.Namespace,
    dataset_path: Path,
    grid: GridSpec,
    params: FusionParams,
    limits: Limits,
) -> int:
    """``rangefuse fuse DATASET --store DIR``."""
    dataset = open_dataset(dataset_path, **scan_read_options(args))
    if not Path(args.store).exists():  # the budgets before the store is created
        check_scans(dataset.scans(), params, grid, limits)
    with (
        _runner(args) as runner,
        open_store(args.store, grid, params, cache_mb=args.cache_mb, runner=runner) as scene,
    ):
        _announce_recovery(scene)
        new = ((s, scan) for s, scan in dataset.scans() if s not in scene)
        check_scans(new, params, grid, limits, scene.catalog.n_tiles(scene.scene_id))
        _store_and_integrate(scene, dataset.scans(), args.quiet, "fuse")
        _write_scene_outputs(args, scene)
    return 0


@contextlib.contextmanager
def _runner(args: argparse.Namespace) -> Iterator[Runner]:
    """Here, on a local cluster of ``--workers N``, or on the cluster of ``--scheduler``."""
    workers = getattr(args, "workers", None)
    scheduler = getattr(args, "scheduler", None)
    if workers is None and scheduler is None:
        yield InProcess()
        return
    if workers is not None and scheduler is not None:
        raise CommandError("--workers starts a cluster, --scheduler joins one: give one of them")
    from .cluster import Cluster

    try:
        cluster = Cluster(workers or 1, scheduler=scheduler)
    except OSError as exc:  # no scheduler there
        raise CommandError(f"--scheduler {scheduler}: cannot reach it ({exc})") from None
    with cluster:
        yield cluster.runner()


def _open_existing(args: argparse.Namespace, runner: Runner | None = None) -> Scene:
    path = Path(args.store)
    if not path.exists():
        raise CommandError(f"{path}: no such store")
    scene = open_store(path, cache_mb=getattr(args, "cache_mb", CACHE_MB), runner=runner)
    _announce_recovery(scene)
    return scene


def _sensor_file_for(scan_path: Path, explicit: Path | None) -> Path | None:
    if explicit is not None:
        return explicit
    for folder in (scan_path.parent, scan_path.parent.parent):
        if (folder / "sensor.json").is_file():
            return folder / "sensor.json"
    return None


def _cmd_add(args: argparse.Namespace) -> int:
    from rangefuse.engine import sensor_from_dict

    scans = []
    for path in args.scans:
        sensor_path = _sensor_file_for(path, args.sensor)
        default = None
        if sensor_path is not None:
            try:
                default = sensor_from_dict(json.loads(sensor_path.read_text()))
            except (OSError, ValueError) as exc:
                raise CommandError(f"{sensor_path}: not a usable sensor.json ({exc})") from None
        # all read before storing
        scans.append((path.stem, read_scan_file(path, default, **scan_read_options(args))))
    with _runner(args) as runner, _open_existing(args, runner) as scene:
        duplicate = [s for s, _ in scans if s in scene]
        if duplicate:
            raise CommandError(f"the store already holds a scan named {duplicate[0]!r}")
        check_scans(  # the budgets before any scan is stored (docs/budgets.md)
            scans, scene.params, scene.grid, budget_limits(args),
            scene.catalog.n_tiles(scene.scene_id),
        )  # fmt: skip
        _store_and_integrate(scene, scans, args.quiet, "add")
    return 0


def _cmd_remove(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    with _runner(args) as runner, _open_existing(args, runner) as scene:
        if args.scan_id not in scene:
            raise CommandError(f"the store holds no scan {args.scan_id!r}")
        report = scene.remove(args.scan_id)
    print(
        f"removed scan {args.scan_id}: updated {report.tiles_written} tiles, deleted "
        f"{report.tiles_deleted} in {time.perf_counter() - t0:.2f} s"
    )
    return 0


def _cmd_extract(args: argparse.Namespace) -> int:
    if args.output is None and args.grid_out is None:
        raise CommandError("nothing to write: give -o MESH and/or --grid-out GRID.npz")
    check_outputs(args)
    with _runner(args) as runner, _open_existing(args, runner) as scene:
        if scene.scan_rows(("stored",)):
            print("note: some scans are stored but not fused yet; run `rangefuse add` or fuse")
        _write_scene_outputs(args, scene)
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    with _open_existing(args) as scene:
        info = scene.info()
    if args.json:
        print(json.dumps(info, indent=1))
        return 0
    states = ", ".join(f"{n} {s}" for s, n in sorted(info["scan_states"].items())) or "none"
    grid = info["grid"]
    print(f"store      {info['store']} (layout version {info['version']})")
    print(f"scans      {info['scans']} ({states})")
    print(f"tiles      {info['tiles']} of {grid['tile_size']}^3 voxels")
    print(f"voxel      {grid['voxel_size']} m, mode {grid['mode']}, bounds {grid['bounds']}")
    print(f"on disk    {info['bytes_on_disk'] / 2**20:.1f} MiB")
    return 0


def add_arguments(add: argparse.ArgumentParser) -> None:
    """The arguments of ``add``."""
    add.add_argument("store", type=Path, metavar="DIR", help="the store (made by fuse --store)")
    add.add_argument(
        "scans",
        type=Path,
        nargs="+",
        metavar="SCAN.npz",
        help="scan files (docs/formats.md), each named in the store by its file's stem",
    )
    add.add_argument(
        "--sensor",
        type=Path,
        default=None,
        metavar="sensor.json",
        help="sensor of scans that hold none (default: sensor.json beside or above them)",
    )
    cache_option(add)
    workers_option(add)
    add_budget_options(add)
    add_far_ranges_option(add)
    add.add_argument("--quiet", action="store_true", help="no progress bar")
    add.set_defaults(func=_cmd_add)


def remove_arguments(remove: argparse.ArgumentParser) -> None:
    """The arguments of ``remove``."""
    remove.add_argument("store", type=Path, metavar="DIR", help="the store")
    remove.add_argument(
        "scan_id", metavar="SCAN_ID", help="the scan to remove, as `rangefuse info` names it"
    )
    cache_option(remove)
    workers_option(remove)
    remove.set_defaults(func=_cmd_remove)


def extract_arguments(extract: argparse.ArgumentParser) -> None:
    """The arguments of ``extract``."""
    extract.add_argument("store", type=Path, metavar="DIR", help="the store")
    add_output_options(extract)
    extract.add_argument(
        "--bounds",
        type=finite_float,
        nargs=6,
        default=None,
        metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
        help="only this box (world metres)",
    )
    cache_option(extract)
    workers_option(extract)
    extract.set_defaults(func=_cmd_extract)


def info_arguments(info: argparse.ArgumentParser) -> None:
    """The arguments of ``info``."""
    info.add_argument("store", type=Path, metavar="DIR", help="the store")
    info.add_argument("--json", action="store_true", help="print JSON")
    info.set_defaults(func=_cmd_info)


def workers_option(parser: argparse.ArgumentParser) -> None:
    """``--workers N`` and ``--scheduler ADDRESS``: where the units of work run."""
    parser.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        metavar="N",
        help="run the units of work on a local Dask cluster of N worker processes, numba "
        "threads divided among them (default: in this process; same bits either way)",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="tcp://HOST:PORT",
        help="run the units of work on a running Dask cluster; the store must be on a file "
        "system its workers see",
    )


def cache_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--cache-mb",
        type=positive_float,
        default=CACHE_MB,
        metavar="MB",
        help=f"memory budget of the tile cache of a persistent store (default {CACHE_MB})",
    )
