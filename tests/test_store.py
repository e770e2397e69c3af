"""Persistent scenes: equal to in-memory fusion, incremental, exact removal, crash recovery."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, Scan, Volume
from rangefuse.engine.grid import pack_keys
from rangefuse.engine.synth import make_dataset
from rangefuse.service.cli import main
from rangefuse.storage import (
    SceneConflictError,
    Store,
    StoreError,
    StoreLockedError,
    StoreVersionError,
    groups,
    open_store,
    read_grid,
    write_dataset,
)
from rangefuse.storage.archive import ArchiveError
from rangefuse.storage.catalog import ScanRow
from rangefuse.storage.staging import Staging
from rangefuse.storage.store import DEFAULT_SCENE, STORE_VERSION

H = 0.04
PARAMS = FusionParams(NoiseModel(eps=2 * H, rho=0.05))


@pytest.fixture(scope="module")
def room():
    return make_dataset("room", views=6)


def _grid(mode: str = "mapping", data=None) -> GridSpec:
    bounds = data.bounds if mode == "closed" else None
    return GridSpec(H, 8, mode, bounds)


def _same_dense(a, b) -> None:
    assert a.logodds.shape == b.logodds.shape
    np.testing.assert_array_equal(a.first_voxel, b.first_voxel)
    assert np.array_equal(a.logodds, b.logodds, equal_nan=True)


def _memory(scans, grid) -> Volume:
    volume = Volume(grid, PARAMS)
    volume.add_many(scans)
    return volume


def _fill(scene, scans) -> None:
    for scan_id, scan in scans:
        scene.store_scan(scan_id, scan)
    scene.integrate_pending()


@pytest.mark.parametrize("mode", ["mapping", "closed"])
def test_store_equals_memory_and_survives_reopening(tmp_path, room, mode):
    grid = _grid(mode, room)
    expected = _memory(room.scans, grid)
    with open_store(tmp_path / "s", grid, PARAMS, cache_mb=1) as scene:  # tiny cache: evictions
        _fill(scene, room.scans)
        np.testing.assert_array_equal(scene.tile_keys(), expected.tile_keys())
        _same_dense(scene.to_dense(), expected.to_dense())
    with open_store(tmp_path / "s") as scene:
        _same_dense(scene.to_dense(), expected.to_dense())
        assert scene.recovered["rebuilt_tiles"] == 0
        info = scene.info()
        assert info["scans"] == 6 and info["scan_states"] == {"fused": 6}
        assert info["tiles"] == len(expected.tile_keys()) and info["bytes_on_disk"] > 0


def test_tile_cache_stages_evicted_tiles_and_reads_them_back(tmp_path):
    from rangefuse.storage.tile_cache import TileCache
    from rangefuse.storage.zarr_tiles import ZarrTiles

    tiles = ZarrTiles.create(tmp_path / "g.zarr", 4)
    staging = Staging(tmp_path / "staging", tiles)
    cache = TileCache(tiles, staging, budget_bytes=16 * 4**3 * 8)  # 16 tiles
    keys = np.array([[k, -k, 2 * k] for k in range(40)], np.int64)
    new = np.ones(len(keys), bool)
    for start in range(0, 40, 8):
        part = slice(start, start + 8)
        data = cache.fetch(keys[part], new[part])
        assert not data.any()
        data += np.arange(start, start + 8)[:, None, None, None] + 1
        cache.store(keys[part], data)
    assert cache.writes > 0  # evicted while over budget
    again = cache.fetch(keys, new)  # evicted new tiles come back from the staging area
    np.testing.assert_array_equal(again[:, 0, 0, 0], np.arange(40) + 1)
    cache.flush()
    assert len(cache.written) == 40  # every tile staged, once each
    assert not tiles.read(keys).any()  # nothing written in place
    np.testing.assert_array_equal(staging.read(keys)[:, 1, 2, 3], np.arange(40) + 1)
    assert len(Staging(tmp_path / "staging", tiles).staged_keys()) == 0  # unfinished: unseen
    staging.finish()
    assert staging.publish() == 40
    np.testing.assert_array_equal(tiles.read(keys)[:, 1, 2, 3], np.arange(40) + 1)


def test_adding_later_equals_all_at_once(tmp_path, room):
    grid = _grid()
    expected = _memory(room.scans, grid).to_dense()
    order = [room.scans[k] for k in (4, 1, 5)]
    rest = [room.scans[k] for k in (0, 3, 2)]
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, order)
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        for item in rest:  # one scan per group
            scene.store_scan(*item)
            assert scene.catalog.n_scans(scene.scene_id, ("stored",)) == 1
            assert scene.catalog.n_scans(scene.scene_id, ("stored", "fused")) == len(
                scene.scan_rows()
            )
            scene.integrate_pending(group_scans=1)
        assert scene.catalog.n_scans(scene.scene_id, ("stored",)) == 0
        _same_dense(scene.to_dense(), expected)


def test_groups_take_scans_that_share_tiles_within_their_budgets(tmp_path, room):
    """A checkpoint per group (one progress call each): a group takes the next scan while
    it has fewer than ``group_scans`` scans and the scan lies within GROUP_SPAN of the
    group's first scan, and its planner takes them while their pairs fit GROUP_PAIRS; the
    bits are those of fusing all at once."""
    far = np.eye(4)
    far[0, 3] = 1000.0  # a kilometre away: its sphere meets none of the others'
    moved = [(f"{scan_id}-far", Scan(s.range_m, far @ s.T_W_S, s.sensor, s.noise))
             for scan_id, s in room.scans[:2]]  # fmt: skip
    scans = [*room.scans[:3], moved[0], room.scans[3], *room.scans[4:], moved[1]]
    expected = _memory(scans, _grid()).to_dense()

    def checkpoints(path, **kwargs) -> list[int]:
        calls: list[int] = []
        with open_store(path, _grid(), PARAMS) as scene:
            for item in scans:
                scene.store_scan(*item)
            scene.integrate_pending(progress=lambda done, _: calls.append(done), **kwargs)
            _same_dense(scene.to_dense(), expected)
        return calls

    assert checkpoints(tmp_path / "a") == [3, 4, 7, 8]  # far, near again, far
    assert checkpoints(tmp_path / "b", group_scans=2) == [2, 3, 4, 6, 7, 8]
    # a group's planner takes its scans while their (scan, tile) pairs fit GROUP_PAIRS
    assert checkpoints(tmp_path / "e", group_pairs=1) == [1, 2, 3, 4, 5, 6, 7, 8]
    # an unreadable archive entry fails its own group, not the groups before it (also when
    # the count would have put it with them)
    for most in (2, 8):
        with open_store(tmp_path / f"d{most}", _grid(), PARAMS) as scene:
            for item in room.scans[:3]:
                scene.store_scan(*item)
            lost = room.scans[2][0]
            scene.archive.delete(lost)
            with pytest.raises(ArchiveError, match=lost):
                scene.integrate_pending(group_scans=most)
            fused = [r.id for r in scene.scan_rows(("fused",))]
            assert fused == [i for i, _ in room.scans[:2]]


def test_a_plan_comes_back_without_the_memory_of_its_candidates(tmp_path, room):
    """The views replace the steps' candidates: a plan unit returns empty arrays of its
    own for them (an empty slice would keep each candidate array alive while the units
    run: 97 MB for a group of 32 scans at 1 cm)."""
    with open_store(tmp_path / "s", _grid(), PARAMS) as scene:
        for item in room.scans[:3]:
            scene.store_scan(*item)
        ids = [scan_id for scan_id, _ in room.scans[:3]]
        plan, views = scene._plan(kind="add", existing=np.zeros(0, np.int64), scans=ids)
    assert views and len(plan.steps) == 3
    assert all(len(s.candidates) == 0 and s.candidates.base is None for s in plan.steps)


def test_a_groups_scans_lie_within_its_span_of_the_first(room, monkeypatch):
    """A drive: a scan stays in the group while its origin lies within GROUP_SPAN times the
    sum of its radius and the first scan's, up to the count."""
    sensor = room.scans[0][1].sensor.to_dict()

    class Archive:
        def placement(self, scan_id):
            return {"sensor": sensor}

    def sizes(xs, **kwargs) -> list[int]:
        rows = [ScanRow(f"s{n}", n, None, "stored", (x, 0.0, 0.0), 10.0, "", 0.0)
                for n, x in enumerate(xs)]  # fmt: skip
        return [len(g) for g in groups.scan_groups(rows, Archive(), **kwargs)]

    drive = [5.0 * n for n in range(10)]  # 5 m apart, reach 10 m
    monkeypatch.setattr(groups, "GROUP_SPAN", 1.0)  # the spheres meet: up to 20 m
    assert sizes(drive) == [5, 5]
    monkeypatch.setattr(groups, "GROUP_SPAN", 1.5)  # up to 30 m
    assert sizes(drive) == [7, 3]
    assert sizes([0.0, 30.0, 30.5]) == [2, 1]
    assert sizes(drive, most=4) == [4, 4, 2]


