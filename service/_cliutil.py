"""Helpers shared by the command-line modules: user errors, argument types, outputs, and the
options of the declared parameters.

Only the standard library is imported here at first: the engine, storage, trimesh and dask
are imported inside the helpers that need them, so that ``rangefuse --help`` starts at once.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rangefuse.engine import DenseGrid, Scan
    from rangefuse.engine.budget import Limits
    from rangefuse.engine.meshing import Mesh
    from rangefuse.engine.params import Param


class CommandError(Exception):
    """A user error: printed as ``rangefuse CMD: error: MESSAGE``, exit status 2."""


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return value


def finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text!r}")
    return value


def param_type(param: Param) -> Callable[[str], Any]:
    """The argparse ``type`` of a declared number: converts, then checks it as declared
    (``--rho: outlier probability must be in (0, 1/2), got 0.7``)."""
    from rangefuse.engine import InvalidInputError

    integer = param.kind == "int"

    def convert(text: str) -> Any:
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"not {'an integer' if integer else 'a number'}: {text!r}"
            ) from None
        try:
            return param.validate(value)
        except InvalidInputError as exc:
            raise argparse.ArgumentTypeError(exc.problem) from None

    convert.__name__ = param.name
    return convert


def add_param_option(parser: argparse.ArgumentParser, param: Param, note: str = "") -> None:
    """``--name`` for a parameter declared in ``engine/params.py``: its type and range,
    choices, default, and help with unit, range and default (``note`` adds a sentence)."""
    kwargs: dict[str, Any] = {"default": param.default, "required": param.required}
    if param.kind == "choice":
        kwargs["choices"] = param.choices
    elif param.kind == "bounds":  # the box as a whole is checked by GridSpec
        kwargs.update(type=finite_float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"))
    else:
        kwargs.update(type=param_type(param), metavar=param.metavar)
    kwargs["help"] = param.describe(param.metavar or None) + (f"; {note}" if note else "")
    parser.add_argument(param.flag, **kwargs)


def check_writable(path: Path, option: str, make_parents: bool = False) -> None:
    """Fail before any work when ``path`` cannot be written.

    Refuses an existing folder, a parent that is a file, a missing parent folder (unless
    ``make_parents``: a folder that the command creates, such as a dataset folder), and a
    folder that does not accept files (probed with a temporary file that leaves nothing
    behind).
    """
    if path.is_dir():
        raise CommandError(f"{option} {path}: is a directory")
    parent = path.parent
    if not parent.exists() and not make_parents:
        raise CommandError(
            f"{option} {path}: no folder {parent} (create it first, or choose another path)"
        )
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise CommandError(f"{option} {path}: {parent} is not a directory")
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as exc:
        raise CommandError(f"{option} {path}: cannot write in {parent} ({exc.strerror})") from None


def check_outputs(args: argparse.Namespace) -> None:
    """Refuse unwritable ``--grid-out`` / ``-o`` paths and unknown mesh types before work."""
    from rangefuse.storage.meshes import MeshFormatError, mesh_format

    if getattr(args, "grid_out", None) is not None:
        check_writable(args.grid_out, "--grid-out")
    if getattr(args, "output", None) is not None:
        try:
            mesh_format(args.output)
        except MeshFormatError as exc:
            raise CommandError(f"-o: {exc}") from None
        check_writable(args.output, "-o")


def write_outputs(
    args: argparse.Namespace,
    to_dense: Callable[[Sequence[float] | None], DenseGrid],
    extract_mesh: Callable[[bool, Sequence[float] | None], Mesh],
) -> None:
    """Write ``--grid-out`` and ``-o`` when asked (the region: ``--bounds`` if given)."""
    from rangefuse.storage import write_grid
    from rangefuse.storage.meshes import write_mesh

    if args.grid_out is not None:
        dense = to_dense(args.bounds)
        try:
            write_grid(args.grid_out, dense)
        except OSError as exc:
            raise CommandError(f"--grid-out {args.grid_out}: cannot write ({exc})") from None
        print(f"wrote {'x'.join(map(str, dense.logodds.shape))} grid to {args.grid_out}")
    if args.output is not None:
        t0 = time.perf_counter()
        mesh = extract_mesh(not args.no_refine, args.bounds)
        elapsed = time.perf_counter() - t0
        try:
            write_mesh(args.output, mesh)
        except OSError as exc:
            raise CommandError(f"-o {args.output}: cannot write ({exc})") from None
        inferred = int(mesh.inferred.sum())
        print(
            f"wrote {mesh.n_faces:,} triangles ({inferred:,} inferred), {mesh.n_vertices:,} "
            f"vertices to {args.output} (extracted in {elapsed:.2f} s)"
        )


def add_output_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--grid-out",
        type=Path,
        default=None,
        metavar="GRID.npz",
        help="write the fused log-odds densely (FORMAT.md; NaN = unknown)",
    )
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        metavar="MESH",
        help="write the surface as a mesh: .ply (binary, with an 'inferred' face flag), "
        ".obj, .glb or .stl",
    )
    parser.add_argument(
        "--no-refine",
        action="store_true",
        help="place vertices by linear interpolation of the log-odds instead of re-evaluating "
        "the scans along each edge (faster, less accurate)",
    )


def size_bytes(text: str) -> int:
    """A size such as ``64GiB``, ``500MB`` or a number of bytes."""
    from dask.utils import parse_bytes

    try:
        value = int(parse_bytes(text))
    except (ValueError, TypeError):
        raise argparse.ArgumentTypeError(
            f"not a size such as 64GiB or a number of bytes: {text!r}"
        ) from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1 byte, got {text!r}")
    return value


def add_budget_options(parser: argparse.ArgumentParser, in_memory: bool = False) -> None:
    """``--max-scan-tiles N``, ``--max-scene-tiles N``, ``--max-scene-bytes SIZE``: the limits
    declared in ``engine/budget.py``, checked before any fusion (docs/budgets.md).
    ``in_memory``: the command can fuse in memory, where the bytes default to a share of
    the machine's memory (:func:`budget_limits`)."""
    from rangefuse.engine.budget import LIMITS

    for limit in LIMITS.values():
        if limit.unit == "bytes":
            default = f"{limit.default / 2**30:g} GiB"
            if in_memory:
                share = f"{_MEMORY_SHARE:.0%}".replace("%", "%%")  # argparse formats help
                default += f" with --store; in memory at most {share} of this machine's memory"
            kwargs: dict[str, Any] = {"type": size_bytes, "metavar": "SIZE"}
        else:
            default = f"{limit.default:,}"
            kwargs = {"type": positive_int, "metavar": "N"}
        parser.add_argument(
            "--" + limit.name.replace("_", "-"),
            default=None,
            help=f"{limit.help} (default {default})",
            **kwargs,
        )


