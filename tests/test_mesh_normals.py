"""Mesh files carry vertex normals (PLY ``nx ny nz``, OBJ ``vn``, glTF ``NORMAL``), unit
length and pointing out of the object: each file is read back with a parser of its own
format, not through the writer's library."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, Scan, Volume
from rangefuse.engine.synth import SceneBuilder, render
from rangefuse.storage.meshes import mesh_bytes, vertex_normals

from tests.scenes import poses, sensor

CENTRE = np.array([0.02, -0.03, 0.01])
RADIUS = 0.2


@pytest.fixture(scope="module")
def sphere_mesh():
    """A sphere fused from eight pinhole views, closed mode."""
    scene = SceneBuilder().add_sphere(tuple(CENTRE), RADIUS).build()
    cam = sensor("pinhole_z")
    scans = [
        (f"s{k}", Scan(render(scene, cam, T), T, cam)) for k, T in enumerate(poses("pinhole_z", 8))
    ]
    volume = Volume(GridSpec(0.02, 8, "closed", (-0.4, -0.4, -0.4, 0.4, 0.4, 0.4)),
                    FusionParams(NoiseModel(eps=0.04)))  # fmt: skip
    volume.add_many(scans)
    mesh = volume.extract_mesh(refine=True)
    assert mesh.n_faces > 500
    return mesh


def _outward(vertices: np.ndarray, normals: np.ndarray) -> None:
    """Unit normals pointing out of the sphere: every one within 60 degrees of the radial
    direction (a fused sphere's triangles are not all tangent), most within a few."""
    assert normals.shape == vertices.shape
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    radial = vertices - CENTRE
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    cosines = np.sum(radial * normals, axis=1)
    assert cosines.min() > np.cos(np.radians(60)), cosines.min()
    assert np.median(cosines) > np.cos(np.radians(20)), np.median(cosines)


def test_area_weighted_normals_of_a_tetrahedron() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]], np.float64)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # outward, counter-clockwise
    n = vertex_normals(v, f)
    np.testing.assert_allclose(n[0], -np.ones(3) / np.sqrt(3), atol=1e-6)
    # vertex 1: faces -z (area 1/2), -y (1/2), and the slanted one (area sqrt(3)/2)
    expected = np.array([0.0, -0.5, -0.5]) + np.array([0.5, 0.5, 0.5])
    np.testing.assert_allclose(n[1], expected / np.linalg.norm(expected), atol=1e-6)
    assert np.all(n[4] == 0)  # on no face


def test_ply_has_outward_vertex_normals(sphere_mesh) -> None:
    data = mesh_bytes(sphere_mesh, "ply")
    head, _, body = data.partition(b"end_header\n")
    lines = head.decode().splitlines()
    assert lines[1] == "format binary_little_endian 1.0"
    vertex_props = []
    in_vertex = False
    for line in lines:
        if line.startswith("element"):
            in_vertex = line.startswith("element vertex")
        elif line.startswith("property") and in_vertex:
            vertex_props.append(line.split())
    assert [p[2] for p in vertex_props] == ["x", "y", "z", "nx", "ny", "nz"]
    assert {p[1] for p in vertex_props} == {"float"}
    n = sphere_mesh.n_vertices
    table = np.frombuffer(body[: n * 24], "<f4").reshape(n, 6)
    np.testing.assert_allclose(table[:, :3], sphere_mesh.vertices, atol=1e-5)
    _outward(table[:, :3].astype(np.float64), table[:, 3:].astype(np.float64))


def test_obj_has_outward_vertex_normals(sphere_mesh) -> None:
    text = mesh_bytes(sphere_mesh, "obj").decode()
    v = np.array([ln.split()[1:] for ln in text.splitlines() if ln.startswith("v ")], float)
    vn = np.array([ln.split()[1:] for ln in text.splitlines() if ln.startswith("vn ")], float)
    faces = [ln.split()[1:] for ln in text.splitlines() if ln.startswith("f ")]
    assert len(v) == len(vn) == sphere_mesh.n_vertices
    assert len(faces) == sphere_mesh.n_faces
    # each corner names its vertex and its normal: the same index (v//vn)
    for corner in faces[0]:
        position, _, normal = corner.split("/")
        assert position == normal
    _outward(v, vn)


def test_glb_has_outward_vertex_normals(sphere_mesh) -> None:
    data = mesh_bytes(sphere_mesh, "glb")
    magic, version, _ = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A  # JSON
    gltf = json.loads(data[20 : 20 + json_len])
    bin_start = 20 + json_len + 8
    attributes = gltf["meshes"][0]["primitives"][0]["attributes"]
    assert {"POSITION", "NORMAL"} <= set(attributes)

    def accessor(index: int) -> np.ndarray:
        acc = gltf["accessors"][index]
        view = gltf["bufferViews"][acc["bufferView"]]
        assert acc["componentType"] == 5126 and acc["type"] == "VEC3"  # float32 triples
        start = bin_start + view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        return np.frombuffer(data, "<f4", acc["count"] * 3, start).reshape(-1, 3)

    positions = accessor(attributes["POSITION"]).astype(np.float64)
    normals = accessor(attributes["NORMAL"]).astype(np.float64)
    assert len(normals) == sphere_mesh.n_vertices
    _outward(positions, normals)