def test_remove_then_re_add_is_exact(tmp_path, room):
    grid = _grid()
    without = _memory(room.scans[:2] + room.scans[3:], grid)
    full = _memory(room.scans, grid).to_dense()
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, room.scans)
        report = scene.remove(room.scans[2][0])
        assert report.tiles_written > 0 and report.fuse_seconds > 0
        _same_dense(scene.to_dense(), without.to_dense())
        np.testing.assert_array_equal(scene.tile_keys(), without.tile_keys())
        assert room.scans[2][0] not in scene
        assert room.scans[2][0] not in scene.archive.ids()
        scene.store_scan(*room.scans[2])
        assert scene.integrate_pending().fuse_seconds > 0
        _same_dense(scene.to_dense(), full)


def test_removing_every_scan_leaves_nothing(tmp_path, room):
    grid = _grid()
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, room.scans[:3])
        for scan_id, _ in room.scans[:3]:
            scene.remove(scan_id)
        assert len(scene.tile_keys()) == 0
        assert scene.tiles.stored_keys().shape[0] == 0


def test_store_errors(tmp_path, room):
    grid = _grid()
    with pytest.raises(StoreError, match="not a rangefuse store"):
        open_store(tmp_path / "missing")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(StoreError, match="not an empty folder"):
        open_store(tmp_path / "full", grid, PARAMS)
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, room.scans[:1])
        with pytest.raises(StoreLockedError, match=f"pid {os.getpid()}"):
            open_store(tmp_path / "s")
        with pytest.raises(SceneConflictError, match="already in the scene"):
            scene.store_scan(*room.scans[0])
    with pytest.raises(SceneConflictError, match="voxel_size"):
        open_store(tmp_path / "s", GridSpec(2 * H, 8, "mapping"), PARAMS)
    other = FusionParams(NoiseModel(eps=2 * H, rho=0.1))
    with pytest.raises(SceneConflictError, match="rho"):
        open_store(tmp_path / "s", grid, other)
    marker = tmp_path / "s" / "rangefuse-store.json"
    marker.write_text(json.dumps({"format": "rangefuse-store", "version": 99}))
    with pytest.raises(StoreVersionError, match="version 99.*reads versions 1, 2, 3, 4"):
        open_store(tmp_path / "s")


