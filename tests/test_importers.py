"""Importers (storage/importers) and ``rangefuse import`` / ``fuse --format``.

Every fixture is generated here: analytic scenes (tests/formats.py) rendered and written in
each format, then imported back and compared with what was rendered: range maps within the
format's quantisation, poses to the precision of the text. The sanity checks must fire on
deliberately broken fixtures (depth scale, range convention, inverted poses, non-orthonormal
rotations) and stay silent on the good ones.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import pytest
from rangefuse.engine import PinholeSensor, Scan
from rangefuse.engine.errors import FarRangesError
from rangefuse.storage import open_dataset
from rangefuse.storage.importers import (
    ImportOptions,
    PoseFixes,
    SourceError,
    estimate_beam_elevations,
    read_png,
    read_source,
    snap_rotation,
    write_png,
)
from rangefuse.storage.importers.stanford import linescan_image

from tests import formats
from tests.test_cli import assert_same_grid, run_main

INTRINSICS = (formats.CAMERA.fx, formats.CAMERA.fy, formats.CAMERA.cx, formats.CAMERA.cy)
FRAMES = 6


@pytest.fixture(scope="module")
def room() -> object:
    return formats.room_scene()


@pytest.fixture(scope="module")
def camera_scans(room) -> list[Scan]:
    return formats.render_scans(room, formats.CAMERA, formats.camera_poses(FRAMES))


@pytest.fixture(scope="module")
def lidar_scans(room) -> list[Scan]:
    return formats.render_scans(room, formats.LIDAR, formats.lidar_poses(5))


@pytest.fixture(scope="module")
def seven_scenes(tmp_path_factory: pytest.TempPathFactory, camera_scans) -> Path:
    root = tmp_path_factory.mktemp("7scenes") / "seq-01"
    formats.write_7scenes(root, camera_scans)
    return root


def assert_ranges_within(imported: list, rendered: list[Scan], tol_m: float) -> None:
    """Same NaN pattern (non-finite rendered pixels are invalid after import), values within
    ``tol_m``."""
    assert len(imported) == len(rendered)
    for (_, got), want in zip(imported, rendered, strict=True):
        finite = np.isfinite(want.range_m)
        assert np.array_equal(np.isfinite(got.range_m), finite)
        assert np.max(np.abs(got.range_m[finite] - want.range_m[finite])) <= tol_m


def assert_poses(imported: list, poses: list[np.ndarray], tol: float) -> None:
    for (_, got), want in zip(imported, poses, strict=True):
        np.testing.assert_allclose(got.T_W_S, want, atol=tol)


# --- PNG --------------------------------------------------------------------------------------


@pytest.mark.parametrize("filter", ["none", "sub", "up", "average", "paeth"])
@pytest.mark.parametrize("dtype", [np.uint16, np.uint8])
def test_png_round_trip_every_filter(tmp_path: Path, filter: str, dtype: type) -> None:
    rng = np.random.default_rng(1)
    image = rng.integers(0, np.iinfo(dtype).max, (23, 37), endpoint=True).astype(dtype)
    write_png(tmp_path / "a.png", image, filter)
    back = read_png(tmp_path / "a.png")
    assert back.dtype == dtype and np.array_equal(back, image)


def test_png_agrees_with_pillow(tmp_path: Path) -> None:
    Image = pytest.importorskip("PIL.Image")
    depth = np.random.default_rng(2).integers(0, 9000, (48, 64)).astype(np.uint16)
    Image.fromarray(depth).save(tmp_path / "pil.png", optimize=True)  # Pillow's own filters
    assert np.array_equal(read_png(tmp_path / "pil.png"), depth)
    write_png(tmp_path / "ours.png", depth)
    assert np.array_equal(np.asarray(Image.open(tmp_path / "ours.png")), depth)


def test_png_refuses_what_it_cannot_read(tmp_path: Path) -> None:
    good = tmp_path / "good.png"
    write_png(good, np.arange(12, dtype=np.uint16).reshape(3, 4))
    blob = good.read_bytes()
    cases = {
        "text.png": (b"not a png", "not a PNG file"),
        "cut.png": (blob[:-20], "truncated PNG"),
        "crc.png": (blob[:40] + bytes([blob[40] ^ 1]) + blob[41:], "CRC mismatch"),
    }
    # an RGB image: colour type 2 in the header (with a valid CRC)
    ihdr = bytearray(blob[12:29])
    ihdr[4 + 9] = 2
    rgb = blob[:8] + blob[8:12] + bytes(ihdr) + zlib.crc32(bytes(ihdr)).to_bytes(4, "big")
    cases["rgb.png"] = (rgb + blob[33:], "greyscale PNG of 8 or 16 bits")
    for name, (data, message) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(SourceError, match=message) as info:
            read_png(tmp_path / name)
        assert name in str(info.value)


# --- poses ------------------------------------------------------------------------------------


def test_snap_rotation() -> None:
    R = formats.look_at_cv((1.0, 2.0, 0.5))[:3, :3]
    fixes = PoseFixes()
    assert np.allclose(snap_rotation(R + 1e-9, "f.txt", 3, fixes), R, atol=1e-8)
    assert fixes.warnings() == []  # rounding below the engine's tolerance: silent
    slightly = R + np.array([[2e-4, 0, 0], [0, -1e-4, 0], [0, 0, 0]])
    snapped = snap_rotation(slightly, "f.txt", 7, fixes)
    assert np.allclose(snapped.T @ snapped, np.eye(3), atol=1e-12) and np.linalg.det(snapped) > 0
    assert np.abs(snapped - R).max() < 3e-4
    (warning,) = fixes.warnings()
    assert warning.startswith("f.txt: 1 rotations not orthonormal") and "line 7" in warning
    with pytest.raises(SourceError, match=r"f.txt line 9: not a rotation"):
        snap_rotation(1.1 * R, "f.txt", 9, fixes)
    with pytest.raises(SourceError, match=r"f.txt line 4: a reflection"):
        snap_rotation(R @ np.diag([1.0, 1.0, -1.0]), "f.txt", 4, fixes)


# --- 7-Scenes ---------------------------------------------------------------------------------


def test_7scenes_round_trip(seven_scenes: Path, camera_scans: list[Scan]) -> None:
    result = read_source("7scenes", seven_scenes)
    assert result.warnings == []
    assert [name for name, _ in result.items] == [f"frame-{k:06d}" for k in range(FRAMES)]
    sensor = result.sensor
    assert isinstance(sensor, PinholeSensor) and sensor.range_convention == "z"
    assert (sensor.width, sensor.height, sensor.fx, sensor.fy, sensor.cx, sensor.cy) == (
        80, 64, *INTRINSICS,
    )  # fmt: skip
    assert_ranges_within(result.items, camera_scans, 0.0005 + 1e-6)  # millimetres
    assert_poses(result.items, [s.T_W_S for s in camera_scans], 1e-12)


def test_7scenes_options(seven_scenes: Path, camera_scans: list[Scan]) -> None:
    result = read_source(
        "7scenes", seven_scenes, ImportOptions(intrinsics=(70.0, 71.0, 40.0, 30.0), every=2)
    )
    assert [name for name, _ in result.items] == ["frame-000000", "frame-000002", "frame-000004"]
    assert (result.sensor.fx, result.sensor.fy) == (70.0, 71.0)


def test_7scenes_depth_scale_off_by_1000(seven_scenes: Path) -> None:
    # millimetres read as metres: the engine's range sanity check refuses the scans (the
    # importer's max_range grows with the data, so the ranges are whole numbers near 1000 m)
    with pytest.raises(FarRangesError, match="look like millimetres"):
        read_source("7scenes", seven_scenes, ImportOptions(depth_scale_m=1.0))


def test_7scenes_inverted_poses(tmp_path: Path, camera_scans: list[Scan]) -> None:
    poses = [s.T_W_S for s in camera_scans]
    formats.write_7scenes(tmp_path, camera_scans, poses=[np.linalg.inv(T) for T in poses])
    (warning,) = read_source("7scenes", tmp_path).warnings
    assert "poses look inverted" in warning and "--invert-poses" in warning
    fixed = read_source("7scenes", tmp_path, ImportOptions(invert_poses=True))
    assert fixed.warnings == []
    assert_poses(fixed.items, poses, 1e-9)


def test_7scenes_ray_range_read_as_z_depth(tmp_path: Path, room) -> None:
    ray_camera = PinholeSensor(**{**_fields(formats.CAMERA), "range_convention": "ray"})
    scans = formats.render_scans(room, ray_camera, formats.camera_poses(FRAMES))
    formats.write_7scenes(tmp_path, scans)
    (warning,) = read_source("7scenes", tmp_path).warnings
    assert "look like ray range" in warning and "--range-convention ray" in warning
    fixed = read_source("7scenes", tmp_path, ImportOptions(range_convention="ray"))
    assert fixed.warnings == [] and fixed.sensor.range_convention == "ray"


def _fields(sensor: PinholeSensor) -> dict:
    data = sensor.to_dict()
    data.pop("model")
    return data


def test_7scenes_rotations_snapped_or_refused(tmp_path: Path, camera_scans: list[Scan]) -> None:
    poses = [s.T_W_S.copy() for s in camera_scans[:2]]
    poses[1][:3, :3] *= 1.0 + 5e-5  # rounding in a text file: snapped, with a warning
    formats.write_7scenes(tmp_path, camera_scans[:2], poses=poses)
    result = read_source("7scenes", tmp_path, ImportOptions(checks=False))
    (warning,) = result.warnings
    assert "frame-000001.pose.txt: 1 rotations not orthonormal" in warning
    np.testing.assert_allclose(result.items[1][1].T_W_S, camera_scans[1].T_W_S, atol=1e-9)
    poses[1][:3, :3] *= 1.05  # grossly wrong: refused, naming the file
    formats.write_7scenes(tmp_path, camera_scans[:2], poses=poses)
    with pytest.raises(SourceError, match=r"frame-000001\.pose\.txt line 1: not a rotation"):
        read_source("7scenes", tmp_path)


def test_7scenes_errors(tmp_path: Path, camera_scans: list[Scan]) -> None:
    formats.write_7scenes(tmp_path, camera_scans[:2])
    (tmp_path / "camera-intrinsics.txt").unlink()
    with pytest.raises(SourceError, match=r"camera-intrinsics.txt: missing; give --intrinsics"):
        read_source("7scenes", tmp_path)
    assert len(read_source("7scenes", tmp_path, ImportOptions(intrinsics=INTRINSICS))) == 2
    (tmp_path / "frame-000001.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1\n0 0 0 1\n")
    with pytest.raises(SourceError, match=r"frame-000001.pose.txt: rows of different lengths"):
        read_source("7scenes", tmp_path, ImportOptions(intrinsics=INTRINSICS))
    with pytest.raises(SourceError, match="no frame-"):
        read_source("7scenes", tmp_path / "..")


# --- TUM --------------------------------------------------------------------------------------


def test_tum_round_trip_and_time_matching(tmp_path: Path, camera_scans: list[Scan]) -> None:
    stamps, _ = formats.tum_stamps(FRAMES)
    formats.write_tum(tmp_path, camera_scans, stamps)
    options = ImportOptions(intrinsics=INTRINSICS)
    result = read_source("tum", tmp_path, options)
    assert result.warnings == []
    assert [name for name, _ in result.items] == [f"{s:.6f}" for s in stamps]
    assert_ranges_within(result.items, camera_scans, 0.0001 + 1e-6)  # 1/5000 m units
    assert_poses(result.items, [s.T_W_S for s in camera_scans], 1e-8)
    # drop the ground truth near the third frame: that frame has no pose within 20 ms
    gt = (tmp_path / "groundtruth.txt").read_text().splitlines()
    kept = [ln for ln in gt if ln.startswith("#") or abs(float(ln.split()[0]) - stamps[2]) > 0.03]
    (tmp_path / "groundtruth.txt").write_text("\n".join(kept) + "\n")
    result = read_source("tum", tmp_path, options)
    assert len(result) == FRAMES - 1
    (warning,) = result.warnings
    assert "1 of 6 depth frames have no pose" in warning and "within 0.02 s" in warning
    assert len(read_source("tum", tmp_path, ImportOptions(tolerance_s=0.05))) == FRAMES


def test_tum_bad_lines_name_the_line(tmp_path: Path, camera_scans: list[Scan]) -> None:
    stamps, _ = formats.tum_stamps(2)
    formats.write_tum(tmp_path, camera_scans[:2], stamps)
    gt = tmp_path / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    lines[4] = " ".join(lines[4].split()[:6])
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(SourceError, match=r"groundtruth.txt line 5: expected 8 numbers"):
        read_source("tum", tmp_path)
    lines[4] = "1305031102.0 0 0 0 0 0 0 1.5"  # a quaternion of norm 1.5
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(SourceError, match=r"line 5: quaternion .* has norm 1.5"):
        read_source("tum", tmp_path)


# --- Redwood ----------------------------------------------------------------------------------


def test_redwood_round_trip(tmp_path: Path, camera_scans: list[Scan]) -> None:
    formats.write_redwood(tmp_path, camera_scans)
    result = read_source("redwood", tmp_path, ImportOptions(intrinsics=INTRINSICS))
    assert result.warnings == []
    assert_ranges_within(result.items, camera_scans, 0.0005 + 1e-6)
    assert_poses(result.items, [s.T_W_S for s in camera_scans], 1e-10)
    (tmp_path / "depth" / "000005.png").unlink()
    with pytest.raises(SourceError, match=r"trajectory.log: 6 poses for 5 depth images"):
        read_source("redwood", tmp_path)


# --- KITTI ------------------------------------------------------------------------------------


def test_kitti_round_trip_with_estimated_beams(tmp_path: Path, lidar_scans: list[Scan]) -> None:
    formats.write_kitti(tmp_path, lidar_scans)
    result = read_source("kitti", tmp_path, ImportOptions(beams=16, columns=360))
    assert result.warnings == []
    sensor = result.sensor
    assert sensor.model == "spherical" and sensor.wrap and sensor.width == 360
    # the uneven beam table is found from the points alone (float32 points: 1e-7 rad)
    np.testing.assert_allclose(sensor.elevations, formats.LIDAR.elevations, atol=1e-6)
    assert_ranges_within(result.items, lidar_scans, 1e-5)
    assert_poses(result.items, [s.T_W_S for s in lidar_scans], 1e-9)


def test_kitti_inverted_poses(tmp_path: Path, lidar_scans: list[Scan]) -> None:
    cam = [s.T_W_S @ np.linalg.inv(formats.TR_VELO_TO_CAM) for s in lidar_scans]
    formats.write_kitti(tmp_path, lidar_scans, cam_poses=[np.linalg.inv(T) for T in cam])
    options = ImportOptions(beams=16, columns=360)
    (warning,) = read_source("kitti", tmp_path, options).warnings
    assert "poses look inverted" in warning
    fixed = read_source("kitti", tmp_path, ImportOptions(beams=16, columns=360, invert_poses=True))
    assert fixed.warnings == []
    assert_poses(fixed.items, [s.T_W_S for s in lidar_scans], 1e-9)


def test_kitti_errors(tmp_path: Path, lidar_scans: list[Scan]) -> None:
    formats.write_kitti(tmp_path, lidar_scans[:2])
    with pytest.raises(SourceError, match="fewer than 64 groups; is --beams right"):
        read_source("kitti", tmp_path)  # 16 beams, not the default 64
    (tmp_path / "velodyne" / "000001.bin").write_bytes(b"\0" * 18)
    with pytest.raises(SourceError, match=r"000001.bin: 18 bytes is not a whole number"):
        read_source("kitti", tmp_path, ImportOptions(beams=16, columns=360))
    (tmp_path / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(SourceError, match=r"calib.txt: no 'Tr:' line"):
        read_source("kitti", tmp_path)


def test_beam_estimate_with_jitter_and_strays() -> None:
    rng = np.random.default_rng(3)
    true = np.radians(np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.33, 32)]))
    counts = rng.integers(300, 3000, 64)  # the upper beams see less
    el = np.concatenate(
        [t + rng.normal(0, np.radians(0.02), n) for t, n in zip(true, counts, strict=True)]
    )
    el = np.concatenate([el, rng.uniform(true[-1], true[0], 5)])  # a few strays between beams
    found = estimate_beam_elevations(el, 64, "sweeps")
    assert np.max(np.abs(found - true)) < np.radians(0.005)
    with pytest.raises(SourceError, match="cannot separate 65 beams"):
        estimate_beam_elevations(el, 65, "sweeps")


# --- Stanford ---------------------------------------------------------------------------------


def _back_projection_rms(scan: Scan, points_W: np.ndarray) -> float:
    """RMS difference between each true sample's radial range and the image's range there."""
    from rangefuse.storage.importers.checks import _bilinear

    T = np.linalg.inv(scan.T_W_S)
    p_S = points_W @ T[:3, :3].T + T[:3, 3]
    u, v, d = scan.sensor.project(p_S)
    err = d - _bilinear(scan, u, v)
    covered = np.isfinite(err)
    assert covered.mean() > 0.7  # samples at silhouettes and occlusion edges have no quad
    return float(np.sqrt(np.mean(err[covered] ** 2)))


@pytest.mark.parametrize("binary, descending", [(False, False), (True, True)])
def test_stanford_round_trip(tmp_path: Path, binary: bool, descending: bool) -> None:
    scene = formats.stanford_scene()
    poses = formats.stanford_poses()
    conf = formats.write_stanford(tmp_path, poses, scene, binary=binary, descending=descending)
    result = read_source("stanford", conf)
    assert result.warnings == []
    assert [name for name, _ in result.items] == [f"view{k}" for k in range(len(poses))]
    for (_, scan), T_W_scan, T_scan_S in zip(result.items, poses, result.extrinsics, strict=True):
        s = scan.sensor
        assert s.model == "cylindrical" and s.axial == "linear" and s.range_convention == "radial"
        assert s.height == 2 * formats.COLS  # one image row per half pitch: the interlace
        assert s.fy == pytest.approx(2.0 / formats.PITCH)
        assert (s.az_max - s.az_min) / (s.width - 1) == pytest.approx(0.0015, rel=0.01)
        np.testing.assert_allclose(T_scan_S[:3, 3], (0.0, *formats.AXIS_YZ))
        np.testing.assert_allclose(scan.T_W_S @ np.linalg.inv(T_scan_S), T_W_scan, atol=1e-9)
        # every pixel is a sample or lies between two: on the true surface but at edges
        off = np.abs(scene.signed_distance(scan.points_W()))
        assert np.median(off) < 1e-5 and np.percentile(off, 95) < 1e-4
        # and the image reproduces the samples (float32 PLY coordinates)
        points, _, _ = formats.linescan_grid(scene, T_W_scan, descending=descending)
        points_W = points @ T_W_scan[:3, :3].T + T_W_scan[:3, 3]
        assert _back_projection_rms(scan, points_W) < 0.02 * formats.PITCH


def test_stanford_grid_without_interlace_and_bad_grids(tmp_path: Path) -> None:
    scene = formats.stanford_scene()
    conf = formats.write_stanford(tmp_path, formats.stanford_poses()[:2], scene, interlaced=False)
    result = read_source("stanford", conf)
    assert result.sensor.height == formats.COLS and result.warnings == []
    points, rows, cols = formats.linescan_grid(scene, np.eye(4))
    bent = points.copy()
    bent[:, 0] += 1e-4 * rows  # x no longer a function of the column
    with pytest.raises(SourceError, match="grid.ply: x does not step linearly"):
        linescan_image(
            bent, rows, cols, formats.ROWS, formats.COLS, formats.AXIS_YZ, 0.004, "grid.ply"
        )
    with pytest.raises(SourceError, match="wrong axis"):
        linescan_image(
            points, rows, cols, formats.ROWS, formats.COLS, (0.0, -2.0), 0.004, "grid.ply"
        )


def test_stanford_conf_errors_and_inverted_poses(tmp_path: Path) -> None:
    poses = formats.stanford_poses()
    conf = formats.write_stanford(
        tmp_path, poses, formats.stanford_scene(), conf_poses=[np.linalg.inv(T) for T in poses]
    )
    (warning,) = read_source("stanford", conf).warnings
    assert "poses look inverted" in warning
    text = conf.read_text()
    conf.write_text(text + "mesh_thing view0.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(SourceError, match=r"scans.conf line 8: unknown keyword 'mesh_thing'"):
        read_source("stanford", tmp_path)
    conf.write_text(text.replace("view1.ply", "missing.ply"))
    with pytest.raises(SourceError, match=r"missing.ply: no such file"):
        read_source("stanford", conf)


# --- command line -----------------------------------------------------------------------------


def test_cli_import_writes_a_dataset(
    tmp_path: Path, seven_scenes: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dst = tmp_path / "out" / "ds"
    code, out, err = run_main(["import", "7scenes", seven_scenes, dst], capsys)
    assert code == 0, err
    assert f"wrote {FRAMES} pinhole scans (1 sensor) to {dst}" in out
    dataset = open_dataset(dst)
    imported = read_source("7scenes", seven_scenes)
    assert dataset.names == [name for name, _ in imported.items]
    assert dataset.sensor == imported.sensor
    for (_, a), (_, b) in zip(dataset.scans(), imported.items, strict=True):
        assert np.array_equal(a.range_m, b.range_m, equal_nan=True)
        assert np.array_equal(a.T_W_S, b.T_W_S)
    assert sorted(p.name for p in dst.parent.iterdir()) == ["ds"]  # no temporary folder
    code, _, err = run_main(["import", "7scenes", seven_scenes, dst], capsys)
    assert code == 2 and f"DST {dst}: already exists and is not an empty folder" in err


def test_cli_import_stanford_keeps_per_scan_sensors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    conf = formats.write_stanford(
        tmp_path / "src", formats.stanford_poses()[:3], formats.stanford_scene()
    )
    code, out, err = run_main(["import", "stanford", conf, tmp_path / "ds"], capsys)
    assert code == 0, err
    assert "wrote 3 cylindrical scans (3 sensors)" in out
    sensors = [scan.sensor for _, scan in open_dataset(tmp_path / "ds").scans()]
    assert sensors == [scan.sensor for _, scan in read_source("stanford", conf).items]


def test_cli_import_prints_warnings_and_fails_cleanly(
    tmp_path: Path, seven_scenes: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = run_main(
        ["import", "7scenes", seven_scenes, tmp_path / "km", "--depth-scale", "0.000001"], capsys
    )
    assert code == 0
    assert "rangefuse import: warning: the median measured range" in err
    # millimetres read as metres: refused by the engine's range sanity check, one line
    code, _, err = run_main(
        ["import", "7scenes", seven_scenes, tmp_path / "mm", "--depth-scale", "1"], capsys
    )
    assert code == 2 and not (tmp_path / "mm").exists()
    assert err.startswith("rangefuse import: error: range: the measured ranges look like milli")
    assert len(err.strip().splitlines()) == 1
    broken = tmp_path / "broken"
    broken.mkdir()
    for p in seven_scenes.iterdir():
        (broken / p.name).write_bytes(p.read_bytes())
    (broken / "frame-000003.depth.png").write_bytes(b"garbage")
    code, _, err = run_main(["import", "7scenes", broken, tmp_path / "dst"], capsys)
    assert code == 2
    assert "rangefuse import: error:" in err and "frame-000003.depth.png: not a PNG file" in err
    assert "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken", "km"]  # nothing half-written
    code, _, err = run_main(["import", "tum", tmp_path / "nowhere", tmp_path / "dst"], capsys)
    assert code == 2 and "nowhere: no such folder" in err


def test_cli_fuse_format_equals_fusing_the_import(
    tmp_path: Path, seven_scenes: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from rangefuse.storage import read_grid

    code, _, err = run_main(["import", "7scenes", seven_scenes, tmp_path / "ds"], capsys)
    assert code == 0, err
    common = ["--voxel-size", "0.1", "--quiet", "--bounds", -3, -2.5, 0, 3, 2.5, 2.8]
    code, _, err = run_main(
        ["fuse", tmp_path / "ds", *common, "--grid-out", tmp_path / "a.npz"], capsys
    )
    assert code == 0, err
    code, out, err = run_main(
        ["fuse", seven_scenes, "--format", "7scenes", *common, "--grid-out", tmp_path / "b.npz"],
        capsys,
    )
    assert code == 0, err
    assert f"fused {FRAMES} scans" in out
    assert_same_grid(read_grid(tmp_path / "a.npz"), read_grid(tmp_path / "b.npz"))
    code, _, err = run_main(
        ["fuse", seven_scenes, "--format", "7scenes", *common, "--store", tmp_path / "st"], capsys
    )
    assert code == 2 and "--format with --store" in err and not (tmp_path / "st").exists()


def test_cli_source_option_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_main(["import", "lidar", tmp_path, tmp_path / "x"], capsys)
    assert code == 2 and "invalid choice: 'lidar'" in err
    code, _, err = run_main(["import", "tum", tmp_path, tmp_path / "x", "--every", "0"], capsys)
    assert code == 2 and "--every: must be at least 1" in err
