"""Decoding uploaded scans: the ``range`` part and the ``meta`` JSON of a multipart upload.

Accepted range files (sniffed from their first bytes, not their names): a ``.npy`` float
array (never unpickled), a FORMAT.md scan ``.npz``, a 16-bit greyscale PNG depth image (with
``depth_scale`` metres per unit in the metadata; 0 is invalid) and a float32 TIFF
(uncompressed, one sample per pixel). The metadata are checked first; then each file's
header is checked against the pixel limit and the sensor's height x width before anything
is allocated or inflated (:mod:`storage.bounded`, ``docs/input-safety.md``). Every problem
raises :class:`UploadError` (400) with a message that names the part and what is wrong; a
range map that mostly lies beyond the sensor's ``max_range`` raises
:class:`engine.errors.FarRangesError` (422) unless ``meta.accept_far_ranges`` is true.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from rangefuse.engine import InvalidInputError, NoiseModel, Scan, Sensor, sensor_from_dict
from rangefuse.engine.errors import FarRangesError
from rangefuse.engine.params import params_of
from rangefuse.engine.scans import check_pose
from rangefuse.storage import DatasetError
from rangefuse.storage.bounded import (
    DEFAULT_MAX_PIXELS,
    DecodeError,
    npy_array,
    npy_header,
    read_tiff_float,
)
from rangefuse.storage.dataset import check_range_header, read_scan_file
from rangefuse.storage.importers import decode_png

__all__ = ["META_FIELDS", "UploadError", "UploadedScan", "decode_scan"]

#: The fields of ``meta``.
META_FIELDS = ("name", "pose", "sensor", "noise", "depth_scale", "accept_far_ranges")
#: What building a value object from foreign JSON can raise besides InvalidInputError.
_VALUE_ERRORS = (TypeError, ValueError, KeyError, AttributeError, OverflowError, RecursionError)
_FAR_HINT = "to fuse it anyway, send meta.accept_far_ranges: true"
_NO_SCENE_SENSOR = (
    "the scene has no sensor of its own (give meta.sensor, or the scene's sensor when creating it)"
)
#: Largest ``depth_scale``: 65535 units stay finite in float32.
_MAX_DEPTH_SCALE = 1e30


class UploadError(ValueError):
    """A malformed upload (HTTP 400 with this message)."""


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
    unknown = sorted(set(meta) - set(META_FIELDS))
    if unknown:
        raise UploadError(f"meta.{unknown[0]}: unknown field (known: {sorted(META_FIELDS)})")
    name = meta.get("name")
    if name is not None and (not isinstance(name, str) or not 0 < len(name) <= 200):
        raise UploadError("meta.name: must be a string of 1 to 200 characters")
    if not isinstance(meta.get("accept_far_ranges", False), bool):
        raise UploadError("meta.accept_far_ranges: must be true or false")
    return meta


def decode_scan(
    range_bytes: bytes,
    meta_bytes: bytes,
    max_pixels: int | None = DEFAULT_MAX_PIXELS,
    scene_sensor: Sensor | None = None,
) -> UploadedScan:
    """Build a validated :class:`engine.Scan` from the two parts of an upload, reading no
    range map over ``max_pixels`` pixels (None: no limit). ``scene_sensor``: the scene's
    default sensor, used when ``meta`` (and an ``.npz``) give none."""
    meta = _meta(meta_bytes)
    accept = bool(meta.get("accept_far_ranges", False))
    if not range_bytes:
        raise UploadError("range: empty file")
    head = range_bytes[:8]
    try:
        if head.startswith(b"PK"):
            scan = _npz_scan(range_bytes, meta, max_pixels, accept, scene_sensor)
            return UploadedScan(scan, meta.get("name"))
        kind = _kind(head)
        if "pose" not in meta:
            raise UploadError("meta.pose: missing")
        if "sensor" in meta:
            sensor = _sensor(meta["sensor"])
        elif scene_sensor is not None:
            sensor = scene_sensor
        else:
            raise UploadError(f"meta.sensor: missing, and {_NO_SCENE_SENSOR}")
        pose = _pose(meta["pose"])
        noise = None if meta.get("noise") is None else _noise(meta["noise"])
        if kind == "npy":
            rng = _npy(range_bytes, sensor, max_pixels)
        elif kind == "png":
            rng = _png_depth(range_bytes, meta, sensor, max_pixels)
        else:
            rng = read_tiff_float(range_bytes, "range", max_pixels, sensor.shape)
        scan = Scan(rng, pose, sensor, noise, accept_far_ranges=accept)
    except FarRangesError as exc:
        raise FarRangesError(exc.field, f"{exc.problem}; {_FAR_HINT}") from None
    except (InvalidInputError, DecodeError, DatasetError) as exc:
        raise UploadError(str(exc)) from None
    return UploadedScan(scan, meta.get("name"))


def _kind(head: bytes) -> str:
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        return "tiff"
    raise UploadError("range: not a .npy, .npz, PNG or TIFF file (unrecognised first bytes)")


def _sensor(data: Any, field: str = "meta.sensor") -> Sensor:
    if not isinstance(data, dict):
        raise UploadError(f"{field}: must be an object, got {type(data).__name__}")
    try:
        return sensor_from_dict(data)
    except InvalidInputError:
        raise
    except _VALUE_ERRORS as exc:
        raise UploadError(f"{field}: not a valid sensor ({exc})") from None


def _pose(data: Any) -> np.ndarray:
    """``meta.pose``: 4 rows of 4 numbers, a rigid sensor-to-world transform."""
    rows_ok = isinstance(data, list) and len(data) == 4
    rows_ok = rows_ok and all(isinstance(row, list) and len(row) == 4 for row in data)
    if not rows_ok or not all(
        isinstance(x, (int, float)) and not isinstance(x, bool) for row in data for x in row
    ):
        raise UploadError("meta.pose: must be a 4x4 list of numbers (sensor to world)")
    try:
        values = [[float(x) for x in row] for row in data]
    except OverflowError:
        raise UploadError("meta.pose: has a number too large for a float") from None
    return check_pose(np.array(values, np.float64), "meta.pose")


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
    try:
        return NoiseModel(**data)
    except InvalidInputError:
        raise
    except _VALUE_ERRORS as exc:
        raise UploadError(f"meta.noise: not a valid noise model ({exc})") from None


def _npy(data: bytes, sensor: Sensor, max_pixels: int | None) -> np.ndarray:
    """The range map of a ``.npy``: its header checked before its data are looked at."""
    header = npy_header(io.BytesIO(data), "range")
    if header.dtype.kind != "f" or header.dtype.itemsize not in (4, 8):
        raise UploadError(f"range: must be float32 metres, got dtype {header.dtype}")
    check_range_header(header, "range", ".npy", sensor, max_pixels)
    return npy_array(data, header, "range")


def _npz_scan(
    data: bytes,
    meta: dict[str, Any],
    max_pixels: int | None,
    accept: bool,
    scene_sensor: Sensor | None,
) -> Scan:
    """A FORMAT.md scan ``.npz``, read from memory; ``meta.sensor`` (else the scene's) is its
    default sensor, and ``meta.pose``, when given, must agree with the pose inside."""
    default = _sensor(meta["sensor"]) if "sensor" in meta else scene_sensor
    pose = _pose(meta["pose"]) if "pose" in meta else None
    scan = read_scan_file(
        data,
        default,
        max_pixels=max_pixels,
        accept_far_ranges=accept,
        where="range (.npz)",
        no_sensor=f"no meta.sensor in the upload, and {_NO_SCENE_SENSOR}",
    )
    if pose is not None and not np.allclose(pose, scan.T_W_S):
        raise UploadError("meta.pose: disagrees with the pose inside the .npz")
    return scan


# --- PNG depth images (storage.importers' codec) ------------------------------------------------


def _png_depth(
    data: bytes, meta: dict[str, Any], sensor: Sensor, max_pixels: int | None
) -> np.ndarray:
    scale = meta.get("depth_scale")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)):
        raise UploadError("meta.depth_scale: a PNG depth image needs depth_scale (metres per unit)")
    try:
        scale = float(scale)
    except OverflowError:
        scale = math.inf
    if not 0 < scale <= _MAX_DEPTH_SCALE:  # NaN fails too
        raise UploadError(
            f"meta.depth_scale: must be a positive number of at most {_MAX_DEPTH_SCALE:g} "
            f"metres per unit, got {scale}"
        )
    values = decode_png(data, "range", max_pixels, sensor.shape)
    depth = values.astype(np.float32)
    depth *= np.float32(scale)
    depth[values == 0] = np.nan
    return depth
