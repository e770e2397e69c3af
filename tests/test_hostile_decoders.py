"""Hostile uploads: decompression bombs, lying headers and malformed metadata.

Every case must end in :class:`service.uploads.UploadError` (400) with a message that names
the part and the problem, before anything large is allocated: the bombs are valid files
whose headers declare gigabytes (a 7 MB PNG of 60000 x 60000 pixels, a 6 MB ``.npz`` whose
``range.npy`` declares 40000 x 40000 floats), checked with tracemalloc here and with the
real service's peak RSS at the end. A seeded fuzz loop mutates valid files of each format
and valid metadata and asserts that nothing else escapes (``RANGEFUSE_FUZZ_CASES`` runs more
cases than the few seconds' worth a test run does). See ``docs/input-safety.md``.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import random
import struct
import tracemalloc
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rangefuse.engine import PinholeSensor, SphericalSensor
from rangefuse.engine.errors import FarRangesError
from rangefuse.service.uploads import UploadError, decode_scan
from rangefuse.storage import DatasetError, read_scan_file
from rangefuse.storage.importers import SourceError, decode_png, encode_png, read_png
from rangefuse.storage.importers._ply import read_ply

from tests.hostile_files import (
    Pinger,
    client_of,
    crc32_zeros,
    deflate_zeros,
    garbled_meta,
    mutate,
    new_scene,
    npy_bytes,
    npy_header_only,
    npz_bomb,
    npz_bytes,
    png_bomb,
    rss_kib,
    tiff_bytes,
    tiff_with,
    zip_archive,
)
from tests.test_cli import run_main
from tests.test_service import serving

SENSOR = PinholeSensor(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5, max_range=10.0)
RANGES = np.random.default_rng(0).uniform(1.0, 5.0, SENSOR.shape).astype(np.float32)
META = {"pose": np.eye(4).tolist(), "sensor": SENSOR.to_dict()}
LIMIT_WORDS = "over the limit of 16,777,216 pixels (RANGEFUSE_MAX_PIXELS)"
_MIB = 1 << 20


# --- valid files of each format -----------------------------------------------------------


def meta_bytes(**changes: Any) -> bytes:
    return json.dumps({**META, **changes}).encode()


GOOD: dict[str, tuple[bytes, bytes]] = {
    "npy": (npy_bytes(RANGES), meta_bytes()),
    "npy big-endian float64 fortran": (
        npy_bytes(np.asfortranarray(RANGES.astype(">f8"))),
        meta_bytes(),
    ),
    "npz": (
        npz_bytes(range=RANGES, pose=np.eye(4), sensor=np.array(json.dumps(SENSOR.to_dict()))),
        b"{}",
    ),
    "npz deflated": (
        npz_bytes(True, range=RANGES, pose=np.eye(4)),
        json.dumps({"sensor": SENSOR.to_dict()}).encode(),
    ),
    "png 16-bit": (
        encode_png(np.round(RANGES * 1000).astype(np.uint16)),
        meta_bytes(depth_scale=0.001),
    ),
    "png 8-bit": (
        encode_png(np.round(RANGES * 10).astype(np.uint8), filter="sub"),
        meta_bytes(depth_scale=0.1),
    ),
    "tiff": (tiff_bytes(RANGES), meta_bytes()),
}


def test_valid_files_of_every_format_are_read() -> None:
    for name, (data, meta) in GOOD.items():
        scan = decode_scan(data, meta).scan
        assert scan.shape == SENSOR.shape, name
        assert np.allclose(scan.range_m, RANGES, atol=0.06), name


# --- bombs: small files that declare gigabytes ----------------------------------------------


def test_the_bombs_are_what_they_claim() -> None:
    """The bomb builders make valid files (checked on small sizes with the stock readers)."""
    assert decode_png(png_bomb(300, 200), "png", None).shape == (200, 300)
    with np.load(io.BytesIO(npz_bomb(30, 20))) as npz:
        assert npz["range"].shape == (30, 20) and not npz["range"].any()
    n, crc = 3 * _MIB + 5, zlib.crc32(b"ab")
    assert crc32_zeros(crc, n) == zlib.crc32(bytes(n), crc)


@pytest.fixture(scope="module")
def bombs() -> dict[str, tuple[bytes, bytes, str]]:
    """``{case: (range bytes, meta, words of the message)}``: all refused before reading."""
    png_meta = meta_bytes(depth_scale=0.001)
    return {
        "PNG 60000 x 60000 (7 MB)": (
            png_bomb(60000, 60000),
            png_meta,
            f"range: PNG of 60000 x 60000 pixels is {LIMIT_WORDS}",
        ),
        "PNG 16000 x 16000 (0.5 MB)": (
            png_bomb(16000, 16000),
            png_meta,
            f"range: PNG of 16000 x 16000 pixels is {LIMIT_WORDS}",
        ),
        "PNG header 2^31 x 2^31": (
            png_bomb(2**31 - 1, 2**31 - 1, 8, raw_size=2),
            png_meta,
            f"range: PNG of 2147483647 x 2147483647 pixels is {LIMIT_WORDS}",
        ),
        "npz 40000 x 40000 (6 MB)": (
            npz_bomb(),
            json.dumps({"sensor": SENSOR.to_dict()}).encode(),
            f"range (.npz): key 'range' of 40000 x 40000 pixels is {LIMIT_WORDS}",
        ),
        "npy header 40000 x 40000": (
            npy_header_only((40000, 40000), tail=bytes(4096)),
            meta_bytes(),
            f"range: .npy of 40000 x 40000 pixels is {LIMIT_WORDS}",
        ),
        "npy header 2^62 elements": (
            npy_header_only((2**31, 2**31)),
            meta_bytes(),
            f"range: .npy of 2147483648 x 2147483648 pixels is {LIMIT_WORDS}",
        ),
        "TIFF 2^31 x 2^31": (
            tiff_with(tiff_with(tiff_bytes(RANGES), 257, 2**31), 256, 2**31),
            meta_bytes(),
            f"range: TIFF of 2147483648 x 2147483648 pixels is {LIMIT_WORDS}",
        ),
    }


def test_bombs_are_refused_before_anything_large_is_allocated(bombs) -> None:
    for case, (data, meta, words) in bombs.items():
        tracemalloc.start()
        try:
            with pytest.raises(UploadError) as info:
                decode_scan(data, meta)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert str(info.value) == words, case
        assert peak < len(data) + 4 * _MIB, (case, peak)  # the file itself, no more


def test_the_pixel_limit_is_a_parameter() -> None:
    data, meta = GOOD["npy"]
    with pytest.raises(
        UploadError, match=r"range: .npy of 32 x 24 pixels is over the limit of 700"
    ):
        decode_scan(data, meta, max_pixels=700)
    assert decode_scan(data, meta, max_pixels=768).scan.shape == SENSOR.shape
    png, png_meta = GOOD["png 16-bit"]
    with pytest.raises(UploadError, match="range: PNG of 32 x 24 pixels is over the limit of 700"):
        decode_scan(png, png_meta, max_pixels=700)


def test_a_stream_longer_than_its_header_is_cut_at_the_declared_size() -> None:
    """The zip entry and the .npy header both say 24 x 32 float32, the deflate stream holds
    1 GiB more: reading stops at the declared size (and the CRC then fails)."""
    prefix = npy_bytes(RANGES)
    stream = deflate_zeros(prefix, 1 << 30)
    crc = zlib.crc32(prefix)  # right for the declared part
    pose = npy_bytes(np.eye(4))
    data = zip_archive(
        [
            ("range.npy", stream, crc, len(prefix), 8),
            ("pose.npy", pose, zlib.crc32(pose), len(pose), 0),
        ]
    )
    tracemalloc.start()
    try:
        scan = decode_scan(data, json.dumps({"sensor": SENSOR.to_dict()}).encode()).scan
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert np.array_equal(scan.range_m, RANGES)
    assert peak < 8 * _MIB


def test_the_sensor_shape_is_checked_before_reading() -> None:
    big = np.ones((1000, 1000), np.float32)
    cases = {
        "npy": (npy_bytes(big), meta_bytes()),
        "png": (encode_png(np.ones((1000, 1000), np.uint16)), meta_bytes(depth_scale=0.001)),
        "tiff": (tiff_bytes(big), meta_bytes()),
    }
    for case, (data, meta) in cases.items():
        with pytest.raises(UploadError) as info:
            decode_scan(data, meta)
        assert str(info.value) == (
            "range: shape (1000, 1000) does not match the sensor's height x width (24, 32)"
        ), case


# --- malformed files and metadata: 400 with a message ----------------------------------------


def _bad_zip(flag_bits: int = 0, method: int = 0) -> bytes:
    data = npy_bytes(RANGES)
    pose = npy_bytes(np.eye(4))
    archive = bytearray(
        zip_archive(
            [
                ("range.npy", data, zlib.crc32(data), len(data), method),
                ("pose.npy", pose, zlib.crc32(pose), len(pose), 0),
            ]
        )
    )
    central = archive.index(b"PK\x01\x02")
    archive[central + 8 : central + 10] = struct.pack("<H", flag_bits)
    return bytes(archive)


def _npz_declaring(range_size: int) -> bytes:
    """A scan .npz whose zip entry for range.npy declares ``range_size`` bytes."""
    data, pose = npy_bytes(RANGES), npy_bytes(np.eye(4))
    return zip_archive(
        [
            ("range.npy", data, zlib.crc32(data[:range_size]), range_size, 0),
            ("pose.npy", pose, zlib.crc32(pose), len(pose), 0),
        ]
    )


def _npz_meta(**changes: Any) -> tuple[bytes, bytes]:
    data = npz_bytes(range=RANGES, pose=np.eye(4), sensor=np.array(json.dumps(SENSOR.to_dict())))
    return data, json.dumps(changes).encode()


SENSOR_META = {"sensor": SENSOR.to_dict()}
BAD: dict[str, tuple[bytes, bytes, str]] = {
    # .npy headers
    "npy header not a literal": (
        b"\x93NUMPY\x01\x00\x10\x00{'descr': (((((\n",
        meta_bytes(),
        "range: .npy header is not a Python literal",
    ),
    "npy header a call": (
        b"\x93NUMPY\x01\x00\x20\x00__import__('os').system('x')   \n",
        meta_bytes(),
        "range: .npy header is not a Python literal",
    ),
    "npy header not a dict": (
        b"\x93NUMPY\x01\x00\x10\x00[1, 2, 3]      \n",
        meta_bytes(),
        "range: .npy header must be a dict of descr, fortran_order and shape",
    ),
    "npy header over 10000 bytes": (
        b"\x93NUMPY\x02\x00" + struct.pack("<I", 2**31),
        meta_bytes(),
        "range: .npy header of 2,147,483,648 bytes is over the limit of 10,000",
    ),
    "npy negative shape": (
        npy_header_only((24, 32)).replace(b"(24, 32)", b"(-24, 32)"),
        meta_bytes(),
        "range: .npy header has an invalid shape (-24, 32)",
    ),
    "npy structured dtype": (
        npy_bytes(np.zeros((24, 32), [("a", "<f4")])),
        meta_bytes(),
        "range: structured .npy dtype",
    ),
    "npy object dtype": (
        npy_header_only((24, 32), "|O"),
        meta_bytes(),
        "range: holds pickled Python objects (dtype object), which are never loaded",
    ),
    "npy unknown dtype": (
        npy_header_only((24, 32), "<q9"),
        meta_bytes(),
        "range: .npy header has an unknown dtype '<q9'",
    ),
    "npy version 9": (
        npy_bytes(RANGES)[:6] + b"\x09\x00" + npy_bytes(RANGES)[8:],
        meta_bytes(),
        "range: unknown .npy format version 9.0",
    ),
    "npy trailing data": (
        npy_bytes(RANGES) + b"x",
        meta_bytes(),
        "range: .npy holds 1 bytes after the array its header declares",
    ),
    "npy float16": (npy_bytes(RANGES.astype(np.float16)), meta_bytes(), "range: must be float32"),
    # .npz archives
    "npz encrypted member": (_bad_zip(flag_bits=1), json.dumps(SENSOR_META).encode(), "encrypted"),
    "npz bzip2 member": (
        _bad_zip(method=12),
        json.dumps(SENSOR_META).encode(),
        "key 'range' uses zip compression 12",
    ),
    "npz size disagrees with header": (
        _npz_declaring(len(npy_bytes(RANGES)) - 8),
        json.dumps(SENSOR_META).encode(),
        "key 'range' is not a readable array (its .npy header declares",
    ),
    "npz pose a string (meta)": (*_npz_meta(pose="eye"), "meta.pose: must be a 4x4 list"),
    "npz pose 2x2 (meta)": (
        *_npz_meta(pose=[[1, 0], [0, 1]]),
        "meta.pose: must be a 4x4 list of numbers",
    ),
    "npz pose disagrees (meta)": (
        *_npz_meta(pose=[[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
        "meta.pose: disagrees with the pose inside the .npz",
    ),
    "npz pose 3x3 inside": (
        npz_bytes(range=RANGES, pose=np.eye(3)),
        json.dumps(SENSOR_META).encode(),
        "range (.npz): pose: must be 4x4, got shape (3, 3)",
    ),
    "npz sensor JSON a list": (
        npz_bytes(range=RANGES, pose=np.eye(4), sensor=np.array("[1, 2]")),
        b"{}",
        "range (.npz): sensor: sensor: must be a JSON object, got list",
    ),
    # PNG
    "png CRC": (
        encode_png(np.ones((24, 32), np.uint16))[:-4] + b"\x00\x00\x00\x00",
        meta_bytes(depth_scale=0.001),
        "range: corrupted PNG (CRC mismatch in chunk b'IEND')",
    ),
    "png truncated": (
        encode_png(np.ones((24, 32), np.uint16))[:60],
        meta_bytes(depth_scale=0.001),
        "range: truncated PNG",
    ),
    "png image data short": (
        png_bomb(32, 24, raw_size=12 * 65),
        meta_bytes(depth_scale=0.001),
        "range: PNG image data is shorter than its 32x24 header says",
    ),
    "png colour": (
        encode_png(np.ones((24, 32, 3), np.uint8)),
        meta_bytes(depth_scale=0.001),
        "range: a depth image must be a greyscale PNG",
    ),
    "png depth_scale NaN": (
        GOOD["png 16-bit"][0],
        meta_bytes(depth_scale=float("nan")),
        "meta.depth_scale: must be a positive number",
    ),
    "png depth_scale huge int": (
        GOOD["png 16-bit"][0],
        json.dumps(META)[:-1].encode() + b', "depth_scale": 1' + b"0" * 400 + b"}",
        "meta.depth_scale: must be a positive number",
    ),
    # TIFF
    "tiff directory outside": (
        b"II*\x00" + struct.pack("<I", 10**9) + tiff_bytes(RANGES)[8:],
        meta_bytes(),
        "range: TIFF directory offset 1000000000 lies outside the file",
    ),
    "tiff strip outside": (
        tiff_with(tiff_bytes(RANGES), 273, 10**9),
        meta_bytes(),
        "range: TIFF strip 0 lies outside",
    ),
    "tiff strip short": (
        tiff_with(tiff_bytes(RANGES), 279, 16),
        meta_bytes(),
        "range: truncated TIFF image data",
    ),
    "tiff width 0 values": (
        tiff_bytes(RANGES)[:14] + struct.pack("<I", 0) + tiff_bytes(RANGES)[18:],
        meta_bytes(),
        "range: TIFF tag 256 (ImageWidth) has no value",
    ),
    "tiff values outside": (
        tiff_bytes(RANGES)[:14] + struct.pack("<I", 2**30) + tiff_bytes(RANGES)[18:],
        meta_bytes(),
        "range: the values of TIFF tag 256 (ImageWidth) lie outside the file",
    ),
    "tiff truncated directory": (tiff_bytes(RANGES)[:40], meta_bytes(), "range: truncated TIFF"),
    # meta
    "meta pose a string": (GOOD["npy"][0], meta_bytes(pose="eye(4)"), "meta.pose: must be a 4x4"),
    "meta pose 2x2": (GOOD["npy"][0], meta_bytes(pose=[[1, 0], [0, 1]]), "meta.pose: must be"),
    "meta pose nested": (
        GOOD["npy"][0],
        meta_bytes(pose=[[1, 0, 0, [0]], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
        "meta.pose: must be a 4x4 list of numbers",
    ),
    "meta pose strings": (
        GOOD["npy"][0],
        meta_bytes(pose=[["1", "0", "0", "0"]] * 4),
        "meta.pose: must be a 4x4 list of numbers",
    ),
    "meta pose NaN": (
        GOOD["npy"][0],
        json.dumps({**META, "pose": [[float("nan")] * 4] * 4}).encode(),
        "meta.pose: has non-finite entries",
    ),
    "meta pose huge int": (
        GOOD["npy"][0],
        json.dumps(META).replace("0.0", "1" + "0" * 400, 1).encode(),
        "meta.pose: has a number too large for a float",
    ),
    "meta sensor a list": (
        GOOD["npy"][0],
        meta_bytes(sensor=[1]),
        "meta.sensor: must be an object",
    ),
    "meta sensor model a dict": (
        GOOD["npy"][0],
        meta_bytes(sensor={**SENSOR.to_dict(), "model": {"a": 1}}),
        "sensor.model: unknown sensor model",
    ),
    "meta sensor width huge": (
        GOOD["npy"][0],
        meta_bytes(sensor={**SENSOR.to_dict(), "width": 10**30}),
        "sensor",
    ),
    "meta noise a list": (GOOD["npy"][0], meta_bytes(noise=[1]), "meta.noise: must be an object"),
    "meta noise eps a string": (GOOD["npy"][0], meta_bytes(noise={"eps": "x"}), "eps"),
    "meta accept_far_ranges a string": (
        GOOD["npy"][0],
        meta_bytes(accept_far_ranges="yes"),
        "meta.accept_far_ranges: must be true or false",
    ),
    "meta name a number": (GOOD["npy"][0], meta_bytes(name=5), "meta.name: must be a string"),
    "meta deeply nested": (GOOD["npy"][0], b"[" * 100_000, "meta: not valid JSON"),
    "meta not UTF-8": (GOOD["npy"][0], b"\xff\xfe{}", "meta: not valid JSON"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_uploads_are_400_with_a_message(case: str) -> None:
    data, meta, words = BAD[case]
    with pytest.raises(UploadError) as info:
        decode_scan(data, meta)
    assert words in str(info.value), str(info.value)


# --- fuzz: mutated files and metadata raise only UploadError ----------------------------------

#: Mutations per format in a test run (a few seconds in all); RANGEFUSE_FUZZ_CASES for more.
FUZZ_CASES = int(os.environ.get("RANGEFUSE_FUZZ_CASES", "120"))


def _decodes_or_refuses(data: bytes, meta: bytes) -> None:
    with contextlib.suppress(UploadError, FarRangesError):
        decode_scan(data, meta)


@pytest.mark.parametrize("name", sorted(GOOD))
def test_fuzzed_files_raise_only_upload_errors(name: str) -> None:
    data, meta = GOOD[name]
    rnd = random.Random(f"files {name}")
    for _ in range(FUZZ_CASES):
        _decodes_or_refuses(mutate(data, rnd), meta)


_SPHERICAL = SphericalSensor(
    width=32, height=24, az_min=-3.0, az_max=3.0, el_min=-0.4, el_max=0.1, max_range=10.0,
    elevations=tuple(np.linspace(0.1, -0.4, 24)),
)  # fmt: skip


def test_fuzzed_metadata_raises_only_upload_errors() -> None:
    rnd = random.Random("meta")
    files = {"npy": GOOD["npy"][0], "png": GOOD["png 16-bit"][0],
             "npz": npz_bytes(range=RANGES, pose=np.eye(4))}  # fmt: skip
    for _ in range(4 * FUZZ_CASES):
        meta = garbled_meta(rnd, rnd.choice([SENSOR, _SPHERICAL]))
        _decodes_or_refuses(files[rnd.choice(sorted(files))], json.dumps(meta).encode())


# --- the same readers on the command line's paths ----------------------------------------------


def test_dataset_files_and_importer_pngs_are_bounded(tmp_path: Path, bombs) -> None:
    path = tmp_path / "scans" / "bomb.npz"
    path.parent.mkdir()
    path.write_bytes(bombs["npz 40000 x 40000 (6 MB)"][0])
    with pytest.raises(DatasetError) as info:
        read_scan_file(path, SENSOR)
    assert str(info.value) == f"{path}: key 'range' of 40000 x 40000 pixels is {LIMIT_WORDS}"
    png = tmp_path / "depth.png"
    png.write_bytes(bombs["PNG 60000 x 60000 (7 MB)"][0])
    with pytest.raises(SourceError, match=f"{png}: PNG of 60000 x 60000 pixels is over"):
        read_png(png)
    ply = tmp_path / "scan.ply"
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10000000000000\n"
                    b"property list uchar int v\nend_header\n")  # fmt: skip
    with pytest.raises(SourceError, match="declares 10000000000000 items"):
        read_ply(ply)


def test_cli_refuses_a_bomb_in_one_line(tmp_path: Path, bombs, capsys) -> None:
    from rangefuse.engine import Scan
    from rangefuse.storage import write_dataset

    root = write_dataset(tmp_path / "ds", SENSOR, [("a", Scan(RANGES, np.eye(4), SENSOR))])
    bomb = root / "scans" / "b.npz"
    bomb.write_bytes(bombs["npz 40000 x 40000 (6 MB)"][0])
    code, _, err = run_main(["fuse", root, "--voxel-size", "0.1", "--quiet"], capsys)
    assert code == 2
    assert (
        err
        == f"rangefuse fuse: error: {bomb}: key 'range' of 40000 x 40000 pixels is {LIMIT_WORDS}\n"
    )
    os.environ["RANGEFUSE_MAX_PIXELS"] = "100"
    try:
        code, _, err = run_main(["fuse", root, "--voxel-size", "0.1", "--quiet"], capsys)
    finally:
        del os.environ["RANGEFUSE_MAX_PIXELS"]
    assert code == 2 and "a.npz: key 'range' of 32 x 24 pixels is over the limit of 100" in err


# --- the real service: 4xx, nothing stored, the others served, peak RSS -------------------------


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    yield from serving(tmp_path_factory.mktemp("data"), max_upload_mb=16)


def test_service_refuses_every_hostile_upload_and_keeps_serving(server, bombs) -> None:
    cases: dict[str, tuple[bytes, bytes, int, str]] = {
        name: (data, meta, 400, words) for name, (data, meta, words) in bombs.items()
    }
    for name in ("npy header not a literal", "npz pose a string (meta)", "npz pose 2x2 (meta)",
                 "tiff strip outside", "meta sensor model a dict", "npz bzip2 member"):  # fmt: skip
        data, meta, words = BAD[name]
        cases[name] = (data, meta, 400, words)
    pid = server.proc.pid
    with client_of(server) as client:
        sid = new_scene(client)
        Path(f"/proc/{pid}/clear_refs").write_text("5")  # restart the peak (VmHWM) from now
        before, _ = rss_kib(pid)
        with Pinger(server, sid) as pinger:
            for name, (data, meta, status, words) in cases.items():
                files = {"range": ("r", data), "meta": (None, meta.decode("utf-8", "replace"))}
                r = client.post(f"/v1/scenes/{sid}/scans", files=files)
                assert r.status_code == status, (name, r.text)
                assert words in r.json()["detail"], (name, r.json())
                assert client.get(f"/v1/scenes/{sid}/scans").json() == [], name
                assert client.get("/healthz").status_code == 200, name
        _, peak = rss_kib(pid)
        print(f"\nAPI process: {before / 1024:.0f} MiB before the hostile uploads, peak "
              f"{peak / 1024:.0f} MiB during {len(cases)} of them")  # fmt: skip
        assert peak < 500 * 1024, peak
        assert pinger.statuses and set(pinger.statuses) == {200}, pinger.statuses
        # and a good upload is still accepted
        r = client.post(
            f"/v1/scenes/{sid}/scans",
            files={"range": ("r.npy", GOOD["npy"][0]), "meta": (None, GOOD["npy"][1].decode())},
        )
        assert r.status_code == 202, r.text


@pytest.mark.parametrize(
    ("at", "words"),
    [
        ("1e308", "at: 1e+308 m lies beyond the grid's reach"),
        ("-1e300", "at: -1e+300 m lies beyond the grid's reach"),
        ("1" + "0" * 30, "at: 1e+30 m lies beyond the grid's reach"),
        ("inf", "at: must be a finite number of metres"),
        ("-inf", "at: must be a finite number of metres"),
        ("nan", "at: must be a finite number of metres"),
        ("1e400", "at: must be a finite number of metres"),
        ("x", "at: Input should be a valid number"),
    ],
)
def test_slice_at_absurd_positions_is_422(server, at: str, words: str) -> None:
    with client_of(server) as client:
        sid = new_scene(client)
        r = client.get(f"/v1/scenes/{sid}/slice", params={"axis": "z", "at": at})
        assert r.status_code == 422, r.text
        assert words in r.json()["detail"], r.json()
        ok = client.get(f"/v1/scenes/{sid}/slice", params={"axis": "z", "at": "0.5"})
        assert ok.status_code == 200 and ok.headers["content-type"] == "image/png"
