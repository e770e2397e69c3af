"""Mesh files: binary PLY, OBJ, GLB and STL through trimesh, chosen by extension.

PLY, OBJ and GLB carry a unit normal per vertex (PLY ``nx ny nz``, OBJ ``vn``, glTF
``NORMAL``): the area-weighted mean of the normals of the faces around it, which point from
occupied into free space (the engine winds faces counter-clockwise seen from outside), so
a viewer shades the surface smoothly and lights its outer side. STL has face normals only.
PLY also keeps each face's *inferred* flag (``uchar inferred``: 1 where the face lies
against unknown space or the region's boundary, closed mode) as a face property, so that a
user can drop or colour the inferred part.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import trimesh
from rangefuse.engine.meshing import Mesh

from ._files import atomic_write

__all__ = ["MESH_FORMATS", "MeshFormatError", "mesh_bytes", "vertex_normals", "write_mesh"]

#: File extension -> trimesh export type.
MESH_FORMATS = {"ply": "ply", "obj": "obj", "glb": "glb", "stl": "stl"}


class MeshFormatError(ValueError):
    """An unsupported mesh file type."""


def mesh_format(path: str | os.PathLike[str]) -> str:
    """The mesh format named by a path's extension; :class:`MeshFormatError` if unknown."""
    ext = Path(path).suffix.lower().lstrip(".")
    if ext not in MESH_FORMATS:
        raise MeshFormatError(
            f"{path}: unknown mesh file type {('.' + ext) if ext else '(no extension)'!r}; "
            f"use one of {', '.join('.' + e for e in MESH_FORMATS)}"
        )
    return ext


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals: at each vertex, the sum of its faces' normals weighted by their
    areas, normalised.

    Parameters
    ----------
    vertices : float (n, 3)
    faces : int (m, 3)
        Wound counter-clockwise seen from the side the normals are to point to.

    Returns
    -------
    float32 (n, 3)
        Zero for a vertex of no face, or of faces of zero area only.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    n = v.shape[0]
    # |cross| is twice the face's area: the sum is area-weighted
    face_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    corners = f.reshape(-1)
    out = np.empty((n, 3), np.float64)
    for axis in range(3):
        out[:, axis] = np.bincount(corners, np.repeat(face_n[:, axis], 3), minlength=n)
    length = np.linalg.norm(out, axis=1)
    good = length > 0
    out[good] /= length[good, None]
    out[~good] = 0.0
    return out.astype(np.float32)


def mesh_bytes(mesh: Mesh, fmt: str) -> bytes:
    """The mesh encoded as ``fmt`` (one of :data:`MESH_FORMATS`), with vertex normals in
    PLY, OBJ and GLB."""
    if fmt not in MESH_FORMATS:
        raise MeshFormatError(f"unknown mesh format {fmt!r}; use one of {', '.join(MESH_FORMATS)}")
    normals = None if fmt == "stl" else vertex_normals(mesh.vertices, mesh.faces)
    tm = trimesh.Trimesh(
        vertices=mesh.vertices, faces=mesh.faces, vertex_normals=normals, process=False
    )
    if fmt == "ply":
        tm.face_attributes["inferred"] = mesh.inferred.astype(np.uint8)
        data = tm.export(file_type="ply", encoding="binary", vertex_normal=True)
    elif fmt == "obj":
        data = tm.export(file_type="obj", include_normals=True, include_texture=False)
    elif fmt == "glb":
        data = tm.export(file_type="glb", include_normals=True)
    else:
        data = tm.export(file_type=MESH_FORMATS[fmt])
    if isinstance(data, str):
        data = data.encode()
    return bytes(data)


def write_mesh(path: str | os.PathLike[str], mesh: Mesh) -> Path:
    """Write a mesh atomically, in the format its extension names."""
    path = Path(path)
    data = mesh_bytes(mesh, mesh_format(path))
    atomic_write(path, lambda fh: fh.write(data))
    return path


def read_ply_inferred(path: str | os.PathLike[str]) -> np.ndarray:
    """The ``inferred`` face flags of a PLY written by :func:`write_mesh`."""
    loaded = trimesh.load(io.BytesIO(Path(path).read_bytes()), file_type="ply", process=False)
    raw = loaded.metadata["_ply_raw"]["face"]["data"]
    return np.asarray(raw["inferred"]).astype(bool).reshape(-1)
