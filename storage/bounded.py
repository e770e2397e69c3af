"""Bounded readers of array files: ``.npy``, ``.npz`` and float32 TIFF.

A hostile file can declare far more data than it holds (a 6 MB ``.npz`` whose ``range.npy``
declares 40000 x 40000 floats) or hold far more than it takes (a deflate stream inflates
about 1000-fold). Each reader here parses the header first, lets the caller check the
declared dtype and shape (against a pixel limit and the sensor, see
:func:`check_pixels`) before anything is allocated, and then reads or inflates exactly the
bytes that header declares, never more. Every problem with the bytes raises
:class:`DecodeError` whose message starts with ``where`` (a file or an upload's part).
PNG depth images have their own bounded codec (:mod:`storage.importers._png`).
See ``docs/input-safety.md``.
"""

from __future__ import annotations

import ast
import io
import math
import os
import struct
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np

__all__ = [
    "DEFAULT_MAX_PIXELS",
    "LIMIT_SETTING",
    "DecodeError",
    "NpyHeader",
    "NpzArchive",
    "check_pixels",
    "npy_array",
    "npy_header",
    "read_tiff_float",
]

#: Largest range map read by default (pixels): 4096 x 4096.
DEFAULT_MAX_PIXELS = 1 << 24
#: The setting that raises the limit (named in messages).
LIMIT_SETTING = "RANGEFUSE_MAX_PIXELS"

_NPY_MAGIC = b"\x93NUMPY"
#: numpy's own limit on an .npy header (``max_header_size``).
_MAX_HEADER = 10_000
#: Bytes copied out of a zip member at a time.
_CHUNK = 1 << 20
#: What zipfile and zlib raise on damaged or foreign archives (a lying central directory,
#: bad CRCs or deflate streams, unsupported features, names that are not UTF-8).
_ZIP_ERRORS = (
    OSError,
    EOFError,
    zipfile.BadZipFile,
    zlib.error,
    NotImplementedError,
    RuntimeError,
    ValueError,
    struct.error,
    OverflowError,
    MemoryError,
)
_COMPRESSIONS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflated"}


class DecodeError(ValueError):
    """Bytes that cannot be read as what they claim to be; the message starts with the file
    or part they came from."""


def check_pixels(where: str, what: str, height: int, width: int, max_pixels: int | None) -> None:
    """Refuse an image of ``height`` x ``width`` pixels over ``max_pixels`` (None: no limit)."""
    if max_pixels is not None and height * width > max_pixels:
        raise DecodeError(
            f"{where}: {what} of {width} x {height} pixels is over the limit of "
            f"{max_pixels:,} pixels ({LIMIT_SETTING})"
        )


# --- .npy ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class NpyHeader:
    """What an ``.npy`` header declares; ``offset`` is where its data begin."""

    dtype: np.dtype
    shape: tuple[int, ...]
    fortran_order: bool
    offset: int

    @property
    def size(self) -> int:
        """Elements declared (a Python int: no overflow)."""
        return math.prod(self.shape)

    @property
    def nbytes(self) -> int:
        return self.size * self.dtype.itemsize


def _read_exactly(fh: IO[bytes], n: int, where: str, what: str) -> bytes:
    data = fh.read(n)
    if len(data) != n:
        raise DecodeError(f"{where}: truncated {what}")
    return data


def _npy_dict(text: str, where: str) -> dict[str, Any]:
    try:  # literal_eval on at most _MAX_HEADER characters: no code runs
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError) as exc:
        raise DecodeError(f"{where}: .npy header is not a Python literal ({exc})") from None
    if not isinstance(value, dict) or set(value) != {"descr", "fortran_order", "shape"}:
        raise DecodeError(
            f"{where}: .npy header must be a dict of descr, fortran_order and shape, got "
            f"{text.strip()[:80]!r}"
        )
    return value


def _npy_dtype(descr: Any, where: str) -> np.dtype:
    if not isinstance(descr, str):  # a list: a structured dtype, maybe holding objects
        raise DecodeError(f"{where}: structured .npy dtype {str(descr)[:80]} is not supported")
    try:
        dtype = np.dtype(descr)
    except (TypeError, ValueError, SyntaxError) as exc:
        raise DecodeError(f"{where}: .npy header has an unknown dtype {descr!r} ({exc})") from None
    if dtype.hasobject:
        raise DecodeError(
            f"{where}: holds pickled Python objects (dtype object), which are never loaded"
        )
    if dtype.itemsize == 0:
        raise DecodeError(f"{where}: .npy dtype {descr!r} has no size")
    return dtype


