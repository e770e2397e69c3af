"""Dataset folders and grid files on disk (FORMAT.md): round trips and every way to be wrong.

Every malformed input must end in a :class:`storage.DatasetError` whose message names the
file and the key or field; no NumPy, zipfile or zlib exception may escape, and nothing is
ever unpickled.
"""

from __future__ import annotations

import io
import json
import math
import os
import pickle
import stat
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rangefuse.engine import (
    CylindricalSensor,
    DenseGrid,
    OrthographicSensor,
    PinholeSensor,
    Scan,
    Sensor,
    SphericalSensor,
)
from rangefuse.storage import (
    DatasetError,
    open_dataset,
    read_grid,
    read_scan_file,
    write_dataset,
    write_grid,
    write_scan_file,
)

PINHOLE = PinholeSensor(
    width=8, height=6, fx=6.0, fy=6.0, cx=3.5, cy=2.5, range_convention="z", max_range=5.0
)
SENSORS: dict[str, Sensor] = {
    "pinhole": PINHOLE,
    "spherical": SphericalSensor(
        width=16,
        height=4,
        az_min=-math.pi,
        az_max=math.pi,
        wrap=True,
        elevations=(0.1, 0.0, -0.05, -0.3),
        min_range=0.5,
        max_range=50.0,
    ),
    "cylindrical": CylindricalSensor(
        width=12,
        height=5,
        az_min=-1.0,
        az_max=1.0,
        fy=4.0,
        cy=2.0,
        range_convention="radial",
        max_range=20.0,
    ),
    "orthographic": OrthographicSensor(width=5, height=7, sx=0.01, sy=0.02, max_range=3.0),
}


def pose(angle: float = 0.3, t: tuple[float, float, float] = (0.1, -0.2, 0.5)) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = t
    return T


def ranges(sensor: Sensor, seed: int = 0) -> np.ndarray:
    """A range map with measurements, a no-return pixel and an invalid one."""
    rng = np.random.default_rng(seed)
    out = rng.uniform(1.0, 2.0, sensor.shape).astype(np.float32)
    out[0, 0] = np.inf
    out[-1, -1] = np.nan
    return out


def scan_of(sensor: Sensor, seed: int = 0) -> Scan:
    return Scan(range_m=ranges(sensor, seed), T_W_S=pose(0.1 * seed), sensor=sensor)


def assert_same_scan(a: Scan, b: Scan) -> None:
    assert a.sensor == b.sensor
    assert a.range_m.dtype == b.range_m.dtype == np.float32
    assert np.array_equal(a.range_m.view(np.uint32), b.range_m.view(np.uint32))
    assert np.array_equal(a.T_W_S, b.T_W_S)


def save_npz(path: Path, **arrays: Any) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as fh:
        np.savez(fh, **arrays)
    return path


def expect_error(path: Path, sensor: Sensor | None, *fragments: str) -> str:
    """Read ``path``; it must fail with a DatasetError naming the file and each fragment."""
    with pytest.raises(DatasetError) as info:
        read_scan_file(path, sensor)
    message = str(info.value)
    assert str(path) in message
    for fragment in fragments:
        assert fragment in message, message
    return message


# --- round trips -------------------------------------------------------------------------------


@pytest.mark.parametrize("model", sorted(SENSORS))
def test_dataset_round_trip(tmp_path: Path, model: str) -> None:
    sensor = SENSORS[model]
    scans = [(f"scan_{k:04d}", scan_of(sensor, k)) for k in range(3)]
    root = write_dataset(tmp_path / "ds", sensor, scans, {"scene.json": '{"x": 1}\n'})
    assert root == tmp_path / "ds"
    assert json.loads((root / "sensor.json").read_text()) == sensor.to_dict()
    assert (root / "scene.json").read_text() == '{"x": 1}\n'
    dataset = open_dataset(root)
    assert dataset.sensor == sensor
    assert len(dataset) == 3
    assert dataset.names == ["scan_0000", "scan_0001", "scan_0002"]
    read = list(dataset.scans())
    assert [name for name, _ in read] == dataset.names
    for (_, expected), (_, got) in zip(scans, read, strict=True):
        assert_same_scan(expected, got)
    # The shared sensor is not repeated in every scan; writes leave no temporary files.
    with np.load(root / "scans" / "scan_0000.npz", allow_pickle=False) as npz:
        assert sorted(npz.files) == ["pose", "range"]
        assert npz["range"].dtype == np.float32 and npz["pose"].dtype == np.float64
    assert sorted(p.name for p in (root / "scans").iterdir()) == [
        "scan_0000.npz",
        "scan_0001.npz",
        "scan_0002.npz",
    ]


