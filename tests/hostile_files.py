"""Files for the hostile-input tests: valid files of each upload format, decompression bombs
(small files that declare gigabytes, with right CRCs) built in milliseconds, a hand-written
zip whose headers can say anything, and a seeded mutator."""

from __future__ import annotations

import copy
import io
import random
import struct
import threading
import time
import zlib
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from rangefuse.engine import Sensor

from tests import test_service
from tests.test_service import Server

_MIB = 1 << 20


def npy_bytes(array: np.ndarray) -> bytes:
    return test_service._npy(array)


def npz_bytes(compressed: bool = False, **arrays: Any) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return buf.getvalue()


def tiff_bytes(array: np.ndarray) -> bytes:
    """A little-endian float32 TIFF: one strip, uncompressed."""
    height, width = array.shape
    body = array.astype("<f4").tobytes()
    tags = [(256, 4, width), (257, 4, height), (258, 3, 32), (259, 3, 1), (273, 4, 0),
            (277, 3, 1), (279, 4, len(body)), (339, 3, 3)]  # fmt: skip
    start = 8 + 2 + 12 * len(tags) + 4
    entries = b"".join(
        struct.pack("<HHII", tag, typ, 1, start if tag == 273 else value)
        if typ == 4
        else struct.pack("<HHIHH", tag, typ, 1, value, 0)
        for tag, typ, value in tags
    )
    return b"II*\x00" + struct.pack("<IH", 8, len(tags)) + entries + bytes(4) + body


def deflate_zeros(prefix: bytes, zeros: int) -> bytes:
    """A raw deflate stream of ``prefix`` and ``zeros`` zero bytes: about 1 KB per MiB, built
    from one fully flushed block repeated (identical after a full flush)."""
    comp = zlib.compressobj(9, zlib.DEFLATED, -15)
    head = comp.compress(prefix) + comp.flush(zlib.Z_FULL_FLUSH)
    block = comp.compress(bytes(_MIB)) + comp.flush(zlib.Z_FULL_FLUSH)
    whole, rest = divmod(zeros, _MIB)
    return head + block * whole + comp.compress(bytes(rest)) + comp.flush()


def png_bomb(width: int, height: int, bits: int = 16, raw_size: int | None = None) -> bytes:
    """A valid greyscale PNG of zeros (CRCs and Adler-32 right): a few MB for gigapixels.
    ``raw_size``: inflate to that many bytes instead (a header that lies)."""
    if raw_size is None:
        raw_size = height * (1 + width * bits // 8)
    stream = b"\x78\xda" + deflate_zeros(b"", raw_size)
    stream += struct.pack(">I", ((raw_size % 65521) << 16) | 1)  # Adler-32 of zeros

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body)
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", width, height, bits, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", stream) + chunk(b"IEND", b"")
    )


def crc32_zeros(crc: int, n: int) -> int:
    """``zlib.crc32(bytes(n), crc)`` in O(log n) (zlib's crc32_combine, zero operator)."""

    def times(matrix: list[int], vector: int) -> int:
        out, i = 0, 0
        while vector:
            if vector & 1:
                out ^= matrix[i]
            vector >>= 1
            i += 1
        return out

    def square(matrix: list[int]) -> list[int]:
        return [times(matrix, matrix[k]) for k in range(32)]

    op = [0xEDB88320] + [1 << k for k in range(31)]  # one zero bit
    for _ in range(3):  # one zero byte
        op = square(op)
    crc ^= 0xFFFFFFFF
    while n:
        if n & 1:
            crc = times(op, crc)
        op = square(op)
        n >>= 1
    return crc ^ 0xFFFFFFFF


def zip_archive(members: list[tuple[str, bytes, int, int, int]]) -> bytes:
    """A zip of ``(name, deflated stream, crc, file size, method)`` members written by hand,
    with a ZIP64 extra field for a file size of 4 GiB or more."""
    local, central = b"", b""
    for name, stream, crc, size, method in members:
        big = size >= 0xFFFFFFFF
        extra = struct.pack("<HHQ", 1, 8, size) if big else b""
        fields = (45, 0, method, 0, 0x21, crc, len(stream), 0xFFFFFFFF if big else size)
        head = struct.pack("<IHHHHHIII", 0x04034B50, *fields)
        offset = len(local)
        local += head + struct.pack("<HH", len(name), len(extra)) + name.encode() + extra + stream
        central += (
            struct.pack("<IH", 0x02014B50, 45)
            + struct.pack("<HHHHHIII", *fields)
            + struct.pack("<HHHHHII", len(name), len(extra), 0, 0, 0, 0, offset)
            + name.encode()
            + extra
        )
    n = len(members)
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, n, n, len(central), len(local), 0)
    return local + central + end


def npz_bomb(height: int = 40000, width: int = 40000) -> bytes:
    """A valid scan ``.npz`` whose ``range.npy`` holds height x width float32 zeros: 6 MB."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f4", "fortran_order": False, "shape": (height, width)}
    )
    prefix = header.getvalue()
    zeros = 4 * height * width
    crc = crc32_zeros(zlib.crc32(prefix), zeros)
    pose = npy_bytes(np.eye(4))
    return zip_archive(
        [
            ("range.npy", deflate_zeros(prefix, zeros), crc, len(prefix) + zeros, 8),
            ("pose.npy", pose, zlib.crc32(pose), len(pose), 0),
        ]
    )


def npy_header_only(shape: tuple[int, ...], descr: str = "<f4", tail: bytes = b"") -> bytes:
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": descr, "fortran_order": False, "shape": shape}
    )
    return header.getvalue() + tail


def tiff_with(data: bytes, tag: int, value: int) -> bytes:
    """A TIFF from :func:`tiff_bytes` with a tag's value replaced by one LONG."""
    out = bytearray(data)
    (count,) = struct.unpack("<H", out[8:10])
    for k in range(count):
        at = 10 + 12 * k
        if struct.unpack("<H", out[at : at + 2])[0] == tag:
            out[at + 2 : at + 12] = struct.pack("<HII", 4, 1, value)
    return bytes(out)