def npy_header(fh: IO[bytes], where: str) -> NpyHeader:
    """Parse an ``.npy`` header from ``fh`` (positioned at its start), reading nothing more.

    The header is a Python literal read with :func:`ast.literal_eval`; its dtype, shape and
    order are checked, never its data (a shape may declare any size: check it before
    reading with :func:`npy_array` or :meth:`NpzArchive.read`).
    """
    magic = _read_exactly(fh, 8, where, ".npy header")
    if not magic.startswith(_NPY_MAGIC):
        raise DecodeError(f"{where}: not .npy data (no NumPy magic)")
    major, minor = magic[6], magic[7]
    if major not in (1, 2, 3) or minor != 0:
        raise DecodeError(f"{where}: unknown .npy format version {major}.{minor}")
    size_format = "<H" if major == 1 else "<I"
    raw_length = _read_exactly(fh, struct.calcsize(size_format), where, ".npy header")
    (length,) = struct.unpack(size_format, raw_length)
    if length > _MAX_HEADER:
        raise DecodeError(
            f"{where}: .npy header of {length:,} bytes is over the limit of {_MAX_HEADER:,}"
        )
    raw = _read_exactly(fh, length, where, ".npy header")
    try:
        text = raw.decode("utf8" if major == 3 else "latin1")
    except UnicodeDecodeError:
        raise DecodeError(f"{where}: .npy header is not UTF-8 text") from None
    value = _npy_dict(text, where)
    shape, order = value["shape"], value["fortran_order"]
    if (
        not isinstance(shape, tuple)
        or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)
        or len(shape) > 32
    ):
        raise DecodeError(f"{where}: .npy header has an invalid shape {str(shape)[:80]}")
    if not isinstance(order, bool):
        raise DecodeError(f"{where}: .npy header has an invalid fortran_order {order!r}")
    dtype = _npy_dtype(value["descr"], where)
    return NpyHeader(dtype, shape, order, 8 + len(raw_length) + length)


def _shaped(buffer: Any, header: NpyHeader) -> np.ndarray:
    array = np.frombuffer(buffer, header.dtype, header.size)
    return array.reshape(header.shape, order="F" if header.fortran_order else "C")


def npy_array(data: bytes, header: NpyHeader, where: str) -> np.ndarray:
    """The array of an ``.npy`` file held in ``data`` whose header was checked: a read-only
    view of ``data`` (no copy)."""
    end = header.offset + header.nbytes
    if len(data) < end:
        raise DecodeError(
            f"{where}: truncated .npy (its header declares {header.nbytes:,} bytes of data, "
            f"the file holds {max(0, len(data) - header.offset):,})"
        )
    if len(data) > end:
        raise DecodeError(
            f"{where}: .npy holds {len(data) - end:,} bytes after the array its header declares"
        )
    return _shaped(memoryview(data)[header.offset : end], header)


# --- .npz ----------------------------------------------------------------------------------