def test_scans_are_taken_in_name_order_and_other_files_ignored(tmp_path: Path) -> None:
    names = ["b", "a", "c_10", "c_02"]
    write_dataset(tmp_path, PINHOLE, [(n, scan_of(PINHOLE, k)) for k, n in enumerate(names)])
    (tmp_path / "scans" / "notes.txt").write_text("ignored")
    (tmp_path / "README").write_text("ignored")
    assert open_dataset(tmp_path).names == ["a", "b", "c_02", "c_10"]


def test_per_scan_sensor_overrides_sensor_json(tmp_path: Path) -> None:
    other = PinholeSensor(
        width=4, height=3, fx=3.0, fy=3.0, cx=1.5, cy=1.0, range_convention="ray", max_range=9.0
    )
    scans = [("scan_0000", scan_of(PINHOLE)), ("scan_0001", scan_of(other, 1))]
    write_dataset(tmp_path, PINHOLE, scans)
    with np.load(tmp_path / "scans" / "scan_0001.npz", allow_pickle=False) as npz:
        assert json.loads(str(npz["sensor"])) == other.to_dict()
    read = dict(open_dataset(tmp_path).scans())
    assert read["scan_0000"].sensor == PINHOLE
    assert read["scan_0001"].sensor == other
    assert_same_scan(scans[1][1], read["scan_0001"])
    # A scan with its own sensor needs no sensor.json; one without does.
    (tmp_path / "sensor.json").unlink()
    dataset = open_dataset(tmp_path)
    assert dataset.sensor is None
    assert read_scan_file(tmp_path / "scans" / "scan_0001.npz", None).sensor == other
    expect_error(tmp_path / "scans" / "scan_0000.npz", None, "no per-scan 'sensor'", "sensor.json")


def test_foreign_writers_any_float_dtype_and_bytes_sensor(tmp_path: Path) -> None:
    """Files written by other tools: float64 ranges, integer poses, a bytes sensor string."""
    rng = ranges(PINHOLE).astype(np.float64)
    path = save_npz(
        tmp_path / "s.npz",
        range=rng,
        pose=np.eye(4, dtype=np.int32),
        sensor=np.bytes_(json.dumps(PINHOLE.to_dict()).encode()),
    )
    scan = read_scan_file(path, None)
    assert scan.sensor == PINHOLE
    assert scan.range_m.dtype == np.float32
    assert np.array_equal(scan.range_m, rng.astype(np.float32), equal_nan=True)
    assert np.array_equal(scan.T_W_S, np.eye(4))


def test_written_files_get_the_usual_mode(tmp_path: Path) -> None:
    """Files are written through a temporary file (mkstemp: 0600) but end up 0666 & ~umask."""
    path = tmp_path / "x.npz"
    write_scan_file(path, scan_of(PINHOLE, 0), include_sensor=False)
    umask = os.umask(0o022)
    os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask


def test_write_scan_file_replaces_atomically(tmp_path: Path) -> None:
    path = tmp_path / "scans" / "x.npz"
    write_scan_file(path, scan_of(PINHOLE, 0), include_sensor=False)
    write_scan_file(path, scan_of(PINHOLE, 1), include_sensor=True)
    assert [p.name for p in path.parent.iterdir()] == ["x.npz"]
    assert_same_scan(read_scan_file(path, None), scan_of(PINHOLE, 1))


# --- malformed scan files ---------------------------------------------------------------------


def good(**changes: Any) -> dict[str, Any]:
    arrays: dict[str, Any] = {"range": ranges(PINHOLE), "pose": pose()}
    arrays.update(changes)
    return {k: v for k, v in arrays.items() if v is not None}


def rotation_scaled() -> np.ndarray:
    T = pose()
    T[:3, :3] *= 1.01
    return T


def reflection() -> np.ndarray:
    T = pose()
    T[:3, 2] *= -1.0
    return T


