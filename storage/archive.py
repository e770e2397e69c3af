"""The immutable scan archive of one scene (docs/storage.md, layout 1).

Each archived scan is a Zarr v3 group ``scans/<scan_id>/`` inside the scene's group: an array
``range`` (float32 H x W, one chunk, NaN and ``+inf`` kept bit for bit) and the attributes
``sensor`` (:meth:`engine.Sensor.to_dict`), ``pose`` (4 x 4 list), ``noise``
(:meth:`engine.NoiseModel.to_dict` or null), ``name`` and ``checksum``.

A scan is written once. :meth:`ScanArchive.put` writes the group into
``scans/.tmp-<scan_id>-<random>/``, fsyncs every file and folder, renames it into place and
fsyncs ``scans/``: a reader (or a recovery after kill -9) sees the whole scan or none of it;
a killed put leaves a ``.tmp-*`` folder that :meth:`ScanArchive.remove_temporaries` deletes.
:meth:`ScanArchive.get` verifies the checksum (:func:`scan_checksum`) before returning.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import secrets
import shutil
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from numcodecs import Zstd
from rangefuse.engine import InvalidInputError, NoiseModel, Scan, Sensor, sensor_from_dict
from zarr.storage import LocalStore

from ._files import fsync_path, fsync_paths

__all__ = [
    "SCANS_GROUP",
    "ArchiveError",
    "ScanArchive",
    "StagedScan",
    "check_scan_id",
    "scan_checksum",
]

#: Name of the archive group inside a scene's group.
SCANS_GROUP = "scans"
#: Name of the range array of an archived scan.
RANGE_ARRAY = "range"
#: Prefix of the folders of puts in progress (and of deletes in progress).
TMP_PREFIX = ".tmp-"
#: zstd level of archived range maps (no-return areas shrink to almost nothing).
RANGE_ZSTD_LEVEL = 1
#: Longest scan id.
MAX_SCAN_ID = 128

_SCAN_ID = re.compile(rf"[A-Za-z0-9_-][A-Za-z0-9_.-]{{0,{MAX_SCAN_ID - 1}}}")
#: Names a scan group cannot take inside ``scans/`` (its own metadata file).
_RESERVED = frozenset({"zarr.json"})


class ArchiveError(ValueError):
    """A scan id that is refused, a scan missing from the archive, or a corrupt entry."""


def check_scan_id(scan_id: str) -> str:
    """Return ``scan_id`` if it is a safe folder name, else raise :class:`ArchiveError`.

    Safe: 1 to 128 ASCII letters, digits, ``_``, ``-`` and ``.``, not starting with ``.``.
    """
    if not isinstance(scan_id, str):
        raise ArchiveError(f"scan id must be a string, got {type(scan_id).__name__}")
    if _SCAN_ID.fullmatch(scan_id) is None or scan_id in _RESERVED:
        raise ArchiveError(
            f"scan id {scan_id!r} is not allowed: use 1 to {MAX_SCAN_ID} letters, digits, "
            "'_', '-' or '.', not starting with '.' (and not 'zarr.json')"
        )
    return scan_id


def _canonical_json(value: Any) -> bytes:
    return json.dumps(value, sort_keys=True).encode()


def _checksum(range_m: np.ndarray, pose: np.ndarray, sensor: Any, noise: Any) -> str:
    h = hashlib.sha256()
    for part in (
        np.ascontiguousarray(range_m, "<f4").tobytes(),
        np.ascontiguousarray(pose, "<f8").tobytes(),
        _canonical_json(sensor),
        _canonical_json(noise),
    ):
        h.update(len(part).to_bytes(8, "little"))
        h.update(part)
    return "sha256:" + h.hexdigest()


def scan_checksum(scan: Scan) -> str:
    """The archive checksum of a scan: ``"sha256:<hex>"``.

    SHA-256 over four parts, each preceded by its length in bytes (8-byte little-endian):
    the ranges (float32 little-endian, C order), the pose (float64 little-endian, C order),
    the sensor JSON and the noise JSON (``null`` without overrides), both
    ``json.dumps(..., sort_keys=True)`` in UTF-8.
    """
    noise = None if scan.noise is None else scan.noise.to_dict()
    return _checksum(scan.range_m, scan.T_W_S, scan.sensor.to_dict(), noise)


@dataclass(frozen=True)
class StagedScan:
    """A scan written to a temporary folder of the archive (:meth:`ScanArchive.stage`)."""

    scan_id: str
    tmp: Path
    final: Path
    checksum: str
    #: Its files, then its folders (deepest first): what to fsync.
    paths: list[Path]


def _json(value: Any) -> bytes:
    return json.dumps(value, indent=2).encode()


def _range_metadata(shape: tuple[int, ...]) -> dict[str, Any]:
    """The Zarr v3 metadata of an archived range map: float32, one chunk, NaN fill, little
    endian bytes then zstd (what ``zarr.create_array`` writes for these options; a test
    compares the two)."""
    return {
        "shape": list(shape),
        "data_type": "float32",
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": list(shape)}},
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": "NaN",
        "codecs": [
            {"name": "bytes", "configuration": {"endian": "little"}},
            {"name": "zstd", "configuration": {"level": RANGE_ZSTD_LEVEL, "checksum": False}},
        ],
        "attributes": {},
        "zarr_format": 3,
        "node_type": "array",
        "storage_transformers": [],
    }


def _write_entry(root: Path, attrs: dict[str, Any], range_m: np.ndarray) -> list[Path]:
    """Write an archive entry as a Zarr v3 group at ``root``: its ``zarr.json`` (with
    ``attrs``), the array ``range`` and its one chunk ``range/c/0/0``. Written directly, not
    through zarr-python (whose asynchronous store costs about 13 ms a scan); returns the
    files and folders written, folders deepest first."""
    data = np.ascontiguousarray(range_m, "<f4")
    chunk_dir = root / RANGE_ARRAY / "c" / "0"
    chunk_dir.mkdir(parents=True)
    files = {
        root / "zarr.json": _json({"attributes": attrs, "zarr_format": 3, "node_type": "group"}),
        root / RANGE_ARRAY / "zarr.json": _json(_range_metadata(data.shape)),
        chunk_dir / "0": Zstd(level=RANGE_ZSTD_LEVEL).encode(data.tobytes()),
    }
    for path, content in files.items():
        with open(path, "wb") as fh:
            fh.write(content)
    return [*files, chunk_dir, chunk_dir.parent, root / RANGE_ARRAY, root]


_GROUP_LOCK = threading.Lock()


class ScanArchive:
    """The scans of one scene, in the Zarr v3 group at ``group_path`` (``scans/<scan_id>``).

    Parameters
    ----------
    group_path : Path
        The scene's group folder; it and ``scans/`` are created by the first :meth:`put`.
    """

    def __init__(self, group_path: Path) -> None:
        self.group_path = Path(group_path)
        #: The folder of the archive group (``<group>/scans``).
        self.path = self.group_path / SCANS_GROUP

    def _scan_path(self, scan_id: str) -> Path:
        return self.path / check_scan_id(scan_id)

    def _ensure_group(self) -> None:
        """Create the scene group and ``scans/`` if missing, durably."""
        if (self.path / "zarr.json").is_file():
            return
        with _GROUP_LOCK:  # the upload threads of a new scene stage side by side
            if not (self.path / "zarr.json").is_file():
                self._create_group()

    def _create_group(self) -> None:
        new_dirs = [p for p in (self.path, *self.path.parents) if not p.exists()]
        scene = zarr.open_group(LocalStore(self.group_path), mode="a", zarr_format=3)
        scene.require_group(SCANS_GROUP)
        for path in (self.path / "zarr.json", self.group_path / "zarr.json"):
            fsync_path(path)
        for folder in {self.path, self.group_path, *(d.parent for d in new_dirs)}:
            fsync_path(folder)

    # --- writing -----------------------------------------------------------------------------
    def put(self, scan_id: str, scan: Scan, name: str | None = None) -> str:
        """Archive ``scan`` as ``scan_id`` durably and atomically; returns its checksum.

        When this returns, the scan's files and folder entries are on disk (fsynced).

        Raises
        ------
        ArchiveError
            For an unsafe scan id or one that the archive already holds.
        """
        staged = self.stage(scan_id, scan, name)
        self.publish([staged])
        return staged.checksum

    def stage(self, scan_id: str, scan: Scan, name: str | None = None) -> StagedScan:
        """Write ``scan`` into a temporary folder of the archive, not yet durable nor visible;
        :meth:`publish` makes it both (several at once: one round of fsyncs)."""
        final = self._scan_path(scan_id)
        if not isinstance(scan, Scan):
            raise ArchiveError(f"scan {scan_id!r}: expected an engine.Scan, got {type(scan)}")
        if name is not None and not isinstance(name, str):
            raise ArchiveError(f"scan {scan_id!r}: name must be a string or None, got {name!r}")
        if final.exists():
            raise ArchiveError(f"scan {scan_id!r} is already in the archive; scans are immutable")
        self._ensure_group()
        sensor = scan.sensor.to_dict()
        noise = None if scan.noise is None else scan.noise.to_dict()
        checksum = _checksum(scan.range_m, scan.T_W_S, sensor, noise)
        attrs = {
            "sensor": sensor,
            "pose": scan.T_W_S.tolist(),
            "noise": noise,
            "name": name,
            "checksum": checksum,
        }
        tmp = self.path / f"{TMP_PREFIX}{scan_id}-{secrets.token_hex(8)}"
        try:
            paths = _write_entry(tmp, attrs, scan.range_m)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return StagedScan(scan_id, tmp, final, checksum, paths)

    def publish(self, staged: Sequence[StagedScan]) -> None:
        """Make staged scans durable and visible: fsync all their files and folders (side by
        side), rename each into place, fsync ``scans/``. On an error every staged folder is
        removed and nothing published stays (the error is raised)."""
        done: list[StagedScan] = []
        try:
            fsync_paths([p for entry in staged for p in entry.paths])
            for entry in staged:
                try:
                    os.rename(entry.tmp, entry.final)  # fails on a non-empty target
                except OSError as exc:
                    if entry.final.exists():
                        raise ArchiveError(
                            f"scan {entry.scan_id!r} is already in the archive; scans are immutable"
                        ) from exc
                    raise
                done.append(entry)
            fsync_path(self.path)
        except BaseException:
            for entry in staged:
                shutil.rmtree(entry.tmp, ignore_errors=True)
            for entry in done:
                self.delete(entry.scan_id)
            raise

    def discard(self, staged: Sequence[StagedScan]) -> None:
        """Remove staged scans that will not be published."""
        for entry in staged:
            shutil.rmtree(entry.tmp, ignore_errors=True)

    # --- reading -----------------------------------------------------------------------------
    def _attrs(self, scan_id: str) -> dict[str, Any]:
        path = self._scan_path(scan_id)
        meta_path = path / "zarr.json"
        if not meta_path.is_file():
            if path.exists():
                raise ArchiveError(f"scan {scan_id!r}: archive entry is incomplete (no zarr.json)")
            raise ArchiveError(f"scan {scan_id!r} is not in the archive")
        try:
            meta = json.loads(meta_path.read_bytes())
            attrs = meta["attributes"]
        except (ValueError, KeyError, TypeError) as exc:
            raise ArchiveError(f"scan {scan_id!r}: unreadable metadata ({exc})") from exc
        missing = [k for k in ("sensor", "pose", "noise", "checksum") if k not in attrs]
        if missing:
            raise ArchiveError(f"scan {scan_id!r}: archive entry lacks {', '.join(missing)}")
        return dict(attrs)

    def checksum(self, scan_id: str) -> str:
        """The stored checksum of ``scan_id`` (not verified; :meth:`get` verifies)."""
        return str(self._attrs(scan_id)["checksum"])

    def placement(self, scan_id: str) -> dict[str, Any]:
        """``{"pose": 4 x 4 list, "sensor": sensor.json form}`` of ``scan_id`` (its metadata
        only; the ranges are not read)."""
        attrs = self._attrs(scan_id)
        return {"pose": attrs["pose"], "sensor": attrs["sensor"]}

    def name(self, scan_id: str) -> str | None:
        """The name given to :meth:`put` (such as the file the scan came from)."""
        value = self._attrs(scan_id).get("name")
        return None if value is None else str(value)

    def get(self, scan_id: str) -> Scan:
        """Read ``scan_id`` back bit for bit, verifying its checksum.

        Raises
        ------
        ArchiveError
            When the scan is not archived, a part is missing or unreadable, or the checksum
            does not match (the message names the scan).
        """
        attrs = self._attrs(scan_id)
        path = self._scan_path(scan_id)
        try:
            array = zarr.open_array(LocalStore(path), path=RANGE_ARRAY, mode="r", zarr_format=3)
            if array.dtype != np.float32 or array.ndim != 2:
                raise ValueError(f"range is {array.dtype} {array.shape}, expected float32 H x W")
            chunk = path / RANGE_ARRAY / array.metadata.encode_chunk_key((0, 0))
            if not chunk.is_file():
                raise ValueError(f"range data {chunk} is missing")
            range_m = np.ascontiguousarray(array[...], np.float32)
            pose = np.array(attrs["pose"], np.float64)
        except Exception as exc:
            raise ArchiveError(f"scan {scan_id!r}: archive entry is unreadable ({exc})") from exc
        computed = _checksum(range_m, pose, attrs["sensor"], attrs["noise"])
        if computed != attrs["checksum"]:
            raise ArchiveError(
                f"scan {scan_id!r}: checksum mismatch (stored {attrs['checksum']}, "
                f"computed {computed}); the archive entry is corrupt"
            )
        try:
            sensor: Sensor = sensor_from_dict(attrs["sensor"])
            noise = None if attrs["noise"] is None else NoiseModel.from_dict(attrs["noise"])
            # accepted when it was stored: the range check does not refuse it again
            return Scan(range_m, pose, sensor, noise, accept_far_ranges=True)
        except (InvalidInputError, TypeError) as exc:
            raise ArchiveError(f"scan {scan_id!r}: archived scan is invalid ({exc})") from exc

    def ids(self) -> list[str]:
        """Ids of the archived scans, sorted (puts and deletes in progress left out)."""
        try:
            entries = list(os.scandir(self.path))
        except FileNotFoundError:
            return []
        return sorted(
            e.name
            for e in entries
            if not e.name.startswith(".")
            and e.name not in _RESERVED
            and _SCAN_ID.fullmatch(e.name)
            and e.is_dir(follow_symlinks=False)
        )

    def __contains__(self, scan_id: str) -> bool:
        try:
            return self._scan_path(scan_id).is_dir()
        except ArchiveError:
            return False

    # --- removing ----------------------------------------------------------------------------
    def delete(self, scan_id: str) -> None:
        """Remove ``scan_id`` from the archive durably; a missing scan is ignored.

        The group is first renamed to a ``.tmp-*`` folder (fsynced), then removed: a kill
        midway never leaves a half-deleted scan under its id.
        """
        path = self._scan_path(scan_id)
        if not path.exists():
            return
        doomed = self.path / f"{TMP_PREFIX}{scan_id}-{secrets.token_hex(8)}"
        os.rename(path, doomed)
        fsync_path(self.path)
        shutil.rmtree(doomed)
        fsync_path(self.path)

    def remove_temporaries(self) -> int:
        """Delete the ``.tmp-*`` folders of killed puts and deletes; returns how many.

        Only while no process writes the archive (at open, under the store lock).
        """
        try:
            entries = list(os.scandir(self.path))
        except FileNotFoundError:
            return 0
        removed = 0
        for entry in entries:
            if entry.name.startswith(TMP_PREFIX):
                if entry.is_dir(follow_symlinks=False):
                    shutil.rmtree(entry.path, ignore_errors=True)
                else:
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(entry.path)
                removed += 1
        if removed:
            fsync_path(self.path)
        return removed