class NpzArchive:
    """An ``.npz`` (a zip of ``.npy`` members) opened for bounded reading.

    Nothing is read until asked: :meth:`header` parses a member's ``.npy`` header, and
    :meth:`read` inflates exactly the bytes that header declares (a member whose deflate
    stream holds more is refused when the first extra byte appears). Only stored and
    deflated members are read (what ``np.savez`` and ``np.savez_compressed`` write).

    Parameters
    ----------
    source : path-like or bytes
        The file, or its contents (an upload: no temporary file is written).
    where : str
        Names the archive in messages.
    """

    def __init__(
        self, source: str | os.PathLike[str] | bytes, where: str, expected: tuple[str, ...] = ()
    ) -> None:
        self.where = where
        self._zip: zipfile.ZipFile | None = None
        try:
            target: IO[bytes] | Path
            if isinstance(source, bytes):
                head, target = source[:8], io.BytesIO(source)
            else:
                target = Path(source)
                with target.open("rb") as probe:
                    head = probe.read(8)
            if not head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
                if head.startswith(_NPY_MAGIC):
                    raise DecodeError(
                        f"{where}: holds a single .npy array, not an .npz archive with keys "
                        + ", ".join(map(repr, expected))
                    )
                raise DecodeError(
                    f"{where}: not an .npz file (neither a zip archive nor NumPy data)"
                )
            self._zip = zipfile.ZipFile(target)
            members = self._zip.infolist()
        except DecodeError:
            raise
        except _ZIP_ERRORS as exc:
            raise DecodeError(f"{where}: not a readable .npz file ({exc})") from None
        self._members: dict[str, zipfile.ZipInfo] = {}
        for info in members:  # np.load's names: "range.npy" is "range"
            name = info.filename
            self._members[name[:-4] if name.endswith(".npy") else name] = info

    def __enter__(self) -> NpzArchive:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        if self._zip is not None:
            self._zip.close()

    @property
    def keys(self) -> list[str]:
        return sorted(self._members)

    def __contains__(self, key: str) -> bool:
        return key in self._members

    def _info(self, key: str) -> zipfile.ZipInfo:
        if key not in self._members:
            raise DecodeError(f"{self.where}: missing key {key!r} (has {self.keys})")
        info = self._members[key]
        if info.flag_bits & 0x1:
            raise DecodeError(f"{self.where}: key {key!r} is encrypted")
        if info.compress_type not in _COMPRESSIONS:
            raise DecodeError(
                f"{self.where}: key {key!r} uses zip compression {info.compress_type}; only "
                "stored and deflated members are read (np.savez, np.savez_compressed)"
            )
        return info

    def _open(self, info: zipfile.ZipInfo) -> IO[bytes]:
        assert self._zip is not None
        return self._zip.open(info)

    def header(self, key: str) -> NpyHeader:
        """The ``.npy`` header of ``key``, checked against the member's declared size."""
        info = self._info(key)
        where = f"{self.where}: key {key!r}"
        try:
            with self._open(info) as fh:
                header = npy_header(fh, where)
        except DecodeError:
            raise
        except _ZIP_ERRORS as exc:
            raise DecodeError(f"{where} is not a readable array ({exc})") from None
        declared = header.offset + header.nbytes
        if info.file_size != declared:
            raise DecodeError(
                f"{where} is not a readable array (its .npy header declares {declared:,} "
                f"bytes with the data, the zip entry {info.file_size:,})"
            )
        return header

    def read(self, key: str, header: NpyHeader) -> np.ndarray:
        """The array of ``key`` whose :meth:`header` was checked: exactly ``header.nbytes``
        are inflated, in chunks, into one preallocated buffer."""
        info = self._info(key)
        where = f"{self.where}: key {key!r}"
        try:
            buffer = bytearray(header.nbytes)
            view = memoryview(buffer)
            with self._open(info) as fh:
                fh.read(header.offset)
                filled = 0
                while filled < header.nbytes:
                    chunk = fh.read(min(_CHUNK, header.nbytes - filled))
                    if not chunk:
                        raise DecodeError(
                            f"{where} is not a readable array (truncated after {filled:,} of "
                            f"{header.nbytes:,} bytes)"
                        )
                    view[filled : filled + len(chunk)] = chunk
                    filled += len(chunk)
                if fh.read(1):  # also checks the CRC at the end
                    raise DecodeError(
                        f"{where} is not a readable array (more data than its header declares)"
                    )
        except DecodeError:
            raise
        except _ZIP_ERRORS as exc:
            raise DecodeError(f"{where} is not a readable array ({exc})") from None
        return _shaped(buffer, header)


# --- TIFF (float32, uncompressed, one sample per pixel) -------------------------------------

#: Tags read: their names in messages.
_TIFF_TAGS = {
    256: "ImageWidth",
    257: "ImageLength",
    258: "BitsPerSample",
    259: "Compression",
    273: "StripOffsets",
    277: "SamplesPerPixel",
    279: "StripByteCounts",
    339: "SampleFormat",
}
_TIFF_TYPES = {3: "u2", 4: "u4"}  # SHORT, LONG


