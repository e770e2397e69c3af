"""The ``rangefuse`` command line.

``rangefuse synth`` writes analytic test scenes as dataset folders;
``rangefuse fuse`` fuses a dataset folder into a volume and, with ``-o``,
writes its surface as a mesh (with ``--grid-out``, the volume densely for
NumPy tools). Bad input ends with exit
status 2 and a message that names the problem.

Only the standard library is imported before the command is known: each command's
arguments are added by a function of its module, imported when that command is used
(:data:`_COMMANDS`), and the engine, storage, NumPy, numba, Zarr, trimesh, FastAPI and Dask
are imported by the commands that need them. ``rangefuse --help`` and ``--version`` so start
at once.
"""

from __future__ import annotations

import argparse
import importlib
import json
import re
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

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
from ._progress import ProgressBar

if TYPE_CHECKING:
    from rangefuse.engine import NoiseModel, Scan

__all__ = ["build_parser", "main"]


# --- synth ------------------------------------------------------------------------------------


def _cmd_synth(args: argparse.Namespace) -> int:
    from rangefuse.engine.synth import make_dataset, parse_noise
    from rangefuse.storage import write_dataset

    noise = parse_noise(args.noise)
    if args.out.exists() and not args.out.is_dir():
        raise CommandError(f"OUT {args.out}: exists and is not a directory")
    check_writable(args.out / "sensor.json", "OUT", make_parents=True)
    t0 = time.perf_counter()
    bar = ProgressBar("render", enabled=not args.quiet)
    try:
        data = make_dataset(
            args.scene,
            views=args.views,
            noise=noise,
            seed=args.seed,
            length_m=args.length,
            progress=bar,
        )
    finally:
        bar.close()
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
    bar = ProgressBar("write", enabled=not args.quiet)
    try:
        out = write_dataset(
            args.out, data.sensor, _counted(data.scans, bar), {"scene.json": scene_json + "\n"}
        )
    except OSError as exc:
        raise CommandError(f"OUT {args.out}: cannot write the dataset ({exc})") from None
    finally:
        bar.close()
    print(
        f"wrote {len(data.scans)} {data.sensor.model} scans of the {data.name} scene to {out} "
        f"in {time.perf_counter() - t0:.1f} s; region of interest "
        f"{' '.join(f'{b:g}' for b in data.bounds)}"
    )
    return 0


def _counted(items: Sequence[Any], bar: ProgressBar) -> Iterable[Any]:
    """``items``, with ``bar(done, total)`` after each has been used."""
    for n, item in enumerate(items):
        yield item
        bar(n + 1, len(items))


# --- fuse -------------------------------------------------------------------------------------


#: What ``fuse`` adds to a declared parameter's help.
_FUSE_NOTES = {
    "bounds": "closed mode without it: the box of the measured points plus a margin",
}


def _noise_from_args(args: argparse.Namespace) -> NoiseModel:
    from rangefuse.engine import NoiseModel
    from rangefuse.engine.params import default_eps

    eps = args.eps if args.eps is not None else default_eps(args.voxel_size)
    return NoiseModel(
        eps=eps, eps_per_m=args.eps_per_m, rho=args.rho, falloff=args.falloff, shape=args.shape
    )


def _bounds_from_data(scans: Iterable[Scan], noise: NoiseModel, voxel_size: float) -> tuple:
    import numpy as np

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
    from rangefuse.engine import FusionParams, GridSpec, Volume
    from rangefuse.engine.budget import check_grid, check_scans
    from rangefuse.storage import open_dataset

    from ._import_cli import read_source_for_fuse
    from ._store_cli import fuse_into_store

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


def _synth_arguments(synth: argparse.ArgumentParser) -> None:
    synth.add_argument(
        "scene",
        choices=("object", "room", "street"),
        metavar="SCENE",
        help="object (a robot arm, pinhole camera), room (a furnished room, RGB-D camera) or "
        "street (a street, spherical LiDAR)",
    )
    synth.add_argument(
        "out", type=Path, metavar="OUT", help="dataset folder to write (created if missing)"
    )
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
    synth.add_argument("--quiet", action="store_true", help="no progress bars")
    synth.set_defaults(func=_cmd_synth)