def test_staged_tiles_without_a_checkpoint_are_discarded_at_the_next_open(tmp_path, room):
    """A crash while units stage a group: the committed chunks are untouched, the staged
    ones (and an unacknowledged archived scan) are dropped, and the group runs again."""
    grid = _grid()
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, room.scans[:4])
        scene.store_scan(*room.scans[4])  # acknowledged, not fused yet
        keys = scene.tile_keys()[:5]
        staging_root, tiles, archive = scene.staging_root, scene.tiles, scene.archive
    # what a process killed mid-group leaves (a scene closed normally drops its staging)
    T = grid.tile_size
    dead = Staging(staging_root / "an-attempt-that-died", tiles)
    dead.write(keys, np.full((len(keys), T, T, T), 12345, np.int64))
    dead.finish()  # a unit that finished, in a group that never reached its checkpoint
    archive.put("ghost", room.scans[5][1])  # archived, never acknowledged
    with open_store(tmp_path / "s") as scene:
        assert scene.recovered["discarded"] == 5 and scene.recovered["published"] == 0
        assert scene.recovered["orphan_scans"] == 1
        assert "ghost" not in scene.archive.ids()
        assert not scene.staging_root.exists()
        _same_dense(scene.to_dense(), _memory(room.scans[:4], grid).to_dense())
        scene.integrate_pending()
        _same_dense(scene.to_dense(), _memory(room.scans[:5], grid).to_dense())


