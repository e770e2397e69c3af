"""The ``rangefuse`` command line.

``rangefuse synth`` writes analytic test scenes as dataset folders;
``rangefuse fuse`` fuses a dataset folder into a volume and, with ``-o``,
writes its surface as a mesh (with ``--grid-out``, the volume densely for
NumPy tools). Bad input ends with exit
status 2 and a message that names the problem.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from rangefuse.engine import FusionParams, GridSpec, InvalidInputError, NoiseModel, Scan, Volume
from rangefuse.engine.budget import check_grid, check_scans
from rangefuse.engine.params import PARAMS, default_eps
from rangefuse.storage import DatasetError, StoreError, open_dataset, write_dataset

from ._cliutil import (
    CommandError,
    add_budget_options,
    add_far_ranges_option,
    add_output_options,
    add_param_option,
    budget_limits,
    check_outputs,
    check_writable,
    far_ranges_hint,
    far_ranges_note,
    positive_float,
    positive_int,
    scan_read_options,
    write_outputs,
)
from ._import_cli import add_import_command, read_source_for_fuse
from ._progress import ProgressBar
from ._serve_cli import add_serve_commands
from ._store_cli import add_store_commands, cache_option, fuse_into_store, workers_option
from .warmup import add_warmup_command

__all__ = ["main"]


# --- synth ------------------------------------------------------------------------------------


def _cmd_synth(args: argparse.Namespace) -> int:
    from rangefuse.engine.synth import make_dataset, parse_noise

    noise = parse_noise(args.noise)
    if args.out.exists() and not args.out.is_dir():
        raise CommandError(f"OUT {args.out}: exists and is not a directory")
    check_writable(args.out / "sensor.json", "OUT")
    t0 = time.perf_counter()
    data = make_dataset(
        args.scene, views=args.views, noise=noise, seed=args.seed, length_m=args.length
    )
    scene_json = json.dumps(
        {
            "scene": data.name,
            "bounds": list(data.bounds),
            "noise": args.noise,
            "seed": args.seed,
            "solids": data.scene.to_dict(),
        },
        indent=1,
    )
    stale = sorted(
        p.name
        for p in (args.out / "scans").glob("*.npz")
        if p.stem not in {name for name, _ in data.scans}
    )
    if stale:
        raise CommandError(
            f"OUT {args.out}: already holds {len(stale)} scans that this run would not replace "
            f"({stale[0]}, ...), which would mix two datasets; remove them or choose another folder"
        )
    try:
        out = write_dataset(args.out, data.sensor, data.scans, {"scene.json": scene_json + "\n"})
    except OSError as exc:
        raise CommandError(f"OUT {args.out}: cannot write the dataset ({exc})") from None
    print(
        f"wrote {len(data.scans)} {data.sensor.model} scans of the {data.name} scene to {out} "
        f"in {time.perf_counter() - t0:.1f} s; region of interest "
        f"{' '.join(f'{b:g}' for b in data.bounds)}"
    )
    return 0


# --- fuse -------------------------------------------------------------------------------------


#: What ``fuse`` adds to a declared parameter's help.
_FUSE_NOTES = {
    "bounds": "closed mode without it: the box of the measured points plus a margin",
}


def _noise_from_args(args: argparse.Namespace) -> NoiseModel:
    eps = args.eps if args.eps is not None else default_eps(args.voxel_size)
    return NoiseModel(
        eps=eps, eps_per_m=args.eps_per_m, rho=args.rho, falloff=args.falloff, shape=args.shape
    )


def _bounds_from_data(scans: Iterable[Scan], noise: NoiseModel, voxel_size: float) -> tuple:
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    max_range = 0.0
    for scan in scans:
        pts = scan.points_W()
        if len(pts):
            lo = np.minimum(lo, pts.min(axis=0))
            hi = np.maximum(hi, pts.max(axis=0))
            max_range = max(max_range, float(np.nanmax(scan.range_m[np.isfinite(scan.range_m)])))
    if not np.all(np.isfinite(lo)):
        raise CommandError("closed mode: no scan has a measured point; give --bounds")
    pad = 2.0 * (noise.eps + noise.eps_per_m * max_range) + 2.0 * voxel_size
    return tuple(float(x) for x in np.concatenate([lo - pad, hi + pad]))


def _kept(items: Iterable[tuple[str, Scan]], into: list) -> Iterable[tuple[str, Scan]]:
    """``items``, each also appended to ``into`` (the scans are read once)."""
    for item in items:
        into.append(item)
        yield item


def _cmd_fuse(args: argparse.Namespace) -> int:
    # --format KIND: a source in a foreign format, read into memory (service/_import_cli.py)
    read = scan_read_options(args)  # pixel limit, --accept-far-ranges
    dataset = read_source_for_fuse(args) if args.format else open_dataset(args.dataset, **read)
    noise = _noise_from_args(args)
    params = FusionParams(
        noise=noise,
        filter=args.filter,
        max_discontinuity=args.max_discontinuity,
        no_return=args.no_return,
    )
    GridSpec(args.voxel_size, args.tile_size, "mapping", args.bounds)  # validate early
    check_outputs(args)
    t0 = time.perf_counter()
    bounds = tuple(args.bounds) if args.bounds is not None else None
    if args.mode == "closed" and bounds is None:  # reads the scans one at a time
        bounds = _bounds_from_data((s for _, s in dataset.scans()), noise, args.voxel_size)
        if not args.quiet:
            print(
                "closed mode: region of interest from the data: "
                + " ".join(f"{b:.4g}" for b in bounds),
                file=sys.stderr,
            )
    grid = GridSpec(args.voxel_size, args.tile_size, args.mode, bounds)
    limits = budget_limits(args, in_memory=args.store is None)
    check_grid(grid, limits)  # resource budgets before any fusion (docs/budgets.md)
    if args.store is not None:
        return fuse_into_store(args, args.dataset, grid, params, limits)
    scans: list[tuple[str, Scan]] = []
    check_scans(_kept(dataset.scans(), scans), params, grid, limits)
    for name, scan in scans:
        if scan.far_ranges:
            print(f"note: {name}:{far_ranges_note(scan)}", file=sys.stderr)
    volume = Volume(grid, params)
    bar = ProgressBar("fuse", enabled=not args.quiet)
    try:
        report = volume.add_many(scans, progress=bar)
    finally:
        bar.close()
    elapsed = time.perf_counter() - t0
    n_tiles = len(volume.tile_keys())
    print(
        f"fused {report.scans} scans into {n_tiles} tiles of {grid.tile_size}^3 voxels "
        f"({report.voxel_updates:,} voxel updates) in {elapsed:.2f} s"
    )
    write_outputs(
        args, volume.to_dense, lambda refine, b: volume.extract_mesh(refine=refine, bounds=b)
    )
    return 0


# --- parser -----------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rangefuse",
        description="Fuse registered range scans into 3D models (certainty fusion, "
        "Elsner, Whitaker & Abidi 1999).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    synth = sub.add_parser("synth", help="write an analytic test scene as a dataset folder")
    synth.add_argument("scene", choices=("object", "room", "street"))
    synth.add_argument("out", type=Path, metavar="OUT", help="dataset folder to write")
    synth.add_argument(
        "--views",
        type=positive_int,
        default=None,
        help="number of scans (default: 12 object, 100 room, one per 2 m street)",
    )
    synth.add_argument(
        "--noise",
        default="none",
        help="comma-separated noise: uniform:M, gaussian:M, spikes:FRACTION, "
        "dropouts:FRACTION, background:inf|nan (default: none)",
    )
    synth.add_argument("--seed", type=int, default=0, help="seed of the noise (default 0)")
    synth.add_argument(
        "--length",
        type=positive_float,
        default=None,
        help="street length in metres (street only; default 40)",
    )
    synth.set_defaults(func=_cmd_synth)

    fuse = sub.add_parser("fuse", help="fuse a dataset folder into a volume")
    fuse.add_argument("dataset", type=Path, metavar="DATASET")
    for param in PARAMS.values():  # every fusion and grid parameter, as declared
        add_param_option(fuse, param, _FUSE_NOTES.get(param.name, ""))
    add_output_options(fuse)
    fuse.add_argument(
        "--store",
        type=Path,
        default=None,
        metavar="DIR",
        help="fuse into a persistent store (created if missing; re-running resumes and adds "
        "the scans it does not hold yet)",
    )
    cache_option(fuse)
    workers_option(fuse)
    add_budget_options(fuse, in_memory=True)
    add_far_ranges_option(fuse)
    fuse.add_argument("--quiet", action="store_true", help="no progress bar")
    fuse.set_defaults(func=_cmd_fuse)
    add_store_commands(sub)
    add_serve_commands(sub)
    add_import_command(sub)
    add_warmup_command(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (CommandError, InvalidInputError, DatasetError, StoreError) as exc:
        print(
            f"rangefuse {args.command}: error: {exc}{far_ranges_hint(args, exc)}", file=sys.stderr
        )
        return 2
    except KeyboardInterrupt:
        print(f"rangefuse {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