def _tiff_tags(data: bytes, endian: str, where: str) -> dict[int, np.ndarray]:
    """The SHORT and LONG values of the tags in :data:`_TIFF_TAGS` (first IFD)."""
    if len(data) < 8:
        raise DecodeError(f"{where}: truncated TIFF (no header)")
    (ifd,) = struct.unpack(endian + "I", data[4:8])
    if not 8 <= ifd <= len(data) - 2:
        raise DecodeError(f"{where}: TIFF directory offset {ifd} lies outside the file")
    (count,) = struct.unpack(endian + "H", data[ifd : ifd + 2])
    if ifd + 2 + 12 * count > len(data):
        raise DecodeError(f"{where}: truncated TIFF directory ({count} entries)")
    tags: dict[int, np.ndarray] = {}
    for n in range(count):
        entry = data[ifd + 2 + 12 * n : ifd + 14 + 12 * n]
        tag, typ, num = struct.unpack(endian + "HHI", entry[:8])
        if tag not in _TIFF_TAGS:
            continue
        name = f"TIFF tag {tag} ({_TIFF_TAGS[tag]})"
        if typ not in _TIFF_TYPES:
            raise DecodeError(f"{where}: {name} has type {typ}, not SHORT or LONG")
        if num == 0:
            raise DecodeError(f"{where}: {name} has no value")
        dtype = np.dtype(endian + _TIFF_TYPES[typ])
        size = dtype.itemsize * num
        if size <= 4:
            body = entry[8 : 8 + size]
        else:
            (offset,) = struct.unpack(endian + "I", entry[8:12])
            if offset + size > len(data):
                raise DecodeError(f"{where}: the values of {name} lie outside the file")
            body = data[offset : offset + size]
        tags[tag] = np.frombuffer(body, dtype).astype(np.int64)
    return tags


def _tiff_value(tags: dict[int, np.ndarray], tag: int, default: int | None, where: str) -> int:
    if tag not in tags:
        if default is None:
            raise DecodeError(f"{where}: TIFF without tag {tag} ({_TIFF_TAGS[tag]})")
        return default
    return int(tags[tag][0])


def read_tiff_float(
    data: bytes,
    where: str,
    max_pixels: int | None = DEFAULT_MAX_PIXELS,
    shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """Decode a float32 TIFF (uncompressed strips, one sample per pixel) into float32 (H, W).

    The size is checked against ``max_pixels`` and ``shape`` (the sensor's height x width,
    when known) before anything is allocated; every strip must lie inside ``data``.
    """
    if data[:4] not in (b"II*\x00", b"MM\x00*"):
        raise DecodeError(f"{where}: not a classic TIFF file (BigTIFF is not supported)")
    endian = "<" if data[:2] == b"II" else ">"
    tags = _tiff_tags(data, endian, where)
    width = _tiff_value(tags, 256, None, where)
    height = _tiff_value(tags, 257, None, where)
    bits, compression = _tiff_value(tags, 258, 1, where), _tiff_value(tags, 259, 1, where)
    fmt, spp = _tiff_value(tags, 339, 1, where), _tiff_value(tags, 277, 1, where)
    if bits != 32 or fmt != 3 or spp != 1:
        raise DecodeError(f"{where}: TIFF must hold float32 samples, one per pixel")
    if compression != 1:
        raise DecodeError(f"{where}: compressed TIFF is not supported; write it uncompressed")
    if width == 0 or height == 0:
        raise DecodeError(f"{where}: empty TIFF ({width} x {height} pixels)")
    check_pixels(where, "TIFF", height, width, max_pixels)
    if shape is not None and (height, width) != tuple(shape):
        raise DecodeError(
            f"{where}: shape {(height, width)} does not match the sensor's height x width "
            f"{tuple(shape)}"
        )
    offsets, counts = tags.get(273), tags.get(279)
    if offsets is None or counts is None or len(offsets) != len(counts):
        raise DecodeError(f"{where}: TIFF strips: StripOffsets and StripByteCounts disagree")
    needed = width * height * 4
    out = np.empty(needed, np.uint8)
    filled = 0
    for k, (offset, count) in enumerate(zip(offsets.tolist(), counts.tolist(), strict=True)):
        if offset + count > len(data):
            raise DecodeError(f"{where}: TIFF strip {k} lies outside the file")
        take = min(count, needed - filled)
        out[filled : filled + take] = np.frombuffer(data, np.uint8, take, offset)
        filled += take
        if filled == needed:
            break
    if filled < needed:
        raise DecodeError(
            f"{where}: truncated TIFF image data ({filled:,} of {needed:,} bytes in its strips)"
        )
    return out.view(endian + "f4").reshape(height, width).astype(np.float32)
