"""Marching-cubes case tables, derived from first principles at import.

Numbering (used by :mod:`engine.meshing`):

* corner ``n`` of a cube sits at offset ``(n & 1, (n >> 1) & 1, (n >> 2) & 1)`` from the
  cube's lowest voxel;
* edge ``4 * axis + o`` runs along ``axis`` from the corner whose ``axis`` bit is 0 and whose
  other two bits (the lower-numbered axis first) are those of ``o``.

Each case (the 8-bit set of *inside* corners) is triangulated by tracing, on every face of
the cube, the segments that separate inside from outside corners. A face with two inside
corners on a diagonal is ambiguous; it is always resolved by cutting each inside corner off
on its own. The rule depends on the face's four corners only, so the two cubes that share a
face make the same choice: the surface has no cracks. Chaining the segments gives closed
loops on the cube's surface, each triangulated with no diagonal that lies on a face of the
cube (the first such triangulation in a fixed enumeration; it always exists). Segments are
oriented so that triangles wind counter-clockwise seen from the outside (normals point from
inside to outside); two cubes traverse their shared segment in opposite directions, so the mesh is
consistently oriented.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EDGE_AXIS", "EDGE_CORNER", "TRI_COUNT", "TRI_TABLE", "corner_offset"]


def corner_offset(n: int) -> tuple[int, int, int]:
    return n & 1, (n >> 1) & 1, (n >> 2) & 1


def _edge_of(p: int, q: int) -> int:
    diff = p ^ q
    axis = diff.bit_length() - 1
    lower = p & ~diff
    others = [a for a in range(3) if a != axis]
    o = ((lower >> others[0]) & 1) | (((lower >> others[1]) & 1) << 1)
    return 4 * axis + o


def _faces() -> list[list[int]]:
    """The six faces' corners, counter-clockwise seen from outside the cube."""
    faces = []
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3
        for side in (0, 1):
            ring = []
            for ob, oc in ((0, 0), (1, 0), (1, 1), (0, 1)):
                ring.append((side << axis) | (ob << b) | (oc << c))
            faces.append(ring if side == 1 else ring[::-1])
    return faces


def _triangulate(case: int, faces: list[list[int]]) -> list[tuple[int, int, int]]:
    inside = [(case >> n) & 1 for n in range(8)]
    nxt: dict[int, int] = {}
    for ring in faces:
        crossings = []  # (edge, is_exit) in counter-clockwise order
        for n in range(4):
            p, q = ring[n], ring[(n + 1) % 4]
            if inside[p] != inside[q]:
                crossings.append((_edge_of(p, q), bool(inside[p])))
        for n, (edge, is_exit) in enumerate(crossings):
            if is_exit:  # pair with the crossing just before it: cuts one inside corner off
                prev = crossings[n - 1][0]
                nxt[edge] = prev
    tris: list[tuple[int, int, int]] = []
    seen: set[int] = set()
    for start in sorted(nxt):
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        e = nxt[start]
        while e != start:
            loop.append(e)
            seen.add(e)
            e = nxt[e]
        tris.extend(_triangulate_loop(loop))
    return tris


def _faces_of_edge(e: int) -> set[tuple[int, int]]:
    axis, o = divmod(e, 4)
    others = [a for a in range(3) if a != axis]
    return {(others[0], o & 1), (others[1], (o >> 1) & 1)}


def _polygon_triangulations(idx: tuple[int, ...]):
    """Every triangulation of the convex polygon ``idx`` (as index triples, in order)."""
    if len(idx) < 3:
        yield []
        return
    first, last = idx[0], idx[-1]
    for k in range(1, len(idx) - 1):
        for left in _polygon_triangulations(idx[: k + 1]):
            for right in _polygon_triangulations(idx[k:]):
                yield [*left, (first, idx[k], last), *right]


def _triangulate_loop(loop: list[int]) -> list[tuple[int, int, int]]:
    """Triangulate a loop of cube edges with no diagonal lying on a face of the cube.

    Such a diagonal would also be drawn by the neighbouring cube across that face (which
    sees the same vertices), making an edge of four triangles. Triangles wind against the
    loop's direction (outward normals, see the module note).
    """
    n = len(loop)
    for tris in _polygon_triangulations(tuple(range(n))):
        ok = True
        for tri in tris:
            for i, j in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[0], tri[2])):
                adjacent = (j - i) % n in (1, n - 1)
                if not adjacent and _faces_of_edge(loop[i]) & _faces_of_edge(loop[j]):
                    ok = False
        if ok:
            return [(loop[a], loop[c], loop[b]) for a, b, c in tris]
    raise AssertionError(f"no face-free triangulation of the loop {loop}")  # pragma: no cover


def _build() -> tuple[np.ndarray, np.ndarray]:
    faces = _faces()
    count = np.zeros(256, np.int64)
    table = np.full((256, 16), -1, np.int64)
    for case in range(256):
        tris = _triangulate(case, faces)
        count[case] = len(tris)
        for n, tri in enumerate(tris):
            table[case, 3 * n : 3 * n + 3] = tri
    return count, table


TRI_COUNT, TRI_TABLE = _build()
#: Axis of each of the 12 edges, and the corner each starts from.
EDGE_AXIS = np.array([e // 4 for e in range(12)], np.int64)
EDGE_CORNER = np.zeros((12, 3), np.int64)
for _e in range(12):
    _axis, _o = divmod(_e, 4)
    _others = [a for a in range(3) if a != _axis]
    EDGE_CORNER[_e, _others[0]] = _o & 1
    EDGE_CORNER[_e, _others[1]] = (_o >> 1) & 1
