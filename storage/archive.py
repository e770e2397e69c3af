"""The immutable scan archive of one scene (docs/storage.md, layout 3).

Each archived scan is a Zarr v3 group inside the scene's group: an array ``range`` (float32
H x W, one chunk, NaN and ``+inf`` kept bit for bit) and the attributes ``sensor``
(:meth:`engine.Sensor.to_dict`), ``pose`` (4 x 4 list), ``noise``
(:meth:`engine.NoiseModel.to_dict` or null), ``name`` and ``checksum``. Since layout 3 the
group is one file, ``scans/<scan_id>.zip``: a zip archive (stored, not deflated) of the
group's three files, as zarr's ``ZipStore`` reads it; the folders ``scans/<scan_id>/`` that
earlier layouts wrote are read as before.

A scan is written once. :meth:`ScanArchive.stage` writes the file as
``scans/.tmp-<scan_id>-<random>.zip``; :meth:`ScanArchive.publish` fsyncs it, links it into
place (never over another entry) and fsyncs ``scans/`` once for all the scans it publishes:
a reader (or a recovery after kill -9) sees the whole scan or none of it; a killed put
leaves a ``.tmp-*`` file that :meth:`ScanArchive.remove_temporaries` deletes.
:meth:`ScanArchive.get` verifies the checksum (:func:`scan_checksum`) before returning.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import re
import secrets
import shutil
import threading
import zipfile
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
#: Prefix of the files of puts in progress (and of deletes in progress).
TMP_PREFIX = ".tmp-"
#: zstd level of archived range maps (no-return areas shrink to almost nothing).
RANGE_ZSTD_LEVEL = 1
#: Suffix of an entry's file (layout 3); an entry without it is a folder (layouts 1, 2).
ENTRY_SUFFIX = ".zip"
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
    parts: list[memoryview] = [
        np.ascontiguousarray(range_m, "<f4").data,  # hashed in place: no copy of the ranges
        np.ascontiguousarray(pose, "<f8").data,
        memoryview(_canonical_json(sensor)),
        memoryview(_canonical_json(noise)),
    ]
    for part in parts:
        h.update(part.nbytes.to_bytes(8, "little"))
        h.update(part.cast("B"))
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
    """A scan written to a temporary file of the archive (:meth:`ScanArchive.stage`)."""

    scan_id: str
    tmp: Path
    final: Path
    checksum: str

    def discard(self) -> None:
        """Remove the temporary file (the scan will not be published)."""
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.tmp)


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


#: The members of an entry's file: the group's metadata, the array's, the one chunk.
_GROUP_META = "zarr.json"
_RANGE_META = f"{RANGE_ARRAY}/zarr.json"
_RANGE_CHUNK = f"{RANGE_ARRAY}/c/0/0"


def _write_entry(path: Path, attrs: dict[str, Any], range_m: np.ndarray) -> None:
    """Write an archive entry as the file ``path``: a zip (members stored) of a Zarr v3
    group, its ``zarr.json`` (with ``attrs``), the array's ``range/zarr.json`` and its one
    chunk ``range/c/0/0``, as zarr's ``ZipStore`` reads it. Written directly, not through
    zarr-python (whose asynchronous store cost about 13 ms a scan)."""
    data = np.ascontiguousarray(range_m, "<f4")
    members = {
        _GROUP_META: _json({"attributes": attrs, "zarr_format": 3, "node_type": "group"}),
        _RANGE_META: _json(_range_metadata(data.shape)),
        _RANGE_CHUNK: Zstd(level=RANGE_ZSTD_LEVEL).encode(data),
    }
    with zipfile.ZipFile(path, "x", zipfile.ZIP_STORED) as zf:
        for name, content in members.items():
            zf.writestr(name, content)


def _decode_range(meta: dict[str, Any], chunk: bytes | None) -> np.ndarray:
    """The range map of an entry from its array metadata and chunk: the layout this module
    writes (float32, one chunk, little-endian bytes then zstd, at any level)."""
    shape = tuple(int(n) for n in meta["shape"])
    codecs = [c["name"] for c in meta["codecs"]]
    endian = meta["codecs"][0].get("configuration", {}).get("endian")
    if meta["data_type"] != "float32" or len(shape) != 2:
        raise ValueError(f"range is {meta['data_type']} {shape}, expected float32 H x W")
    if codecs != ["bytes", "zstd"] or endian != "little":
        raise ValueError(f"range codecs {codecs} ({endian}), expected bytes (little), zstd")
    if [int(n) for n in meta["chunk_grid"]["configuration"]["chunk_shape"]] != list(shape):
        raise ValueError("range is not one chunk")
    if chunk is None:
        raise ValueError(f"range data {_RANGE_CHUNK} is missing")
    raw = Zstd().decode(chunk)
    if len(raw) != 4 * shape[0] * shape[1]:
        raise ValueError(f"range data is {len(raw)} bytes, expected {4 * shape[0] * shape[1]}")
    return np.frombuffer(raw, "<f4").reshape(shape).astype(np.float32)


def _members(path: Path, names: Sequence[str]) -> dict[str, bytes]:
    """The files ``names`` of an entry that it has (its zip opened once)."""
    if path.is_dir():
        return {n: (path / n).read_bytes() for n in names if (path / n).is_file()}
    with zipfile.ZipFile(path) as zf:
        present = set(zf.namelist())
        return {n: zf.read(n) for n in names if n in present}


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

    def _file(self, scan_id: str) -> Path:
        """Where the entry of ``scan_id`` is written (layout 3)."""
        return self.path / f"{check_scan_id(scan_id)}{ENTRY_SUFFIX}"

    def _entry(self, scan_id: str) -> Path | None:
        """The entry of ``scan_id`` on disk: its file, or its folder (layouts 1 and 2)."""
        file = self._file(scan_id)
        if file.is_file():
            return file
        folder = self.path / scan_id
        return folder if folder.is_dir() else None

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
        """Write ``scan`` into a temporary file of the archive, not yet durable nor visible;
        :meth:`publish` makes it both (several at once: one round of fsyncs)."""
        final = self._file(scan_id)
        if not isinstance(scan, Scan):
            raise ArchiveError(f"scan {scan_id!r}: expected an engine.Scan, got {type(scan)}")
        if name is not None and not isinstance(name, str):
            raise ArchiveError(f"scan {scan_id!r}: name must be a string or None, got {name!r}")
        if self._entry(scan_id) is not None:
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
        staged = StagedScan(
            scan_id, self.path / f"{TMP_PREFIX}{scan_id}-{secrets.token_hex(8)}{ENTRY_SUFFIX}",
            final, checksum,
        )  # fmt: skip
        try:
            _write_entry(staged.tmp, attrs, scan.range_m)
        except BaseException:
            staged.discard()
            raise
        return staged

    def publish(self, staged: Sequence[StagedScan]) -> None:
        """Make staged scans durable and visible: fsync their files (side by side), link
        each into place, fsync ``scans/`` once. On an error every staged file is removed and
        nothing published stays (the error is raised)."""
        done: list[StagedScan] = []
        try:
            fsync_paths([entry.tmp for entry in staged])
            for entry in staged:
                self._place(entry)
                done.append(entry)
            fsync_path(self.path)
        except BaseException:
            for entry in staged:
                entry.discard()
            for entry in done:
                self.delete(entry.scan_id)
            raise

    def _place(self, entry: StagedScan) -> None:
        """Give a staged file its final name, never over another entry: a hard link (which
        fails on an existing name), then the temporary name removed; a rename after a check
        on file systems without hard links."""
        taken = ArchiveError(
            f"scan {entry.scan_id!r} is already in the archive; scans are immutable"
        )
        if (self.path / entry.scan_id).is_dir():  # an entry of layout 1 or 2
            raise taken
        try:
            os.link(entry.tmp, entry.final)
        except FileExistsError:
            raise taken from None
        except OSError as exc:
            if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK):
                raise
            if entry.final.exists():
                raise taken from None
            os.rename(entry.tmp, entry.final)
            return
        os.unlink(entry.tmp)

    # --- reading -----------------------------------------------------------------------------
    def _attrs(self, scan_id: str) -> dict[str, Any]:
        return self._group(scan_id)[0]

    def _group(
        self, scan_id: str, also: Sequence[str] = ()
    ) -> tuple[dict[str, Any], dict[str, bytes]]:
        """The attributes of ``scan_id``'s group, and those of its files ``also`` that it
        has (read with them: the entry is opened once)."""
        path = self._entry(scan_id)
        if path is None:
            raise ArchiveError(f"scan {scan_id!r} is not in the archive")
        try:
            found = _members(path, [_GROUP_META, *also])
        except (OSError, zipfile.BadZipFile) as exc:
            raise ArchiveError(f"scan {scan_id!r}: archive entry is unreadable ({exc})") from exc
        if _GROUP_META not in found:
            raise ArchiveError(f"scan {scan_id!r}: archive entry is incomplete (no zarr.json)")
        try:
            attrs = json.loads(found[_GROUP_META])["attributes"]
        except (ValueError, KeyError, TypeError) as exc:
            raise ArchiveError(f"scan {scan_id!r}: unreadable metadata ({exc})") from exc
        if not isinstance(attrs, dict):
            raise ArchiveError(f"scan {scan_id!r}: unreadable metadata (attributes {attrs!r})")
        missing = [k for k in ("sensor", "pose", "noise", "checksum") if k not in attrs]
        if missing:
            raise ArchiveError(f"scan {scan_id!r}: archive entry lacks {', '.join(missing)}")
        return dict(attrs), found

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
        attrs, found = self._group(scan_id, [_RANGE_META, _RANGE_CHUNK])
        try:
            range_m = _decode_range(json.loads(found[_RANGE_META]), found.get(_RANGE_CHUNK))
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
        found = set()
        for e in entries:
            if e.name.startswith("."):
                continue
            if e.is_dir(follow_symlinks=False):
                scan_id = e.name
            elif e.name.endswith(ENTRY_SUFFIX) and e.is_file(follow_symlinks=False):
                scan_id = e.name[: -len(ENTRY_SUFFIX)]
            else:
                continue
            if scan_id not in _RESERVED and _SCAN_ID.fullmatch(scan_id):
                found.add(scan_id)
        return sorted(found)

    def __contains__(self, scan_id: str) -> bool:
        try:
            return self._entry(scan_id) is not None
        except ArchiveError:
            return False

    # --- removing ----------------------------------------------------------------------------
    def delete(self, scan_id: str) -> None:
        """Remove ``scan_id`` from the archive durably; a missing scan is ignored.

        The entry is first renamed to a ``.tmp-*`` name (fsynced), then removed: a kill
        midway never leaves a half-deleted scan under its id.
        """
        path = self._entry(scan_id)
        if path is None:
            return
        folder = path.is_dir()
        suffix = "" if folder else ENTRY_SUFFIX
        doomed = self.path / f"{TMP_PREFIX}{scan_id}-{secrets.token_hex(8)}{suffix}"
        os.rename(path, doomed)
        fsync_path(self.path)
        if folder:
            shutil.rmtree(doomed)
        else:
            os.unlink(doomed)
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
