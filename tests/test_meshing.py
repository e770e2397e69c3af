"""Meshing: marching-cubes tables, stitching, refinement, unknown space, mesh files."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from rangefuse.engine import FusionParams, GridSpec, MemoryTileStore, NoiseModel, Volume
from rangefuse.engine._mc_tables import TRI_COUNT, TRI_TABLE
from rangefuse.engine.defaults import COUNT_BITS
from rangefuse.engine.meshing import Mesh, extract_mesh, mesh_tiles, stitch
from rangefuse.engine.synth import make_dataset
from rangefuse.service.cli import main
from rangefuse.storage.meshes import MeshFormatError, read_ply_inferred, write_mesh
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from tests import scenes

# --------------------------------------------------------------------------------------------
# helpers


def store_from_field(values: np.ndarray, T: int, known: np.ndarray | None = None):
    """A tile store holding integer log-odds ``values`` (voxel (0, 0, 0) at index 0), each
    voxel informed by one scan; ``known=False`` voxels are unknown."""
    values = np.asarray(values, np.int64)
    known = np.ones(values.shape, bool) if known is None else known
    packed = np.where(known, values * (1 << COUNT_BITS) + 1, 0)
    shape = -(-np.array(values.shape) // T) * T
    padded = np.zeros(shape, np.int64)
    padded[: values.shape[0], : values.shape[1], : values.shape[2]] = packed
    store = MemoryTileStore(T)
    keys, tiles = [], []
    for a in range(shape[0] // T):
        for b in range(shape[1] // T):
            for c in range(shape[2] // T):
                tile = padded[a * T : (a + 1) * T, b * T : (b + 1) * T, c * T : (c + 1) * T]
                if np.any(tile):
                    keys.append((a, b, c))
                    tiles.append(tile)
    if keys:
        store.write(np.array(keys, np.int64), np.stack(tiles), [frozenset({"s"})] * len(keys))
    return store


def as_trimesh(mesh: Mesh) -> trimesh.Trimesh:
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)


def face_key_set(mesh: Mesh) -> set[tuple]:
    """Faces as sets of rotation-normalised vertex-key triples (winding kept)."""
    out = set()
    for f in mesh.faces:
        keys = [tuple(mesh.vertex_keys[v]) for v in f]
        k = keys.index(min(keys))
        out.add(tuple(keys[k:] + keys[:k]))
    return out


def vertex_map(mesh: Mesh) -> dict[tuple, tuple]:
    return {
        tuple(k): tuple(v)
        for k, v in zip(mesh.vertex_keys.tolist(), mesh.vertices.tolist(), strict=True)
    }


PARAMS = FusionParams(NoiseModel(eps=1.0, rho=0.05))


@pytest.fixture(scope="module")
def object_volumes():
    """The synthetic object (12 noiseless views) fused in closed mode at 12 mm."""
    data = make_dataset("object", views=12)
    h = 0.012
    params = FusionParams(NoiseModel(eps=h, rho=0.05), max_discontinuity=0.05)
    volume = Volume(GridSpec(h, 16, "closed", data.bounds), params)
    volume.add_many(data.scans)
    return data, volume


# --------------------------------------------------------------------------------------------
# tables and topology


def test_tables_have_the_classic_shape():
    assert TRI_COUNT[0] == 0 and TRI_COUNT[255] == 0
    assert TRI_COUNT.max() == 5
    corner = np.array([[n & 1, (n >> 1) & 1, (n >> 2) & 1] for n in range(8)])
    for case in range(1, 255):
        edges = TRI_TABLE[case, : 3 * TRI_COUNT[case]]
        assert np.all(edges >= 0) and np.all(edges < 12)
        inside = [(case >> n) & 1 for n in range(8)]
        crossing = set()
        for e in range(12):  # an edge carries a vertex iff its ends differ
            axis, o = divmod(e, 4)
            others = [a for a in range(3) if a != axis]
            lo = np.zeros(3, int)
            lo[others[0]], lo[others[1]] = o & 1, o >> 1
            hi = lo.copy()
            hi[axis] = 1
            n_lo = int(np.flatnonzero((corner == lo).all(1))[0])
            n_hi = int(np.flatnonzero((corner == hi).all(1))[0])
            if inside[n_lo] != inside[n_hi]:
                crossing.add(e)
        assert set(edges.tolist()) == crossing
    for n in range(8):  # one corner in: one triangle
        assert TRI_COUNT[1 << n] == 1 and TRI_COUNT[255 ^ (1 << n)] == 1
    assert np.all(TRI_TABLE[:, 15] == -1)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), T=st.sampled_from([4, 5, 8]))
def test_random_fields_give_watertight_outward_meshes(seed, T):
    """Closed mode on random sign patterns (every ambiguous case occurs): the mesh is closed,
    2-manifold, consistently wound with outward normals."""
    rng = np.random.default_rng(seed)
    n = 9
    values = rng.integers(-1000, 1000, size=(n, n, n))
    values[values == 0] = 1
    grid = GridSpec(1.0, T, "closed", (0.0, 0.0, 0.0, float(n), float(n), float(n)))
    mesh = extract_mesh(store_from_field(values, T), grid, PARAMS, [], refine=False)
    tm = as_trimesh(mesh)
    assert mesh.n_faces > 0
    assert tm.is_watertight and tm.is_winding_consistent
    assert tm.volume > 0
    # each edge of the mesh is shared by exactly two faces
    edges = np.sort(tm.edges, axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)


def test_single_inside_voxel_is_an_octahedron():
    values = -np.ones((5, 5, 5), np.int64)
    values[2, 2, 2] = 1
    grid = GridSpec(1.0, 4, "mapping")
    mesh = extract_mesh(store_from_field(values, 4), grid, PARAMS, [], refine=False)
    assert mesh.n_faces == 8 and mesh.n_vertices == 6
    centre = np.array([2.5, 2.5, 2.5])
    np.testing.assert_allclose(np.linalg.norm(mesh.vertices - centre, axis=1), 0.5)
    tm = as_trimesh(mesh)
    assert tm.is_watertight and tm.volume > 0
    assert not mesh.inferred.any()


# --------------------------------------------------------------------------------------------
# dense reference (scikit-image)


def _skimage_reference(values, known):
    """skimage's marching cubes on the dense field; cubes with an unknown corner masked
    (skimage tests its mask at the cube's upper corner)."""
    cube = known.copy()
    cube[:-1] &= known[1:]
    cube[:, :-1] &= cube[:, 1:]
    cube[:, :, :-1] &= cube[:, :, 1:]
    cube[-1, :, :] = False
    cube[:, -1, :] = False
    cube[:, :, -1] = False
    mask = np.zeros_like(cube)
    mask[1:, 1:, 1:] = cube[:-1, :-1, :-1]
    field = np.where(known, values, 0).astype(np.float64)
    verts, faces, _, _ = marching_cubes(field, 0.0, mask=mask, method="lorensen")
    return verts, faces


@pytest.mark.parametrize("with_unknown", [False, True])
@pytest.mark.parametrize("T", [4, 8])
def test_agrees_with_skimage_on_a_dense_field(with_unknown, T):
    rng = np.random.default_rng(3)
    shape = (21, 18, 15)
    smooth = gaussian_filter(rng.standard_normal(shape), 2.0)
    values = np.round(smooth / smooth.std() * 5000).astype(np.int64)
    values[values == 0] = 1  # skimage and rangefuse differ on which side the level lies
    known = np.ones(shape, bool)
    if with_unknown:
        known = gaussian_filter(rng.standard_normal(shape), 1.5) < 0.25
    grid = GridSpec(1.0, T, "mapping")
    mesh = extract_mesh(store_from_field(values, T, known), grid, PARAMS, [], refine=False)
    ref_v, ref_f = _skimage_reference(values, known)
    assert mesh.n_faces == len(ref_f)
    ours = mesh.vertices - 0.5  # index space: voxel i is centred at i + 1/2
    theirs = ref_v.astype(np.float64)
    # the same vertex set (skimage computes in float32 and may repeat shared vertices)
    d_ours, _ = cKDTree(theirs).query(ours)
    d_theirs, _ = cKDTree(ours).query(theirs)
    assert d_ours.max() < 1e-5 and d_theirs.max() < 1e-5
    assert len(np.unique(np.round(theirs, 4), axis=0)) == mesh.n_vertices
    area_ref = trimesh.Trimesh(ref_v, ref_f, process=False).area
    # the tables triangulate some loops along other diagonals: the areas differ slightly
    assert as_trimesh(mesh).area == pytest.approx(area_ref, rel=2e-3)


def test_mapping_mode_leaves_unknown_space_open():
    values = -np.ones((12, 12, 12), np.int64)
    values[:, :, :6] = 7  # a slab of occupied space: one planar surface at z between 5 and 6
    known = np.ones(values.shape, bool)
    known[:, :, 9:] = False
    mesh = extract_mesh(
        store_from_field(values, 4, known), GridSpec(1.0, 4, "mapping"), PARAMS, [], refine=False
    )
    # a 11 x 11 grid of squares where L crosses 0 between voxels 5 (7) and 6 (-1)
    assert mesh.n_faces == 2 * 11 * 11
    np.testing.assert_allclose(mesh.vertices[:, 2], 5.5 + 7.0 / 8.0)
    assert not mesh.inferred.any()
    assert not as_trimesh(mesh).is_watertight
    # closed mode closes it against the unknown part and the region's boundary
    grid = GridSpec(1.0, 4, "closed", (0.0, 0.0, 0.0, 12.0, 12.0, 12.0))
    closed = extract_mesh(store_from_field(values, 4, known), grid, PARAMS, [], refine=False)
    tm = as_trimesh(closed)
    assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    assert closed.inferred.any() and not closed.inferred.all()
    observed = closed.faces[~closed.inferred]
    np.testing.assert_allclose(closed.vertices[observed.ravel(), 2], 5.5 + 7.0 / 8.0)


# --------------------------------------------------------------------------------------------
# fused scenes


def test_closed_object_is_watertight_and_accurate(object_volumes):
    data, volume = object_volumes
    refined = volume.extract_mesh(refine=True)
    linear = volume.extract_mesh(refine=False)
    for mesh in (refined, linear):
        tm = as_trimesh(mesh)
        assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    err_refined = np.abs(data.scene.signed_distance(refined.vertices)).mean()
    err_linear = np.abs(data.scene.signed_distance(linear.vertices)).mean()
    assert err_refined < 1e-3
    assert err_refined < 0.6 * err_linear
    # same edges either way: refinement moves vertices along their edges only
    np.testing.assert_array_equal(refined.vertex_keys, linear.vertex_keys)
    np.testing.assert_array_equal(refined.faces, linear.faces)


def test_mesh_is_the_same_whatever_the_tile_size():
    data = make_dataset("object", views=6)
    h = 0.03
    params = FusionParams(NoiseModel(eps=h, rho=0.05), max_discontinuity=0.05)
    meshes = []
    for T in (16, 32, 64):
        volume = Volume(GridSpec(h, T, "closed", data.bounds), params)
        volume.add_many(data.scans)
        meshes.append(volume.extract_mesh(refine=True))
    first = meshes[0]
    assert first.n_faces > 1000
    for other in meshes[1:]:
        assert vertex_map(other) == vertex_map(first)  # keys and bit-identical positions
        assert face_key_set(other) == face_key_set(first)
        assert other.n_faces == first.n_faces


def test_tiles_meshed_separately_stitch_to_the_whole(object_volumes):
    _, volume = object_volumes
    scans = [volume._prepare(s) for s in volume.scan_ids]
    whole = mesh_tiles(volume.store, volume.grid, volume.params, scans)
    # five interleaved groups: every tile's neighbours are meshed in other calls
    parts = [
        mesh_tiles(volume.store, volume.grid, volume.params, scans, keys=whole.keys[k::5])
        for k in range(5)
    ]
    a, b = stitch(whole), stitch(parts)
    assert vertex_map(a) == vertex_map(b)
    assert face_key_set(a) == face_key_set(b)
    # a shared edge is computed by both tiles with the same position
    assert len(np.concatenate([p.vertex_keys for p in parts])) > a.n_vertices


def test_mesh_does_not_depend_on_scan_order():
    data = make_dataset("object", views=5)
    h = 0.03
    params = FusionParams(NoiseModel(eps=h, rho=0.05))
    grid = GridSpec(h, 16, "closed", data.bounds)
    a, b = Volume(grid, params), Volume(grid, params)
    a.add_many(data.scans)
    for item in reversed(data.scans):
        b.add(*item)
    ma, mb = a.extract_mesh(), b.extract_mesh()
    for name in ("vertices", "faces", "inferred", "vertex_keys"):
        np.testing.assert_array_equal(getattr(ma, name), getattr(mb, name))


def test_one_view_shows_an_inferred_shadow():
    scans = scenes.scans("pinhole_ray", 1)
    params = FusionParams(NoiseModel(eps=0.03, rho=0.05), max_discontinuity=0.05)
    volume = Volume(GridSpec(0.02, 8, "closed", scenes.BOUNDS), params)
    volume.add_many(scans)
    mesh = volume.extract_mesh()
    tm = as_trimesh(mesh)
    assert tm.is_watertight and tm.is_winding_consistent
    assert mesh.inferred.sum() > 0 and (~mesh.inferred).sum() > 0
    # observed faces lie on the visible surface, the inferred ones need not
    observed = np.unique(mesh.faces[~mesh.inferred])
    d = np.abs(scenes.small_scene().signed_distance(mesh.vertices[observed]))
    assert np.median(d) < 0.002 and np.percentile(d, 75) < 0.005


def test_mapping_mode_room_has_open_observed_surfaces():
    data = make_dataset("room", views=4)
    h = 0.05
    volume = Volume(GridSpec(h, 16, "mapping"), FusionParams(NoiseModel(eps=2 * h, rho=0.05)))
    volume.add_many(data.scans)
    mesh = volume.extract_mesh(refine=True)
    assert mesh.n_faces > 1000 and not mesh.inferred.any()
    assert not as_trimesh(mesh).is_watertight
    # vertices lie near the true surface (walls, furniture)
    d = np.abs(data.scene.signed_distance(mesh.vertices))
    assert np.median(d) < 0.2 * h
    # bounds restrict the mesh
    box = (0.0, 0.0, 0.0, 2.0, 2.0, 2.0)
    part = volume.extract_mesh(bounds=box)
    assert 0 < part.n_faces < mesh.n_faces
    assert np.all(part.vertices >= -h) and np.all(part.vertices <= 2.0 + h)


def test_empty_volume_gives_an_empty_mesh():
    volume = Volume(GridSpec(0.05, 8, "mapping"), FusionParams(NoiseModel(eps=0.1)))
    mesh = volume.extract_mesh()
    assert mesh.n_faces == 0 and mesh.n_vertices == 0


# --------------------------------------------------------------------------------------------
# files and the command line


def _small_mesh() -> Mesh:
    values = -np.ones((6, 6, 6), np.int64)
    values[1:4, 2:5, 1:3] = 9
    grid = GridSpec(0.5, 4, "closed", (0.0, 0.0, 0.0, 3.0, 3.0, 3.0))
    known = np.ones(values.shape, bool)
    known[3:, :, :] = False
    return extract_mesh(store_from_field(values, 4, known), grid, PARAMS, [], refine=False)


@pytest.mark.parametrize("ext", ["ply", "obj", "glb", "stl"])
def test_mesh_files_round_trip(tmp_path, ext):
    mesh = _small_mesh()
    path = write_mesh(tmp_path / f"m.{ext}", mesh)
    loaded = trimesh.load(io.BytesIO(path.read_bytes()), file_type=ext, process=False)
    if isinstance(loaded, trimesh.Scene):
        loaded = loaded.to_geometry()
    if ext == "stl":  # STL stores each triangle's corners
        loaded.merge_vertices()
    assert len(loaded.faces) == mesh.n_faces
    if ext in ("ply", "obj", "glb"):
        assert len(loaded.vertices) == mesh.n_vertices
    np.testing.assert_allclose(loaded.bounds, as_trimesh(mesh).bounds, atol=1e-5)
    assert loaded.is_watertight
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"m.{ext}"]


