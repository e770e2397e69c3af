"""Decoding uploaded scans: the ``range`` part and the ``meta`` JSON of a multipart upload.

Accepted range files (sniffed from their first bytes, not their names): a ``.npy`` float
array (never unpickled), a FORMAT.md scan ``.npz``, a 16-bit greyscale PNG depth image (with
``depth_scale`` metres per unit in the metadata; 0 is invalid) and a float32 TIFF
(uncompressed, one sample per pixel). Every problem raises :class:`UploadError` with a
message that names the part and what is wrong.
"""

from __future__ import annotations

import io
import json
import math
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rangefuse.engine import InvalidInputError, NoiseModel, Scan, sensor_from_dict
from rangefuse.engine.params import params_of
from rangefuse.storage import DatasetError
from rangefuse.storage.dataset import read_scan_file
from rangefuse.storage.importers import decode_png
from rangefuse.storage.importers.errors import SourceError

__all__ = ["UploadError", "UploadedScan", "decode_scan"]

#: Largest image side accepted (pixels).
MAX_SIDE = 1 << 15


class UploadError(ValueError):
    """A malformed upload (HTTP 400/422 with this message)."""


@dataclass(frozen=True)
class UploadedScan:
    scan: Scan
    name: str | None


def _meta(text: bytes) -> dict[str, Any]:
    try:
        meta = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise UploadError(f"meta: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise UploadError(f"meta: must be a JSON object, got {type(meta).__name__}")
    known = {"name", "pose", "sensor", "noise", "depth_scale"}
    unknown = sorted(set(meta) - known)
    if unknown:
        raise UploadError(f"meta.{unknown[0]}: unknown field (known: {sorted(known)})")
    return meta


def decode_scan(range_bytes: bytes, meta_bytes: bytes) -> UploadedScan:
    """Build a validated :class:`engine.Scan` from the two parts of an upload."""
    meta = _meta(meta_bytes)
    name = meta.get("name")
    if name is not None and (not isinstance(name, str) or not 0 < len(name) <= 200):
        raise UploadError("meta.name: must be a string of 1 to 200 characters")
    if not range_bytes:
        raise UploadError("range: empty file")
    head = range_bytes[:8]
    try:
        if head.startswith(b"PK"):
            scan = _npz_scan(range_bytes, meta)
            return UploadedScan(scan, name)
        if head.startswith(b"\x93NUMPY"):
            rng = _npy(range_bytes)
        elif head.startswith(b"\x89PNG\r\n\x1a\n"):
            rng = _png_depth(range_bytes, meta)
        elif head[:4] in (b"II*\x00", b"MM\x00*"):
            rng = _tiff_float(range_bytes)
        else:
            raise UploadError(
                "range: not a .npy, .npz, PNG or TIFF file (unrecognised first bytes)"
            )
        for field in ("pose", "sensor"):
            if field not in meta:
                raise UploadError(f"meta.{field}: missing")
        sensor = sensor_from_dict(meta["sensor"])
        noise = None if meta.get("noise") is None else _noise(meta["noise"])
        pose = meta["pose"]
        if not isinstance(pose, list):
            raise UploadError("meta.pose: must be a 4x4 list of numbers (sensor to world)")
        try:
            pose_arr = np.array(pose, dtype=np.float64)
        except (TypeError, ValueError):
            raise UploadError(
                "meta.pose: must be a 4x4 list of numbers (sensor to world)"
            ) from None
        return UploadedScan(Scan(range_m=rng, T_W_S=pose_arr, sensor=sensor, noise=noise), name)
    except InvalidInputError as exc:
        raise UploadError(str(exc)) from None


def _noise(data: Any) -> NoiseModel:
    """A scan's own noise model (``meta.noise``): the declared noise parameters, ``eps``
    required."""
    if not isinstance(data, dict):
        raise UploadError("meta.noise: must be an object")
    known = [p.name for p in params_of("noise")]
    for key in data:
        if key not in known:
            raise UploadError(f"meta.noise.{key}: unknown (known: {', '.join(known)})")
    if "eps" not in data:
        raise UploadError("meta.noise.eps: missing")
    return NoiseModel(**data)


def _npy(data: bytes) -> np.ndarray:
    try:
        arr = np.load(io.BytesIO(data), allow_pickle=False)
    except ValueError as exc:
        if "pickle" in str(exc).lower():
            raise UploadError("range: the .npy holds Python objects (pickled); refused") from None
        raise UploadError(f"range: not a readable .npy ({exc})") from None
    except (OSError, EOFError) as exc:
        raise UploadError(f"range: truncated or damaged .npy ({exc})") from None
    if arr.dtype.kind != "f" or arr.dtype.itemsize not in (4, 8):
        raise UploadError(f"range: must be float32 metres, got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise UploadError(f"range: must be a 2-D array (H x W), got shape {arr.shape}")
    return arr.astype(np.float32)


def _npz_scan(data: bytes, meta: dict[str, Any]) -> Scan:
    default = sensor_from_dict(meta["sensor"]) if "sensor" in meta else None
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scan.npz"
        path.write_bytes(data)
        try:
            scan = read_scan_file(path, default)
        except DatasetError as exc:
            raise UploadError(f"range: {str(exc).split(': ', 1)[-1]}") from None
    if "pose" in meta and not np.allclose(np.asarray(meta["pose"], float), scan.T_W_S):
        raise UploadError("meta.pose: disagrees with the pose inside the .npz")
    return scan


# --- PNG depth images (storage.importers' codec) ------------------------------------------------


def _png_depth(data: bytes, meta: dict[str, Any]) -> np.ndarray:
    scale = meta.get("depth_scale")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)):
        raise UploadError("meta.depth_scale: a PNG depth image needs depth_scale (metres per unit)")
    if not (math.isfinite(scale) and scale > 0):
        raise UploadError(f"meta.depth_scale: must be a positive number, got {scale}")
    try:
        values = decode_png(data, "range")
    except SourceError as exc:
        raise UploadError(str(exc)) from None
    depth = values.astype(np.float32) * np.float32(scale)
    depth[values == 0] = np.nan
    return depth