def test_a_publish_cut_short_is_finished_at_the_next_open(tmp_path, room, monkeypatch):
    """A crash after the checkpoint committed, while the staged chunks were being moved."""
    from rangefuse.storage import shards

    grid = _grid()
    moved = []

    class DyingOs:  # the shards module's os: dies after 3 shards written into the tiles
        def __getattr__(self, name):
            return getattr(os, name)

        def replace(self, src, dst):
            if "scene.zarr" in str(dst):
                if len(moved) == 3:
                    raise KeyboardInterrupt("killed while publishing")
                moved.append(dst)
            os.replace(src, dst)

    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, room.scans[:3])
        scene.store_scan(*room.scans[3])
        monkeypatch.setattr(shards, "os", DyingOs())
        with pytest.raises(KeyboardInterrupt):
            scene.integrate_pending()
        monkeypatch.undo()
        assert scene.catalog.publishing(scene.scene_id)
    with open_store(tmp_path / "s") as scene:
        assert scene.recovered["published"] > 0 and scene.recovered["discarded"] == 0
        assert not scene.catalog.publishing(scene.scene_id)
        assert [r.state for r in scene.scan_rows()] == ["fused"] * 4
        _same_dense(scene.to_dense(), _memory(room.scans[:4], grid).to_dense())


def test_a_version_1_store_killed_mid_group_is_upgraded_and_rebuilt(tmp_path, room):
    """Layout 1 wrote tiles in place after journaling them: its journaled tiles are rebuilt
    from the archive, and the store is the current version from then on."""
    grid = _grid()
    expected = _memory(room.scans[:4], grid).to_dense()
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, room.scans[:4])
        keys = scene.tile_keys()[:5]
        gone = np.array([[900, 900, 900]], np.int64)  # journaled, written, never owned
        with scene.catalog.transaction():
            scene.catalog._db.executemany(
                "INSERT INTO journal(scene_id, tile) VALUES(?,?)",
                [(scene.scene_id, int(t)) for t in pack_keys(np.concatenate([keys, gone]))],
            )
        T = grid.tile_size
        torn = np.full((len(keys) + 1, T, T, T), 12345, np.int64)
        scene.tiles.write(np.concatenate([keys, gone]), torn)  # what a killed run left
    marker = tmp_path / "s" / "rangefuse-store.json"
    marker.write_text(json.dumps({"format": "rangefuse-store", "version": 1}))
    with open_store(tmp_path / "s") as scene:
        assert scene.recovered["rebuilt_tiles"] == 6
        _same_dense(scene.to_dense(), expected)
        assert len(scene.catalog.journal(scene.scene_id)) == 0
        stored = pack_keys(scene.tiles.stored_keys())
        assert np.isin(stored, pack_keys(scene.tile_keys())).all()  # the unowned one is gone
    assert json.loads(marker.read_text())["version"] == STORE_VERSION


