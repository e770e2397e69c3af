"""Shards of a tile array: ``B^3`` tiles in one file (docs/sharded-tiles.md).

A sharded tile array (layout version 4) has Zarr v3's ``sharding_indexed`` codec: its chunk
(a *shard*) is ``(B T)^3`` voxels and holds ``B^3`` inner chunks of one tile each, encoded
as an unsharded array's chunks, one after the other, then an index of ``B^3`` pairs
``(offset, nbytes)`` (little-endian uint64, inner chunks in C order; both ``2^64 - 1`` for
an absent tile) followed by its crc32c (little-endian uint32). That is the byte layout
zarr-python reads and writes (``tests/test_shards.py`` compares them).

Only whole shards are written here: :func:`merge_shard` reads the committed shard, replaces
some of its inner chunks and writes the result through a temporary file and a rename (or
deletes the file when no tile is left). Replacing inner chunks by the same bytes again
gives the same file, so a merge cut short can simply run again.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator, Mapping

import google_crc32c
import numpy as np

__all__ = [
    "ABSENT",
    "ShardError",
    "build_shard",
    "index_nbytes",
    "merge_shard",
    "read_shard",
    "shard_index",
    "tiles_per_shard_side",
]

#: An absent inner chunk's offset and length in a shard's index.
ABSENT = np.uint64(2**64 - 1)

#: The side of a shard in voxels that :func:`tiles_per_shard_side` aims at (64^3 int64
#: voxels: 2 MiB raw, about 20-60 KiB for a 10 cm street's shard after zstd).
SHARD_VOXELS = 64
#: At most this many tiles a shard side (512 tiles per shard, an 8 KiB index).
MAX_SHARD = 8


class ShardError(ValueError):
    """A shard file that is not a valid shard of the array (corrupt or truncated)."""


def tiles_per_shard_side(tile_size: int) -> int:
    """``B`` for a new array of ``tile_size`` voxel tiles: ``SHARD_VOXELS // T`` tiles a side
    (4 for 16^3 tiles, 2 for 32^3) up to ``MAX_SHARD``, 1 (no sharding) for tiles of 64
    voxels or more."""
    return max(1, min(MAX_SHARD, SHARD_VOXELS // int(tile_size)))


def index_nbytes(B: int) -> int:
    """Bytes of a shard's index (16 per inner chunk and the crc32c)."""
    return 16 * B**3 + 4


def shard_index(raw: bytes | memoryview, B: int, what: str) -> np.ndarray:
    """The index of the shard ``raw`` (its whole bytes) as uint64 (B^3, 2): offset and length
    of each inner chunk in C order, ``ABSENT`` for an absent one.

    Raises
    ------
    ShardError
        For a shard too short for its index, a bad checksum, or chunks outside the file.
    """
    n = index_nbytes(B)
    if len(raw) < n:
        raise ShardError(f"{what} is corrupt ({len(raw)} bytes, shorter than its index)")
    tail = bytes(raw[len(raw) - n :])
    body, crc = tail[:-4], tail[-4:]
    if np.uint32(google_crc32c.value(body)).astype("<u4").tobytes() != crc:
        raise ShardError(f"{what} is corrupt (the checksum of its index does not match)")
    index = np.frombuffer(body, "<u8").reshape(B**3, 2)
    present = index[:, 0] != ABSENT
    if np.any(index[present, 0] + index[present, 1] > len(raw) - n):
        raise ShardError(f"{what} is corrupt (an inner chunk lies outside the file)")
    return index


def read_shard(path: str, B: int) -> tuple[bytes, np.ndarray] | None:
    """The bytes and index of the shard file ``path``, or None when there is none."""
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except (FileNotFoundError, NotADirectoryError):
        return None
    return raw, shard_index(raw, B, f"shard {path}")


def inner_chunks(raw: bytes, index: np.ndarray) -> Iterator[tuple[int, bytes]]:
    """``(inner index, bytes)`` of each present inner chunk of a shard."""
    for n in np.flatnonzero(index[:, 0] != ABSENT).tolist():
        offset, length = int(index[n, 0]), int(index[n, 1])
        yield n, raw[offset : offset + length]


def build_shard(chunks: Mapping[int, bytes], B: int) -> bytes:
    """A shard's bytes from its inner chunks (inner index in C order -> encoded bytes; the
    others absent), the chunks in index order, the index at the end."""
    index = np.full((B**3, 2), ABSENT, "<u8")
    parts = []
    offset = 0
    for n in sorted(chunks):
        payload = chunks[n]
        index[n] = (offset, len(payload))
        parts.append(payload)
        offset += len(payload)
    body = index.tobytes()
    parts.append(body)
    parts.append(np.uint32(google_crc32c.value(body)).astype("<u4").tobytes())
    return b"".join(parts)


def merge_shard(path: str, updates: Mapping[int, bytes | None], B: int) -> bool:
    """Replace inner chunks of the shard file ``path`` (inner index -> new bytes, or None to
    drop it) and write it whole through ``<path>.<32 hex>.partial`` and a rename; the file
    is deleted when no inner chunk is left. Returns whether the file exists afterwards.

    Raises
    ------
    ShardError
        When the committed shard is corrupt (nothing is written then).
    """
    found = read_shard(path, B)
    chunks: dict[int, bytes] = {} if found is None else dict(inner_chunks(*found))
    for n, payload in updates.items():
        if payload:
            chunks[n] = payload
        else:
            chunks.pop(n, None)
    if not chunks:
        with contextlib.suppress(FileNotFoundError, NotADirectoryError):
            os.unlink(path)
        return False
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = f"{path}.{uuid.uuid4().hex}.partial"
    try:
        with open(tmp, "wb") as fh:
            fh.write(build_shard(chunks, B))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return True
