"""Reading the PLY files of range scanners (ASCII and binary).

Stanford's range scans are PLY files with an ``element vertex`` (x y z, perhaps more
properties) and an ``element range_grid`` whose cells each list 0 or 1 vertex indices, plus
``obj_info`` lines (``num_cols``, ``num_rows``, ``is_interlaced``). This reader returns
those pieces; it handles elements whose properties are all scalars, and elements that hold
a single list property (``range_grid``, ``face``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import SourceError

__all__ = ["PlyElement", "PlyFile", "read_ply"]

_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass
class PlyElement:
    name: str
    count: int
    scalars: list[tuple[str, str]] = field(default_factory=list)  # (name, numpy type)
    list_prop: tuple[str, str, str] | None = None  # (name, count type, item type)
    # filled by the reader
    data: np.ndarray | None = None  # structured array of the scalar properties
    counts: np.ndarray | None = None  # list property: items per element
    items: np.ndarray | None = None  # list property: the items, concatenated


@dataclass
class PlyFile:
    path: Path
    elements: dict[str, PlyElement]
    obj_info: dict[str, str]


def _header(path: Path, blob: bytes) -> tuple[str, list[PlyElement], dict[str, str], int]:
    end = blob.find(b"end_header")
    if not blob.startswith(b"ply") or end < 0:
        raise SourceError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header)")
    newline = blob.find(b"\n", end)
    if newline < 0:
        raise SourceError(f"{path}: truncated PLY header")
    text = blob[:end].decode("ascii", errors="replace")
    fmt = ""
    elements: list[PlyElement] = []
    info: dict[str, str] = {}
    for number, line in enumerate(text.splitlines()[1:], start=2):
        tokens = line.split()
        if not tokens or tokens[0] == "comment":
            continue
        where = f"{path} line {number}"
        if tokens[0] == "format":
            fmt = tokens[1] if len(tokens) > 1 else ""
        elif tokens[0] == "obj_info":
            if len(tokens) >= 3:
                info[tokens[1]] = tokens[2]
        elif tokens[0] == "element":
            try:
                elements.append(PlyElement(tokens[1], int(tokens[2])))
            except (IndexError, ValueError):
                raise SourceError(f"{where}: malformed element line {line!r}") from None
            if not 0 <= elements[-1].count <= len(blob):  # each takes a byte at least
                raise SourceError(
                    f"{where}: element {tokens[1]!r} declares {tokens[2]} items, more than "
                    f"the file's {len(blob):,} bytes can hold"
                )
        elif tokens[0] == "property":
            if not elements:
                raise SourceError(f"{where}: property before any element")
            el = elements[-1]
            if len(tokens) == 5 and tokens[1] == "list":
                if tokens[2] not in _TYPES or tokens[3] not in _TYPES:
                    raise SourceError(f"{where}: unknown PLY type in {line!r}")
                if el.list_prop is not None or el.scalars:
                    raise SourceError(
                        f"{where}: element {el.name!r} mixes a list with other properties "
                        "(not supported)"
                    )
                el.list_prop = (tokens[4], _TYPES[tokens[2]], _TYPES[tokens[3]])
            elif len(tokens) == 3 and tokens[1] in _TYPES:
                if el.list_prop is not None:
                    raise SourceError(
                        f"{where}: element {el.name!r} mixes a list with other properties "
                        "(not supported)"
                    )
                el.scalars.append((tokens[2], _TYPES[tokens[1]]))
            else:
                raise SourceError(f"{where}: malformed property line {line!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise SourceError(f"{path}: unknown PLY format {fmt!r}")
    return fmt, elements, info, newline + 1


def _read_ascii(path: Path, body: bytes, elements: list[PlyElement]) -> None:
    tokens = body.split()
    pos = 0
    for el in elements:
        if el.list_prop is None:
            n = el.count * len(el.scalars)
            chunk = tokens[pos : pos + n]
            if len(chunk) != n:
                raise SourceError(f"{path}: truncated PLY (element {el.name!r})")
            try:
                values = np.array(chunk, dtype=np.float64).reshape(el.count, len(el.scalars))
            except ValueError:
                raise SourceError(f"{path}: non-numeric value in element {el.name!r}") from None
            dtype = np.dtype([(name, typ) for name, typ in el.scalars])
            data = np.empty(el.count, dtype)
            for i, (name, _) in enumerate(el.scalars):
                data[name] = values[:, i]
            el.data = data
            pos += n
            continue
        counts = np.empty(el.count, np.int64)
        items: list[bytes] = []
        try:
            for i in range(el.count):
                k = int(tokens[pos])
                counts[i] = k
                items.extend(tokens[pos + 1 : pos + 1 + k])
                pos += 1 + k
        except (IndexError, ValueError):
            raise SourceError(f"{path}: truncated or malformed PLY (element {el.name!r})") from None
        if len(items) != int(counts.sum()):
            raise SourceError(f"{path}: truncated PLY (element {el.name!r})")
        el.counts = counts
        el.items = np.array(items, dtype=np.float64) if items else np.zeros(0)


def _read_binary(path: Path, body: bytes, elements: list[PlyElement], order: str) -> None:
    pos = 0
    for el in elements:
        if el.list_prop is None:
            dtype = np.dtype([(name, order + typ) for name, typ in el.scalars])
            n = el.count * dtype.itemsize
            if pos + n > len(body):
                raise SourceError(f"{path}: truncated PLY (element {el.name!r})")
            el.data = np.frombuffer(body, dtype, el.count, pos).copy()
            pos += n
            continue
        _, count_type, item_type = el.list_prop
        ctype = np.dtype(order + count_type)
        itype = np.dtype(order + item_type)
        counts = np.empty(el.count, np.int64)
        starts = np.empty(el.count, np.int64)
        try:
            for i in range(el.count):  # sequential: each count says where the next begins
                k = int(np.frombuffer(body, ctype, 1, pos)[0])
                counts[i] = k
                starts[i] = pos + ctype.itemsize
                pos += ctype.itemsize + k * itype.itemsize
        except ValueError:
            raise SourceError(f"{path}: truncated PLY (element {el.name!r})") from None
        if pos > len(body):
            raise SourceError(f"{path}: truncated PLY (element {el.name!r})")
        items = [
            np.frombuffer(body, itype, int(k), int(s))
            for k, s in zip(counts, starts, strict=True)
            if k
        ]
        el.counts = counts
        el.items = np.concatenate(items).astype(np.float64) if items else np.zeros(0)


def read_ply(path: Path) -> PlyFile:
    """Read a PLY file's elements (see :class:`PlyElement`) and ``obj_info`` entries.

    Raises
    ------
    SourceError
        For a missing, truncated or malformed file; the message names it.
    """
    try:
        blob = path.read_bytes()
    except FileNotFoundError:
        raise SourceError(f"{path}: no such file") from None
    except OSError as exc:
        raise SourceError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    fmt, elements, info, start = _header(path, blob)
    body = blob[start:]
    if fmt == "ascii":
        _read_ascii(path, body, elements)
    else:
        _read_binary(path, body, elements, "<" if fmt == "binary_little_endian" else ">")
    return PlyFile(path, {el.name: el for el in elements}, info)
