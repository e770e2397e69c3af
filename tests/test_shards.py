"""Tiles in shards (storage.shards, layout version 4) and the packs units stage them in
(storage.staging), on real Zarr directories."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, Volume
from rangefuse.engine.grid import KEY_LIMIT
from rangefuse.engine.synth import make_dataset
from rangefuse.storage import open_store
from rangefuse.storage.shards import inner_chunks, read_shard, tiles_per_shard_side
from rangefuse.storage.staging import Staging
from rangefuse.storage.zarr_tiles import TileArrayError, ZarrTiles

OFFSET = KEY_LIMIT


def _tiles(rng: np.random.Generator, n: int, T: int) -> np.ndarray:
    data = rng.integers(-(2**40), 2**40, (n, T, T, T), dtype=np.int64)
    data[:, 0] = 0  # partly unknown, like a real tile
    return data


def _block(tiles: ZarrTiles, first: np.ndarray) -> tuple[slice, ...]:
    """The voxels of the shard whose first tile is ``first``."""
    span = tiles.shard * tiles.tile_size
    return tuple(slice(int(k + OFFSET) * tiles.tile_size, int(k + OFFSET) * tiles.tile_size + span)
                 for k in first)  # fmt: skip


@pytest.mark.parametrize(("T", "B"), [(4, 8), (8, 8), (16, 4), (32, 2), (64, 1), (100, 1)])
def test_new_arrays_are_sharded_by_tile_size(tmp_path: Path, T: int, B: int) -> None:
    assert tiles_per_shard_side(T) == B
    tiles = ZarrTiles.create(tmp_path / "g", T)
    assert tiles.shard == B and ZarrTiles.open(tmp_path / "g").shard == B
    meta = tiles.array.metadata.to_dict()
    names = [c["name"] for c in meta["codecs"]]
    assert names == (["bytes", "zstd"] if B == 1 else ["sharding_indexed"])
    assert meta["chunk_grid"]["configuration"]["chunk_shape"] == (B * T,) * 3
    assert meta["shape"] == (2**21 * T,) * 3


def test_zarr_reads_our_shards_and_we_read_zarrs(tmp_path: Path) -> None:
    T, rng = 4, np.random.default_rng(3)
    tiles = ZarrTiles.create(tmp_path / "g", T, shard=4)
    inner = np.array([[0, 0, 0], [3, 1, 2], [1, 0, 0], [2, 3, 3]], np.int64)
    data = _tiles(rng, len(inner), T)
    ours, theirs = inner + np.array([8, 0, -4]), inner + np.array([12, 0, -4])
    tiles.write(ours, data)
    block = np.zeros((4 * T,) * 3, np.int64)
    for (i, j, k), tile in zip(inner.tolist(), data, strict=True):
        block[i * T : (i + 1) * T, j * T : (j + 1) * T, k * T : (k + 1) * T] = tile
    tiles.array[_block(tiles, np.array([12, 0, -4]))] = block  # zarr writes a whole shard
    np.testing.assert_array_equal(tiles.array[_block(tiles, np.array([8, 0, -4]))], block)
    np.testing.assert_array_equal(tiles.read(theirs), data)
    # the same inner chunks, byte for byte (zarr lays them out in its own order)
    mine = read_shard(str(tiles.chunk_path(ours[0])), 4)
    zarrs = read_shard(str(tiles.chunk_path(theirs[0])), 4)
    assert mine is not None and zarrs is not None
    assert dict(inner_chunks(*mine)) == dict(inner_chunks(*zarrs))
    assert tiles.chunk_path(ours[0]).parent.parent.parent == tiles.path / "c"


def test_shards_round_trip_at_the_edges_of_the_key_range(tmp_path: Path) -> None:
    T, rng = 4, np.random.default_rng(4)
    tiles = ZarrTiles.create(tmp_path / "g", T, shard=4)
    keys = np.array(
        [[-KEY_LIMIT + 1, KEY_LIMIT - 1, 0], [-KEY_LIMIT + 2, KEY_LIMIT - 2, 0], [0, 0, 0],
         [-1, -1, -1], [3, 3, 3], [4, 4, 4], [-4, 0, 5]], np.int64,
    )  # fmt: skip
    data = _tiles(rng, len(keys), T)
    tiles.write(keys, data)
    np.testing.assert_array_equal(tiles.read(keys), data)
    np.testing.assert_array_equal(tiles.read(keys[::-1]), data[::-1])
    order = np.lexsort(keys.T[::-1])
    np.testing.assert_array_equal(tiles.stored_keys(), keys[order])
    files = [p for p in (tiles.path / "c").rglob("*") if p.is_file()]
    assert len(files) == 5  # the two extreme keys share a shard, as do 0 and 3
    tiles.write(keys[:1], np.zeros((1, T, T, T), np.int64))  # zeros delete the tile only
    np.testing.assert_array_equal(tiles.read(keys[1:2]), data[1:2])
    tiles.delete(keys[1:3])
    assert len([p for p in (tiles.path / "c").rglob("*") if p.is_file()]) == 4  # 3 holds on
    assert not tiles.read(keys[:3]).any()
    tiles.fsync(keys)


def test_writing_a_shard_again_gives_the_same_file(tmp_path: Path) -> None:
    T, rng = 4, np.random.default_rng(5)
    tiles = ZarrTiles.create(tmp_path / "g", T, shard=2)
    keys = np.array([[0, 0, 0], [1, 1, 1], [0, 1, 0]], np.int64)
    data = _tiles(rng, 3, T)
    tiles.write(keys, data)
    path = tiles.chunk_path(keys[0])
    first = path.read_bytes()
    tiles.write(keys[1:], data[1:])  # a publish cut short and run again
    assert path.read_bytes() == first
    assert not list(tiles.path.rglob("*.partial"))


def test_a_corrupt_shard_names_the_tile_and_is_not_rewritten(tmp_path: Path) -> None:
    T = 4
    tiles = ZarrTiles.create(tmp_path / "g", T, shard=2)
    keys = np.array([[5, -6, 7], [4, -6, 7]], np.int64)
    tiles.write(keys, np.ones((2, T, T, T), np.int64))
    path = tiles.chunk_path(keys[0])
    good = path.read_bytes()
    for bad, why in ((good[:-1] + bytes([good[-1] ^ 1]), "checksum"), (b"short", "shorter")):
        path.write_bytes(bad)
        with pytest.raises(TileArrayError, match=rf"tile \[5, -6, 7\]: shard .* corrupt.*{why}"):
            tiles.read(keys[:1])
        with pytest.raises(TileArrayError, match=rf"tile \[5, -6, 7\]: shard .* corrupt.*{why}"):
            tiles.write(keys[:1], np.full((1, T, T, T), 2, np.int64))
        assert path.read_bytes() == bad  # left for the operator, not silently replaced
        with pytest.raises(TileArrayError, match="corrupt"):
            tiles.stored_keys()
    # an index that points past the end of the file (with a valid checksum)
    index = np.frombuffer(good[-4 - 16 * 8 : -4], "<u8").copy()
    present = np.flatnonzero(index[0::2] != 2**64 - 1)[0]
    index[2 * present + 1] = 10**6
    body = index.astype("<u8").tobytes()
    import google_crc32c

    crc = np.uint32(google_crc32c.value(body)).astype("<u4").tobytes()
    path.write_bytes(good[: -4 - 16 * 8] + body + crc)
    with pytest.raises(TileArrayError, match="outside the file"):
        tiles.read(keys)


def test_a_foreign_shard_index_is_refused_at_open(tmp_path: Path) -> None:
    ZarrTiles.create(tmp_path / "g", 8)
    meta_path = tmp_path / "g" / "tiles" / "zarr.json"
    meta = json.loads(meta_path.read_text())
    meta["codecs"][0]["configuration"]["index_location"] = "start"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(TileArrayError, match="not a rangefuse tile array: shard index"):
        ZarrTiles.open(tmp_path / "g")
    with pytest.raises(TileArrayError, match=r"shard: must be in \[1, 8\]"):
        ZarrTiles.create(tmp_path / "h", 8, shard=9)


# --- packs -------------------------------------------------------------------------------------
def _run(folder: Path, tiles: ZarrTiles, unit: str, keys: np.ndarray, data: np.ndarray,
         finish: bool = True) -> Staging:  # fmt: skip
    run = Staging(folder, tiles, unit)
    for part in np.array_split(np.arange(len(keys)), 3):  # three cache writes: three packs
        run.write(keys[part], data[part])
    if finish:
        run.finish()
    return run


def test_only_finished_runs_are_published_and_the_scene_s_deletions_last(tmp_path: Path) -> None:
    T, rng = 4, np.random.default_rng(6)
    tiles = ZarrTiles.create(tmp_path / "g", T)
    folder = tmp_path / "attempt"
    keys = np.array([[k, k % 3, -k] for k in range(12)], np.int64)
    data = _tiles(rng, len(keys), T)
    killed = _run(folder, tiles, "u0", keys[:6], data[:6] + 1, finish=False)  # a killed run
    (folder / f"u0.{killed._run}.done.partial").write_text("")  # killed writing its done file
    assert len(list(folder.glob("u0.*.pack"))) == 3 and not list(folder.glob("*.done"))
    np.testing.assert_array_equal(killed.read(keys[:6]), data[:6] + 1)  # reads its own packs
    _run(folder, tiles, "u0", keys[:6], data[:6])  # the unit run again
    _run(folder, tiles, "u0", keys[:6], data[:6])  # and once more beside it (duplicate)
    second = Staging(folder, tiles, "u1")
    second.write(keys[6:], data[6:])
    second.write(keys[6:8], np.zeros((2, T, T, T), np.int64))  # later in the run: unknown
    second.write(keys[[9, 9]], data[[8, 9]])  # a key given twice in one write: the last
    assert not second.read(keys[6:8]).any()  # a run reads the latest pack of each tile
    np.testing.assert_array_equal(second.read(keys[[9, 8]]), data[[9, 8]])
    with pytest.raises(TileArrayError, match=r"tile \[0, 0, 0\] was not staged"):
        second.read(keys[[8, 0]])
    second.finish()
    scene = Staging(folder, tiles)
    scene.delete(keys[:1])  # the checkpoint's own deletion of a tile a unit staged
    scene.finish()
    assert len(Staging(folder, tiles).staged_keys()) == 12
    assert Staging(folder, tiles).publish() == 12
    want = data.copy()
    want[[0, 6, 7]] = 0
    np.testing.assert_array_equal(tiles.read(keys), want)
    assert not folder.exists()
    assert Staging(folder, tiles).publish() == 0  # nothing left: a publish run again


def test_a_damaged_pack_or_run_file_is_named(tmp_path: Path) -> None:
    T, rng = 4, np.random.default_rng(7)
    tiles = ZarrTiles.create(tmp_path / "g", T)
    folder = tmp_path / "attempt"
    keys = np.array([[1, 2, 3], [4, 5, 6]], np.int64)
    _run(folder, tiles, "u0", keys, _tiles(rng, 2, T))
    (pack,) = [p for p in folder.glob("*.1.pack")]
    raw = pack.read_bytes()
    for bad in (raw[:-3], raw[:-16] + np.int64(10**9).astype("<i8").tobytes() + raw[-8:]):
        pack.write_bytes(bad)
        with pytest.raises(TileArrayError, match=rf"staged pack {pack} is corrupt"):
            Staging(folder, tiles).publish()
    pack.unlink()
    with pytest.raises(TileArrayError, match=rf"staged pack {pack} is missing"):
        Staging(folder, tiles).publish()
    (done,) = folder.glob("*.done")
    done.write_text("three")
    with pytest.raises(TileArrayError, match="staged run .* is corrupt"):
        Staging(folder, tiles).publish()
    assert not tiles.stored_keys().size  # nothing was published from a damaged attempt
    with pytest.raises(ValueError, match="alphanumeric"):
        Staging(folder, tiles, "u.0")


# --- a store of layout version 3 --------------------------------------------------------------
def _version_3_store(path: Path, room) -> tuple[GridSpec, FusionParams, Path]:
    """A store of three fused scans as version 3 left it: the same tiles, unsharded."""
    h = 0.04
    grid = GridSpec(h, 8, "mapping")
    params = FusionParams(NoiseModel(eps=2 * h, rho=0.1))
    with open_store(path, grid, params) as scene:
        for scan_id, scan in room.scans[:3]:
            scene.store_scan(scan_id, scan)
        scene.integrate_pending()
        keys, data = scene.tile_keys(), scene.tiles.read(scene.tile_keys())
        group = scene.tiles.group_path
    shutil.rmtree(group / "tiles")
    ZarrTiles.create(group, 8, shard=1).write(keys, data)
    marker = path / "rangefuse-store.json"
    marker.write_text(json.dumps({"format": "rangefuse-store", "version": 3}))
    return grid, params, group


def test_a_version_3_scene_keeps_its_unsharded_tiles_and_fuses_right(tmp_path: Path) -> None:
    """A scene created before shards (one chunk file per tile) is read and written as it
    is: its staged packs are published chunk by chunk."""
    room = make_dataset("room", views=5)
    grid, params, group = _version_3_store(tmp_path / "s", room)
    with open_store(tmp_path / "s") as scene:
        assert scene.tiles.shard == 1
        for scan_id, scan in room.scans[3:5]:
            scene.store_scan(scan_id, scan)
        scene.integrate_pending()
        got = scene.to_dense()
        files = [p for p in (scene.tiles.path / "c").rglob("*") if p.is_file()]
        assert len(files) == len(scene.tiles.stored_keys()) > 1000  # still one file per tile
    expected = Volume(grid, params)
    expected.add_many(room.scans[:5])
    want = expected.to_dense()
    np.testing.assert_array_equal(got.first_voxel, want.first_voxel)
    assert np.array_equal(got.logodds, want.logodds, equal_nan=True)
    assert (
        zarr.open_array(group, path="tiles", mode="r").metadata.to_dict()["codecs"][0]["name"]
        == "bytes"
    )


def test_a_version_3_publish_cut_short_is_finished(tmp_path: Path) -> None:
    """Version 3 staged a chunk file per tile: a store killed while publishing them is
    finished by this rangefuse at the next open."""
    room = make_dataset("room", views=3)
    _version_3_store(tmp_path / "s", room)
    with open_store(tmp_path / "s") as scene:
        keys = scene.tiles.stored_keys()[:2]
        replaced = np.full((8, 8, 8), 5, np.int64)
        attempt = "0123456789abcdef"
        staged = scene.staging_root / attempt / "c"
        for key, payload in zip(keys.tolist(), [scene.tiles.encode(replaced), b""], strict=True):
            i, j, k = (np.array(key) + OFFSET).tolist()
            (staged / str(i) / str(j)).mkdir(parents=True, exist_ok=True)
            (staged / str(i) / str(j) / str(k)).write_bytes(payload)
        with scene.catalog.transaction():
            scene.catalog.set_publishing(scene.scene_id, attempt)
    with open_store(tmp_path / "s") as scene:
        assert scene.recovered["published"] == 2
        np.testing.assert_array_equal(scene.tiles.read(keys[:1])[0], replaced)
        assert not scene.tiles.read(keys[1:]).any()
        assert not scene.staging_root.exists()
