"""A small PNG codec for depth images: greyscale, 8 or 16 bits, no interlace.

Depth cameras and the datasets built on them (7-Scenes, TUM RGB-D, Redwood) store depth
as 16-bit greyscale PNGs. Pillow is not a dependency of rangefuse, and these files need
none of its generality: this module reads every filter type of the PNG specification
(None, Sub, Up, Average, Paeth; the unfiltering runs in a numba kernel because Sub,
Average and Paeth depend on the pixel just decoded) and writes with a chosen filter, so
the tests can produce every case. Chunk CRCs are checked; colour, palette and interlaced
images are refused with a message that names the file.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np
from numba import njit

from .._files import atomic_write
from ..bounded import DEFAULT_MAX_PIXELS, DecodeError, check_pixels
from .errors import SourceError

__all__ = ["FILTERS", "decode_png", "encode_png", "read_png", "write_png"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: PNG filter types by name (PNG specification, section 9).
FILTERS = {"none": 0, "sub": 1, "up": 2, "average": 3, "paeth": 4}


@njit(cache=True)
def _unfilter(raw: np.ndarray, height: int, stride: int, bpp: int, out: np.ndarray) -> int:
    """Undo the per-row filters of ``raw`` (height rows of ``1 + stride`` bytes) into ``out``.

    Returns -1 on success, else the row whose filter type is unknown.
    """
    for y in range(height):
        base = y * (stride + 1)
        ftype = raw[base]
        for x in range(stride):
            value = np.int32(raw[base + 1 + x])
            a = np.int32(out[y, x - bpp]) if x >= bpp else np.int32(0)
            b = np.int32(out[y - 1, x]) if y > 0 else np.int32(0)
            if ftype == 0:
                pass
            elif ftype == 1:
                value += a
            elif ftype == 2:
                value += b
            elif ftype == 3:
                value += (a + b) // 2
            elif ftype == 4:
                c = np.int32(out[y - 1, x - bpp]) if (y > 0 and x >= bpp) else np.int32(0)
                p = a + b - c
                pa = abs(p - a)
                pb = abs(p - b)
                pc = abs(p - c)
                if pa <= pb and pa <= pc:
                    value += a
                elif pb <= pc:
                    value += b
                else:
                    value += c
            else:
                return y
            out[y, x] = np.uint8(value & 0xFF)
    return -1


def read_png(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a greyscale PNG file; see :func:`decode_png`.

    Raises
    ------
    SourceError
        For a file that cannot be read or decoded; the message names the file.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SourceError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    return decode_png(data, str(path))


def decode_png(
    data: bytes,
    where: str = "PNG",
    max_pixels: int | None = DEFAULT_MAX_PIXELS,
    shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """Decode a greyscale PNG.

    The header's size is checked against ``max_pixels`` and ``shape`` before anything is
    inflated, and the image data are inflated in steps into one buffer of the size the
    header declares, never past it (a small file can inflate to gigabytes).

    Parameters
    ----------
    data : bytes
        The file's contents.
    where : str
        Names the data in messages (a file name).
    max_pixels : int or None
        Largest image decoded (None: no limit).
    shape : (height, width) or None
        The size the image must have (a sensor's), when known.

    Returns
    -------
    array (H, W), uint16 for 16-bit images, uint8 for 8-bit ones
        Raw stored values (no scaling).

    Raises
    ------
    SourceError
        For data that are not a PNG, truncated or corrupted (CRC), a PNG that is not plain
        greyscale at 8 or 16 bits without interlace, or one over ``max_pixels`` or not of
        ``shape``; the message starts with ``where``.
    """
    path = where
    if not data.startswith(_SIGNATURE):
        raise SourceError(f"{path}: not a PNG file")
    pos = len(_SIGNATURE)
    header: tuple[int, ...] | None = None
    idat: list[memoryview] = []  # views of data: the chunks are not copied
    view = memoryview(data)
    ended = False
    while pos + 8 <= len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = view[pos + 8 : pos + 8 + length]
        crc_bytes = data[pos + 8 + length : pos + 12 + length]
        if len(body) != length or len(crc_bytes) != 4:
            raise SourceError(f"{path}: truncated PNG (chunk {kind!r} is cut short)")
        if zlib.crc32(body, zlib.crc32(kind)) != struct.unpack(">I", crc_bytes)[0]:
            raise SourceError(f"{path}: corrupted PNG (CRC mismatch in chunk {kind!r})")
        pos += 12 + length
        if kind == b"IHDR":
            if length != 13:
                raise SourceError(f"{path}: malformed PNG header")
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            ended = True
            break
    if header is None:
        raise SourceError(f"{path}: PNG without a header chunk")
    if not ended:
        raise SourceError(f"{path}: truncated PNG (no IEND chunk)")
    width, height, depth, colour, _compression, _filter, interlace = header
    if colour != 0 or depth not in (8, 16):
        raise SourceError(
            f"{path}: a depth image must be a greyscale PNG of 8 or 16 bits, got colour type "
            f"{colour} with {depth} bits"
        )
    if interlace != 0:
        raise SourceError(f"{path}: interlaced (Adam7) PNGs are not supported")
    if width == 0 or height == 0:
        raise SourceError(f"{path}: empty PNG ({width}x{height})")
    try:
        check_pixels(path, "PNG", height, width, max_pixels)
    except DecodeError as exc:
        raise SourceError(str(exc)) from None
    if shape is not None and (height, width) != tuple(shape):
        raise SourceError(
            f"{path}: shape {(height, width)} does not match the sensor's height x width "
            f"{tuple(shape)}"
        )
    bpp = depth // 8
    stride = width * bpp
    raw = _inflate(idat, height * (stride + 1), f"{width}x{height}", path)
    out = np.empty((height, stride), np.uint8)
    bad_row = _unfilter(raw, height, stride, bpp, out)
    if bad_row >= 0:
        raise SourceError(f"{path}: unknown PNG filter type in row {bad_row}")
    if depth == 16:
        return out.view(">u2").astype(np.uint16).reshape(height, width)
    return out.reshape(height, width)


def _inflate(stream: list[memoryview], expected: int, size: str, path: str) -> np.ndarray:
    """Inflate the IDAT chunks ``stream`` into ``expected`` bytes, in steps that never produce
    more than the room left (plus one byte, to see that a stream is longer than its header
    says)."""
    out = np.empty(expected, np.uint8)
    filled = 0
    inflater = zlib.decompressobj()
    try:
        for part in [*stream, memoryview(b"")]:  # the empty one drains what is held back
            pending: bytes | memoryview = part
            while True:
                chunk = inflater.decompress(pending, expected - filled + 1)
                if len(chunk) > expected - filled:
                    raise SourceError(
                        f"{path}: PNG image data is longer than its {size} header says "
                        f"({expected} bytes)"
                    )
                out[filled : filled + len(chunk)] = np.frombuffer(chunk, np.uint8)
                filled += len(chunk)
                pending = inflater.unconsumed_tail
                if inflater.eof or not pending:
                    break
            if inflater.eof:
                break
    except zlib.error as exc:
        raise SourceError(f"{path}: corrupted PNG image data ({exc})") from None
    if filled != expected:
        raise SourceError(
            f"{path}: PNG image data is shorter than its {size} header says ({expected} bytes)"
        )
    return out


def _filter_rows(rows: np.ndarray, bpp: int, ftype: int) -> np.ndarray:
    """Apply one PNG filter to every row of ``rows`` (uint8, H x stride), vectorised."""
    x = rows.astype(np.int32)
    a = np.zeros_like(x)
    a[:, bpp:] = x[:, :-bpp]
    b = np.zeros_like(x)
    b[1:] = x[:-1]
    if ftype == 0:
        out = x
    elif ftype == 1:
        out = x - a
    elif ftype == 2:
        out = x - b
    elif ftype == 3:
        out = x - (a + b) // 2
    else:
        c = np.zeros_like(x)
        c[1:, bpp:] = x[:-1, :-bpp]
        p = a + b - c
        pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
        pred = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
        out = x - pred
    return (out & 0xFF).astype(np.uint8)


def encode_png(image: np.ndarray, filter: str = "paeth") -> bytes:
    """A PNG of a greyscale (H, W) uint8/uint16 image or an RGB (H, W, 3) uint8 image.

    ``filter`` is the filter of every row: "none", "sub", "up", "average" or "paeth" (Paeth
    compresses depth images best).
    """
    image = np.asarray(image)
    rgb = image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8
    grey = image.ndim == 2 and image.dtype in (np.uint8, np.uint16)
    if not (rgb or grey) or 0 in image.shape:
        raise ValueError(
            "image must be a non-empty 2-D uint8 or uint16 array or an (H, W, 3) uint8 array, "
            f"got {image.dtype} {image.shape}"
        )
    if filter not in FILTERS:
        raise ValueError(f"filter must be one of {', '.join(FILTERS)}, got {filter!r}")
    height, width = image.shape[:2]
    channels = 3 if rgb else 1
    bpp = image.dtype.itemsize * channels
    rows = np.ascontiguousarray(image.astype(image.dtype.newbyteorder(">"))).view(np.uint8)
    rows = rows.reshape(height, width * bpp)
    filtered = _filter_rows(rows, bpp, FILTERS[filter])
    raw = np.empty((height, width * bpp + 1), np.uint8)
    raw[:, 0] = FILTERS[filter]
    raw[:, 1:] = filtered

    def chunk(kind: bytes, body: bytes) -> bytes:
        return (
            struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
        )

    colour = 2 if rgb else 0
    header = struct.pack(">IIBBBBB", width, height, 8 * image.dtype.itemsize, colour, 0, 0, 0)
    return (
        _SIGNATURE
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
        + chunk(b"IEND", b"")
    )


def write_png(path: str | os.PathLike[str], image: np.ndarray, filter: str = "paeth") -> None:
    """Write a PNG (atomically); see :func:`encode_png`."""
    blob = encode_png(image, filter)
    atomic_write(Path(path), lambda fh: fh.write(blob))