#: The in-memory volume's bytes by default: this share of the machine's memory at most.
_MEMORY_SHARE = 0.75


def budget_limits(args: argparse.Namespace, in_memory: bool = False) -> Limits:
    """The limits of ``--max-*`` (their defaults when not given), named by their options in
    messages. In memory (``fuse`` without ``--store``) the scene's voxels are held in this
    process: their bytes are limited to ``_MEMORY_SHARE`` of the machine's memory too."""
    from rangefuse.engine.budget import LIMITS, Limits

    values = {}
    knobs = {name: "--" + name.replace("_", "-") for name in LIMITS}
    for limit in LIMITS.values():
        given = getattr(args, limit.name, None)
        values[limit.name] = limit.default if given is None else given
    if in_memory and getattr(args, "max_scene_bytes", None) is None:
        try:
            memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError):
            memory = 0
        if 0 < memory * _MEMORY_SHARE < values["max_scene_bytes"]:
            values["max_scene_bytes"] = int(memory * _MEMORY_SHARE)
            knobs["max_scene_bytes"] += (
                f"; by default {_MEMORY_SHARE:.0%} of this machine's memory when fusing in memory"
            )
    return Limits(**values, knobs=knobs)


# --- reading scan files (docs/input-safety.md) ------------------------------------------------


def add_far_ranges_option(parser: argparse.ArgumentParser) -> None:
    """``--accept-far-ranges``: fuse range maps that the range sanity check would refuse."""
    parser.add_argument(
        "--accept-far-ranges",
        action="store_true",
        help="fuse scans whose measured ranges mostly lie beyond the sensor's max_range or "
        "look like millimetres (refused otherwise); ranges beyond max_range stay invalid",
    )


def scan_read_options(args: argparse.Namespace) -> dict[str, Any]:
    """How scan files are read: the pixel limit ``RANGEFUSE_MAX_PIXELS`` (as the service
    reads it) and ``--accept-far-ranges``."""
    from rangefuse.storage.bounded import DEFAULT_MAX_PIXELS, LIMIT_SETTING

    text = os.environ.get(LIMIT_SETTING)
    max_pixels = DEFAULT_MAX_PIXELS
    if text is not None:
        try:
            max_pixels = int(text)
        except ValueError:
            max_pixels = 0
        if max_pixels < 1:
            raise CommandError(f"{LIMIT_SETTING}: must be a positive integer, got {text!r}")
    accept = bool(getattr(args, "accept_far_ranges", False))
    if accept and getattr(args, "format", None):
        raise CommandError(
            "--accept-far-ranges applies to dataset folders; with --format, give the source's "
            "--depth-scale or --max-range instead"
        )
    return {"max_pixels": max_pixels, "accept_far_ranges": accept}


def far_ranges_note(scan: Scan) -> str:
    """`` (N ranges beyond max_range M m set invalid)`` for a scan that had some, else ''."""
    if not scan.far_ranges:
        return ""
    return (
        f" ({scan.far_ranges:,} ranges beyond the sensor's max_range of "
        f"{scan.sensor.max_range:g} m set invalid)"
    )


def far_ranges_hint(args: argparse.Namespace, exc: Exception) -> str:
    """What to add to a refusal of far ranges: the option that overrides it, if any."""
    from rangefuse.engine.errors import FarRangesError

    if not isinstance(exc, FarRangesError) or not hasattr(args, "accept_far_ranges"):
        return ""
    if getattr(args, "format", None):
        return ""
    return "; to fuse it anyway, pass --accept-far-ranges"