# --- TIFF (float32, uncompressed, one sample per pixel) ---------------------------------------


def _tiff_float(data: bytes) -> np.ndarray:
    endian = "<" if data[:2] == b"II" else ">"
    try:
        (ifd,) = struct.unpack(endian + "I", data[4:8])
        (count,) = struct.unpack(endian + "H", data[ifd : ifd + 2])
        tags: dict[int, list[int]] = {}
        sizes = {3: (2, "H"), 4: (4, "I")}
        for n in range(count):
            entry = data[ifd + 2 + 12 * n : ifd + 14 + 12 * n]
            tag, typ, num = struct.unpack(endian + "HHI", entry[:8])
            if typ not in sizes:
                continue
            size, code = sizes[typ]
            if size * num <= 4:
                body = entry[8 : 8 + size * num]
            else:
                (off,) = struct.unpack(endian + "I", entry[8:12])
                body = data[off : off + size * num]
            tags[tag] = list(struct.unpack(endian + code * num, body))
    except struct.error:
        raise UploadError("range: truncated TIFF") from None
    width, height = tags.get(256, [0])[0], tags.get(257, [0])[0]
    bits, compression = tags.get(258, [0])[0], tags.get(259, [1])[0]
    fmt, spp = tags.get(339, [1])[0], tags.get(277, [1])[0]
    if bits != 32 or fmt != 3 or spp != 1:
        raise UploadError("range: TIFF must hold float32 samples, one per pixel")
    if compression != 1:
        raise UploadError("range: compressed TIFF is not supported; write it uncompressed")
    if not (0 < width <= MAX_SIDE and 0 < height <= MAX_SIDE):
        raise UploadError(f"range: TIFF of {width} x {height} pixels is not sensible")
    offsets, counts = tags.get(273, []), tags.get(279, [])
    body = b"".join(data[o : o + c] for o, c in zip(offsets, counts, strict=False))
    if len(body) < width * height * 4:
        raise UploadError("range: truncated TIFF image data")
    return (
        np.frombuffer(body[: width * height * 4], endian + "f4")
        .reshape(height, width)
        .astype(np.float32)
    )
