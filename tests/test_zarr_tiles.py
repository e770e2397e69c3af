"""The Zarr tile array (storage.zarr_tiles) on real Zarr directories."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import zarr
from rangefuse.engine.grid import KEY_LIMIT
from rangefuse.storage.zarr_tiles import TileArrayError, ZarrTiles, _syncfs
from zarr.storage import LocalStore

OFFSET = KEY_LIMIT


def _tiles(rng: np.random.Generator, n: int, T: int) -> np.ndarray:
    data = rng.integers(-(2**40), 2**40, (n, T, T, T), dtype=np.int64)
    data[:, 0] = 0  # partly unknown, like a real tile
    return data


def _keys(rng: np.random.Generator, n: int, spread: int = 40) -> np.ndarray:
    keys = np.unique(rng.integers(-spread, spread, (3 * n, 3)), axis=0)[:n]
    return rng.permutation(keys).astype(np.int64)


def _slices(key: np.ndarray, T: int) -> tuple[slice, ...]:
    return tuple(slice((int(k) + OFFSET) * T, (int(k) + OFFSET + 1) * T) for k in key)


@pytest.mark.parametrize("T", [4, 16])
def test_round_trip_negative_and_extreme_keys(tmp_path: Path, T: int) -> None:
    rng = np.random.default_rng(T)
    tiles = ZarrTiles.create(tmp_path / "scene.zarr", T)
    keys = np.array(
        [[-3, 0, 5], [0, 0, 0], [-1, -1, -1], [KEY_LIMIT - 1, -(KEY_LIMIT - 1), 7]], np.int64
    )
    data = _tiles(rng, len(keys), T)
    tiles.write(keys, data)
    assert np.array_equal(tiles.read(keys), data)
    assert np.array_equal(tiles.read(keys[::-1]), data[::-1])
    missing = np.array([[1, 2, 3], [-5, -5, -5]], np.int64)
    assert np.array_equal(tiles.read(missing), np.zeros((2, T, T, T), np.int64))
    assert tiles.read(np.zeros((0, 3), np.int64)).shape == (0, T, T, T)
    # reopened, and read by zarr itself at the documented chunk position
    again = ZarrTiles.open(tmp_path / "scene.zarr")
    assert again.tile_size == T
    assert np.array_equal(again.read(keys), data)
    array = zarr.open_array(LocalStore(tmp_path / "scene.zarr"), path="tiles", mode="r")
    for key, tile in zip(keys, data, strict=True):
        assert np.array_equal(array[_slices(key, T)], tile)


def test_many_tiles_overwrite_and_delete(tmp_path: Path) -> None:
    T = 4
    rng = np.random.default_rng(1)
    tiles = ZarrTiles.create(tmp_path / "g", T)
    keys = _keys(rng, 2000)
    data = _tiles(rng, len(keys), T)
    tiles.write(keys, data)
    assert np.array_equal(tiles.read(keys), data)
    order = np.lexsort(keys.T[::-1])
    assert np.array_equal(tiles.stored_keys(), keys[order])
    data[:500] += 1
    tiles.write(keys[:500], data[:500])
    gone = keys[500:1200]
    tiles.delete(gone)
    tiles.delete(gone)  # missing ones are ignored
    expect = data.copy()
    expect[500:1200] = 0
    assert np.array_equal(tiles.read(keys), expect)
    kept = np.concatenate([keys[:500], keys[1200:]])
    assert np.array_equal(tiles.stored_keys(), kept[np.lexsort(kept.T[::-1])])


def test_zero_tiles_are_not_stored(tmp_path: Path) -> None:
    T = 4
    tiles = ZarrTiles.create(tmp_path / "g", T, shard=1)
    keys = np.array([[1, 1, 1], [2, 2, 2]], np.int64)
    data = np.zeros((2, T, T, T), np.int64)
    data[1, 3, 2, 1] = 7
    tiles.write(keys, data)
    assert not tiles.chunk_path(keys[0]).exists()
    assert tiles.chunk_path(keys[1]).is_file()
    assert np.array_equal(tiles.stored_keys(), keys[1:])
    tiles.write(keys[1:], np.zeros((1, T, T, T), np.int64))  # zeros over a tile delete it
    assert not tiles.chunk_path(keys[1]).exists()
    assert tiles.stored_keys().shape == (0, 3)
    assert not tiles.read(keys).any()


def test_zarr_deletes_a_chunk_overwritten_with_zeros(tmp_path: Path) -> None:
    """What zarr itself does with write_empty_chunks=False (the behaviour we mirror)."""
    T = 4
    tiles = ZarrTiles.create(tmp_path / "g", T, shard=1)
    key = np.array([3, -2, 1], np.int64)
    tiles.array[_slices(key, T)] = np.ones((T, T, T), np.int64)
    assert tiles.chunk_path(key).is_file()
    tiles.array[_slices(key, T)] = 0
    assert not tiles.chunk_path(key).exists()


def test_chunk_bytes_are_zarrs_own(tmp_path: Path) -> None:
    """A tile written here has the bytes zarr writes for it, in the file zarr names."""
    T = 16
    rng = np.random.default_rng(2)
    tiles = ZarrTiles.create(tmp_path / "g", T, shard=1)
    tile = _tiles(rng, 1, T)
    ours, theirs = np.array([[-7, 0, 9]], np.int64), np.array([[-7, 0, 10]], np.int64)
    tiles.write(ours, tile)
    tiles.array[_slices(theirs[0], T)] = tile[0]
    assert tiles.chunk_path(ours[0]).read_bytes() == tiles.chunk_path(theirs[0]).read_bytes()
    assert np.array_equal(tiles.read(theirs), tile)  # and zarr's chunks read here
    chunk = (OFFSET - 7, OFFSET, OFFSET + 9)
    expected = tmp_path / "g" / "tiles" / tiles.array.metadata.encode_chunk_key(chunk)
    assert tiles.chunk_path(ours[0]) == expected
    assert expected.relative_to(tmp_path / "g").parts == ("tiles", "c", *map(str, chunk))


def test_metadata_and_open_errors(tmp_path: Path) -> None:
    tiles = ZarrTiles.create(tmp_path / "g", 8, shard=1)
    meta = tiles.array.metadata.to_dict()
    assert meta["shape"] == (2**21 * 8,) * 3
    assert meta["chunk_grid"]["configuration"]["chunk_shape"] == (8, 8, 8)
    assert meta["fill_value"] == 0 and meta["data_type"] == "int64"
    assert [c["name"] for c in meta["codecs"]] == ["bytes", "zstd"]  # no sharding
    with pytest.raises(TileArrayError, match="already has a tile array"):
        ZarrTiles.create(tmp_path / "g", 8)
    with pytest.raises(TileArrayError, match="no tile array"):
        ZarrTiles.open(tmp_path / "nothing")
    with pytest.raises(TileArrayError, match="tile_size"):
        ZarrTiles.create(tmp_path / "h", 0)
    other = zarr.open_group(LocalStore(tmp_path / "other"), mode="a", zarr_format=3)
    other.create_array("tiles", shape=(64, 64, 64), chunks=(8, 8, 8), dtype="float32")
    with pytest.raises(TileArrayError, match="not a rangefuse tile array"):
        ZarrTiles.open(tmp_path / "other")
    # an existing group keeps its attributes
    scene = zarr.open_group(LocalStore(tmp_path / "s"), mode="a", zarr_format=3)
    scene.attrs["rangefuse"] = {"version": 1}
    ZarrTiles.create(tmp_path / "s", 4)
    reopened = zarr.open_group(LocalStore(tmp_path / "s"), mode="r")
    assert reopened.attrs["rangefuse"] == {"version": 1}


def test_bad_keys_and_data(tmp_path: Path) -> None:
    T = 4
    tiles = ZarrTiles.create(tmp_path / "g", T)
    good = np.zeros((1, T, T, T), np.int64)
    with pytest.raises(TileArrayError, match=r"keys: must be an integer array \(n, 3\)"):
        tiles.read(np.zeros((2, 2), np.int64))
    with pytest.raises(TileArrayError, match="keys: must be integers"):
        tiles.read(np.zeros((1, 3), np.float64))
    with pytest.raises(TileArrayError, match="keys: tile keys must lie in"):
        tiles.write(np.array([[0, 0, KEY_LIMIT]]), good)
    with pytest.raises(TileArrayError, match="keys: tile keys must lie in"):
        tiles.chunk_path([-KEY_LIMIT, 0, 0])
    with pytest.raises(TileArrayError, match="data: tiles must be an int64 array"):
        tiles.write(np.zeros((1, 3), np.int64), good.astype(np.int32))
    with pytest.raises(TileArrayError, match=r"data: expected shape \(2, 4, 4, 4\)"):
        tiles.write(np.array([[0, 0, 0], [0, 0, 1]]), good)
    with pytest.raises(TileArrayError, match="written twice"):
        tiles.write(np.zeros((2, 3), np.int64), np.ones((2, T, T, T), np.int64))


def test_corrupt_chunk_names_the_tile(tmp_path: Path) -> None:
    T = 4
    tiles = ZarrTiles.create(tmp_path / "g", T, shard=1)
    key = np.array([[5, -6, 7]], np.int64)
    tiles.write(key, np.ones((1, T, T, T), np.int64))
    tiles.chunk_path(key[0]).write_bytes(b"not zstd")
    with pytest.raises(TileArrayError, match=r"tile \[5, -6, 7\]: chunk .* is corrupt"):
        tiles.read(key)


def test_fsync_and_chunk_path(tmp_path: Path) -> None:
    T = 4
    tiles = ZarrTiles.create(tmp_path / "g", T)
    keys = np.array([[0, 0, 0], [0, 0, 1], [-9, 4, 2]], np.int64)
    tiles.write(keys[:2], np.ones((2, T, T, T), np.int64))
    assert all(tiles.chunk_path(k).is_file() for k in keys[:2])
    assert not tiles.chunk_path(keys[2]).exists()
    tiles.fsync(keys)  # existing and missing keys
    tiles.delete(keys[:1])
    tiles.fsync(keys[:1])  # a deleted key: its folders
    tiles.fsync(np.zeros((0, 3), np.int64))


def test_stored_keys_skip_foreign_files(tmp_path: Path) -> None:
    T = 4
    tiles = ZarrTiles.create(tmp_path / "g", T)
    assert tiles.stored_keys().shape == (0, 3)
    key = np.array([[-2, 3, 4]], np.int64)
    tiles.write(key, np.ones((1, T, T, T), np.int64))
    folder = tiles.chunk_path(key[0]).parent
    (folder / f"{OFFSET + 4}.{'a' * 32}.partial").write_bytes(b"x")
    (folder / "007").write_bytes(b"x")
    (folder / "notes.txt").write_bytes(b"x")
    (tiles.path / "c" / str(2 * OFFSET)).mkdir()  # chunk index out of range
    keys = tiles.stored_keys()
    assert keys.dtype == np.int64
    assert np.array_equal(keys, key)


def test_remove_partials(tmp_path: Path) -> None:
    T = 4
    tiles = ZarrTiles.create(tmp_path / "g", T)
    key = np.array([[1, 2, 3]], np.int64)
    tiles.write(key, np.ones((1, T, T, T), np.int64))
    chunk = tiles.chunk_path(key[0])
    orphan = chunk.with_suffix(f".{'0123456789abcdef' * 2}.partial")  # zarr's own naming
    orphan.write_bytes(b"half a chunk")
    other = chunk.parent / "notes.partial"  # not zarr's pattern: kept
    other.write_bytes(b"x")
    assert tiles.remove_partials() == 1
    assert not orphan.exists() and other.exists() and chunk.exists()
    assert tiles.remove_partials() == 0


_KILLED_WRITER = textwrap.dedent(
    """
    import pathlib, sys, time
    import numpy as np
    from rangefuse.storage.zarr_tiles import ZarrTiles

    def stuck(self, target):  # killed between writing the temporary file and the rename
        print("written", flush=True)
        time.sleep(60)

    tiles = ZarrTiles.open(pathlib.Path(sys.argv[1]))
    pathlib.Path.replace = stuck
    tiles.write(np.array([[1, 2, 3]]), np.full((1, 4, 4, 4), 2, np.int64))
    """
)


def test_remove_partials_after_a_killed_writer(tmp_path: Path) -> None:
    T = 4
    tiles = ZarrTiles.create(tmp_path / "g", T, shard=1)
    key = np.array([[1, 2, 3]], np.int64)
    tiles.write(key, np.ones((1, T, T, T), np.int64))
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    proc = subprocess.Popen(
        [sys.executable, "-c", _KILLED_WRITER, str(tmp_path / "g")],
        stdout=subprocess.PIPE,
        env=env,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == b"written"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    partials = list(tiles.chunk_path(key[0]).parent.glob("*.partial"))
    assert len(partials) == 1
    assert partials[0].name.startswith(f"{OFFSET + 3}.")
    assert np.array_equal(tiles.read(key), np.ones((1, T, T, T), np.int64))  # old tile intact
    assert np.array_equal(tiles.stored_keys(), key)
    assert tiles.remove_partials() == 1
    assert not list(tiles.path.rglob("*.partial"))


def test_syncfs_syncs_the_file_system_that_holds_a_path(tmp_path):
    """Many chunks are made durable with one ``syncfs(2)`` (through the C library that the
    store loads in one place, ``storage/_heap.py``)."""
    assert _syncfs(tmp_path) is True
