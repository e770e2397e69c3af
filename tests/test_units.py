"""Units of work that can run again (docs/storage.md): a unit killed at any point, then run
again alone, gives the bits of a run that was never interrupted, without the recovery that
opening a store does."""

from __future__ import annotations

import os
import pickle
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, Volume, prepare_scan
from rangefuse.engine.synth import make_dataset
from rangefuse.storage import open_store
from rangefuse.storage.scene import SceneReport
from rangefuse.storage.units import InProcess, integrate_unit

H = 0.04
PARAMS = FusionParams(NoiseModel(eps=2 * H, rho=0.05))
GRID = GridSpec(H, 8, "mapping")
#: A cache of a few tiles: the unit stages tiles all along, not only at its end.
CACHE_MB = 0.02
TRIALS = 20

_CHILD = """
import pickle, sys
from rangefuse.storage.units import integrate_unit
unit = pickle.load(open(sys.argv[1], "rb"))
print("start", flush=True)
integrate_unit(unit)
print("done", flush=True)
"""


def _base_store(tmp_path: Path, data) -> Path:
    """A store with the first 3 scans fused and the other 3 acknowledged, not fused."""
    path = tmp_path / "base"
    with open_store(path, GRID, PARAMS, cache_mb=CACHE_MB) as scene:
        for item in data.scans[:3]:
            scene.store_scan(*item)
        scene.integrate_pending()
        for item in data.scans[3:]:
            scene.store_scan(*item)
    return path


