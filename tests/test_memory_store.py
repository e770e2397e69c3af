"""The in-memory tile store against a dict of tiles: writes, overwrites, deletes, reads."""

from __future__ import annotations

import numpy as np
import pytest
from rangefuse.engine import MemoryTileStore

T = 4


def _tile(rng: np.random.Generator) -> np.ndarray:
    return rng.integers(-(2**40), 2**40, (T, T, T), dtype=np.int64)


@pytest.mark.parametrize("seed", range(4))
def test_memory_store_matches_a_dict_of_tiles(seed: int) -> None:
    rng = np.random.default_rng(seed)
    store = MemoryTileStore(T)
    model: dict[tuple[int, int, int], tuple[np.ndarray, frozenset[str]]] = {}
    universe = [tuple(int(x) for x in k) for k in rng.integers(-50, 50, (400, 3))]
    for step in range(60):
        # grow the pool past its first size, then delete most tiles (compaction), and so on
        n = int(rng.integers(1, 120 if step % 20 < 12 else 40))
        picked = [universe[i] for i in rng.integers(0, len(universe), n)]
        keys = np.array(picked, np.int64).reshape(-1, 3)
        if step % 20 < 12:
            data = np.stack([_tile(rng) for _ in picked])
            owners = [frozenset({f"s{int(rng.integers(0, 5))}"}) for _ in picked]
            store.write(keys, data, owners)
            for key, tile, own in zip(picked, data, owners, strict=True):
                model[key] = (tile.copy(), own)  # a key given twice: the last one counts
            data[:] = 0  # the store holds its own copy
        else:  # most of what is there, and some keys that are not
            held = sorted(model)
            picked += [held[i] for i in rng.permutation(len(held))[: len(held) * 2 // 3]]
            store.delete(np.array(picked, np.int64).reshape(-1, 3))
            for key in picked:
                model.pop(key, None)
        assert len(store) == len(model)
        expected = sorted(model)
        assert np.array_equal(store.keys(), np.array(expected, np.int64).reshape(-1, 3))
        probe = universe[:50] + expected[:50]
        probe_keys = np.array(probe, np.int64).reshape(-1, 3)
        got = store.read(probe_keys)
        for key, tile in zip(probe, got, strict=True):
            want = model[key][0] if key in model else np.zeros((T, T, T), np.int64)
            assert np.array_equal(tile, want)
        assert store.owners(probe_keys) == [model.get(k, (None, frozenset()))[1] for k in probe]
        got[:] = 1  # a read is a copy
        if expected:
            assert np.array_equal(store.read(probe_keys[-1:])[0], model[probe[-1]][0])


def test_memory_store_refuses_bad_writes_and_keeps_what_it_had() -> None:
    store = MemoryTileStore(T)
    keys = np.array([[0, 0, 0], [1, 0, 0]], np.int64)
    good = np.ones((2, T, T, T), np.int64)
    store.write(keys, good, [frozenset({"a"}), frozenset({"b"})])
    with pytest.raises(ValueError, match="int64"):
        store.write(keys, good.astype(np.int32), [frozenset({"a"})] * 2)
    with pytest.raises(ValueError, match="owner"):
        store.write(keys, 2 * good, [frozenset({"a"}), frozenset()])
    with pytest.raises(ValueError, match="owner sets"):
        store.write(keys, 2 * good, [frozenset({"a"})])
    assert np.array_equal(store.read(keys), good)
    assert store.owners(keys) == [frozenset({"a"}), frozenset({"b"})]


def test_a_handed_over_batch_becomes_the_pool_of_an_empty_store() -> None:
    rng = np.random.default_rng(5)
    keys = np.array([[0, 0, 0], [3, -1, 2], [1, 1, 1]], np.int64)
    batch = np.stack([_tile(rng) for _ in keys])
    kept = batch.copy()
    store = MemoryTileStore(T)
    store.write(keys, batch, [frozenset({"a"})] * 3, take=True)
    assert store.read(keys).tobytes() == kept.tobytes()
    # the store grows from the adopted array, and a later handed-over batch is copied
    more = np.array([[9, 9, 9], [0, 0, 0]], np.int64)
    update = np.stack([_tile(rng) for _ in more])
    store.write(more, update, [frozenset({"b"})] * 2, take=True)
    update_kept = update.copy()
    update[:] = 0
    assert np.array_equal(store.read(more), update_kept)
    assert np.array_equal(store.read(keys[1:]), kept[1:])
    assert store.owners(keys) == [frozenset({"b"}), frozenset({"a"}), frozenset({"a"})]
