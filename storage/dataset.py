"""The FORMAT.md dataset folder: ``sensor.json`` and ``scans/*.npz``.

Reading never unpickles (``allow_pickle=False``) and refuses malformed files
with a :class:`DatasetError` whose message names the file and what is wrong.
Writing goes through a temporary file and a rename, so an interrupted writer
never leaves a half-written scan behind.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rangefuse.engine import InvalidInputError, Scan, Sensor, sensor_from_dict

from ._files import atomic_write, atomic_write_text

__all__ = [
    "Dataset",
    "DatasetError",
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
    except (TypeError, ValueError) as exc:  # defence in depth: a value of a foreign type
        raise DatasetError(f"{where}: not a valid sensor ({exc})") from None


#: What reading a damaged or foreign file can raise inside ``np.load`` and ``zipfile``:
#: truncation, bad CRCs or deflate streams, unsupported zip features, encrypted members,
#: a corrupted ``.npy`` header claiming an impossible shape.
_READ_ERRORS = (
    OSError,
    EOFError,
    zipfile.BadZipFile,
    zlib.error,
    NotImplementedError,
    RuntimeError,
    MemoryError,
)


def _read_npz(
    path: Path, where: str, required: tuple[str, ...], optional: tuple[str, ...] = ()
) -> dict[str, np.ndarray]:
    """The ``required`` and present ``optional`` arrays of an ``.npz`` file, by key.

    Never unpickles (``allow_pickle=False``); every failure is a :class:`DatasetError`
    naming ``where`` and, once the archive opens, the key. Shared with :mod:`storage.grids`.
    """
    try:
        loaded = np.load(path, allow_pickle=False)
    except ValueError as exc:
        if "pickle" in str(exc).lower():  # neither zip nor .npy magic: np.load would unpickle
            raise DatasetError(
                f"{where}: not an .npz file (neither a zip archive nor NumPy data)"
            ) from None
        raise DatasetError(f"{where}: not a readable .npz file ({exc})") from None
    except _READ_ERRORS as exc:
        raise DatasetError(f"{where}: not a readable .npz file ({exc})") from None
    if not isinstance(loaded, np.lib.npyio.NpzFile):
        raise DatasetError(
            f"{where}: holds a single .npy array, not an .npz archive with keys "
            + ", ".join(map(repr, required))
        )
    arrays: dict[str, np.ndarray] = {}
    with loaded as npz:
        names = set(npz.files)
        for key in required:
            if key not in names:
                raise DatasetError(f"{where}: missing key {key!r} (has {sorted(names)})")
        for key in required + optional:
            if key not in names:
                continue
            try:
                arrays[key] = npz[key]
            except (ValueError, *_READ_ERRORS) as exc:
                if isinstance(exc, ValueError) and "pickle" in str(exc).lower():
                    raise DatasetError(
                        f"{where}: key {key!r} holds pickled Python objects (dtype object), "
                        "which are never loaded"
                    ) from None
                raise DatasetError(
                    f"{where}: key {key!r} is not a readable array ({exc})"
                ) from None
    return arrays


def read_scan_file(path: str | os.PathLike[str], default_sensor: Sensor | None) -> Scan:
    """Read one ``scans/*.npz`` file (FORMAT.md) into a validated :class:`Scan`.

    Raises
    ------
    DatasetError
        For a file that is not a readable ``.npz`` (truncated, corrupted, pickled objects),
        a missing key, or a range map, pose or sensor that fails validation; the message
        names the file and the key or field.
    """
    path = Path(path)
    where = str(path)
    arrays = _read_npz(path, where, ("range", "pose"), ("sensor",))
    range_m = arrays["range"]
    pose = arrays["pose"]
    sensor_text = arrays.get("sensor")
    if sensor_text is not None:
        if sensor_text.dtype.kind not in "US" or sensor_text.ndim != 0:
            raise DatasetError(f"{where}: key 'sensor' must be a JSON string")
        value = sensor_text.item()
        if isinstance(value, bytes):
            try:
                value = value.decode()
            except UnicodeDecodeError:
                raise DatasetError(f"{where}: key 'sensor' is not UTF-8 text") from None
        sensor = _sensor_from_json(value, f"{where}: sensor")
    elif default_sensor is not None:
        sensor = default_sensor
    else:
        raise DatasetError(f"{where}: no per-scan 'sensor' and no {SENSOR_FILE} in the dataset")
    if pose.dtype.kind not in "fiu":
        raise DatasetError(f"{where}: pose: must be numeric, got dtype {pose.dtype}")
    try:
        return Scan(range_m=range_m, T_W_S=pose.astype(np.float64), sensor=sensor)
    except InvalidInputError as exc:
        raise DatasetError(f"{where}: {exc}") from None


@dataclass(frozen=True)
class Dataset:
    """A dataset folder: its default sensor (if any) and its scan files in name order."""

    path: Path
    sensor: Sensor | None
    scan_paths: tuple[Path, ...]

    def __len__(self) -> int:
        return len(self.scan_paths)

    @property
    def names(self) -> list[str]:
        """Scan names: the file stems."""
        return [p.stem for p in self.scan_paths]

    def scans(self) -> Iterator[tuple[str, Scan]]:
        """Yield ``(name, Scan)`` in file-name order, reading one file at a time."""
        for p in self.scan_paths:
            yield p.stem, read_scan_file(p, self.sensor)


def open_dataset(path: str | os.PathLike[str]) -> Dataset:
    """Open a FORMAT.md dataset folder (reads ``sensor.json`` and lists ``scans/*.npz``)."""
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
    return Dataset(root, sensor, paths)


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
