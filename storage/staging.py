"""Where units of work write their tiles until a checkpoint publishes them (docs/storage.md,
"Units that can run again"; docs/sharded-tiles.md, "Writing").

A unit never writes a scene's committed chunks: it reads them, and stages each tile it
changes here, in *packs*: one file per write of its tile cache, ``<unit>.<run>.<n>.pack`` in
the attempt's folder, holding the encoded chunks one after the other and a footer of their
keys, offsets and lengths (a tile that became all unknown has length 0, a *tombstone*).
When the unit is done it fsyncs its packs and writes ``<unit>.<run>.done`` (how many packs
the run wrote). A run killed at any point leaves no ``done`` file, and its packs are never
read; a unit run twice at once writes beside itself (``run`` is a fresh token), and any
finished run of a unit holds the same tiles (units are deterministic).

Once the catalog has committed a group's checkpoint, :meth:`Staging.publish` writes the
staged chunks of one finished run per unit into the tile array (the last state of each
tile; a tombstone deletes it; the scene's own deletions, staged as unit ``scene``, last),
makes that durable, then empties the folder. Writing the same chunks again gives the same
array, so a publish cut short is finished at the next open. Without a committed checkpoint,
the staged packs are discarded.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import uuid
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from rangefuse.engine.grid import pack_keys, unpack_keys

from ._files import fsync_path
from .zarr_tiles import KEY_OFFSET, TileArrayError, ZarrTiles, stored_chunk_keys, tile_rows

__all__ = ["Staging"]

_MAGIC = b"RFPACK1\n"
#: A publish writes at most this many tiles, or this many bytes of chunks, at once.
_PUBLISH_TILES = 4096
_PUBLISH_BYTES = 64 * 2**20
#: The unit name of the scene's own deletions (published after the units').
SCENE_UNIT = "scene"
#: The file that holds the room a publish needs (:meth:`Staging.reserve`).
_ROOM = "room"


class Staging:
    """The staging area of one attempt of a scene, for the chunks of its tile array
    ``tiles``; this object writes as one run of the unit ``unit``."""

    def __init__(self, folder: Path, tiles: ZarrTiles, unit: str = SCENE_UNIT) -> None:
        if not unit or not unit.isalnum():
            raise ValueError(f"unit: must be a non-empty alphanumeric name, got {unit!r}")
        self.folder = Path(folder)
        self.tiles = tiles
        self.unit = unit
        self._run = uuid.uuid4().hex
        self._packs: list[str] = []  # this run's packs, in order
        # per pack: its packed keys (sorted), their offsets and lengths (24 bytes a tile)
        self._footers: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    # --- one run's packs -----------------------------------------------------------------
    def write(self, keys: np.ndarray, data: Sequence[np.ndarray]) -> None:
        """Stage whole tiles (each int64 (T, T, T): an (n, T, T, T) array or a list of the
        cache's tiles, which need no copy into one array); an all-unknown tile as a
        tombstone. One pack per call."""
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        self._pack(keys, self.tiles.payloads(data))

    def delete(self, keys: np.ndarray) -> None:
        """Stage the deletion of tiles (tombstones)."""
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        self._pack(keys, [b""] * len(keys))

    def _pack(self, keys: np.ndarray, payloads: list[bytes]) -> None:
        if len(payloads) != len(keys):
            raise ValueError(f"{len(payloads)} tiles for {len(keys)} keys")
        if not len(keys):
            return
        if not self._packs:
            os.makedirs(self.folder, exist_ok=True)
        lengths = np.array([len(p) for p in payloads], np.int64)
        offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
        footer = np.column_stack([keys, offsets, lengths]).astype("<i8").tobytes()
        path = f"{self.folder}/{self.unit}.{self._run}.{len(self._packs) + 1}.pack"
        with open(path, "wb") as fh:
            fh.writelines(payloads)  # not joined: a pack of 1 cm tiles is tens of MB
            fh.write(footer + np.int64(len(keys)).astype("<i8").tobytes() + _MAGIC)
        self._packs.append(path)
        # sorted, the last of a key given twice
        packed, last = np.unique(pack_keys(keys)[::-1], return_index=True)
        last = len(keys) - 1 - last
        self._footers.append((packed, offsets[last], lengths[last]))

    def read(
        self, keys: np.ndarray, out: np.ndarray | None = None, rows: np.ndarray | None = None
    ) -> np.ndarray:
        """Tiles this run staged (they must have been); a tombstone reads as unknown.
        ``out`` and ``rows`` as in :meth:`ZarrTiles.read`."""
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        out, flat, at = tile_rows(out, rows, len(keys), self.tiles.tile_size)
        packed = pack_keys(keys)
        pack = np.full(len(keys), -1, np.int64)
        offset, length = np.zeros_like(pack), np.zeros_like(pack)
        for n in range(len(self._packs) - 1, -1, -1):  # the latest pack of each tile
            todo = np.flatnonzero(pack < 0)
            if not len(todo):
                break
            staged, offsets, lengths = self._footers[n]
            at_n = np.minimum(np.searchsorted(staged, packed[todo]), len(staged) - 1)
            hit = staged[at_n] == packed[todo]
            pack[todo[hit]] = n
            offset[todo[hit]], length[todo[hit]] = offsets[at_n[hit]], lengths[at_n[hit]]
        if (pack < 0).any():
            missing = keys[np.flatnonzero(pack < 0)[0]].tolist()
            raise TileArrayError(f"tile {missing} was not staged")
        where = zip(pack.tolist(), offset.tolist(), length.tolist(), range(len(keys)), strict=True)
        for pack_path, payloads in _payloads(self._packs, sorted(where)):
            for n, raw in payloads:
                what = f"staged tile {keys[n].tolist()}: {pack_path}"
                flat[at[n]] = self.tiles.decode(raw, what) if raw else 0
        return out

    def finish(self) -> None:
        """Make this run's packs durable and mark the run finished (its ``done`` file)."""
        if not self._packs and not self.folder.is_dir():
            os.makedirs(self.folder, exist_ok=True)
        for path in self._packs:
            fd = os.open(path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        done = self.folder / f"{self.unit}.{self._run}.done"
        tmp = done.with_name(done.name + ".partial")  # a run killed here has no done file
        with open(tmp, "w") as fh:
            fh.write(str(len(self._packs)))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, done)
        fsync_path(self.folder)

    # --- the attempt's folder ------------------------------------------------------------
    def _finished_packs(self) -> list[str]:
        """The packs of one finished run of each unit, the scene's last, each unit's in
        order."""
        runs: dict[str, tuple[str, int]] = {}
        try:
            names = sorted(os.listdir(self.folder))
        except FileNotFoundError:
            return []
        for name in names:
            parts = name.split(".")
            if len(parts) != 3 or parts[2] != "done" or parts[0] in runs:
                continue
            try:
                count = int((self.folder / name).read_text())
            except ValueError:
                raise TileArrayError(f"staged run {self.folder / name} is corrupt") from None
            runs[parts[0]] = (parts[1], count)
        units = sorted(runs, key=lambda u: (u == SCENE_UNIT, u))
        return [
            f"{self.folder}/{u}.{runs[u][0]}.{n}.pack"
            for u in units
            for n in range(1, runs[u][1] + 1)
        ]

    def _index(self) -> tuple[list[str], np.ndarray, np.ndarray]:
        """The finished runs' packs, the packed keys they staged (sorted) and, for each, its
        last ``(pack, offset, length)`` (int64 (n, 3))."""
        packs = self._finished_packs()
        keys, where = [np.zeros(0, np.int64)], [np.zeros((0, 3), np.int64)]
        for n, path in enumerate(packs):
            footer = _footer(path)
            keys.append(pack_keys(footer[:, :3]))
            where.append(np.column_stack([np.full(len(footer), n), footer[:, 3:]]))
        packed, at = np.concatenate(keys), np.concatenate(where)
        # the last staging of each key: unique over the reversed order keeps the last one
        unique, last = np.unique(packed[::-1], return_index=True)
        return packs, unique, at[::-1][last]

    def staged_keys(self) -> np.ndarray:
        """Keys of every tile the finished runs staged (sorted int64 (n, 3))."""
        return unpack_keys(self._index()[1])

    def reserve(self) -> int:
        """Hold on disk, in a file of the attempt's folder, the most room that publishing the
        finished runs takes (:meth:`ZarrTiles.room_to_put`); :meth:`publish` frees it first.
        Called before the checkpoint commits, so that a disk too full to publish fails the
        group while what it staged can still be dropped: once committed, the packs must
        stay until they are published. Returns the bytes held.

        Raises
        ------
        OSError
            ``ENOSPC`` when the disk has not that much room (nothing is held then).
        """
        _, packed, where = self._index()
        need = self.tiles.room_to_put(unpack_keys(packed), int(where[:, 2].sum()))
        if need:
            path = self.folder / _ROOM
            os.makedirs(self.folder, exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                os.posix_fallocate(fd, 0, need)
            except BaseException:
                os.unlink(path)
                raise
            finally:
                os.close(fd)
        return need

    def publish(self) -> int:
        """Write the finished runs' staged chunks into the tile array (a tombstone deletes
        the tile), make that durable, then empty the staging area. Idempotent; returns the
        tiles published."""
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.folder / _ROOM)  # the room it holds is the publish's
        legacy = self._publish_version_3()
        packs, packed, where = self._index()
        keys = unpack_keys(packed)
        shard = self.tiles.shards_of(keys)[1]
        order = np.lexsort((where[:, 1], where[:, 0], shard))  # a shard's tiles together
        for batch in _batches(shard[order], where[order, 2]):
            rows = order[batch]
            payloads: list[bytes] = [b""] * len(rows)
            spots = sorted((*where[r].tolist(), n) for n, r in enumerate(rows.tolist()))
            for _, found in _payloads(packs, spots):
                for n, raw in found:
                    payloads[n] = raw
            self.tiles.put(keys[rows], payloads)
        if len(keys) or len(legacy):
            self.tiles.fsync(np.concatenate([keys, legacy]))
        for name in os.listdir(self.folder) if self.folder.is_dir() else ():
            if name.endswith(".done"):  # first: a cut-short discard leaves nothing to publish
                os.unlink(self.folder / name)
        if self.folder.is_dir():
            fsync_path(self.folder)
        self.discard()
        return len(keys) + len(legacy)

    def _publish_version_3(self) -> np.ndarray:
        """Write what a version-3 rangefuse staged (a chunk file per tile under ``c/``, an
        empty one a tombstone) and was killed publishing; returns its keys."""
        keys = stored_chunk_keys(self.folder / "c")
        for start in range(0, len(keys), _PUBLISH_TILES):
            part = keys[start : start + _PUBLISH_TILES]
            payloads = []
            for i, j, k in (part + KEY_OFFSET).tolist():
                with open(f"{self.folder}/c/{i}/{j}/{k}", "rb") as fh:
                    payloads.append(fh.read())
            self.tiles.put(part, payloads)
        return keys

    def discard(self) -> None:
        """Drop whatever is staged (a group that was never committed)."""
        shutil.rmtree(self.folder, ignore_errors=True)


def _footer(path: str) -> np.ndarray:
    """A pack's footer: int64 (n, 5) of key, offset and length per staged tile."""
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            if size < 16:
                raise ValueError(f"{size} bytes")
            fh.seek(size - 16)
            tail = fh.read(16)
            n = int(np.frombuffer(tail[:8], "<i8")[0])
            if tail[8:] != _MAGIC or not 0 <= n <= (size - 16) // 40:
                raise ValueError("no footer")
            fh.seek(size - 16 - 40 * n)
            footer = np.frombuffer(fh.read(40 * n), "<i8").reshape(n, 5).astype(np.int64)
    except FileNotFoundError:
        raise TileArrayError(f"staged pack {path} is missing") from None
    except ValueError as exc:
        raise TileArrayError(f"staged pack {path} is corrupt ({exc})") from None
    if n and (footer[:, 3:].min() < 0 or (footer[:, 3] + footer[:, 4]).max() > size - 16 - 40 * n):
        raise TileArrayError(f"staged pack {path} is corrupt (a tile lies outside it)")
    return footer


def _payloads(
    packs: Sequence[str], spots: Sequence[tuple[int, int, int, int]]
) -> Iterator[tuple[str, list[tuple[int, bytes]]]]:
    """For ``spots`` ``(pack, offset, length, n)`` sorted by pack and offset: per pack, its
    path and ``(n, bytes)`` of each spot (each pack opened once)."""
    for pack, group in itertools.groupby(spots, key=lambda spot: spot[0]):
        with open(packs[pack], "rb") as fh:
            fd = fh.fileno()
            found = [(n, os.pread(fd, length, offset) if length else b"")
                     for _, offset, length, n in group]  # fmt: skip
        yield packs[pack], found


def _batches(shard: np.ndarray, nbytes: np.ndarray) -> Iterator[np.ndarray]:
    """Rows (sorted by ``shard``) in runs of at most ``_PUBLISH_TILES`` tiles or
    ``_PUBLISH_BYTES`` bytes, cut between shards where a shard is smaller than that."""
    total = np.concatenate([[0], np.cumsum(nbytes)])
    start, n = 0, len(shard)
    while start < n:
        by_bytes = int(np.searchsorted(total, total[start] + _PUBLISH_BYTES, side="right")) - 1
        end = min(n, start + _PUBLISH_TILES, max(start + 1, by_bytes))
        if end < n:
            cut = int(np.searchsorted(shard, shard[end], side="left"))
            end = cut if cut > start else end
        yield np.arange(start, end)
        start = end
