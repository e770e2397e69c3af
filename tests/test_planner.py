"""The planner's rules (docs/planner.md), checked on plans of their own."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, prepare_scan
from rangefuse.engine.allocation import tiles_touched
from rangefuse.engine.classify import OUT, bounding_sphere, classify_tiles, reach_radius
from rangefuse.engine.grid import pack_keys, unique_keys, unpack_keys
from rangefuse.engine.planner import (
    Sphere,
    plan_add,
    plan_rebuild,
    plan_remove,
    scans_near,
    tiles_near,
)
from rangefuse.engine.synth import make_dataset

H = 0.04
PARAMS = FusionParams(NoiseModel(eps=2 * H, rho=0.05))
GRID = GridSpec(H, 8, "mapping")


@pytest.fixture(scope="module")
def scans():
    data = make_dataset("room", views=6)
    return {scan_id: prepare_scan(scan, PARAMS) for scan_id, scan in data.scans}


def _sphere(scan_id, prepared) -> Sphere:
    return Sphere(scan_id, tuple(prepared.origin_W.tolist()), reach_radius(prepared))


def _in(keys: np.ndarray, among: np.ndarray) -> np.ndarray:
    return np.isin(pack_keys(keys), pack_keys(among))


def test_the_first_scans_create_what_they_touch_and_own_it(scans):
    ids = list(scans)[:3]
    plan = plan_add(GRID, np.zeros((0, 3), np.int64), ids, [], scans.__getitem__)
    touched = {s: tiles_touched(scans[s], GRID) for s in ids}
    np.testing.assert_array_equal(plan.keys, unique_keys(np.concatenate(list(touched.values()))))
    assert plan.created.all()
    assert [step.scan_id for step in plan.steps] == ids  # no earlier scan: no backfill
    for step in plan.steps:  # rule 2: a new scan is tested against every tile
        np.testing.assert_array_equal(step.candidates, np.arange(len(plan.keys)))
    for s in ids:  # rule 4
        np.testing.assert_array_equal(plan.keys[plan.owned[s]], touched[s])


def test_new_tiles_are_backfilled_by_every_earlier_scan_that_sees_them(scans):
    ids = list(scans)
    first, later = ids[:4], ids[4:]
    existing = unique_keys(np.concatenate([tiles_touched(scans[s], GRID) for s in first]))
    far = Sphere("far", (1000.0, 0.0, 0.0), 5.0)
    earlier = [_sphere(s, scans[s]) for s in first] + [far]
    plan = plan_add(GRID, existing, later, earlier, scans.__getitem__)
    created = plan.created_keys()
    assert len(created) and not _in(created, existing).any()  # rule 1
    assert _in(existing, plan.keys).all()
    backfill = {step.scan_id: step for step in plan.steps[len(later) :]}
    assert "far" not in backfill  # its sphere does not reach the new tiles
    for s in first:  # rule 3, and its sphere test is conservative
        sees = (classify_tiles(scans[s], GRID, created) != OUT).any()
        if sees:
            assert s in backfill
        if s in backfill:
            np.testing.assert_array_equal(backfill[s].candidates, np.flatnonzero(plan.created))


def _pairs(plan, earlier) -> int:
    """What the pair budget counts: owned rows, new scans' candidates, and per earlier
    scan the created tiles its sphere reaches."""
    created = plan.created_keys()
    new = plan.steps[: len(plan.owned)]
    return (
        sum(len(rows) for rows in plan.owned.values())
        + sum(len(step.candidates) for step in new)
        + sum(int(tiles_near(s, created, GRID).sum()) for s in earlier)
    )


@pytest.mark.parametrize("backfill", [False, True])
def test_a_pair_budget_takes_the_longest_prefix_that_fits(scans, backfill):
    """``max_pairs``: the plan of the longest prefix of the new scans whose pairs fit (the
    same plan as without a budget on that prefix), and one scan at least."""
    ids = list(scans)
    first, later = (ids[:2], ids[2:]) if backfill else ([], ids)
    existing = np.zeros((0, 3), np.int64)
    if first:
        existing = unique_keys(np.concatenate([tiles_touched(scans[s], GRID) for s in first]))
    earlier = [_sphere(s, scans[s]) for s in first]
    full = [_pairs(plan_add(GRID, existing, later[:k], earlier, scans.__getitem__), earlier)
            for k in range(1, len(later) + 1)]  # fmt: skip
    assert full == sorted(full) and full[0] < full[-1]
    for most, taken in [(full[-1], len(later)), (full[2], 3), (full[2] - 1, 2), (0, 1)]:
        plan = plan_add(GRID, existing, later, earlier, scans.__getitem__, max_pairs=most)
        assert list(plan.owned) == later[:taken]
        alone = plan_add(GRID, existing, later[:taken], earlier, scans.__getitem__)
        np.testing.assert_array_equal(plan.keys, alone.keys)
        np.testing.assert_array_equal(plan.created, alone.created)
        assert [s.scan_id for s in plan.steps] == [s.scan_id for s in alone.steps]
        for a, b in zip(plan.steps, alone.steps, strict=True):
            np.testing.assert_array_equal(a.candidates, b.candidates)


def test_views_with_a_halo_hold_the_views_without(scans):
    ids = list(scans)[:2]
    for halo in (0, 1):
        plan = plan_add(GRID, np.zeros((0, 3), np.int64), ids, [], scans.__getitem__, halo=halo)
        views = {v.scan_id: v for v in plan.views(scans.__getitem__)}
        if halo == 0:
            plain = views
            continue
        for s in ids:
            assert np.isin(plain[s].rows, views[s].rows).all()
            free_with_halo = views[s].rows[views[s].free]
            assert np.isin(free_with_halo, plain[s].rows[plain[s].free]).all()


def test_a_removal_subtracts_where_it_sees_and_deletes_what_it_alone_owned(scans):
    ids = list(scans)
    plan = plan_add(GRID, np.zeros((0, 3), np.int64), ids, [], scans.__getitem__)
    owners = plan.owners_after(np.arange(len(plan.keys)), [frozenset()] * len(plan.keys))
    by_key = dict(zip(pack_keys(plan.keys).tolist(), owners, strict=True))
    victim = ids[2]
    sphere = _sphere(victim, scans[victim])

    def owners_of(keys):
        return [by_key[k] for k in pack_keys(keys).tolist()]

    removal = plan_remove(GRID, sphere, plan.keys, owners_of)
    alone = np.array([own == {victim} for own in owners])
    np.testing.assert_array_equal(removal.deleted, plan.keys[alone])
    assert not _in(removal.keys, removal.deleted).any()
    # every tile it has in view (of all tiles) is a candidate: the sphere is conservative
    seen = plan.keys[classify_tiles(scans[victim], GRID, plan.keys) != OUT]
    assert _in(seen[~_in(seen, removal.deleted)], removal.keys).all()
    (step,) = removal.steps
    assert step.scan_id == victim and step.sign == -1
    after = removal.owners_after(
        removal.owned_rows(), owners_of(removal.keys[removal.owned_rows()])
    )
    assert all(victim not in own and own for own in after)


def test_spheres_near_tiles(scans):
    s = _sphere("a", next(iter(scans.values())))
    keys = np.array([[0, 0, 0], [10_000, 0, 0]], np.int64)
    assert tiles_near(s, keys, GRID).tolist() == [True, False]
    assert scans_near([s], keys[:1], GRID) == ["a"]
    assert scans_near([s], keys[1:], GRID) == []
    unbounded = Sphere("u", (0.0, 0.0, 0.0), float("inf"))
    assert tiles_near(unbounded, keys, GRID).all()
    # the sphere recorded at upload holds the one from the prepared scan
    scan_id, scan = make_dataset("room", views=1).scans[0]
    origin, radius = bounding_sphere(scan, PARAMS)
    np.testing.assert_array_equal(origin, scans[scan_id].origin_W)
    assert radius >= reach_radius(scans[scan_id])


def test_a_rebuild_starts_from_unknown(scans):
    keys = np.array([[0, 0, 0], [1, 0, 0]], np.int64)
    plan = plan_rebuild(GRID, keys, {"b": np.array([1]), "a": np.array([0, 1])})
    assert plan.created.all() and [s.scan_id for s in plan.steps] == ["a", "b"]
    assert all(step.sign == 1 for step in plan.steps)


def test_the_pair_counts_windows_keep_every_tile_a_sphere_reaches():
    """``_PairCount`` counts a sphere's created tiles among those in its x reach and the
    pairs of new tiles among the spheres that meet their box: the same counts as over
    every tile and every sphere (a long drive's count no longer grows with the map)."""
    from rangefuse.engine.planner import _in_x_reach, _pairs_near, _reaching_box

    rng = np.random.default_rng(5)
    tile_m = GRID.tile_size_m
    keys = unique_keys(rng.integers([-400, -20, -5], [400, 20, 5], (3000, 3)))
    packed = np.sort(pack_keys(keys))
    origins = rng.uniform(-60, 60, (40, 3)) * [tile_m * 6, 1, 1]
    radii = rng.uniform(0.1, 30, 40) * tile_m
    spheres = [
        Sphere(f"s{n}", tuple(o), float(r))
        for n, (o, r) in enumerate(zip(origins, radii, strict=True))
    ]
    spheres.append(Sphere("far", (0.0, 0.0, 0.0), math.inf))
    for s in spheres:
        window = unpack_keys(_in_x_reach(packed, s, tile_m))
        assert len(window) < len(keys) or not math.isfinite(s.radius_m)
        assert tiles_near(s, window, GRID).sum() == tiles_near(s, keys, GRID).sum()
    for n in range(20):
        some = keys[rng.choice(len(keys), 30)] if n % 2 else keys[n * 100 : n * 100 + 40]
        near = _reaching_box(spheres[:-1], some, tile_m)
        assert len(near) < 40
        assert _pairs_near(near, some, GRID) == _pairs_near(spheres[:-1], some, GRID)