_NUMBERS = [0, 1, 2, 0x7F, 0x80, 0xFF, 0xFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF, 40000]


def mutate(data: bytes, rnd: random.Random) -> bytes:
    """One to three of: bit flips, a cut, a byte or a 16/32-bit number written in the first
    300 bytes (headers), inserted bytes, or a digit of a text header replaced."""
    out = bytearray(data)
    for _ in range(rnd.choice([1, 1, 2, 3])):
        if not out:
            break
        head = min(len(out), 300)
        op = rnd.randrange(7)
        if op == 0:
            for _ in range(rnd.randint(1, 8)):
                out[rnd.randrange(len(out))] ^= 1 << rnd.randrange(8)
        elif op == 1:
            del out[rnd.randrange(len(out)) :]
        elif op == 2:
            out[rnd.randrange(head)] = rnd.choice([0, 0xFF, 0x7F, 0x80, rnd.randrange(256)])
        elif op in (3, 4):
            size, code = (4, "I") if op == 3 else (2, "H")
            at = rnd.randrange(max(1, head - size))
            value = rnd.choice(_NUMBERS) & (0xFFFFFFFF if size == 4 else 0xFFFF)
            out[at : at + size] = struct.pack(rnd.choice("<>") + code, value)
        elif op == 5:
            at = rnd.randrange(len(out))
            out[at:at] = bytes(rnd.randrange(256) for _ in range(rnd.randint(1, 16)))
        else:
            digits = [k for k in range(head) if 48 <= out[k] <= 57]
            if digits:
                k = rnd.choice(digits)
                out[k : k + 1] = rnd.choice([b"99999", b"0", b"-1", b"1,", b"1e9", b"'", b"("])
    return bytes(out)


# --- garbled metadata ----------------------------------------------------------------------

GARBAGE: list[Any] = [None, True, 0, -1, 2**63, 10**400, 1e308, float("nan"), float("inf"),
                       "", "x", [], {}, [1], [[1, 2], [3, 4]], [["1"] * 4] * 4, {"a": 1},
                       [[[]]], 0.5, 1e-320, 65536, {"eps": 0.01}]  # fmt: skip


def garbage(rnd: random.Random, depth: int = 0) -> Any:
    if depth < 3 and rnd.random() < 0.3:
        if rnd.random() < 0.5:
            return [garbage(rnd, depth + 1) for _ in range(rnd.randint(0, 5))]
        keys = ["eps", "width", "model", "fx", "x"]
        return {rnd.choice(keys): garbage(rnd, depth + 1) for _ in range(rnd.randint(0, 3))}
    return copy.deepcopy(rnd.choice(GARBAGE))


def garbled_meta(rnd: random.Random, sensor: Sensor) -> dict[str, Any]:
    meta: dict[str, Any] = {"pose": np.eye(4).tolist(), "sensor": sensor.to_dict(),
                            "noise": {"eps": 0.02}, "depth_scale": 0.001}  # fmt: skip
    for _ in range(rnd.randint(1, 3)):
        where = rnd.random()
        if where < 0.3:
            fields = ["pose", "sensor", "noise", "name", "depth_scale", "accept_far_ranges"]
            meta[rnd.choice(fields)] = garbage(rnd)
        elif where < 0.7 and isinstance(meta["sensor"], dict):
            keys = [*sensor.to_dict(), "elevations", "wrap", "extra"]
            meta["sensor"][rnd.choice(keys)] = garbage(rnd)
        elif where < 0.85 and isinstance(meta["noise"], dict):
            keys = ["eps", "eps_per_m", "rho", "falloff", "shape"]
            meta["noise"][rnd.choice(keys)] = garbage(rnd)
        elif isinstance(meta["pose"], list) and len(meta["pose"]) == 4:
            meta["pose"][rnd.randrange(4)] = [garbage(rnd) for _ in range(4)]
    return meta


# --- the service under attack ----------------------------------------------------------------


def rss_kib(pid: int) -> tuple[int, int]:
    """(VmRSS, VmHWM) of a process in KiB: its resident memory now and at its peak."""
    values = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = int(value.split()[0])
    return values["VmRSS"], values["VmHWM"]


def client_of(server: Server) -> httpx.Client:
    return test_service.client_of(server, timeout=120)


def new_scene(client: httpx.Client) -> str:
    body = {"name": "hostile", "voxel_size": 0.05, "mode": "mapping", "tile_size": 8}
    return client.post("/v1/scenes", json=body).json()["id"]


class Pinger:
    """Another client, asking for the scene's scans every 20 ms while the hostile ones post."""

    def __init__(self, server: Server, scene_id: str) -> None:
        self.statuses: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(server, scene_id), daemon=True)

    def _run(self, server: Server, scene_id: str) -> None:
        with client_of(server) as client:
            while not self._stop.is_set():
                self.statuses.append(client.get(f"/v1/scenes/{scene_id}/scans").status_code)
                time.sleep(0.02)

    def __enter__(self) -> Pinger:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=60)
