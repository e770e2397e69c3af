"""The analytic scene: validated solids and the API over the ray-casting kernels.

An :class:`AnalyticScene` is a union of convex solids (oriented boxes, spheres and capped
cylinders, :mod:`._solids`) with exact ray casting and exact signed distances, so that tests
and benchmarks know the true surface of everything they fuse. The class checks the solids,
builds their hierarchy once (:mod:`._hierarchy`) and hands both to the kernels.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InvalidInputError
from ._hierarchy import _build_hierarchy, _cast_kernel, _distance_kernel
from ._solids import (
    _BOX_COLUMNS,
    _CYLINDER_COLUMNS,
    _SPHERE_COLUMNS,
    _check_solids,
    _solid_boxes,
    _solid_rows,
)


def _points(value: Any, name: str) -> np.ndarray:
    try:
        points = np.ascontiguousarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(name, "must be an (n, 3) array of numbers") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(name, f"must have shape (n, 3), got {points.shape}")
    return points


#: ``(boxes, spheres, cylinders, bounds, links, solids)``: a scene as the kernels take it.
_KernelScene = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _empty_rows(columns: int) -> Callable[[], np.ndarray]:
    return lambda: np.zeros((0, columns))


@dataclass(frozen=True, eq=False)
class AnalyticScene:
    """A union of convex solids: oriented boxes, spheres, capped cylinders.

    Parameters
    ----------
    boxes : array (nb, 15)
        Centre (3), half extents (3, metres, > 0), rotation matrix box -> world, row-major (9):
        ``x_W = centre + R x_B``.
    spheres : array (ns, 4)
        Centre (3), radius (metres, > 0).
    cylinders : array (nc, 7)
        End point ``a`` (3), end point ``b`` (3), radius (metres, > 0); flat caps at both ends.

    All arrays are stored as read-only float64. Invalid solids raise
    :class:`~engine.errors.InvalidInputError` naming the array.
    """

    boxes: np.ndarray = field(default_factory=_empty_rows(_BOX_COLUMNS))
    spheres: np.ndarray = field(default_factory=_empty_rows(_SPHERE_COLUMNS))
    cylinders: np.ndarray = field(default_factory=_empty_rows(_CYLINDER_COLUMNS))
    # Derived in __post_init__: the solids' axis-aligned boxes and the kernels' arguments.
    _lo: np.ndarray = field(init=False, repr=False)
    _hi: np.ndarray = field(init=False, repr=False)
    _kernel_args: _KernelScene = field(init=False, repr=False)

    def __post_init__(self) -> None:
        boxes = _solid_rows(self.boxes, _BOX_COLUMNS, "scene.boxes")
        spheres = _solid_rows(self.spheres, _SPHERE_COLUMNS, "scene.spheres")
        cylinders = _solid_rows(self.cylinders, _CYLINDER_COLUMNS, "scene.cylinders")
        _check_solids(boxes, spheres, cylinders)
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "spheres", spheres)
        object.__setattr__(self, "cylinders", cylinders)
        lo, hi, kind, row = _solid_boxes(boxes, spheres, cylinders)
        object.__setattr__(self, "_lo", lo)
        object.__setattr__(self, "_hi", hi)
        tree = _build_hierarchy(lo, hi, kind, row)
        object.__setattr__(self, "_kernel_args", (boxes, spheres, cylinders, *tree))

    @property
    def n_solids(self) -> int:
        """Number of solids (boxes, spheres and cylinders together)."""
        return len(self.boxes) + len(self.spheres) + len(self.cylinders)

    def _cast(
        self, origins_W: np.ndarray, directions_W: np.ndarray, t_max: np.ndarray
    ) -> np.ndarray:
        out = np.empty(origins_W.shape[0], np.float64)
        _cast_kernel(*self._kernel_args, origins_W, directions_W, t_max, out)
        return out

    def cast(self, origins_W: np.ndarray, directions_W: np.ndarray) -> np.ndarray:
        """Distance along each ray to the first surface.

        Parameters
        ----------
        origins_W : array (n, 3)
            Ray origins, world frame, metres.
        directions_W : array (n, 3)
            Unit ray directions, world frame (with other lengths ``t`` is in their units).

        Returns
        -------
        t : float64 array (n,)
            Smallest ``t >= 0`` at which ``origin + t direction`` enters a solid whose exit lies
            ahead (``t = 0`` for a ray that starts inside a solid); ``+inf`` on a miss.
        """
        origins = _points(origins_W, "origins_W")
        directions = _points(directions_W, "directions_W")
        if origins.shape != directions.shape:
            raise InvalidInputError(
                "directions_W", f"shape {directions.shape} differs from origins {origins.shape}"
            )
        return self._cast(origins, directions, np.full(origins.shape[0], math.inf))

    def signed_distance(self, points_W: np.ndarray) -> np.ndarray:
        """Signed distance of points to the scene, metres (negative inside a solid).

        Parameters
        ----------
        points_W : array (n, 3)
            World points, metres.

        Returns
        -------
        float64 array (n,)
            The minimum over solids of each solid's exact signed distance: exact outside the
            union; inside, minus the depth within the solid that holds the point deepest.
            ``+inf`` for an empty scene.
        """
        points = _points(points_W, "points_W")
        out = np.empty(points.shape[0], np.float64)
        _distance_kernel(*self._kernel_args, points, out)
        return out

    def bounds(self) -> tuple[float, float, float, float, float, float]:
        """Axis-aligned bounds ``(x0, y0, z0, x1, y1, z1)`` of all solids, metres."""
        if self.n_solids == 0:
            raise InvalidInputError("scene", "is empty: it has no bounds")
        lo = self._lo.min(axis=0)
        hi = self._hi.max(axis=0)
        return (float(lo[0]), float(lo[1]), float(lo[2]), float(hi[0]), float(hi[1]), float(hi[2]))

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form: ``{"boxes": [[15 numbers], ...], "spheres": ..., "cylinders": ...}``."""
        return {
            "boxes": self.boxes.tolist(),
            "spheres": self.spheres.tolist(),
            "cylinders": self.cylinders.tolist(),
        }

    @staticmethod
    def from_dict(data: dict[str, Any]) -> AnalyticScene:
        """Inverse of :meth:`to_dict`; a missing list means no solids of that kind."""
        if not isinstance(data, dict):
            raise InvalidInputError("scene", f"must be a JSON object, got {type(data).__name__}")
        unknown = sorted(set(data) - {"boxes", "spheres", "cylinders"})
        if unknown:
            raise InvalidInputError(f"scene.{unknown[0]}", "unknown field")
        return AnalyticScene(
            boxes=data.get("boxes", np.zeros((0, _BOX_COLUMNS))),
            spheres=data.get("spheres", np.zeros((0, _SPHERE_COLUMNS))),
            cylinders=data.get("cylinders", np.zeros((0, _CYLINDER_COLUMNS))),
        )
