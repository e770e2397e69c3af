"""The FORMAT.md dataset folder: ``sensor.json`` and ``scans/*.npz``.

Reading never unpickles, never reads more than a header declares, and checks the range
map's declared size against a pixel limit before reading it (:mod:`storage.bounded`);
it refuses malformed files with a :class:`DatasetError` whose message names the file and
what is wrong.
Writing goes through a temporary file and a rename, so an interrupted writer
never leaves a half-written scan behind.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rangefuse.engine import InvalidInputError, InvalidScanError, Scan, Sensor, sensor_from_dict
from rangefuse.engine.errors import FarRangesError
from rangefuse.engine.scans import check_range_layout

from ._files import atomic_write, atomic_write_text
from .bounded import DEFAULT_MAX_PIXELS, DecodeError, NpyHeader, NpzArchive, check_pixels

__all__ = [
    "Dataset",
    "DatasetError",
    "check_range_header",
    "open_dataset",
    "read_scan_file",
    "write_dataset",
    "write_scan_file",
]

SENSOR_FILE = "sensor.json"
SCANS_DIR = "scans"


class DatasetError(ValueError):
    """A dataset folder or scan file that cannot be read; the message names the file."""


def _sensor_from_json(text: str, where: str) -> Sensor:
    try:
        data = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise DatasetError(f"{where}: not valid JSON ({exc})") from None
    try:
        return sensor_from_dict(data)
    except InvalidInputError as exc:
        raise DatasetError(f"{where}: {exc}") from None
    except (TypeError, ValueError, OverflowError, AttributeError, KeyError) as exc:
        # defence in depth: a value of a foreign type, an integer too large for a float
        raise DatasetError(f"{where}: not a valid sensor ({exc})") from None


def _read_npz(
    path: Path, where: str, required: tuple[str, ...], optional: tuple[str, ...] = ()
) -> dict[str, np.ndarray]:
    """The ``required`` and present ``optional`` arrays of an ``.npz`` file, by key.

    Never unpickles; reads each member through :class:`storage.bounded.NpzArchive` (never more
    than its header declares); every failure is a :class:`DatasetError` naming ``where`` and,
    once the archive opens, the key. Shared with :mod:`storage.grids`.
    """
    try:
        with NpzArchive(path, where, required) as npz:
            for key in required:
                if key not in npz:
                    raise DatasetError(f"{where}: missing key {key!r} (has {npz.keys})")
            return {
                key: npz.read(key, npz.header(key)) for key in required + optional if key in npz
            }
    except DecodeError as exc:
        raise DatasetError(str(exc)) from None


#: Largest per-scan ``sensor`` JSON read (bytes).
_MAX_SENSOR_BYTES = 1 << 20


def _scan_sensor(npz: NpzArchive, where: str, default: Sensor | None, no_sensor: str) -> Sensor:
    if "sensor" not in npz:
        if default is None:
            raise DatasetError(f"{where}: no per-scan 'sensor' and {no_sensor}")
        return default
    header = npz.header("sensor")
    if header.dtype.kind not in "US" or header.shape != ():
        raise DatasetError(f"{where}: key 'sensor' must be a JSON string")
    if header.nbytes > _MAX_SENSOR_BYTES:
        raise DatasetError(f"{where}: key 'sensor' is over {_MAX_SENSOR_BYTES:,} bytes")
    value = npz.read("sensor", header).item()
    if isinstance(value, bytes):
        try:
            value = value.decode()
        except UnicodeDecodeError:
            raise DatasetError(f"{where}: key 'sensor' is not UTF-8 text") from None
    return _sensor_from_json(value, f"{where}: sensor")


def _scan_pose(npz: NpzArchive, where: str) -> np.ndarray:
    header = npz.header("pose")
    if header.dtype.kind not in "fiu":
        raise DatasetError(f"{where}: pose: must be numeric, got dtype {header.dtype}")
    if header.shape != (4, 4):  # the words of engine.check_pose
        raise DatasetError(f"{where}: pose: must be 4x4, got shape {header.shape}")
    return npz.read("pose", header).astype(np.float64)


def check_range_header(
    header: NpyHeader, where: str, what: str, sensor: Sensor | None, max_pixels: int | None
) -> None:
    """Check a range map's declared dtype and shape before it is read: a float array of
    2 dimensions, at most ``max_pixels`` pixels, of the sensor's height x width. Raises
    :class:`engine.InvalidScanError` (the scan's own words) or :class:`DecodeError`."""
    check_range_layout(header.dtype, header.shape)
    if header.dtype.itemsize > 8:
        raise InvalidScanError(
            "range", f"must be float16, float32 or float64, got dtype {header.dtype}"
        )
    check_pixels(where, what, header.shape[0], header.shape[1], max_pixels)
    check_range_layout(header.dtype, header.shape, None if sensor is None else sensor.shape)


def read_scan_file(
    path: str | os.PathLike[str] | bytes,
    default_sensor: Sensor | None,
    *,
    max_pixels: int | None = DEFAULT_MAX_PIXELS,
    accept_far_ranges: bool = False,
    where: str | None = None,
    no_sensor: str = f"no {SENSOR_FILE} in the dataset",
) -> Scan:
    """Read one ``scans/*.npz`` file (FORMAT.md) into a validated :class:`Scan`.

    The ``range`` key's header is checked (dtype, 2-D, at most ``max_pixels`` pixels, the
    sensor's height x width) before its data are read, and no member is ever inflated past
    what its header declares (:class:`storage.bounded.NpzArchive`).

    Parameters
    ----------
    path : path-like or bytes
        The file, or its contents (an upload; then give ``where``).
    default_sensor : Sensor or None
        The dataset's ``sensor.json``; a per-scan ``sensor`` key replaces it.
    max_pixels : int or None
        Largest range map read (None: no limit).
    accept_far_ranges : bool
        Passed to :class:`Scan`: keep a map whose ranges mostly lie beyond ``max_range``.
    where : str or None
        Names the file in messages (default: the path).
    no_sensor : str
        Where else a sensor could have come from, for the message when the file holds none
        and ``default_sensor`` is None (an upload has no ``sensor.json``).

    Raises
    ------
    DatasetError
        For a file that is not a readable ``.npz`` (truncated, corrupted, pickled objects,
        a header declaring too much), a missing key, or a range map, pose or sensor that fails
        validation; the message names the file and the key or field.
    engine.FarRangesError
        A range map whose ranges mostly lie beyond the sensor's ``max_range`` or look like
        millimetres (unless ``accept_far_ranges``); the message names the file.
    """
    if where is None:
        where = str(path) if not isinstance(path, bytes) else "scan"
    try:
        with NpzArchive(path, where, ("range", "pose")) as npz:
            for key in ("range", "pose"):
                if key not in npz:
                    raise DatasetError(f"{where}: missing key {key!r} (has {npz.keys})")
            sensor = _scan_sensor(npz, where, default_sensor, no_sensor)
            pose = _scan_pose(npz, where)
            header = npz.header("range")
            check_range_header(header, where, "key 'range'", sensor, max_pixels)
            range_m = npz.read("range", header)
        return Scan(range_m, pose, sensor, accept_far_ranges=accept_far_ranges)
    except DecodeError as exc:
        raise DatasetError(str(exc)) from None
    except FarRangesError as exc:
        raise FarRangesError(f"{where}: {exc.field}", exc.problem) from None
    except InvalidInputError as exc:
        raise DatasetError(f"{where}: {exc}") from None


@dataclass(frozen=True)
class Dataset:
    """A dataset folder: its default sensor (if any) and its scan files in name order."""

    path: Path
    sensor: Sensor | None
    scan_paths: tuple[Path, ...]
    max_pixels: int | None = DEFAULT_MAX_PIXELS
    accept_far_ranges: bool = False

    def __len__(self) -> int:
        return len(self.scan_paths)

    @property
    def names(self) -> list[str]:
        """Scan names: the file stems."""
        return [p.stem for p in self.scan_paths]

    def scans(self) -> Iterator[tuple[str, Scan]]:
        """Yield ``(name, Scan)`` in file-name order, reading one file at a time."""
        for p in self.scan_paths:
            yield (
                p.stem,
                read_scan_file(
                    p,
                    self.sensor,
                    max_pixels=self.max_pixels,
                    accept_far_ranges=self.accept_far_ranges,
                ),
            )


def open_dataset(
    path: str | os.PathLike[str],
    *,
    max_pixels: int | None = DEFAULT_MAX_PIXELS,
    accept_far_ranges: bool = False,
) -> Dataset:
    """Open a FORMAT.md dataset folder (reads ``sensor.json`` and lists ``scans/*.npz``);
    its scans are read with ``max_pixels`` and ``accept_far_ranges`` (see
    :func:`read_scan_file`)."""
    root = Path(path)
    if not root.exists():
        raise DatasetError(f"{root}: no such dataset folder")
    if not root.is_dir():
        raise DatasetError(f"{root}: not a directory")
    sensor_path = root / SENSOR_FILE
    sensor = None
    if sensor_path.exists():
        try:
            text = sensor_path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{sensor_path}: cannot be read as UTF-8 text ({exc})") from None
        sensor = _sensor_from_json(text, str(sensor_path))
    scans_dir = root / SCANS_DIR
    if not scans_dir.is_dir():
        raise DatasetError(f"{root}: no {SCANS_DIR}/ folder")
    paths = tuple(sorted(p for p in scans_dir.glob("*.npz") if p.is_file()))
    if not paths:
        raise DatasetError(f"{scans_dir}: no .npz scans")
    return Dataset(root, sensor, paths, max_pixels, accept_far_ranges)


def write_scan_file(path: str | os.PathLike[str], scan: Scan, include_sensor: bool) -> None:
    """Write one scan as a FORMAT.md ``.npz`` (atomically)."""
    arrays: dict[str, Any] = {
        "range": np.asarray(scan.range_m, np.float32),
        "pose": np.asarray(scan.T_W_S, np.float64),
    }
    if include_sensor:
        arrays["sensor"] = np.array(json.dumps(scan.sensor.to_dict()))
    atomic_write(Path(path), lambda fh: np.savez(fh, **arrays))


def write_dataset(
    path: str | os.PathLike[str],
    sensor: Sensor,
    scans: Iterable[tuple[str, Scan]],
    extra_files: dict[str, str] | None = None,
) -> Path:
    """Write a dataset folder: ``sensor.json``, ``scans/NAME.npz`` and optional extra text files.

    A scan whose sensor differs from ``sensor`` carries its own in the ``sensor`` key.
    """
    root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    text = json.dumps(sensor.to_dict(), indent=2) + "\n"
    atomic_write_text(root / SENSOR_FILE, text)
    for name, scan in scans:
        write_scan_file(root / SCANS_DIR / f"{name}.npz", scan, scan.sensor != sensor)
    for name, content in (extra_files or {}).items():
        atomic_write_text(root / name, content)
    return root
