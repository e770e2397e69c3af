"""The tile array of one scene: one Zarr v3 chunk per tile (docs/storage.md, layout 1), in
shards of ``B^3`` tiles since layout version 4 (docs/sharded-tiles.md, :mod:`.shards`).

The array ``tiles`` of a scene's Zarr group holds int64 packed voxels (see
:mod:`engine.certainty`; 0 is *unknown*, the fill value). Its chunk is one tile ``(T, T, T)``
and its shape is ``2**21`` tiles per axis: tile key ``k`` (``|k| < 2**20``, may be negative)
is chunk ``k + 2**20`` on each axis, stored in the file ``tiles/c/<i>/<j>/<k>`` (the default
chunk key encoding, separator ``/``). A tile of zeros is never stored (its chunk is deleted),
exactly as zarr does with ``write_empty_chunks=False``.

Chunks are encoded with the ``bytes`` (little endian) and ``zstd`` (level 1, no checksum)
codecs of the Zarr v3 spec. Tiles are read and written here without zarr's per-call
machinery (indexing, an event loop round trip and a thread hop per chunk: 3-5x slower); the
bytes are those zarr itself writes (the tests compare them), and each chunk is still written
through zarr's ``LocalStore`` (temporary file then rename, so a chunk is never torn; a kill
leaves ``<chunk>.<32 hex>.partial`` orphans, see :meth:`ZarrTiles.remove_partials`). Zarr never
fsyncs: :meth:`ZarrTiles.fsync` makes written chunks durable.

A sharded array (new scenes, ``B = 64 // T`` tiles a side: 4 for 16^3 tiles) keeps the same
shape, keys and inner chunk bytes; a tile's chunk is an inner chunk of the shard file
``tiles/c/<i // B>/<j // B>/<k // B>``, and a write rewrites each shard it touches whole
(:func:`~storage.shards.merge_shard`). Arrays of version-3 scenes (unsharded) are read and
written as they are.

Never ask zarr for ``nchunks_initialized`` or to list this array (it walks every possible
chunk of a huge sparse array); :meth:`ZarrTiles.stored_keys` walks the directory instead.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zarr
import zarr.codecs
from numcodecs import Zstd
from rangefuse.engine.grid import KEY_LIMIT, unique_keys
from zarr.core.buffer import default_buffer_prototype
from zarr.storage import LocalStore

from ._files import fsync_path
from ._heap import libc
from .shards import (
    MAX_SHARD,
    ShardError,
    index_nbytes,
    inner_chunks,
    merge_shard,
    read_shard,
    tiles_per_shard_side,
)

__all__ = ["TILES_ARRAY", "TileArrayError", "ZarrTiles"]

#: Name of the tile array inside a scene's group.
TILES_ARRAY = "tiles"
#: Chunk index of tile key 0 on each axis (keys are shifted by it).
KEY_OFFSET = KEY_LIMIT
#: Chunks (tiles) per axis of the array.
TILES_PER_AXIS = 2 * KEY_LIMIT
#: zstd level of new arrays: 16^3 tiles of a fused scene shrink ~40x, ~25 us to encode.
ZSTD_LEVEL = 1
#: Largest accepted tile size (voxels per edge).
MAX_TILE_SIZE = 256

#: Temporary files of zarr's LocalStore: ``path.with_suffix(f".{uuid4().hex}.partial")``.
_PARTIAL = re.compile(r"\.[0-9a-f]{32}\.partial\Z")
_BYTES_CODEC = {"name": "bytes", "configuration": {"endian": "little"}}
_INDEX_CODECS = [_BYTES_CODEC, {"name": "crc32c"}]
#: A file's size on disk is rounded up to blocks of (at most, on the usual file systems) this.
_BLOCK = 4096


class TileArrayError(ValueError):
    """A missing or unusable tile array, a corrupt chunk, or bad keys or tile data."""


def tile_rows(
    out: np.ndarray | None, rows: np.ndarray | None, n: int, T: int
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Where a read of ``n`` tiles puts them: ``out`` (a new int64 (n, T, T, T) when None),
    its tiles flattened (a view), and the row of each tile read."""
    if out is None:
        out = np.empty((n, T, T, T), np.int64)
    if out.dtype != np.int64 or out.shape[1:] != (T, T, T) or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous int64 (m, {T}, {T}, {T})")
    at = list(range(n)) if rows is None else np.asarray(rows, np.int64).tolist()
    if len(at) != n:
        raise ValueError(f"{len(at)} rows for {n} tiles")
    return out, out.reshape(len(out), T**3), at