def test_an_interrupted_removal_is_finished_at_the_next_open(tmp_path, room):
    grid = _grid()
    without = _memory(room.scans[1:4], grid)
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, room.scans[:4])
        victim = room.scans[0][0]
        with scene.catalog.transaction():  # what remove() commits before touching tiles
            scene.catalog.set_scan_state(scene.scene_id, [victim], "removing")
        half = scene.tile_keys()[::2]
        T = grid.tile_size
        dead = Staging(scene.staging_root / "a-removal-that-died", scene.tiles)
        dead.write(half, np.full((len(half), T, T, T), 7, np.int64))  # killed midway
    with open_store(tmp_path / "s") as scene:
        assert scene.recovered["removals_resumed"] == 1
        assert victim not in scene and victim not in scene.archive.ids()
        _same_dense(scene.to_dense(), without.to_dense())
        np.testing.assert_array_equal(scene.tile_keys(), without.tile_keys())


def test_incremental_meshing_reuses_unchanged_tiles(tmp_path, room):
    grid = _grid()
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, room.scans[:3])
        mesh1, counts1 = scene.extract_mesh()
        assert counts1["reused"] == 0 and counts1["meshed"] == counts1["tiles"]
        again, counts2 = scene.extract_mesh()
        assert counts2["meshed"] == 0
        np.testing.assert_array_equal(again.faces, mesh1.faces)
        np.testing.assert_array_equal(again.vertices, mesh1.vertices)
        scene.store_scan(*room.scans[3])
        scene.integrate_pending()
        seen: list[tuple[int, int]] = []
        mesh3, counts3 = scene.extract_mesh(progress=lambda *a: seen.append(a))
        assert 0 < counts3["meshed"] < counts3["tiles"]
        # progress: the reused tiles at once, then as each unit finishes, up to every tile
        n = counts3["tiles"]
        assert seen[0] == (counts3["reused"], n) and seen[-1] == (n, n)
        assert [d for d, _ in seen] == sorted(d for d, _ in seen) and len(seen) >= 2
    fresh = _memory(room.scans[:4], grid).extract_mesh()
    # cached and fresh tile meshes stitch into the bytes of a fresh extraction
    for field in ("vertices", "faces", "inferred", "vertex_keys"):
        np.testing.assert_array_equal(getattr(mesh3, field), getattr(fresh, field))


# --------------------------------------------------------------------------------------------
# the command line, and kill -9


def test_cli_store_commands(tmp_path, capsys):
    data_dir = tmp_path / "room"
    data = make_dataset("room", views=4)
    write_dataset(data_dir, data.sensor, data.scans)
    store = tmp_path / "store"
    args = ["fuse", str(data_dir), "--voxel-size", str(H), "--tile-size", "8", "--quiet"]
    assert main([*args, "--store", str(store)]) == 0
    out = capsys.readouterr().out
    assert out.count("stored scan_") == 4
    assert main([*args, "--store", str(store)]) == 0  # nothing new
    assert "0 new scans stored" in capsys.readouterr().out
    assert main(["info", str(store), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["scans"] == 4 and info["version"] == STORE_VERSION
    grid_path = tmp_path / "g.npz"
    assert (
        main(["extract", str(store), "--grid-out", str(grid_path), "-o", str(tmp_path / "m.ply")])
        == 0
    )
    expected = _memory(data.scans, GridSpec(H, 8, "mapping")).to_dense()
    _same_dense(read_grid(grid_path), expected)
    assert main(["remove", str(store), "scan_0002"]) == 0
    assert main(["add", str(store), str(data_dir / "scans" / "scan_0002.npz")]) == 0
    assert main(["extract", str(store), "--grid-out", str(grid_path)]) == 0
    _same_dense(read_grid(grid_path), expected)
    # errors: exit 2 with a message
    capsys.readouterr()
    assert main(["remove", str(store), "nope"]) == 2
    assert "no scan 'nope'" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "nowhere")]) == 2
    assert main([*args[:3], str(2 * H), *args[4:], "--store", str(store)]) == 2
    assert "voxel_size" in capsys.readouterr().err
    assert main(["extract", str(store)]) == 2