def last_row() -> np.ndarray:
    T = pose()
    T[3, 3] = 2.0
    return T


def nan_pose() -> np.ndarray:
    T = pose()
    T[0, 3] = np.nan
    return T


BAD_SCANS: dict[str, tuple[dict[str, Any], tuple[str, ...]]] = {
    "no range": (good(range=None), ("missing key 'range'", "pose")),
    "no pose": (good(pose=None), ("missing key 'pose'",)),
    "range int": (good(range=np.ones(PINHOLE.shape, np.int32)), ("range:", "int32")),
    "range uint16 depth": (good(range=np.ones(PINHOLE.shape, np.uint16)), ("range:", "metres")),
    "range bool": (good(range=np.ones(PINHOLE.shape, bool)), ("range:", "bool")),
    "range complex": (good(range=np.ones(PINHOLE.shape, complex)), ("range:", "complex")),
    "range string": (good(range=np.full(PINHOLE.shape, "1.0")), ("range:", "<U3")),
    "range 1-D": (good(range=np.ones(48, np.float32)), ("range:", "2-D", "(48,)")),
    "range 3-D": (good(range=np.ones((1, 6, 8), np.float32)), ("range:", "2-D", "(1, 6, 8)")),
    "range 0-D": (good(range=np.float32(1.0)), ("range:", "2-D")),
    "range transposed": (
        good(range=np.ones((8, 6), np.float32)),
        ("range:", "(8, 6)", "does not match", "(6, 8)"),
    ),
    "range negative": (good(range=-np.ones(PINHOLE.shape, np.float32)), ("range:", "<= 0")),
    "range -inf": (good(range=np.full(PINHOLE.shape, -np.inf, np.float32)), ("range:", "-inf")),
    "pose 3x3": (good(pose=np.eye(3)), ("pose:", "4x4", "(3, 3)")),
    "pose 16": (good(pose=np.eye(4).ravel()), ("pose:", "4x4", "(16,)")),
    "pose 4x4x1": (good(pose=np.eye(4)[..., None]), ("pose:", "4x4")),
    "pose scaled": (good(pose=rotation_scaled()), ("pose:", "not rigid")),
    "pose reflection": (good(pose=reflection()), ("pose:", "reflection")),
    "pose last row": (good(pose=last_row()), ("pose:", "last row")),
    "pose NaN": (good(pose=nan_pose()), ("pose:", "non-finite")),
    "pose strings": (good(pose=np.full((4, 4), "1")), ("pose:", "numeric", "<U1")),
    "pose complex": (good(pose=np.eye(4, dtype=complex)), ("pose:", "numeric", "complex")),
    "sensor not JSON": (good(sensor=np.array("{model: pinhole")), ("sensor", "not valid JSON")),
    "sensor not a string": (good(sensor=np.arange(3)), ("'sensor'", "JSON string")),
    "sensor unknown model": (
        good(sensor=np.array(json.dumps({**PINHOLE.to_dict(), "model": "fisheye"}))),
        ("sensor.model", "fisheye"),
    ),
    "sensor model a list": (
        good(sensor=np.array(json.dumps({**PINHOLE.to_dict(), "model": ["pinhole"]}))),
        ("sensor.model", "unknown sensor model"),
    ),
    "sensor missing fx": (
        good(
            sensor=np.array(json.dumps({k: v for k, v in PINHOLE.to_dict().items() if k != "fx"}))
        ),
        ("sensor.fx", "missing"),
    ),
    "sensor shape mismatch": (
        good(sensor=np.array(json.dumps({**PINHOLE.to_dict(), "width": 9}))),
        ("range:", "(6, 8)", "(6, 9)"),
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_SCANS))
def test_bad_scan_files(tmp_path: Path, case: str) -> None:
    arrays, fragments = BAD_SCANS[case]
    path = save_npz(tmp_path / "scan.npz", **arrays)
    expect_error(path, PINHOLE, *fragments)


