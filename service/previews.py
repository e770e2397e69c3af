"""Preview meshes for the web page: a reconstruction simplified to at most
:data:`PREVIEW_FACES` faces, made once by the reconstruction job (a unit of work on the
cluster, like meshing) and stored next to the mesh; ``GET /v1/scenes/{id}/preview`` serves it.

The measured faces and the inferred ones (closed mode: against unknown space) are simplified
separately, each to its share of the budget, so that every face of the preview is exactly one
or the other and the page can dim or hide the inferred part. Simplification is quadric edge
collapse (``fast-simplification``, a maintained binding of Sven Forstmann's
Fast-Quadric-Mesh-Simplification); the seam between the two parts may open by a fraction of
a simplified edge, which is invisible at viewing distance.

The file is one or two levels, the preview then (when the preview has more than
:data:`COARSE_FACES` faces) a coarser one that the page draws while the camera moves. Each
level is little-endian and 4-byte aligned, made to be turned into WebGL buffers without
parsing (docs/webapp.md)::

    magic  b"RFPV0001"                       8 bytes
    uint32 n_vertices, n_faces, n_measured,  source_faces
    float32 positions[n_vertices, 3]
    uint32 indices[n_faces, 3]               measured faces first, then the inferred ones
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rangefuse.storage._files import atomic_write
from rangefuse.storage.units import Runner

from .cluster import RunInterruptedError

__all__ = [
    "COARSE_FACES",
    "PREVIEW_FACES",
    "PreviewUnit",
    "encode_preview",
    "make_preview",
    "preview_path",
    "preview_unit",
    "simplify_parts",
]

#: Most faces in a preview.
PREVIEW_FACES = 300_000
#: Most faces of the preview's coarse level, drawn while the camera moves: software WebGL
#: (SwiftShader on 2 cores) draws a frame in about 25 ms plus 0.6 us a face, so 300 k faces
#: orbit at 6.6 frames/s, 60 k at 17 and 30 k at over 20 (docs/webapp.md).
COARSE_FACES = 30_000

log = logging.getLogger("rangefuse.previews")

MAGIC = b"RFPV0001"
_HEADER = struct.Struct("<8s4I")


def preview_path(mesh_path: str | Path) -> Path:
    """Where the preview of the mesh file ``mesh_path`` (``meshes/<job>.npz``) is kept."""
    mesh_path = Path(mesh_path)
    return mesh_path.with_name(mesh_path.stem + ".preview.bin")


def _compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vertices ``faces`` use, and the faces renumbered."""
    used, inverse = np.unique(faces.reshape(-1), return_inverse=True)
    return vertices[used], inverse.reshape(-1, 3)


def _simplify(
    vertices: np.ndarray, faces: np.ndarray, target: int
) -> tuple[np.ndarray, np.ndarray]:
    """``faces`` (with their vertices) reduced to about ``target`` faces."""
    v, f = _compact(vertices, faces)
    if len(f) <= target:
        return v.astype(np.float32), f.astype(np.uint32)
    import fast_simplification  # only where previews are made (a worker)

    v2, f2 = fast_simplification.simplify(
        np.ascontiguousarray(v, np.float64), np.ascontiguousarray(f, np.int32),
        target_count=max(int(target), 4),
    )  # fmt: skip
    return np.asarray(v2, np.float32), np.asarray(f2, np.uint32)


#: Quadric simplification takes about 370 bytes a face (measured on 1.5 M faces); a mesh over
#: this many times the preview's faces is first clustered, so that a worker's memory stays
#: within about 0.6 GB over the mesh itself.
CLUSTER_OVER = 5