def _fuse_arguments(fuse: argparse.ArgumentParser) -> None:
    from rangefuse.engine.params import PARAMS

    from ._import_cli import add_source_options
    from ._store_cli import cache_option, workers_option

    fuse.add_argument(
        "dataset",
        type=Path,
        metavar="DATASET",
        help="dataset folder (sensor.json and scans/*.npz; docs/formats.md), or with --format "
        "a source in a foreign format",
    )
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
    add_source_options(fuse)
    fuse.set_defaults(func=_cmd_fuse)


#: Every command: its help line, and the module and function that add its arguments (the
#: module is imported only when the command is used).
_COMMANDS: dict[str, tuple[str, str, str]] = {
    "synth": ("write an analytic test scene as a dataset folder", ".cli", "_synth_arguments"),
    "fuse": ("fuse a dataset folder into a volume", ".cli", "_fuse_arguments"),
    "add": ("add scan files to a store and fuse them", "._store_cli", "add_arguments"),
    "remove": ("remove a scan from a store (exactly)", "._store_cli", "remove_arguments"),
    "extract": ("write a store's mesh and/or dense grid", "._store_cli", "extract_arguments"),
    "info": ("describe a store: scans, tiles, bytes, version", "._store_cli", "info_arguments"),
    "serve": ("run the REST service (uvicorn)", "._serve_cli", "serve_arguments"),
    "token": ("manage API tokens", "._serve_cli", "token_arguments"),
    "import": (
        "read scans in a foreign format (stanford, 7scenes, tum, redwood, kitti) into a "
        "dataset folder",
        "._import_cli",
        "import_arguments",
    ),
    "warmup": (
        "compile every kernel into numba's cache (first jobs start at once)",
        ".warmup",
        "add_warmup_command",
    ),
}

#: Commands that run kernels: the first compilation in the process is announced.
_KERNEL_COMMANDS = frozenset({"synth", "fuse", "add", "remove", "extract", "import"})

#: A negative number, exponent included (argparse's own pattern misses ``-1e9``, which it
#: then takes for an option).
_NEGATIVE_NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$|^-inf$|^-infinity$", re.I)


class _Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` that reads ``-1e9`` as a number, not as an option."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE_NUMBER


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("rangefuse")
    except PackageNotFoundError:
        return "unknown (not installed)"


def build_parser(commands: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The command line's parser; the arguments of ``commands`` only (default: every
    command's; every command is listed either way)."""
    wanted = set(_COMMANDS) if commands is None else set(commands)
    parser = _Parser(
        prog="rangefuse",
        description="Fuse registered range scans into 3D models (certainty fusion, "
        "Elsner, Whitaker & Abidi 1999).",
    )
    parser.add_argument(
        "--version",
        action="version",
        version=f"rangefuse {_version()}",
        help="print the version and exit",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (help_text, module, function) in _COMMANDS.items():
        command = sub.add_parser(name, help=help_text, description=help_text)
        if name in wanted:
            adder = getattr(importlib.import_module(module, __package__), function)
            adder(command)
    return parser


def _command_of(argv: Sequence[str]) -> str | None:
    """The command named in ``argv``: its first word that is not an option (the top level
    has no option that takes a value)."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in _COMMANDS else None
    return None


def _user_errors() -> tuple[type[Exception], ...]:
    """The errors that are the input's fault: a message and exit status 2."""
    from rangefuse.engine import InvalidInputError
    from rangefuse.storage import DatasetError, StoreError

    return (CommandError, InvalidInputError, DatasetError, StoreError)


def main(argv: Sequence[str] | None = None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    command = _command_of(words)
    parser = build_parser([command] if command is not None else [])
    args = parser.parse_args(words)
    try:
        if args.command in _KERNEL_COMMANDS:
            from .warmup import announce_compilation

            announce_compilation()
        return int(args.func(args))
    except KeyboardInterrupt:
        print(f"rangefuse {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if not isinstance(exc, CommandError) and not isinstance(exc, _user_errors()):
            raise
        print(
            f"rangefuse {args.command}: error: {exc}{far_ranges_hint(args, exc)}", file=sys.stderr
        )
        return 2


if __name__ == "__main__":
    sys.exit(main())