@pytest.mark.slow
def test_kill_at_random_instants_then_resume(tmp_path):
    """kill -9 `rangefuse fuse --store` at random instants, resume: same bits, and every scan
    acknowledged before a kill is in the store."""
    data_dir = tmp_path / "room"
    data = make_dataset("room", views=10)
    write_dataset(data_dir, data.sensor, data.scans)
    expected = _memory(data.scans, GridSpec(H, 8, "mapping")).to_dense()
    cmd = [
        sys.executable,
        "-m",
        "rangefuse.service.cli",
        "fuse",
        str(data_dir),
        "--voxel-size",
        str(H),
    ]
    cmd += ["--tile-size", "8", "--quiet", "--cache-mb", "1"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    # kill instants are fractions of an uninterrupted run, so that they land mid-run however
    # fast the machine and the engine are (the run also compiles the kernels once)
    t0 = time.perf_counter()
    full = subprocess.run([*cmd, "--store", str(tmp_path / "full")], env=env, capture_output=True)
    assert full.returncode == 0, full.stderr
    full_s = time.perf_counter() - t0
    rng = random.Random(7)
    mid_run = 0  # kills that caught a run with acknowledged scans and work left
    for trial in range(4):
        store = tmp_path / f"store{trial}"
        acked: set[str] = set()
        for _ in range(3):  # up to three kills per trial
            proc = subprocess.Popen(
                [*cmd, "--store", str(store)], stdout=subprocess.PIPE, text=True, env=env
            )
            assert proc.stdout is not None
            # after some of the acknowledgements still to come (none: anywhere, store
            # creation included), then a random instant: a time alone mostly landed in the
            # start-up (imports) or after the last scan once the stores got faster
            lines, after = [], rng.randint(0, max(0, 9 - len(acked)))
            while sum(line.startswith("stored ") for line in lines) < after:
                line = proc.stdout.readline()
                if not line:
                    break
                lines.append(line)
            time.sleep(rng.uniform(0.1, 0.9) * full_s * (1.0 if after == 0 else 0.1))
            proc.send_signal(signal.SIGKILL)
            out, _ = proc.communicate()
            lines += out.splitlines()
            acked |= {line.split()[1] for line in lines if line.startswith("stored ")}
            if not (store / "rangefuse-store.json").exists():  # killed while creating it
                assert not acked
                continue
            with Store.open(store) as created:
                if created.catalog.scene(DEFAULT_SCENE) is None:  # killed before the scene
                    assert not acked
                    continue
            with open_store(store) as scene:
                held = {r.id for r in scene.scan_rows()}
                pending = len(scene.scan_rows(("stored",)))
            assert acked <= held
            if proc.returncode == -signal.SIGKILL and acked and (pending or len(held) < 10):
                mid_run += 1
        done = subprocess.run(
            [*cmd, "--store", str(store), "--grid-out", str(tmp_path / "g.npz")],
            capture_output=True,
            text=True,
            env=env,
        )
        assert done.returncode == 0, done.stderr
        _same_dense(read_grid(tmp_path / "g.npz"), expected)
    assert mid_run >= 3, (mid_run, full_s)  # the kills did interrupt work in progress


def test_a_store_that_recorded_legacy_parameter_names_opens(tmp_path, room):
    """Scenes recorded before the names were unified (``voxel_size_m``, ``eps_m`` ...)."""
    import sqlite3

    grid = _grid()
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, room.scans[:2])
        expected = scene.to_dense()
    legacy_grid = {"voxel_size_m": H, "tile_size_vox": 8, "mode": "mapping", "bounds_m": None}
    noise = {"eps_m": 2 * H, "eps_per_m": 0.0, "rho": 0.05, "falloff_m": None, "shape": "linear"}
    legacy_params = {"noise": noise, "filter": "none", "max_discontinuity_m": None,
                     "no_return": "free"}  # fmt: skip
    db = sqlite3.connect(tmp_path / "s" / "catalog.sqlite")
    with db:
        db.execute("UPDATE scenes SET grid=?, params=?", (json.dumps(legacy_grid),
                                                         json.dumps(legacy_params)))  # fmt: skip
    db.close()
    with open_store(tmp_path / "s", grid, PARAMS) as scene:  # the same parameters: no conflict
        assert scene.grid == grid and scene.params == PARAMS
        _same_dense(scene.to_dense(), expected)
