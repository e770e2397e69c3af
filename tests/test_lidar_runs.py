"""A level LiDAR column's run of voxels settled at once (``engine._parts._run_outcome``, issue
21): where the run's answer is sure it is the answer of each of its voxels, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from rangefuse.engine import SphericalSensor
from rangefuse.engine import _sensor_kernels as _k
from rangefuse.engine._parts import RUN_FREE, RUN_NOTHING, RUN_UNSURE, _fuse_spherical, _run_outcome
from rangefuse.engine._sampling import quad_bounds_array, quad_columns, quad_index
from rangefuse.engine.certainty import SHAPE_LINEAR
from rangefuse.engine.synth import make_dataset

#: What one voxel of a run got from _fuse_spherical (beside RUN_FREE and RUN_NOTHING).
QUEUED = 3


@njit(cache=True)
def _run_two_ways(params, table, tans, chords, fit, bounds, rng, linear, runs, out):
    # per run (column u, distance from the axis rho, sensor-frame height of its first voxel's
    # column base bz, first voxel index k, voxel size h, length S): out[m, 0] the run's
    # outcome, out[m, 1 + c] what voxel c got voxel by voxel (RUN_FREE: logit(rho) added,
    # RUN_NOTHING: nothing, QUEUED: left for pass 3)
    kind = _k.SPHERICAL
    nqu = quad_columns(kind, params)
    flat = bounds.reshape(-1)
    S_max = out.shape[1] - 1
    tile = np.zeros(S_max)
    at = np.empty(S_max, np.int64)
    band = np.empty((3, S_max))
    for m in range(runs.shape[0]):
        cu, rho, bz, k, h, S = runs[m]
        S = int(S)
        q0 = quad_index(kind, params, cu, 0.0)
        if q0 < 0:
            out[m, 0] = -1
            continue
        z_a = bz + 1.0 * (((k + 0) + 0.5) * h)  # as _fuse_block: bz + M[2, 2] * slab_z
        z_b = bz + 1.0 * (((k + S - 1) + 0.5) * h)
        out[m, 0], _ = _run_outcome(
            linear, tans, chords, fit, flat, rng, cu, q0, rho, z_a, z_b, nqu, 0
        )
        row = 0
        for c in range(S):
            tile[c] = 0.0
            z = bz + 1.0 * (((k + c) + 0.5) * h)
            count, queued, row = _fuse_spherical(
                linear, params, table, tans, chords, fit, flat, rng, tile, c, cu, q0, 0.0, 0.0,
                rho, z, row, nqu, 1.0, at, band[0], band[1], band[2], 0, 0,
            )  # fmt: skip
            if queued:
                out[m, 1 + c] = QUEUED
            elif count:
                out[m, 1 + c] = RUN_FREE if tile[c] == 1.0 else -2.0
            else:
                out[m, 1 + c] = RUN_NOTHING


def _sensor(rows: str) -> SphericalSensor:
    e = make_dataset("street", length_m=8).scans[0][1].sensor.elevations
    if rows == "table":
        return SphericalSensor(width=32, height=len(e), max_range=80.0, elevations=e, wrap=True)
    return SphericalSensor(
        width=32, height=len(e), max_range=80.0, el_min=e[-1], el_max=e[0], wrap=True
    )


def _runs(rand, tans, ranges, bounds, fit, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` runs for :func:`_run_two_ways` (a third random, a third at a row's edge, a third
    at a distance threshold), and which end within 1e-10 of a row's edge."""
    H, W = ranges.shape
    cu = rand.uniform(0, W, n)
    rho = rand.uniform(0.5, 80.0, n)
    h = rand.choice([0.005, 0.01, 0.02, 0.05, 0.1], n)
    S = rand.choice([4, 8], n)
    k = rand.integers(-2000, 2000, n)
    t = rand.uniform(tans[-1] - 0.05, tans[0] + 0.05, n)
    # the first voxel's height at tangent t: bz = t rho - its slab height
    bz = t * rho - (k + 0.5) * h
    hair = rand.choice([0.0, 1e-16, 1e-13, 1e-10, 1e-9, 3e-9, 1e-7], n) * rand.choice([-1, 1], n)
    # a third of the runs end a hair from a row's tangent (scaled to the run's last voxel)
    edge = rand.integers(0, H, n)
    at_edge = np.arange(n) % 3 == 1
    t_end = tans[edge] * (1 + hair) + hair
    bz = np.where(at_edge, t_end * rho - (k + S - 1 + 0.5) * h, bz)
    # a third have one end (either) a hair, or a little, from a distance threshold of its
    # quad: its bounds, or the band's edges at the column's bilinear range; a quarter of
    # those straddle the horizon with their nearest voxel in the middle (short runs of
    # small voxels, within one row, a hair nearer than the threshold at their ends'
    # distance but not at their nearest voxel's: about 3e-7 of it at 10 m)
    at_bound = np.arange(n) % 3 == 2
    across = at_bound & (np.arange(n) % 4 == 0)
    t = np.where(across, 0.0, t)
    h = np.where(across, 0.002, h)
    S = np.where(across, 8, S)
    cu = np.where(across, rand.uniform(0, W // 2 - 1, n), cu)  # the wall's valid quads
    r = np.clip(np.searchsorted(-tans, -t) - 1, 0, H - 2)
    qu = np.floor(cu).astype(int)
    fu, fv = cu - qu, (tans[r] - t) / (tans[r] - tans[r + 1])
    top = (1 - fu) * ranges[r, qu] + fu * ranges[r, (qu + 1) % W]
    bottom = (1 - fu) * ranges[r + 1, qu] + fu * ranges[r + 1, (qu + 1) % W]
    r_bil = top + fv * (bottom - top)
    eps = fit[0] + fit[1] * r_bil
    band = [r_bil + eps + (fit[2] or eps), r_bil - eps]
    which = rand.integers(0, 4, n)
    target = np.stack([*bounds.reshape(-1, 2)[qu + r * W].T, *band])[which, np.arange(n)]
    hairs = [0.0, 1e-16, 1e-12, 1e-9, 1e-6, 1e-4, 1e-3, 1e-2]
    far = rand.choice(hairs, n) * rand.choice([-1, 1], n)
    far = np.where(across, rand.choice([-1e-7, -3e-8, -1e-8], n), far)
    target = np.where(np.isfinite(target) & (target > 0.6), target, 10.0) * (1 + far)
    rho = np.where(at_bound, np.maximum(target / np.sqrt(1 + t * t), 0.5), rho)
    end = np.where(across, S // 2, np.where(rand.integers(0, 2, n) == 0, 0, S - 1))
    shift = np.where(across, rand.uniform(-0.5, 0.5, n) * h, 0.0)
    bz = np.where(at_bound, t * rho - (k + end + 0.5) * h + shift, bz)
    runs = np.stack([cu, rho, bz, k, h, S], axis=1).astype(np.float64)
    return runs, at_edge & (np.abs(hair) <= 1e-10)


@pytest.mark.parametrize("rows", ["table", "even"])
@pytest.mark.parametrize("fit", [(0.2, 0.0, 0.0), (0.05, 0.01, 0.3)])
def test_a_level_columns_run_settled_at_once_is_what_each_voxel_gets(rows: str, fit) -> None:
    """Runs of 4 and 8 voxels (a block's column at 16^3 and 32^3 tiles) anywhere in the view,
    runs that end a hair from a row's edge or from a distance threshold, and runs across the
    horizon: where ``_run_outcome`` says free or nothing, every voxel of the run gets that
    voxel by voxel; it says so for most runs away from the edges."""
    rand = np.random.default_rng(5)
    sensor = _sensor(rows)
    _, params, table = sensor.kernel_args()
    tans = _k.row_tangents(params, table)
    chords = _k.row_chords(params, table, tans)
    W, H = 32, len(tans)
    ranges = rand.uniform(2.0, 80.0, (H, W))
    ranges[1::3] = ranges[::3][: len(ranges[1::3])]  # quads whose two rows are the same
    wall = 40.0 + 20.0 * np.sin(np.arange(W // 2) / 3.0)  # half the turn: a smooth wall
    ranges[:, : W // 2] = wall + rand.uniform(0.0, 1.0, (H, W // 2))
    ranges[5, 7] = np.nan  # invalid quads
    fit_a = np.array(fit, np.float64)
    bounds = quad_bounds_array(_k.SPHERICAL, params, ranges, *fit, 12.0)
    n = 30000
    runs, near = _runs(rand, tans, ranges, bounds, fit, n)
    rho, k, h, S = runs[:, 1], runs[:, 3], runs[:, 4], runs[:, 5].astype(int)
    z_a, z_b = runs[:, 2] + (k + 0.5) * h, runs[:, 2] + (k + S - 0.5) * h
    for shape in (SHAPE_LINEAR, 1):
        out = np.full((n, 9), -9.0)
        _run_two_ways(params, table, tans, chords, fit_a, bounds, ranges, shape == SHAPE_LINEAR,
                      runs, out)  # fmt: skip
        run, voxels = out[:, 0], out[:, 1:]
        each = [voxels[m, : int(S[m])] for m in range(n)]
        for outcome in (RUN_FREE, RUN_NOTHING):
            settled = np.flatnonzero(run == outcome)
            assert all((each[m] == outcome).all() for m in settled), outcome
        # runs within one row whose voxels all agree are settled at once, not left to the
        # loop (a run across rows is: the gate of _fuse_block keeps runs from most of them)
        agree = np.array([(e == e[0]).all() and e[0] in (RUN_FREE, RUN_NOTHING) for e in each])
        one_row = np.searchsorted(-tans, -z_a / rho) == np.searchsorted(-tans, -z_b / rho)
        random = np.arange(n) % 3 == 0
        assert (random & agree & one_row).sum() > 3000
        assert (run[random & agree & one_row] != RUN_UNSURE).mean() > 0.99
        assert (run == RUN_NOTHING).sum() > 1000
        assert ((run == RUN_FREE).sum() > 1000) == (shape == SHAPE_LINEAR)
        # runs whose ends are within the margins of a row's edge are left to the loop
        assert near.sum() > 1000 and (run[near] == RUN_UNSURE).mean() > 0.9
        # and across the horizon both ways
        assert (((z_a < 0) != (z_b < 0)) & (run != RUN_UNSURE)).sum() > 10