#: From this many chunks on, :meth:`ZarrTiles.fsync` syncs the whole file system instead.
_SYNCFS_FROM = 256


def _syncfs(path: Path) -> bool:
    """``syncfs(2)`` of the file system holding ``path``; False where unavailable."""
    syncfs = getattr(libc(), "syncfs", None)
    if syncfs is None:
        return False
    fd = os.open(path, os.O_RDONLY)
    try:
        return int(syncfs(fd)) == 0
    finally:
        os.close(fd)


class ZarrTiles:
    """The tile array ``tiles`` of one scene's Zarr v3 group on a local directory.

    Build one with :meth:`create` or :meth:`open`. Keys are int64 arrays ``(n, 3)`` of tile
    indices (``engine.grid``); tile data is int64 ``(n, T, T, T)`` of packed voxels.
    One process writes a given tile at a time (docs/storage.md, "One writer per tile").
    """

    def __init__(
        self,
        group_path: Path,
        array: zarr.Array,
        tile_size: int,
        zstd_level: int | None,
        shard: int = 1,
    ) -> None:
        self.group_path = Path(group_path)
        #: The directory of the array (``<group>/tiles``).
        self.path = self.group_path / TILES_ARRAY
        self.tile_size = int(tile_size)
        #: The zarr array, for tools; tiles go through :meth:`read` and :meth:`write`.
        self.array = array
        self._store = LocalStore(self.group_path)
        self._prototype = default_buffer_prototype()
        self._zstd = None if zstd_level is None else Zstd(level=zstd_level)
        self._nbytes = 8 * self.tile_size**3
        #: Tiles per shard side (1: an unsharded array, one file per tile).
        self.shard = int(shard)

    # --- creating and opening --------------------------------------------------------------
    @classmethod
    def create(cls, group_path: Path, tile_size: int, shard: int | None = None) -> ZarrTiles:
        """Create the tile array in the Zarr v3 group at ``group_path`` (created if missing),
        in shards of ``shard`` tiles a side (1: unsharded; default
        :func:`~storage.shards.tiles_per_shard_side`).

        Its metadata files and folders are fsynced before returning.

        Raises
        ------
        TileArrayError
            For a bad tile size or when the group already has a tile array.
        """
        group_path = Path(group_path)
        if isinstance(tile_size, bool) or not isinstance(tile_size, (int, np.integer)):
            raise TileArrayError(f"tile_size: must be an integer, got {tile_size!r}")
        T = int(tile_size)
        if not 1 <= T <= MAX_TILE_SIZE:
            raise TileArrayError(f"tile_size: must be in [1, {MAX_TILE_SIZE}] voxels, got {T}")
        B = tiles_per_shard_side(T) if shard is None else int(shard)
        if not 1 <= B <= MAX_SHARD:
            raise TileArrayError(f"shard: must be in [1, {MAX_SHARD}] tiles a side, got {B}")
        if (group_path / TILES_ARRAY / "zarr.json").exists():
            raise TileArrayError(f"{group_path} already has a tile array")
        new_dirs = [p for p in (group_path, *group_path.parents) if not p.exists()]
        group = zarr.open_group(LocalStore(group_path), mode="a", zarr_format=3)
        array = group.create_array(
            TILES_ARRAY,
            shape=(TILES_PER_AXIS * T,) * 3,
            chunks=(T,) * 3,
            shards=None if B == 1 else (B * T,) * 3,
            dtype="int64",
            fill_value=0,
            compressors=zarr.codecs.ZstdCodec(level=ZSTD_LEVEL, checksum=False),
            config={"write_empty_chunks": False},
        )
        for path in (
            group_path / TILES_ARRAY / "zarr.json",
            group_path / TILES_ARRAY,
            group_path / "zarr.json",
            group_path,
            *(d.parent for d in new_dirs),
        ):
            fsync_path(path)
        return cls(group_path, array, T, ZSTD_LEVEL, B)

    @classmethod
    def open(cls, group_path: Path) -> ZarrTiles:
        """Open the tile array of the group at ``group_path``.

        Raises
        ------
        TileArrayError
            When there is no tile array there, or its metadata is not the layout this module
            writes (chunk = one cubic int64 tile, fill value 0, bytes + optional zstd codecs).
        """
        group_path = Path(group_path)
        if not (group_path / TILES_ARRAY / "zarr.json").is_file():
            raise TileArrayError(
                f"no tile array at {group_path / TILES_ARRAY} (create it with ZarrTiles.create)"
            )
        array = zarr.open_array(LocalStore(group_path), path=TILES_ARRAY, mode="r+", zarr_format=3)
        meta: dict[str, Any] = array.metadata.to_dict()
        chunk_shape = tuple(meta["chunk_grid"]["configuration"]["chunk_shape"])
        codecs = [dict(c) for c in meta["codecs"]]
        problems = []
        B = 1
        if len(codecs) == 1 and codecs[0].get("name") == "sharding_indexed":
            conf = dict(codecs[0].get("configuration", {}))
            inner = tuple(conf.get("chunk_shape", ()))
            codecs = [dict(c) for c in conf.get("codecs", [])]
            if len(inner) == 3 and inner[0] > 0 and len(chunk_shape) == 3:
                B = int(chunk_shape[0]) // int(inner[0])
            if len(inner) != 3 or tuple(chunk_shape) != tuple(B * int(n) for n in inner):
                problems.append(f"shard shape {chunk_shape} for inner chunks {inner}")
            elif [dict(c) for c in conf.get("index_codecs", [])] != _INDEX_CODECS or conf.get(
                "index_location"
            ) != "end":
                problems.append("shard index (expected bytes + crc32c at the end)")
            chunk_shape = inner
        T = int(chunk_shape[0]) if chunk_shape else 0
        zstd_level: int | None = None
        if len(codecs) == 2 and codecs[1].get("name") == "zstd":
            conf = codecs[1].get("configuration", {})
            if conf.get("checksum") is False:
                zstd_level = int(conf["level"])
                codecs = codecs[:1]
        if meta["data_type"] != "int64":
            problems.append(f"dtype {meta['data_type']} (expected int64)")
        if len(chunk_shape) != 3 or len(set(chunk_shape)) != 1:
            problems.append(f"chunk shape {chunk_shape} (expected a cube)")
        elif T < 1 or tuple(meta["shape"]) != (TILES_PER_AXIS * T,) * 3:
            problems.append(f"shape {tuple(meta['shape'])} (expected {TILES_PER_AXIS} tiles/axis)")
        if meta["fill_value"] != 0:
            problems.append(f"fill value {meta['fill_value']!r} (expected 0)")
        if meta["chunk_key_encoding"] != {"name": "default", "configuration": {"separator": "/"}}:
            problems.append(f"chunk key encoding {meta['chunk_key_encoding']}")
        if codecs != [_BYTES_CODEC]:
            problems.append(f"codecs {meta['codecs']} (expected bytes + zstd without checksum)")
        if problems:
            raise TileArrayError(
                f"{group_path / TILES_ARRAY} is not a rangefuse tile array: {'; '.join(problems)}"
            )
        return cls(group_path, array, T, zstd_level, B)

    # --- tiles -----------------------------------------------------------------------------
    def _check_keys(self, keys: Any) -> np.ndarray:
        arr = np.asarray(keys)
        if arr.size == 0:
            return np.zeros((0, 3), np.int64)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise TileArrayError(f"keys: must be an integer array (n, 3), got shape {arr.shape}")
        if arr.dtype.kind not in "iu":
            raise TileArrayError(f"keys: must be integers, got dtype {arr.dtype}")
        arr = arr.astype(np.int64, copy=False)
        if arr.min() <= -KEY_LIMIT or arr.max() >= KEY_LIMIT:
            raise TileArrayError(f"keys: tile keys must lie in (-{KEY_LIMIT}, {KEY_LIMIT})")
        return arr

    def _outer(self, keys: np.ndarray) -> np.ndarray:
        """The chunk index of each key's file: its shard's (its own in an unsharded array)."""
        return (keys + KEY_OFFSET) // self.shard

    def _chunk_names(self, keys: np.ndarray) -> Iterator[str]:
        """The file of each key: its chunk, or its shard's file in a sharded array."""
        for i, j, k in self._outer(keys).tolist():
            yield _file_name(i, j, k)

    def shards_of(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The shards the keys lie in (int64 (m, 3) shard indices, sorted; a tile is its own
        shard in an unsharded array) and each key's row among them (int64 (n,))."""
        if not len(keys):
            return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
        shards, which = np.unique(self._outer(keys), axis=0, return_inverse=True)
        return shards, which.reshape(-1)

    def _by_shard(self, keys: np.ndarray) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
        """``(file, rows, inner index)`` of the keys of each shard the keys touch."""
        B = self.shard
        inner = (keys + KEY_OFFSET) % B
        flat_inner = (inner[:, 0] * B + inner[:, 1]) * B + inner[:, 2]
        shards, which = self.shards_of(keys)
        order = np.argsort(which, kind="stable")
        bounds = np.searchsorted(which[order], np.arange(len(shards) + 1))
        for n, (i, j, k) in enumerate(shards.tolist()):
            rows = order[bounds[n] : bounds[n + 1]]
            yield _file_name(i, j, k), rows, flat_inner[rows]

    def chunk_path(self, key: Any) -> Path:
        """The file that holds tile ``key`` (int (3,)) when it is stored (its shard's file in
        a sharded array)."""
        keys = self._check_keys(np.asarray(key).reshape(1, 3))
        return self.group_path / next(self._chunk_names(keys))

    def read(
        self, keys: np.ndarray, out: np.ndarray | None = None, rows: np.ndarray | None = None
    ) -> np.ndarray:
        """Voxel data of ``keys`` (int64 (n, 3)) as int64 (n, T, T, T); missing tiles are 0.
        With ``out`` (a C-contiguous int64 (m, T, T, T)), tile ``n`` goes to ``out[rows[n]]``
        (``rows`` defaults to ``0..n-1``) and ``out`` is returned. A shard file is read once
        for all its keys.

        Raises
        ------
        TileArrayError
            For a chunk or shard file that does not decode (naming the key).
        """
        keys = self._check_keys(keys)
        out, flat, at = tile_rows(out, rows, len(keys), self.tile_size)
        if self.shard > 1:
            self._read_shards(keys, flat, at)
            return out
        for n, name in enumerate(self._chunk_names(keys)):
            path = self.group_path / name
            try:
                with open(path, "rb") as fh:
                    raw: bytes = fh.read()
            except (FileNotFoundError, NotADirectoryError):
                flat[at[n]] = 0
                continue
            flat[at[n]] = self.decode(raw, f"tile {keys[n].tolist()}: chunk {path}")
        return out

    def _read_shards(self, keys: np.ndarray, flat: np.ndarray, at: list[int]) -> None:
        """:meth:`read` of a sharded array: each shard file read once, whole."""
        for name, picked, inner in self._by_shard(keys):
            path = str(self.group_path / name)
            try:
                found = read_shard(path, self.shard)
            except ShardError as exc:
                raise TileArrayError(f"tile {keys[picked[0]].tolist()}: {exc}") from exc
            chunks = {} if found is None else dict(inner_chunks(*found))
            for r, n in zip(picked.tolist(), inner.tolist(), strict=True):
                raw = chunks.get(n)
                what = f"tile {keys[r].tolist()}: shard {path}"
                flat[at[r]] = 0 if raw is None else self.decode(raw, what)

    def encode(self, tile: np.ndarray) -> bytes:
        """The bytes of one tile's chunk (int64 (T, T, T)), as zarr writes them."""
        raw = np.ascontiguousarray(tile, "<i8")
        return self._zstd.encode(raw) if self._zstd is not None else raw.tobytes()

    def payloads(self, data: Sequence[np.ndarray] | np.ndarray) -> list[bytes]:
        """The chunk bytes of tiles, ``b""`` (no chunk) for an all-unknown one: a tile whose
        bytes are those of the all-zero tile is all zero (the encoding is lossless and
        deterministic), which costs less than testing every tile's voxels first."""
        zero = self.encode(np.zeros((self.tile_size,) * 3, np.int64))
        return [b"" if p == zero else p for p in map(self.encode, data)]

    def decode(self, raw: bytes, what: str) -> np.ndarray:
        """One tile (int64 (T**3,)) from its chunk bytes; ``what`` names it in the error.

        Raises
        ------
        TileArrayError
            When the bytes do not decode to one tile.
        """
        try:
            if self._zstd is not None:
                raw = self._zstd.decode(raw)
            if len(raw) != self._nbytes:
                raise ValueError(f"{len(raw)} bytes, expected {self._nbytes}")
            return np.frombuffer(raw, "<i8")
        except Exception as exc:
            raise TileArrayError(f"{what} is corrupt ({exc})") from exc

    def write(self, keys: np.ndarray, data: np.ndarray) -> None:
        """Store whole tiles: ``data`` int64 (n, T, T, T) for ``keys`` int64 (n, 3).

        A tile of zeros (all unknown) is not stored: its chunk is deleted. Each file is
        replaced atomically (temporary file and rename) but not fsynced; see :meth:`fsync`.
        """
        keys = self._check_keys(keys)
        T = self.tile_size
        if not isinstance(data, np.ndarray) or data.dtype != np.int64:
            got = data.dtype if isinstance(data, np.ndarray) else type(data).__name__
            raise TileArrayError(f"data: tiles must be an int64 array, got {got}")
        if data.shape != (len(keys), T, T, T):
            raise TileArrayError(
                f"data: expected shape {(len(keys), T, T, T)} for {len(keys)} keys, "
                f"got {data.shape}"
            )
        if len(keys) > 1 and len(unique_keys(keys)) != len(keys):
            raise TileArrayError("keys: the same tile is written twice in one call")
        self.put(keys, self.payloads(data))

    def put(self, keys: np.ndarray, payloads: list[bytes]) -> None:
        """Store encoded chunks (:meth:`encode`) of distinct ``keys``; an empty payload
        deletes the tile. Not fsynced; see :meth:`fsync`.

        Raises
        ------
        TileArrayError
            When a shard to rewrite is corrupt (naming it; that shard is left as it was).
        """
        keys = self._check_keys(keys)
        if self.shard > 1:
            for name, picked, inner in self._by_shard(keys):
                updates = dict(
                    zip(inner.tolist(), [payloads[r] for r in picked.tolist()], strict=True)
                )
                try:
                    merge_shard(str(self.group_path / name), updates, self.shard)
                except ShardError as exc:
                    raise TileArrayError(f"tile {keys[picked[0]].tolist()}: {exc}") from exc
            return
        for payload, name in zip(payloads, self._chunk_names(keys), strict=True):
            if payload:
                self._store.set_sync(name, self._prototype.buffer.from_bytes(payload))
            else:
                with contextlib.suppress(FileNotFoundError, NotADirectoryError):
                    os.unlink(self.group_path / name)

    def room_to_put(self, keys: np.ndarray, nbytes: int) -> int:
        """At most how many bytes of disk a :meth:`put` of ``nbytes`` of chunks to ``keys``
        takes beyond what the array takes now, at its peak: the chunks, one index and one
        block of rounding per file, and, as a shard is rewritten through a copy, the
        largest shard file it rewrites with the chunks added."""
        shards = self.shards_of(self._check_keys(keys))[0]
        largest = 0
        if self.shard > 1:
            for i, j, k in shards.tolist():
                with contextlib.suppress(FileNotFoundError, NotADirectoryError):
                    size = os.stat(self.group_path / _file_name(i, j, k)).st_size
                    largest = max(largest, size)
        index = 0 if self.shard == 1 else index_nbytes(self.shard)
        return 2 * int(nbytes) + largest + len(shards) * (index + _BLOCK)

    def delete(self, keys: np.ndarray) -> None:
        """Remove the chunks of ``keys``; missing ones are ignored (not fsynced)."""
        keys = unique_keys(self._check_keys(keys))
        self.put(keys, [b""] * len(keys))

    # --- durability and recovery -----------------------------------------------------------
    def fsync(self, keys: np.ndarray) -> None:
        """Make the state of ``keys``' chunks durable.

        fsyncs each chunk file that exists and every existing folder from its folder up to
        the array's, so that written, replaced and deleted chunks all survive a power loss.
        For many keys, one ``syncfs`` of the file system is much cheaper than a ``fsync`` per
        file and folder (measured: 102,040 fsyncs took 12 s for 85k tiles) and promises
        the same.
        """
        keys = self._check_keys(keys)
        fsync_paths(self.group_path, sorted(set(self._chunk_names(keys))))

    def remove_partials(self) -> int:
        """Delete the ``<chunk>.<32 hex>.partial`` files that killed writes left behind.

        Only while no process writes the array (at open, under the store lock): a live
        writer's temporary file would be deleted under it. Returns how many were removed.
        """
        removed = 0
        for folder, _, files in os.walk(self.path):
            for name in files:
                if _PARTIAL.search(name):
                    try:
                        os.unlink(os.path.join(folder, name))
                    except FileNotFoundError:
                        continue
                    removed += 1
        return removed

    def stored_keys(self) -> np.ndarray:
        """Keys of every tile stored, by walking ``tiles/c`` (not through zarr; in a sharded
        array, reading each shard's index).

        Returns sorted unique int64 (n, 3). Files that are not chunks of a valid key (such as
        ``.partial`` orphans) are skipped.

        Raises
        ------
        TileArrayError
            For a corrupt shard.
        """
        B = self.shard
        if B == 1:
            return stored_chunk_keys(self.path / "c")
        found = []
        top = -(-TILES_PER_AXIS // B)
        for i, j, k in _chunk_files(self.path / "c", 0, top):
            path = f"{self.group_path}/{_file_name(i, j, k)}"
            try:
                shard = read_shard(path, B)
            except ShardError as exc:
                raise TileArrayError(str(exc)) from exc
            if shard is None:
                continue
            for n, _ in inner_chunks(*shard):
                found.append((i * B + n // (B * B), j * B + n // B % B, k * B + n % B))
        if not found:
            return np.zeros((0, 3), np.int64)
        return unique_keys(np.array(found, np.int64) - KEY_OFFSET)


def _file_name(i: int, j: int, k: int) -> str:
    """A chunk's file in the group (a shard's in a sharded array), from its chunk index."""
    return f"{TILES_ARRAY}/c/{i}/{j}/{k}"


def fsync_paths(root: Path, names: list[str]) -> None:
    """Make the state of the files ``root/name`` durable, written, replaced or deleted.

    fsyncs each file that exists and every existing folder from its folder up to ``root``.
    From ``_SYNCFS_FROM`` files on, one ``syncfs`` of the file system is much cheaper than a
    ``fsync`` per file and folder (measured: 102,040 fsyncs took 12 s for 85k tiles) and
    promises the same.
    """
    if len(names) >= _SYNCFS_FROM and root.exists() and _syncfs(root):
        return
    folders: set[str] = set()
    for name in names:
        try:
            fd = os.open(root / name, os.O_RDONLY)
        except (FileNotFoundError, NotADirectoryError):
            pass
        else:
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        parts = name.split("/")
        for depth in range(1, len(parts)):
            folders.add("/".join(parts[:depth]))
    for folder in sorted(folders, key=len, reverse=True):  # deepest first
        with contextlib.suppress(FileNotFoundError, NotADirectoryError):
            fsync_path(root / folder)


def stored_chunk_keys(folder: Path) -> np.ndarray:
    """Keys of the chunk files under ``folder`` (an array's ``c`` folder, named
    ``<i>/<j>/<k>`` by chunk index), by walking it; other files are skipped. Sorted unique
    int64 (n, 3)."""
    found = list(_chunk_files(folder, 1, TILES_PER_AXIS))  # key -2**20 is outside the range
    if not found:
        return np.zeros((0, 3), np.int64)
    return unique_keys(np.array(found, np.int64) - KEY_OFFSET)


def _chunk_files(folder: str | Path, lo: int, hi: int) -> Iterator[tuple[int, int, int]]:
    """Chunk indices ``(i, j, k)`` in ``[lo, hi)`` of the files ``folder/<i>/<j>/<k>``."""
    for i, dir_i in _int_entries(folder, True, lo, hi):
        for j, dir_j in _int_entries(dir_i, True, lo, hi):
            for k, _ in _int_entries(dir_j, False, lo, hi):
                yield i, j, k


def _int_entries(folder: str | Path, dirs: bool, lo: int, hi: int) -> Iterator[tuple[int, str]]:
    """``(index, path)`` of the entries of ``folder`` named by a chunk index in range."""
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return
    for entry in entries:
        name = entry.name
        if not (name.isascii() and name.isdigit()):
            continue
        index = int(name)
        if str(index) != name:  # zarr writes no leading zeros
            continue
        if not lo <= index < hi:
            continue
        is_dir = entry.is_dir(follow_symlinks=False)
        if is_dir if dirs else entry.is_file(follow_symlinks=False):
            yield index, entry.path
