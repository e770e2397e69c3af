"""One contract for every tile store: the in-memory twin and the Zarr store on disk.

After zarr-python's ``src/zarr/testing/store.py``: the tests live in a base class, and each
store runs them through a subclass that says how to make one. A store holds tiles (int64
``(T, T, T)`` of packed voxels) and their owner scans by integer key; a tile exists while it
has an owner; a missing tile reads as unknown (0).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rangefuse.engine import FusionParams, GridSpec, MemoryTileStore, NoiseModel, Volume
from rangefuse.engine.grid import KEY_LIMIT
from rangefuse.engine.synth import make_dataset
from rangefuse.engine.volume import TileStore
from rangefuse.storage.catalog import Catalog
from rangefuse.storage.tile_store import ZarrTileStore
from rangefuse.storage.zarr_tiles import ZarrTiles

T = 4


def _tile(rng: np.random.Generator) -> np.ndarray:
    return rng.integers(-(2**40), 2**40, (T, T, T), dtype=np.int64)


def _keys(*rows: tuple[int, int, int]) -> np.ndarray:
    return np.array(rows, np.int64).reshape(-1, 3)


class TileStoreContract:
    """The tests every :class:`~engine.volume.TileStore` passes."""

    #: Steps of the random model test (a store on disk runs fewer).
    model_steps = 60

    @pytest.fixture
    def store(self, tmp_path: Path) -> TileStore:
        return self.make(tmp_path, T)

    def make(self, tmp_path: Path, tile_size: int) -> TileStore:
        raise NotImplementedError

    def test_an_empty_store(self, store: TileStore) -> None:
        assert store.tile_size == T
        assert store.keys().shape == (0, 3) and store.keys().dtype == np.int64
        assert not store.read(_keys((0, 0, 0), (5, -5, 1))).any()
        assert store.owners(_keys((0, 0, 0))) == [frozenset()]
        store.delete(_keys((0, 0, 0)))  # missing: ignored

    def test_write_read_owners_round_trip(self, store: TileStore) -> None:
        rng = np.random.default_rng(1)
        keys = _keys((2, 0, 0), (-1, 3, 7), (0, 0, -4))
        data = np.stack([_tile(rng) for _ in keys])
        owners = [frozenset({"a"}), frozenset({"a", "b"}), frozenset({"c"})]
        store.write(keys, data, owners)
        order = np.lexsort(keys.T[::-1])
        np.testing.assert_array_equal(store.keys(), keys[order])  # sorted
        np.testing.assert_array_equal(store.read(keys), data)
        assert store.owners(keys) == owners
        got = store.read(keys)
        got[:] = 0  # a read is a copy
        np.testing.assert_array_equal(store.read(keys), data)

    def test_extreme_keys(self, store: TileStore) -> None:
        rng = np.random.default_rng(2)
        edge = KEY_LIMIT - 1
        keys = _keys((edge, -edge, 0), (-edge, edge, -edge))
        data = np.stack([_tile(rng) for _ in keys])
        store.write(keys, data, [frozenset({"s"})] * 2)
        np.testing.assert_array_equal(store.read(keys), data)

    def test_overwrite_replaces_data_and_owners(self, store: TileStore) -> None:
        rng = np.random.default_rng(3)
        keys = _keys((0, 0, 0), (1, 0, 0))
        store.write(keys, np.stack([_tile(rng) for _ in keys]), [frozenset({"a"})] * 2)
        again = np.stack([_tile(rng) for _ in keys[:1]])
        store.write(keys[:1], again, [frozenset({"b", "c"})])
        np.testing.assert_array_equal(store.read(keys[:1]), again)
        assert store.owners(keys) == [frozenset({"b", "c"}), frozenset({"a"})]

    def test_a_key_given_twice_keeps_its_last_tile(self, store: TileStore) -> None:
        rng = np.random.default_rng(4)
        keys = _keys((3, 3, 3), (3, 3, 3))
        data = np.stack([_tile(rng) for _ in keys])
        store.write(keys, data, [frozenset({"first"}), frozenset({"last"})])
        np.testing.assert_array_equal(store.read(keys[:1])[0], data[1])
        assert store.owners(keys[:1]) == [frozenset({"last"})]
        assert len(store.keys()) == 1

    def test_an_unknown_tile_with_an_owner_exists(self, store: TileStore) -> None:
        keys = _keys((0, 1, 2))
        store.write(keys, np.zeros((1, T, T, T), np.int64), [frozenset({"a"})])
        np.testing.assert_array_equal(store.keys(), keys)
        assert not store.read(keys).any()

    def test_delete(self, store: TileStore) -> None:
        rng = np.random.default_rng(5)
        keys = _keys((0, 0, 0), (1, 0, 0), (2, 0, 0))
        data = np.stack([_tile(rng) for _ in keys])
        store.write(keys, data, [frozenset({"a"})] * 3)
        store.delete(_keys((1, 0, 0), (9, 9, 9)))
        np.testing.assert_array_equal(store.keys(), keys[[0, 2]])
        assert not store.read(keys[1:2]).any()
        assert store.owners(keys[1:2]) == [frozenset()]
        np.testing.assert_array_equal(store.read(keys[[0, 2]]), data[[0, 2]])

    def test_bad_writes_are_refused_and_change_nothing(self, store: TileStore) -> None:
        keys = _keys((0, 0, 0), (1, 0, 0))
        good = np.ones((2, T, T, T), np.int64)
        store.write(keys, good, [frozenset({"a"}), frozenset({"b"})])
        with pytest.raises(ValueError, match="int64"):
            store.write(keys, good.astype(np.int32), [frozenset({"a"})] * 2)
        with pytest.raises(ValueError, match="int64"):
            store.write(keys, good[:1], [frozenset({"a"})] * 2)
        with pytest.raises(ValueError, match="owner"):
            store.write(keys, 2 * good, [frozenset({"a"}), frozenset()])
        with pytest.raises(ValueError, match="owner sets"):
            store.write(keys, 2 * good, [frozenset({"a"})])
        np.testing.assert_array_equal(store.read(keys), good)
        assert store.owners(keys) == [frozenset({"a"}), frozenset({"b"})]

    def test_a_handed_over_batch_is_the_stores(self, store: TileStore) -> None:
        rng = np.random.default_rng(6)
        keys = _keys((0, 0, 0), (3, -1, 2))
        batch = np.stack([_tile(rng) for _ in keys])
        kept = batch.copy()
        store.write(keys, batch, [frozenset({"a"})] * 2, take=True)
        np.testing.assert_array_equal(store.read(keys), kept)

    def test_matches_a_dict_of_tiles(self, store: TileStore) -> None:
        rng = np.random.default_rng(7)
        model: dict[tuple[int, int, int], tuple[np.ndarray, frozenset[str]]] = {}
        universe = [tuple(int(x) for x in k) for k in rng.integers(-50, 50, (400, 3))]
        for step in range(self.model_steps):
            n = int(rng.integers(1, 120 if step % 20 < 12 else 40))
            picked = [universe[i] for i in rng.integers(0, len(universe), n)]
            if step % 20 < 12:
                data = np.stack([_tile(rng) for _ in picked])
                owners = [frozenset({f"s{int(rng.integers(0, 5))}"}) for _ in picked]
                store.write(_keys(*picked), data, owners)
                for key, tile, own in zip(picked, data, owners, strict=True):
                    model[key] = (tile.copy(), own)
                data[:] = 0  # the store holds its own copy
            else:
                held = sorted(model)
                picked += [held[i] for i in rng.permutation(len(held))[: len(held) * 2 // 3]]
                store.delete(_keys(*picked))
                for key in picked:
                    model.pop(key, None)
            expected = sorted(model)
            np.testing.assert_array_equal(store.keys(), _keys(*expected))
            probe = universe[:30] + expected[:30]
            got = store.read(_keys(*probe))
            for key, tile in zip(probe, got, strict=True):
                want = model[key][0] if key in model else np.zeros((T, T, T), np.int64)
                np.testing.assert_array_equal(tile, want)
            assert store.owners(_keys(*probe)) == [
                model.get(k, (None, frozenset()))[1] for k in probe
            ]

    def test_a_volume_fused_into_it_gives_the_same_bits(self, tmp_path: Path) -> None:
        data = make_dataset("room", views=3)
        h = 0.05
        grid = GridSpec(h, 8, "mapping")
        params = FusionParams(NoiseModel(eps=2 * h, rho=0.05))
        reference = Volume(grid, params)
        volume = Volume(grid, params, self.make(tmp_path, 8))
        for item in data.scans:
            reference.add(*item)
            volume.add(*item)
        volume.remove(data.scans[1][0])
        reference.remove(data.scans[1][0])
        np.testing.assert_array_equal(volume.tile_keys(), reference.tile_keys())
        a, b = volume.to_dense(), reference.to_dense()
        assert np.array_equal(a.logodds, b.logodds, equal_nan=True)
        assert volume.store.owners(volume.tile_keys()) == reference.store.owners(
            reference.tile_keys()
        )


class TestMemoryTileStore(TileStoreContract):
    def make(self, tmp_path: Path, tile_size: int) -> TileStore:
        return MemoryTileStore(tile_size)

    def test_a_handed_over_batch_becomes_the_pool_of_an_empty_store(self) -> None:
        rng = np.random.default_rng(5)
        keys = _keys((0, 0, 0), (3, -1, 2), (1, 1, 1))
        batch = np.stack([_tile(rng) for _ in keys])
        kept = batch.copy()
        store = MemoryTileStore(T)
        store.write(keys, batch, [frozenset({"a"})] * 3, take=True)
        assert store.read(keys).tobytes() == kept.tobytes()
        # the store grows from the adopted array, and a later handed-over batch is copied
        more = _keys((9, 9, 9), (0, 0, 0))
        update = np.stack([_tile(rng) for _ in more])
        store.write(more, update, [frozenset({"b"})] * 2, take=True)
        update_kept = update.copy()
        update[:] = 0
        np.testing.assert_array_equal(store.read(more), update_kept)
        np.testing.assert_array_equal(store.read(keys[1:]), kept[1:])
        assert store.owners(keys) == [frozenset({"b"}), frozenset({"a"}), frozenset({"a"})]


class TestMemoryTileStoreInSmallBlocks(TileStoreContract):
    """The contract with a pool that grows by blocks of 2 tiles: reads and writes that span
    many blocks, and compaction after deletions."""

    def make(self, tmp_path: Path, tile_size: int) -> TileStore:
        return MemoryTileStore(tile_size, block_tiles=2)

    def test_the_pool_grows_by_blocks_without_copying_its_tiles(self) -> None:
        rng = np.random.default_rng(6)
        store = MemoryTileStore(T, block_tiles=3)
        keys = _keys(*[(n, 0, 0) for n in range(70)])
        tiles = np.stack([_tile(rng) for _ in keys])
        store.write(keys[:60], tiles[:60].copy(), [frozenset({"a"})] * 60)
        first = store._blocks[0]
        for n in range(60, 70):  # one tile at a time: blocks of 3
            store.write(keys[n : n + 1], tiles[n : n + 1].copy(), [frozenset({"a"})])
        assert [len(b) for b in store._blocks] == [60, 3, 3, 3, 3]
        assert store._blocks[0] is first  # never copied into a larger array
        order = rng.permutation(70)
        np.testing.assert_array_equal(store.read(keys[order]), tiles[order])
        # 10 of 72 slots used: the pool shrinks to one block of 64
        store.delete(keys[:60])
        assert [len(b) for b in store._blocks] == [64]
        np.testing.assert_array_equal(store.read(keys[60:]), tiles[60:])
        assert not store.read(keys[:3]).any()
        assert store.owners(keys[58:62]) == [frozenset()] * 2 + [frozenset({"a"})] * 2


class TestZarrTileStore(TileStoreContract):
    model_steps = 25

    def make(self, tmp_path: Path, tile_size: int) -> TileStore:
        folder = tmp_path / f"store-{tile_size}"
        tiles = ZarrTiles.create(folder / "scene.zarr", tile_size)
        return ZarrTileStore(tiles, Catalog(folder / "catalog.sqlite"), "scene")
