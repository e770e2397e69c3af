"""Mesh files: binary PLY, OBJ, GLB and STL through trimesh, chosen by extension.

PLY keeps each face's *inferred* flag (``uchar inferred``: 1 where the face lies against
unknown space or the region's boundary, closed mode) as a face property, so that a user can
drop or colour the inferred part. The other formats carry geometry only.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import trimesh
from rangefuse.engine.meshing import Mesh

from ._files import atomic_write

__all__ = ["MESH_FORMATS", "MeshFormatError", "mesh_bytes", "write_mesh"]

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


def mesh_bytes(mesh: Mesh, fmt: str) -> bytes:
    """The mesh encoded as ``fmt`` (one of :data:`MESH_FORMATS`)."""
    if fmt not in MESH_FORMATS:
        raise MeshFormatError(f"unknown mesh format {fmt!r}; use one of {', '.join(MESH_FORMATS)}")
    tm = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, process=False)
    if fmt == "ply":
        tm.face_attributes["inferred"] = mesh.inferred.astype(np.uint8)
        data = tm.export(file_type="ply", encoding="binary")
    elif fmt == "obj":
        data = tm.export(file_type="obj", include_normals=False, include_texture=False)
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
