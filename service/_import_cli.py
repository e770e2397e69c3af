"""``rangefuse import KIND SRC DST`` and ``rangefuse fuse SRC --format KIND``.

Both read a source in a foreign format through :func:`storage.importers.read_source`
(``docs/importers.md``) and print its warnings on stderr. ``import`` writes a FORMAT.md
dataset folder: into a temporary folder beside ``DST``, renamed into place at the end, so
a failure leaves nothing half-written.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from rangefuse.storage import write_dataset
from rangefuse.storage.importers import KINDS, ImportOptions, ImportResult, read_source

from ._cliutil import CommandError, check_outputs, finite_float, positive_float, positive_int

__all__ = ["add_source_options", "import_arguments", "read_source_for_fuse"]


def _add_source_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("source options (import, fuse --format)")
    group.add_argument(
        "--depth-scale",
        type=positive_float,
        default=None,
        metavar="M",
        help="metres per stored depth unit (7scenes, redwood 0.001; tum 0.0002; kitti: "
        "a factor on the points, 1)",
    )
    group.add_argument(
        "--intrinsics",
        type=positive_float,
        nargs=4,
        default=None,
        metavar=("FX", "FY", "CX", "CY"),
        help="pinhole intrinsics in pixels (default: camera-intrinsics.txt for 7scenes, "
        "525 525 319.5 239.5 for tum and redwood)",
    )
    group.add_argument(
        "--range-convention",
        choices=("z", "ray"),
        default=None,
        help="what RGB-D depth images hold: z-depth (default) or ray range",
    )
    group.add_argument(
        "--max-range",
        type=positive_float,
        default=None,
        metavar="M",
        help="the sensor's max_range (default per format)",
    )
    group.add_argument(
        "--tolerance",
        type=positive_float,
        default=None,
        metavar="S",
        help="tum: largest time between a depth frame and its pose (0.02)",
    )
    group.add_argument(
        "--trajectory",
        type=Path,
        default=None,
        metavar="FILE",
        help="the pose file when it is not in SRC (redwood .log, kitti poses, tum ground truth)",
    )
    group.add_argument(
        "--every", type=positive_int, default=1, metavar="N", help="take every N-th frame"
    )
    group.add_argument(
        "--beams", type=positive_int, default=None, metavar="N", help="kitti: laser beams (64)"
    )
    group.add_argument(
        "--columns",
        type=positive_int,
        default=None,
        metavar="N",
        help="kitti: azimuth columns of a turn (2048)",
    )
    group.add_argument(
        "--axis",
        type=finite_float,
        nargs=2,
        default=None,
        metavar=("Y", "Z"),
        help="stanford: the scanner's rotation axis in the scan frame (0.1748 1.3731)",
    )
    group.add_argument(
        "--max-step",
        type=positive_float,
        default=None,
        metavar="M",
        help="stanford: largest range step interpolated across (8 column pitches: 0.004 for "
        "the bunny)",
    )
    group.add_argument(
        "--invert-poses",
        action="store_true",
        help="the source's poses are world-to-sensor: invert them",
    )
    group.add_argument(
        "--no-checks",
        action="store_true",
        help="skip the sanity checks (depth scale, range convention, pose direction)",
    )


def _options(args: argparse.Namespace) -> ImportOptions:
    given = {
        "depth_scale_m": args.depth_scale,
        "intrinsics": tuple(args.intrinsics) if args.intrinsics is not None else None,
        "range_convention": args.range_convention,
        "max_range_m": args.max_range,
        "tolerance_s": args.tolerance,
        "trajectory": args.trajectory,
        "beams": args.beams,
        "columns": args.columns,
        "axis_yz_m": tuple(args.axis) if args.axis is not None else None,
        "max_step_m": args.max_step,
    }
    return ImportOptions(
        every=args.every,
        invert_poses=args.invert_poses,
        checks=not args.no_checks,
        **{k: v for k, v in given.items() if v is not None},
    )


def _read(kind: str, src: Path, args: argparse.Namespace) -> ImportResult:
    t0 = time.perf_counter()
    result = read_source(kind, src, _options(args))
    for message in result.warnings:
        print(f"rangefuse {args.command}: warning: {message}", file=sys.stderr)
    print(
        f"read {len(result)} {kind} scans from {result.source} in {time.perf_counter() - t0:.1f} s",
        file=sys.stderr,
    )
    return result


def read_source_for_fuse(args: argparse.Namespace) -> ImportResult:
    """``fuse SRC --format KIND``: the scans of SRC, in memory (refuses ``--store``)."""
    if args.store is not None:
        raise CommandError(
            "--format with --store: import the source into a dataset folder first "
            "(rangefuse import KIND SRC DST), then fuse DST --store DIR"
        )
    check_outputs(args)  # before the (possibly long) read
    return _read(args.format, args.dataset, args)


def _cmd_import(args: argparse.Namespace) -> int:
    dst: Path = args.dst
    if dst.exists() and not (dst.is_dir() and not any(dst.iterdir())):
        raise CommandError(f"DST {dst}: already exists and is not an empty folder")
    parent = dst.resolve().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.", suffix=".import", dir=parent))
    except OSError as exc:
        raise CommandError(f"DST {dst}: cannot write in {parent} ({exc.strerror})") from None
    try:
        result = _read(args.kind, args.src, args)
        write_dataset(tmp, result.sensor, result.scans())
        os.chmod(tmp, 0o777 & ~_umask())
        if dst.is_dir():
            dst.rmdir()
        os.replace(tmp, dst)
    except OSError as exc:
        raise CommandError(f"DST {dst}: cannot write the dataset ({exc})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    sensors = {scan.sensor for _, scan in result.items}
    print(
        f"wrote {len(result)} {result.sensor.model} scans ({len(sensors)} "
        f"sensor{'s' if len(sensors) > 1 else ''}) to {dst}"
    )
    return 0


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def import_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments of ``import``."""
    parser.add_argument("kind", choices=KINDS, metavar="KIND", help=", ".join(KINDS))
    parser.add_argument("src", type=Path, metavar="SRC", help="source folder (or .conf file)")
    parser.add_argument("dst", type=Path, metavar="DST", help="dataset folder to write (new)")
    _add_source_options(parser)
    parser.set_defaults(func=_cmd_import)


def add_source_options(fuse: argparse.ArgumentParser) -> None:
    """Give ``fuse`` its ``--format KIND`` and the source options."""
    fuse.add_argument(
        "--format",
        choices=KINDS,
        default=None,
        metavar="KIND",
        help="DATASET is a source in this format (" + ", ".join(KINDS) + "), read directly",
    )
    _add_source_options(fuse)
