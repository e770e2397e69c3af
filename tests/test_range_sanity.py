"""Physical sanity of range maps (engine/scans.py, docs/input-safety.md).

A finite range beyond the sensor's ``max_range`` is not a surface: it becomes NaN and is
counted in ``Scan.far_ranges``. A map whose measured ranges mostly lie there, or that looks
like millimetres, is refused with the evidence (:class:`FarRangesError`): 422 from the
service, exit status 2 from the command line, unless accepted explicitly. Real data keep
passing: the synthetic datasets (noise and spikes included) and the Stanford bunny.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rangefuse.engine import PinholeSensor, Scan, sensor_from_dict
from rangefuse.engine.errors import FarRangesError, InvalidScanError
from rangefuse.engine.scans import check_far_ranges
from rangefuse.engine.synth import make_dataset
from rangefuse.storage import DatasetError, open_dataset, read_scan_file, write_dataset
from rangefuse.storage.importers import encode_png, read_source

from tests.hostile_files import client_of, new_scene, npy_bytes
from tests.test_bunny import DATA as BUNNY
from tests.test_cli import run_main
from tests.test_service import serving

CAMERA = PinholeSensor(
    width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5, range_convention="z", max_range=10.0
)


def wall(depth_m: float = 3.0) -> np.ndarray:
    """A wall at ``depth_m`` with small ripples, a no-return corner and an invalid pixel."""
    v, u = np.mgrid[0:48, 0:64]
    out = (depth_m + 0.01 * np.sin(u / 3.0) + 0.01 * np.cos(v / 5.0)).astype(np.float32)
    out[:4, :4] = np.inf
    out[10, 10] = np.nan
    return out


def far_map(share: float) -> np.ndarray:
    """``wall()`` with the first ``share`` of its measured pixels at 12 to 15 m (max_range 10)."""
    out = wall()
    flat = out.reshape(-1)
    measured = np.flatnonzero(np.isfinite(flat))
    take = measured[: int(round(share * len(measured)))]
    flat[take] = np.linspace(12.0, 15.0, len(take))
    return out


def millimetres() -> np.ndarray:
    return np.where(np.isfinite(wall()), np.round(wall() * 1000.0), wall())


# --- the engine --------------------------------------------------------------------------------


def test_far_ranges_become_invalid_and_are_counted() -> None:
    rng = far_map(0.1)
    far = np.isfinite(rng) & (rng > 10.0)
    scan = Scan(rng, np.eye(4), CAMERA)
    assert scan.far_ranges == int(far.sum()) == 306
    assert np.isnan(scan.range_m[far]).all()
    assert np.isposinf(scan.range_m[:4, :4]).all()  # no return is not a far range
    assert np.array_equal(scan.range_m[~far], rng[~far], equal_nan=True)
    edge = wall()
    edge[20, :] = np.float32(10.0)  # exactly at max_range: a surface
    assert Scan(edge, np.eye(4), CAMERA).far_ranges == 0
    huge = wall().astype(np.float64)
    huge[30, 30] = 1e300  # past float32: far, not "no return"
    scan = Scan(huge, np.eye(4), CAMERA)
    assert scan.far_ranges == 1 and np.isnan(scan.range_m[30, 30])


def test_less_than_half_far_is_accepted_more_is_refused_with_the_evidence() -> None:
    assert Scan(far_map(0.45), np.eye(4), CAMERA).far_ranges == 1375
    with pytest.raises(FarRangesError) as info:
        Scan(far_map(0.6), np.eye(4), CAMERA)
    assert str(info.value) == (
        "range: 60% of the 3,055 measured ranges lie beyond the sensor's max_range of 10 m "
        "(median 12.5 m, largest 15 m): give the sensor's real max_range, or check the units "
        "of the ranges"
    )
    assert isinstance(info.value, InvalidScanError) and info.value.field == "range"


def test_millimetres_are_refused_however_large_max_range_is() -> None:
    with pytest.raises(FarRangesError) as info:
        Scan(millimetres(), np.eye(4), CAMERA)
    assert str(info.value).startswith("range: 100% of the 3,055 measured ranges lie beyond")
    assert "(median 3,000 m, largest 3,020 m): depth in millimetres?" in str(info.value)
    generous = sensor_from_dict({**CAMERA.to_dict(), "max_range": 1e5})
    with pytest.raises(FarRangesError) as info:
        Scan(millimetres(), np.eye(4), generous)
    assert str(info.value) == (
        "range: the measured ranges look like millimetres, not metres: 100% of them are "
        "whole numbers and their median is 3,000 m (max_range 100000 m); convert them to "
        "metres (depth_scale 0.001 for a PNG)"
    )
    # a long-range scanner with a generous max_range: fractional ranges pass
    assert Scan(wall(300.0), np.eye(4), generous).far_ranges == 0


def test_accept_far_ranges_overrides_the_refusal() -> None:
    scan = Scan(far_map(0.9), np.eye(4), CAMERA, accept_far_ranges=True)
    assert scan.far_ranges == 2750 and np.isfinite(scan.range_m).sum() == 3055 - 2750
    generous = sensor_from_dict({**CAMERA.to_dict(), "max_range": 1e5})
    kept = Scan(millimetres(), np.eye(4), generous, accept_far_ranges=True)
    assert kept.far_ranges == 0 and kept.range_m[np.isfinite(kept.range_m)].max() == 3020.0
    far, count = check_far_ranges(far_map(0.9), 10.0, accept=True)
    assert count == 2750 and far.sum() == count


def test_synthetic_datasets_with_noise_are_accepted() -> None:
    """Their returns reach max_range (spikes up to it, no return as +inf) but none lies
    beyond it: no scan is refused, nothing is set invalid."""
    for name, views in (("street", 3), ("room", 4), ("object", 4)):
        for noise in ("none", "gaussian:0.05,spikes:0.02,dropouts:0.05"):
            data = make_dataset(name, views=views, noise=_noise(noise), seed=1)
            for scan_name, scan in data.scans:
                assert scan.far_ranges == 0, (name, noise, scan_name)


def _noise(text: str):
    from rangefuse.engine.synth import parse_noise

    return parse_noise(text)


def test_the_bunny_is_accepted() -> None:
    if not BUNNY.exists():
        pytest.skip(f"the Stanford bunny is not in {BUNNY}")
    result = read_source("stanford", BUNNY / "scans" / "bun.conf")
    assert len(result.items) == 10
    assert all(scan.far_ranges == 0 for _, scan in result.items)


# --- files and the command line ------------------------------------------------------------------


def test_dataset_files_are_refused_naming_the_file(tmp_path: Path) -> None:
    root = write_dataset(
        tmp_path / "ds",
        CAMERA,
        [("near", Scan(wall(), np.eye(4), CAMERA)),
         ("far", Scan(far_map(0.6), np.eye(4), CAMERA, accept_far_ranges=True))],
    )  # fmt: skip
    # what was written keeps no far range: overwrite it with the raw map
    np.savez(root / "scans" / "far.npz", range=far_map(0.6), pose=np.eye(4))
    path = root / "scans" / "far.npz"
    with pytest.raises(FarRangesError, match=rf"^{path}: range: 60% of the 3,055 measured"):
        read_scan_file(path, CAMERA)
    assert read_scan_file(path, CAMERA, accept_far_ranges=True).far_ranges == 1833
    names = [n for n, _ in open_dataset(root, accept_far_ranges=True).scans()]
    assert names == ["far", "near"]
    with pytest.raises(FarRangesError):
        list(open_dataset(root).scans())
    assert not isinstance(FarRangesError("range", "x"), DatasetError)


def test_cli_refuses_in_one_line_and_the_option_overrides(tmp_path: Path, capsys) -> None:
    root = write_dataset(tmp_path / "ds", CAMERA, [("a", Scan(wall(), np.eye(4), CAMERA))])
    np.savez(root / "scans" / "b.npz", range=far_map(0.6), pose=np.eye(4))
    fuse = ["fuse", root, "--voxel-size", "0.1", "--quiet"]
    code, out, err = run_main(fuse, capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"rangefuse fuse: error: {root / 'scans' / 'b.npz'}: range: 60% of")
    assert err.endswith("; to fuse it anyway, pass --accept-far-ranges\n")
    assert len(err.splitlines()) == 1
    code, out, err = run_main([*fuse, "--accept-far-ranges"], capsys)
    assert code == 0, err
    assert "note: b: (1,833 ranges beyond the sensor's max_range of 10 m set invalid)" in err
    store = tmp_path / "store"
    code, _, err = run_main([*fuse[:2], "--voxel-size", "0.1", "--store", store,
                             "--accept-far-ranges", "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    extra = tmp_path / "c.npz"
    np.savez(extra, range=far_map(0.7), pose=np.eye(4))
    add = ["add", store, extra, "--sensor", root / "sensor.json", "--quiet"]
    code, _, err = run_main(add, capsys)
    assert code == 2 and err.endswith("; to fuse it anyway, pass --accept-far-ranges\n")
    code, out, err = run_main([*add, "--accept-far-ranges"], capsys)
    assert code == 0, err
    assert "stored c (2,138 ranges beyond the sensor's max_range of 10 m set invalid)" in out


def test_cli_accept_far_ranges_is_not_for_importers(tmp_path: Path, capsys) -> None:
    code, _, err = run_main(["fuse", tmp_path, "--format", "tum", "--voxel-size", "0.1",
                             "--accept-far-ranges"], capsys)  # fmt: skip
    assert code == 2
    assert err == (
        "rangefuse fuse: error: --accept-far-ranges applies to dataset folders; with --format, "
        "give the source's --depth-scale or --max-range instead\n"
    )


# --- the service ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    yield from serving(tmp_path_factory.mktemp("data"))


def _meta(**extra) -> str:
    return json.dumps({"pose": np.eye(4).tolist(), "sensor": CAMERA.to_dict(), **extra})


def test_service_refuses_far_ranges_with_422_and_accepts_them_when_asked(server) -> None:
    png_mm = encode_png(np.nan_to_num(millimetres(), nan=0, posinf=0).astype(np.uint16))
    cases = {
        "npy mostly beyond max_range": (npy_bytes(far_map(0.6)), _meta(), "60% of the 3,055"),
        "PNG in millimetres, depth_scale 1": (
            png_mm,
            _meta(depth_scale=1),
            "100% of the 3,055 measured ranges lie beyond the sensor's max_range of 10 m "
            "(median 3,000 m, largest 3,020 m): depth in millimetres?",
        ),
    }
    with client_of(server) as client:
        sid = new_scene(client)
        for name, (data, meta, words) in cases.items():
            r = client.post(
                f"/v1/scenes/{sid}/scans", files={"range": ("r", data), "meta": (None, meta)}
            )
            assert r.status_code == 422, (name, r.text)
            detail = r.json()["detail"]
            assert detail.startswith("range: ") and words in detail, (name, detail)
            assert detail.endswith("; to fuse it anyway, send meta.accept_far_ranges: true")
            assert client.get(f"/v1/scenes/{sid}/scans").json() == [], name
            assert client.get("/healthz").status_code == 200
        data, meta, _ = cases["npy mostly beyond max_range"]
        r = client.post(
            f"/v1/scenes/{sid}/scans",
            files={"range": ("r", data), "meta": (None, _meta(accept_far_ranges=True))},
        )
        assert r.status_code == 202, r.text
        assert r.json()["scan"]["far_ranges"] == 1833  # 60 % of 3,055, now invalid
        assert len(client.get(f"/v1/scenes/{sid}/scans").json()) == 1
        openapi = client.get("/openapi.json").json()
        body = openapi["paths"]["/v1/scenes/{scene_id}/scans"]["post"]["requestBody"]
        schema = body["content"]["multipart/form-data"]["schema"]
        assert "accept_far_ranges" in schema["properties"]["meta"]["description"]