def cluster_vertices(
    vertices: np.ndarray, faces: np.ndarray, inferred: np.ndarray, target: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex clustering (one vertex per cell of a cubic grid, degenerate faces dropped): a
    coarse, linear-time reduction of a surface mesh to about ``target`` faces, in
    O(faces) memory. The cell is 0.8 mean edge lengths times sqrt(faces / target)."""
    v = np.asarray(vertices, np.float64)
    sample = faces[:: max(1, len(faces) // 100_000)]
    edge = float(np.mean(np.linalg.norm(v[sample[:, 0]] - v[sample[:, 1]], axis=1)))
    cell = 0.8 * max(edge, 1e-12) * np.sqrt(len(faces) / max(target, 1))  # 0.8: measured
    cells = np.floor((v - v.min(axis=0)) / cell).astype(np.int64)
    _, vertex_cell = np.unique(cells, axis=0, return_inverse=True)
    vertex_cell = vertex_cell.reshape(-1)
    n_cells = int(vertex_cell.max()) + 1 if len(vertex_cell) else 0
    sums = np.zeros((n_cells, 3))
    np.add.at(sums, vertex_cell, v)
    counts = np.bincount(vertex_cell, minlength=n_cells)[:, None]
    merged = vertex_cell[faces]
    keep = (
        (merged[:, 0] != merged[:, 1]) & (merged[:, 1] != merged[:, 2])
        & (merged[:, 0] != merged[:, 2])
    )  # fmt: skip
    return sums / np.maximum(counts, 1), merged[keep], np.asarray(inferred)[keep]


def simplify_parts(
    vertices: np.ndarray, faces: np.ndarray, inferred: np.ndarray, max_faces: int
) -> tuple[np.ndarray, np.ndarray, int]:
    """``(positions, indices, n_measured)``: the mesh with at most about ``max_faces`` faces,
    its measured faces first. Each part keeps its share of the budget (a part smaller than its
    share is kept whole and leaves the rest to the other)."""
    inferred = np.asarray(inferred, bool).reshape(-1)
    faces = np.asarray(faces).reshape(-1, 3)
    if len(faces) > CLUSTER_OVER * max_faces:
        vertices, faces, inferred = cluster_vertices(
            vertices, faces, inferred, (CLUSTER_OVER - 1) * max_faces
        )
    parts = [faces[~inferred], faces[inferred]]
    n = len(faces)
    if n <= max_faces:
        targets = [len(p) for p in parts]
    else:
        small = min(range(2), key=lambda i: len(parts[i]))
        share = max_faces * len(parts[small]) / n
        targets = [0, 0]
        targets[small] = max(int(share), min(len(parts[small]), 4))
        targets[1 - small] = max_faces - targets[small]
    positions: list[np.ndarray] = []
    indices: list[np.ndarray] = []
    offset = 0
    for part, target in zip(parts, targets, strict=True):
        if len(part) == 0:
            continue
        v, f = _simplify(vertices, part, target)
        positions.append(v)
        indices.append(f + np.uint32(offset))
        offset += len(v)
    n_measured = len(indices[0]) if len(parts[0]) else 0
    if not positions:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32), 0
    return np.concatenate(positions), np.concatenate(indices), n_measured


def encode_preview(
    positions: np.ndarray, indices: np.ndarray, n_measured: int, source_faces: int
) -> bytes:
    """The preview file's bytes (see the module's note)."""
    positions = np.ascontiguousarray(positions, "<f4").reshape(-1, 3)
    indices = np.ascontiguousarray(indices, "<u4").reshape(-1, 3)
    header = _HEADER.pack(MAGIC, len(positions), len(indices), int(n_measured), int(source_faces))
    return header + positions.tobytes() + indices.tobytes()


def preview_of(
    vertices: np.ndarray,
    faces: np.ndarray,
    inferred: np.ndarray,
    max_faces: int = PREVIEW_FACES,
    coarse_faces: int = COARSE_FACES,
) -> bytes:
    """The preview file of a mesh: the preview, then its coarse level when it has more than
    ``coarse_faces`` faces."""
    positions, indices, n_measured = simplify_parts(vertices, faces, inferred, max_faces)
    payload = encode_preview(positions, indices, n_measured, len(faces))
    if len(indices) > coarse_faces:
        flags = np.arange(len(indices)) >= n_measured
        coarse = simplify_parts(positions, indices, flags, coarse_faces)
        payload += encode_preview(*coarse, len(faces))
    return payload


@dataclass(frozen=True)
class PreviewUnit:
    """Make the preview of the mesh file ``mesh_path`` (an ``.npz`` of ``vertices``,
    ``faces``, ``inferred``) at ``preview_path``."""

    mesh_path: str
    preview_path: str
    max_faces: int = PREVIEW_FACES


def preview_unit(unit: PreviewUnit) -> int:
    """Write the preview (atomically); returns its number of faces."""
    with np.load(unit.mesh_path) as data:
        vertices, faces, inferred = data["vertices"], data["faces"], data["inferred"]
    payload = preview_of(vertices, faces, inferred, unit.max_faces)
    del vertices, faces, inferred
    atomic_write(Path(unit.preview_path), lambda fh: fh.write(payload), fsync=True)
    return _HEADER.unpack_from(payload)[2]


def make_preview(runner: Runner, mesh_path: str | Path) -> int | None:
    """Make the preview of a mesh file as a unit of work on ``runner`` (the reconstruction
    job's last step); returns its faces. A preview that cannot be made (its unit failed)
    is logged and skipped: the mesh stays, and the page says there is no preview. A cancelled
    job (:class:`~service.cluster.RunInterruptedError`) stops here as anywhere else."""
    unit = PreviewUnit(str(mesh_path), str(preview_path(mesh_path)))
    try:
        (faces,) = runner.map(preview_unit, [unit])
    except RunInterruptedError:
        raise
    except Exception as exc:
        log.warning("no preview for %s: %s: %s", mesh_path, type(exc).__name__, exc)
        return None
    return int(faces)