def _run_child(unit_file: Path, kill_after: float | None) -> tuple[int, float]:
    """Run the unit in a fresh process; kill -9 it ``kill_after`` seconds after it starts
    the unit. Returns its exit status and how long the unit ran."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(unit_file)], stdout=subprocess.PIPE, text=True,
        env=env,
    )  # fmt: skip
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "start"  # imports done, the unit begins
    t0 = time.perf_counter()
    if kill_after is not None:
        time.sleep(kill_after)
        proc.send_signal(signal.SIGKILL)
    proc.communicate()
    return proc.returncode, time.perf_counter() - t0


@pytest.mark.slow
def test_a_unit_killed_at_random_points_and_run_again_alone_gives_the_same_bits(tmp_path):
    data = make_dataset("room", views=6)
    expected = Volume(GRID, PARAMS)
    expected.add_many(data.scans)
    want = expected.to_dense()
    base = _base_store(tmp_path, data)
    # how long the group's unit runs, uninterrupted, in a process of its own
    with open_store(base, cache_mb=CACHE_MB) as scene:
        ids = [r.id for r in scene.scan_rows(("stored",))]
        (unit,) = scene._group_work(ids).units
    unit_file = tmp_path / "unit.pickle"
    unit_file.write_bytes(pickle.dumps(unit))
    status, unit_s = _run_child(unit_file, None)
    assert status == 0
    shutil.rmtree(base / "scenes" / "default" / "staging")
    rng = random.Random(11)
    mid_write = 0  # kills that left some of the unit's tiles staged
    for trial in range(TRIALS):
        store = tmp_path / f"trial{trial}"
        shutil.copytree(base, store)
        with open_store(store, cache_mb=CACHE_MB) as scene:
            work = scene._group_work(ids)
            (unit,) = work.units
            unit_file.write_bytes(pickle.dumps(unit))
            status, _ = _run_child(unit_file, rng.uniform(0.02, 1.0) * unit_s)
            # killed with packs staged and the run unfinished: its packs are never read
            folder = Path(unit.staging_path)
            packs, done = list(folder.glob("*.pack")), list(folder.glob("*.done"))
            mid_write += status == -signal.SIGKILL and bool(packs) and not done
            # run the unit again, alone, here: no discarding, no recovery
            result = integrate_unit(unit)
            scene._commit_group(work, ids, [result], SceneReport())
            got = scene.to_dense()
        np.testing.assert_array_equal(got.first_voxel, want.first_voxel)
        assert np.array_equal(got.logodds, want.logodds, equal_nan=True), f"trial {trial}"
        shutil.rmtree(store)
    assert mid_write >= TRIALS // 4, (mid_write, unit_s)  # the kills did land mid-unit


def test_units_split_tiles_by_key_and_give_the_same_bits_in_any_number(tmp_path):
    """One unit or five: every staged tile in exactly one unit, and the same volume."""
    data = make_dataset("room", views=6)
    base = _base_store(tmp_path, data)
    dense = []
    for parts in (1, 5):
        store = tmp_path / f"parts{parts}"
        shutil.copytree(base, store)
        with open_store(store, cache_mb=CACHE_MB, runner=_Workers(parts)) as scene:
            ids = [r.id for r in scene.scan_rows(("stored",))]
            work = scene._group_work(ids)
            assert len(work.units) == parts
            keys = np.concatenate([u.keys for u in work.units])
            assert len(keys) == len(work.written) == len(np.unique(keys, axis=0))
            scene._commit_group(work, ids, scene._run(work.units), SceneReport())
            dense.append(scene.to_dense())
    assert np.array_equal(dense[0].logodds, dense[1].logodds, equal_nan=True)


def test_a_unit_holds_a_scan_or_two_not_its_groups_scans(tmp_path, monkeypatch):
    """A tile unit prepares a scan when a batch of its tiles has it in view and lets it go
    after the next one (a group's size is not bounded by its pixels): with a cache of a few
    tiles, many batches, at most two prepared scans alive at once, and the same bits."""
    import weakref

    from rangefuse.storage import units

    data = make_dataset("room", views=6)
    base = _base_store(tmp_path, data)
    alive: weakref.WeakSet = weakref.WeakSet()
    most = [0, 0]  # prepared scans alive at once, preparations

    def prepare(scan, params):
        prepared = prepare_scan(scan, params)
        alive.add(prepared)
        most[:] = [max(most[0], len(alive)), most[1] + 1]
        return prepared

    dense = []
    for tracked in (False, True):
        store = tmp_path / f"tracked{tracked}"
        shutil.copytree(base, store)
        with open_store(store, cache_mb=CACHE_MB if tracked else 64) as scene:
            ids = [r.id for r in scene.scan_rows(("stored",))]
            work = scene._group_work(ids)
            if tracked:
                monkeypatch.setattr(units, "prepare_scan", prepare)
            scene._commit_group(work, ids, scene._run(work.units), SceneReport())
            monkeypatch.undo()
            dense.append(scene.to_dense())
    assert most[0] <= 2 < len(ids) and most[1] > len(ids), most  # re-prepared per batch
    assert np.array_equal(dense[0].logodds, dense[1].logodds, equal_nan=True)


class _Workers(InProcess):
    """Units run here, one after the other, split as for ``workers`` workers."""

    def __init__(self, workers: int) -> None:
        self.workers = workers


def test_a_units_scans_keep_the_first_read_when_they_outgrow_the_budget(tmp_path, monkeypatch):
    """Scans drawn in the same order pass after pass (the planner's two, a unit's batches
    of tiles): with room for two of four, each later pass reads two from the archive, not
    four; every scan comes back as archived."""
    from rangefuse.storage import units
    from rangefuse.storage.archive import ScanArchive

    scans = [scan for _, scan in make_dataset("room", views=4).scans]
    archive = ScanArchive(tmp_path / "g")
    for n, scan in enumerate(scans):
        archive.put(f"s{n}", scan)
    monkeypatch.setattr(units, "RAW_SCAN_BYTES", 2 * scans[0].range_m.nbytes)
    reads = []
    get = ScanArchive.get
    monkeypatch.setattr(ScanArchive, "get", lambda self, s: reads.append(s) or get(self, s))
    load = units._Scans(tmp_path / "g", PARAMS)
    for _ in range(3):
        for n, scan in enumerate(scans):
            np.testing.assert_array_equal(load(f"s{n}").T_W_S, scan.T_W_S)
    assert reads == ["s0", "s1", "s2", "s3", "s2", "s3", "s2", "s3"]