def test_ply_keeps_the_inferred_flag(tmp_path):
    mesh = _small_mesh()
    assert mesh.inferred.any() and not mesh.inferred.all()
    path = write_mesh(tmp_path / "m.ply", mesh)
    np.testing.assert_array_equal(read_ply_inferred(path), mesh.inferred)


def test_unknown_mesh_extension_is_refused(tmp_path):
    with pytest.raises(MeshFormatError, match=r"\.vtk"):
        write_mesh(tmp_path / "m.vtk", _small_mesh())
    assert list(tmp_path.iterdir()) == []


def test_cli_fuse_writes_the_mesh_of_the_python_api(tmp_path, capsys):
    data_dir = tmp_path / "obj"
    assert main(["synth", "object", str(data_dir), "--views", "4"]) == 0
    out = tmp_path / "mesh.ply"
    args = ["fuse", str(data_dir), "--voxel-size", "0.04", "--mode", "closed"]
    args += ["--bounds", "-0.6", "-0.6", "-0.2", "0.6", "0.6", "0.8", "-o", str(out)]
    assert main(args) == 0
    data = make_dataset("object", views=4)
    volume = Volume(
        GridSpec(0.04, 16, "closed", (-0.6, -0.6, -0.2, 0.6, 0.6, 0.8)),
        FusionParams(NoiseModel(eps=0.08, rho=0.05)),
    )
    volume.add_many(data.scans)
    expected = volume.extract_mesh()
    loaded = trimesh.load(out, process=False)
    assert len(loaded.faces) == expected.n_faces
    np.testing.assert_allclose(loaded.vertices, expected.vertices, atol=1e-6)
    np.testing.assert_array_equal(loaded.faces, expected.faces)
    np.testing.assert_array_equal(read_ply_inferred(out), expected.inferred)
    # --no-refine gives the linear vertices
    out2 = tmp_path / "linear.obj"
    assert main([*args[:-2], "-o", str(out2), "--no-refine"]) == 0
    linear = trimesh.load(out2, process=False)
    assert len(linear.faces) == expected.n_faces
    assert not np.allclose(linear.vertices, loaded.vertices, atol=1e-6)


def test_cli_refuses_a_bad_mesh_path(tmp_path, capsys):
    data_dir = tmp_path / "obj"
    assert main(["synth", "object", str(data_dir), "--views", "2"]) == 0
    code = main(["fuse", str(data_dir), "--voxel-size", "0.05", "-o", str(tmp_path / "m.xyz")])
    assert code == 2
    err = capsys.readouterr().err
    assert ".xyz" in err and "Traceback" not in err
    assert not any(Path(p).suffix == ".xyz" for p in tmp_path.iterdir())