def test_shape_mismatch_with_sensor_json(tmp_path: Path) -> None:
    write_dataset(tmp_path, PINHOLE, [("scan_0000", scan_of(PINHOLE))])
    wide = PinholeSensor(
        width=10, height=6, fx=6.0, fy=6.0, cx=4.5, cy=2.5, range_convention="z", max_range=5.0
    )
    (tmp_path / "sensor.json").write_text(json.dumps(wide.to_dict()))
    dataset = open_dataset(tmp_path)  # the folder opens; reading the scan fails
    with pytest.raises(DatasetError, match=r"scan_0000\.npz: range: shape \(6, 8\).*\(6, 10\)"):
        list(dataset.scans())


class _Trap:
    """Unpickling this object creates the file ``marker``: a stand-in for malicious code."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (self.marker,))


@pytest.mark.parametrize("key", ["range", "pose", "sensor"])
def test_pickled_objects_are_never_loaded(tmp_path: Path, key: str) -> None:
    marker = tmp_path / "unpickled"
    trap = np.empty((), dtype=object)
    trap[()] = _Trap(marker)
    path = save_npz(tmp_path / "scan.npz", **good(**{key: trap}))
    # The trap is live: loading with pickles allowed would run it.
    check = tmp_path / "check.npz"
    check.write_bytes(path.read_bytes())
    with np.load(check, allow_pickle=True) as npz:
        npz[key]
    assert marker.exists()
    marker.unlink()
    expect_error(path, PINHOLE, f"key {key!r}", "pickled")
    assert not marker.exists()


def test_a_raw_pickle_is_never_loaded(tmp_path: Path) -> None:
    marker = tmp_path / "unpickled"
    path = tmp_path / "scan.npz"
    path.write_bytes(pickle.dumps(_Trap(marker)))
    expect_error(path, PINHOLE, "not an .npz file")
    assert not marker.exists()


def _npz_bytes(compressed: bool) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, range=ranges(PINHOLE), pose=pose())
    return buf.getvalue()


@pytest.mark.parametrize("cut", [0, 1, 10, 100, 200, -100, -22, -1])
def test_truncated_npz(tmp_path: Path, cut: int) -> None:
    data = _npz_bytes(compressed=False)
    path = tmp_path / "scan.npz"
    path.write_bytes(data[:cut])
    expect_error(path, PINHOLE, "not a")


def test_not_npz_files(tmp_path: Path) -> None:
    text = tmp_path / "text.npz"
    text.write_text("range,pose\n1,2\n")
    expect_error(text, PINHOLE, "not an .npz file")
    npy = tmp_path / "plain.npz"
    with npy.open("wb") as fh:
        np.save(fh, ranges(PINHOLE))
    expect_error(npy, PINHOLE, "single .npy array", "'range'")
    empty_zip = tmp_path / "empty.npz"
    with zipfile.ZipFile(empty_zip, "w"):
        pass
    expect_error(empty_zip, PINHOLE, "missing key 'range'")
    folder = tmp_path / "folder.npz"
    folder.mkdir()
    expect_error(folder, PINHOLE, "not a readable .npz file")


def test_corrupted_header_claiming_a_huge_array(tmp_path: Path) -> None:
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f4", "fortran_order": False, "shape": (10**6, 10**6)}
    )
    pose_npy = io.BytesIO()
    np.save(pose_npy, pose())
    path = tmp_path / "scan.npz"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("range.npy", header.getvalue() + bytes(64))
        zf.writestr("pose.npy", pose_npy.getvalue())
    expect_error(path, PINHOLE, "key 'range'", "not a readable array")


@pytest.mark.parametrize("compressed", [False, True], ids=["stored", "deflated"])
def test_damaged_bytes_never_escape_as_raw_errors(tmp_path: Path, compressed: bool) -> None:
    """Flip every byte (and cut every length) of a small scan: read it or raise DatasetError.

    Damage hits zip headers (bad magic, unsupported versions, "encrypted" flags), CRCs,
    deflate streams (zlib errors), and the .npy headers.
    """
    data = _npz_bytes(compressed)
    path = tmp_path / "scan.npz"
    failures = 0
    for offset in range(len(data)):
        damaged = bytearray(data)
        damaged[offset] ^= 0xFF
        path.write_bytes(bytes(damaged))
        try:
            read_scan_file(path, PINHOLE)
        except DatasetError as exc:
            assert str(path) in str(exc)
            failures += 1
    for cut in range(0, len(data), 13):
        path.write_bytes(data[:cut])
        with pytest.raises(DatasetError):
            read_scan_file(path, PINHOLE)
    assert failures > len(data) // 3


# --- malformed dataset folders ----------------------------------------------------------------


def dataset_with_sensor_json(root: Path, text: str | bytes) -> Path:
    write_dataset(root, PINHOLE, [("scan_0000", scan_of(PINHOLE))])
    target = root / "sensor.json"
    if isinstance(text, bytes):
        target.write_bytes(text)
    else:
        target.write_text(text)
    return root


BAD_SENSOR_JSON: dict[str, tuple[str | bytes, tuple[str, ...]]] = {
    "not JSON": ('{"model": "pinhole",', ("not valid JSON",)),
    "empty": ("", ("not valid JSON",)),
    "a list": ("[1, 2]", ("must be a JSON object", "list")),
    "unknown model": (
        json.dumps({**PINHOLE.to_dict(), "model": "kinect"}),
        ("sensor.model", "kinect", "pinhole"),
    ),
    "no model": (
        json.dumps({k: v for k, v in PINHOLE.to_dict().items() if k != "model"}),
        ("sensor.model", "unknown sensor model None"),
    ),
    "model a list": (json.dumps({"model": ["pinhole"]}), ("sensor.model", "unknown sensor model")),
    "missing field": (
        json.dumps({k: v for k, v in PINHOLE.to_dict().items() if k != "cy"}),
        ("sensor.cy", "missing"),
    ),
    "unknown field": (json.dumps({**PINHOLE.to_dict(), "fov": 60}), ("sensor.fov", "unknown")),
    "width a string": (json.dumps({**PINHOLE.to_dict(), "width": "8"}), ("sensor.width",)),
    "negative fx": (json.dumps({**PINHOLE.to_dict(), "fx": -1.0}), ("fx",)),
    "bad convention": (
        json.dumps({**PINHOLE.to_dict(), "range_convention": "radial"}),
        ("sensor.range_convention", "radial"),
    ),
    "not UTF-8": (b"\xff\xfe{}", ("UTF-8",)),
    "deeply nested": ("[" * 100_000, ("not valid JSON",)),
}


@pytest.mark.parametrize("case", sorted(BAD_SENSOR_JSON))
def test_bad_sensor_json(tmp_path: Path, case: str) -> None:
    text, fragments = BAD_SENSOR_JSON[case]
    root = dataset_with_sensor_json(tmp_path / "ds", text)
    with pytest.raises(DatasetError) as info:
        open_dataset(root)
    message = str(info.value)
    assert str(root / "sensor.json") in message
    for fragment in fragments:
        assert fragment in message, message


def test_sensor_json_that_is_a_folder(tmp_path: Path) -> None:
    write_dataset(tmp_path, PINHOLE, [("scan_0000", scan_of(PINHOLE))])
    (tmp_path / "sensor.json").unlink()
    (tmp_path / "sensor.json").mkdir()
    with pytest.raises(DatasetError, match="sensor.json: cannot be read"):
        open_dataset(tmp_path)


def test_folders_without_scans(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="missing: no such dataset folder"):
        open_dataset(tmp_path / "missing")
    (tmp_path / "file").write_text("x")
    with pytest.raises(DatasetError, match="file: not a directory"):
        open_dataset(tmp_path / "file")
    with pytest.raises(DatasetError, match=r"no scans/ folder"):
        open_dataset(tmp_path)
    (tmp_path / "sensor.json").write_text(json.dumps(PINHOLE.to_dict()))
    (tmp_path / "scans").mkdir()
    with pytest.raises(DatasetError, match=r"scans: no \.npz scans"):
        open_dataset(tmp_path)
    (tmp_path / "scans" / "scan_0000.npy").write_bytes(b"")
    (tmp_path / "scans" / "sub.npz").mkdir()
    with pytest.raises(DatasetError, match=r"scans: no \.npz scans"):
        open_dataset(tmp_path)


def test_a_bad_scan_is_reported_when_read(tmp_path: Path) -> None:
    scans = [(f"scan_{k:04d}", scan_of(PINHOLE, k)) for k in range(3)]
    write_dataset(tmp_path, PINHOLE, scans)
    bad = tmp_path / "scans" / "scan_0001.npz"
    bad.write_bytes(bad.read_bytes()[:50])
    read = open_dataset(tmp_path).scans()
    assert next(read)[0] == "scan_0000"
    with pytest.raises(DatasetError, match=r"scan_0001\.npz: not a readable \.npz file"):
        next(read)


# --- grid files -------------------------------------------------------------------------------


def dense(shape: tuple[int, int, int] = (3, 4, 5), h: float = 0.05) -> DenseGrid:
    rng = np.random.default_rng(1)
    logodds = rng.normal(size=shape).astype(np.float32)
    logodds[0, 0, 0] = np.nan
    logodds[1, 2, 3] = np.nan
    first = np.array([-4, 0, 7], np.int64)
    return DenseGrid(logodds=logodds, origin=(first + 0.5) * h, voxel_size=h, first_voxel=first)


def test_grid_round_trip(tmp_path: Path) -> None:
    grid = dense()
    path = write_grid(tmp_path / "out" / "grid.npz", grid)
    assert path == tmp_path / "out" / "grid.npz"
    assert [p.name for p in path.parent.iterdir()] == ["grid.npz"]
    with np.load(path, allow_pickle=False) as npz:
        assert sorted(npz.files) == ["logodds", "origin", "voxel_size"]
        assert npz["logodds"].dtype == np.float32
        assert npz["origin"].dtype == np.float64 and npz["origin"].shape == (3,)
        assert npz["voxel_size"].dtype == np.float64 and npz["voxel_size"].shape == ()
    back = read_grid(path)
    assert np.array_equal(back.logodds.view(np.uint32), grid.logodds.view(np.uint32))
    assert np.array_equal(back.origin, grid.origin)
    assert back.voxel_size == grid.voxel_size
    assert np.array_equal(back.first_voxel, grid.first_voxel)


def grid_arrays(**changes: Any) -> dict[str, Any]:
    grid = dense()
    arrays: dict[str, Any] = {
        "logodds": grid.logodds,
        "origin": grid.origin,
        "voxel_size": np.float64(grid.voxel_size),
    }
    arrays.update(changes)
    return {k: v for k, v in arrays.items() if v is not None}


BAD_GRIDS: dict[str, tuple[dict[str, Any], tuple[str, ...]]] = {
    "no logodds": (grid_arrays(logodds=None), ("missing key 'logodds'",)),
    "no origin": (grid_arrays(origin=None), ("missing key 'origin'",)),
    "no voxel_size": (grid_arrays(voxel_size=None), ("missing key 'voxel_size'",)),
    "logodds 2-D": (grid_arrays(logodds=np.zeros((3, 4), np.float32)), ("logodds:", "3-D")),
    "logodds int": (grid_arrays(logodds=np.zeros((2, 2, 2), np.int64)), ("logodds:", "int64")),
    "origin 2": (grid_arrays(origin=np.zeros(2)), ("origin:", "(2,)")),
    "origin NaN": (grid_arrays(origin=np.array([0.0, np.nan, 0.0])), ("origin:", "finite")),
    "voxel_size array": (grid_arrays(voxel_size=np.ones(3)), ("voxel_size:",)),
    "voxel_size 0": (grid_arrays(voxel_size=np.float64(0.0)), ("voxel_size:", "positive")),
    "voxel_size string": (grid_arrays(voxel_size=np.array("0.1")), ("voxel_size:",)),
    "pickled logodds": (
        grid_arrays(logodds=np.array([None, 1], dtype=object)),
        ("key 'logodds'", "pickled"),
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_GRIDS))
def test_bad_grid_files(tmp_path: Path, case: str) -> None:
    arrays, fragments = BAD_GRIDS[case]
    path = save_npz(tmp_path / "grid.npz", **arrays)
    with pytest.raises(DatasetError) as info:
        read_grid(path)
    message = str(info.value)
    assert str(path) in message
    for fragment in fragments:
        assert fragment in message, message


def test_unreadable_grid_files(tmp_path: Path) -> None:
    path = write_grid(tmp_path / "grid.npz", dense())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="grid.npz: not a readable .npz file"):
        read_grid(path)
    with pytest.raises(DatasetError, match="missing.npz: not a readable .npz file"):
        read_grid(tmp_path / "missing.npz")
