"""Tile meshes kept between extractions (docs/storage.md, "Incremental meshing").

Each tile has an epoch in the catalog, bumped when its data may have changed; its mesh is
kept in the catalog with the epoch and the options it was made with, and an extraction
re-meshes only the tiles whose epoch moved (DESIGN.md invariant 7).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence

import numpy as np
from rangefuse.engine import GridSpec
from rangefuse.engine.grid import pack_keys, unpack_keys
from rangefuse.engine.meshing import (
    HALO_TILES,
    Mesh,
    TileMeshes,
    mesh_region,
    stitch,
    tiles_to_mesh,
)

from .catalog import Catalog

__all__ = ["MeshBatches", "MeshCache", "encode_tile_mesh"]

#: Meshes batches of tiles (their keys): each batch's tile meshes (:func:`encode_tile_mesh`),
#: calling the second argument, when given, with a batch's index as it is done.
MeshBatches = Callable[[list[np.ndarray], Callable[[int], None] | None], list[list[bytes]]]


class MeshCache:
    """The cached tile meshes and tile epochs of one scene."""

    def __init__(self, catalog: Catalog, scene_id: str) -> None:
        self.catalog = catalog
        self.scene_id = scene_id

    def bump(self, tiles: np.ndarray) -> None:
        """The data of the tiles ``tiles`` (packed keys) may have changed: their meshes and
        those of the 7 tiles whose one-voxel halo they are (meshing reads upwards) are stale.
        Call inside the transaction that commits the change."""
        if len(tiles):
            keys = unpack_keys(tiles)
            below = np.unique(pack_keys(np.concatenate([keys - off for off in HALO_TILES])))
            self.catalog.bump_epochs(self.scene_id, below)

    def extract(
        self,
        existing: np.ndarray,
        grid: GridSpec,
        mesh: MeshBatches,
        *,
        refine: bool,
        bounds: Sequence[float] | None,
        batch: Callable[[int], int],
        progress: Callable[[int, int], None] | None = None,
    ) -> tuple[Mesh, dict[str, int]]:
        """The surface of a volume whose tiles are ``existing`` as one mesh, re-meshing only
        the tiles whose epoch moved since they were meshed with the same options, in batches
        of ``batch(tiles to mesh)`` tiles; returns the mesh and counts.
        ``progress(tiles, total)``: the tiles meshed or reused so far, as batches finish."""
        lo, hi = mesh_region(grid, bounds)
        keys = tiles_to_mesh(existing, grid, lo, hi)
        packed = pack_keys(keys)
        options = json.dumps(
            {"refine": bool(refine), "bounds": None if bounds is None else list(bounds)}
        )
        epochs = self.catalog.epochs(self.scene_id, packed)
        cached = self.catalog.mesh_cache_get(self.scene_id, packed, options)
        hit = np.array(
            [
                p in cached and cached[p][0] == e
                for p, e in zip(packed.tolist(), epochs.tolist(), strict=True)
            ],
            np.bool_,
        )
        blobs = {p: cached[p][1] for p in packed[hit].tolist()}
        todo = np.flatnonzero(~hit)
        size = max(1, batch(len(todo)))
        batches = [todo[start : start + size] for start in range(0, len(todo), size)]
        finished = int(hit.sum())

        def done(i: int) -> None:
            nonlocal finished
            finished += len(batches[i])
            if progress is not None:
                progress(finished, len(keys))

        if progress is not None:
            progress(finished, len(keys))
        meshed = mesh([keys[rows] for rows in batches], done if progress is not None else None)
        for rows, meshes in zip(batches, meshed, strict=True):
            entries = [
                (int(packed[r]), int(epochs[r]), blob)
                for r, blob in zip(rows.tolist(), meshes, strict=True)
            ]
            self.catalog.mesh_cache_put(self.scene_id, options, entries)
            blobs.update((p, blob) for p, _, blob in entries)
        mesh_of_all = stitch(_decode(keys, [blobs[p] for p in packed.tolist()]))
        return mesh_of_all, {"tiles": len(keys), "reused": int(hit.sum()), "meshed": len(todo)}


def encode_tile_mesh(tm: TileMeshes, n: int) -> bytes:
    """Tile ``n`` of ``tm`` as the bytes the cache keeps."""
    v0, v1 = int(tm.vertex_offsets[n]), int(tm.vertex_offsets[n + 1])
    f0, f1 = int(tm.face_offsets[n]), int(tm.face_offsets[n + 1])
    head = np.array([v1 - v0, f1 - f0], np.int64)
    return b"".join(
        [
            head.tobytes(),
            np.ascontiguousarray(tm.vertex_keys[v0:v1], np.int64).tobytes(),
            np.ascontiguousarray(tm.vertices[v0:v1], np.float64).tobytes(),
            np.ascontiguousarray(tm.faces[f0:f1] - v0, np.int64).tobytes(),
            np.ascontiguousarray(tm.inferred[f0:f1], np.bool_).tobytes(),
        ]
    )


def _decode(key: np.ndarray, blobs: Sequence[bytes]) -> TileMeshes:
    vk, vs, fs, inf, v_off, f_off = [], [], [], [], [0], [0]
    for blob in blobs:
        nv, nf = np.frombuffer(blob, np.int64, 2)
        at = 16
        vk.append(np.frombuffer(blob, np.int64, nv * 4, at).reshape(-1, 4))
        at += nv * 32
        vs.append(np.frombuffer(blob, np.float64, nv * 3, at).reshape(-1, 3))
        at += nv * 24
        fs.append(np.frombuffer(blob, np.int64, nf * 3, at).reshape(-1, 3) + v_off[-1])
        at += nf * 24
        inf.append(np.frombuffer(blob, np.bool_, nf, at))
        v_off.append(v_off[-1] + int(nv))
        f_off.append(f_off[-1] + int(nf))
    return TileMeshes(
        keys=key,
        vertex_offsets=np.array(v_off, np.int64),
        face_offsets=np.array(f_off, np.int64),
        vertex_keys=np.concatenate([np.zeros((0, 4), np.int64), *vk]),
        vertices=np.concatenate([np.zeros((0, 3)), *vs]),
        faces=np.concatenate([np.zeros((0, 3), np.int64), *fs]),
        inferred=np.concatenate([np.zeros(0, np.bool_), *inf]),
    )
