"""Rendering: the range map a sensor at a pose would measure of an analytic scene.

:func:`render` casts every pixel ray of a sensor (:meth:`Sensor.pixel_rays`) into the scene and
writes the range of the first hit in the sensor's range convention, in the dataset encoding of
``docs/formats.md`` (``+inf``: no return within ``max_range``, NaN: closer than ``min_range``).
The render kernel walks the scene's hierarchy (:mod:`._hierarchy`) and projects each hit with
the sensor kernels, in the sensor frame.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit, prange

from .. import _sensor_kernels as _k
from ..errors import InvalidInputError
from ..scans import check_pose
from ..sensors import Sensor
from ._hierarchy import _ITEMS_PER_TASK, _STACK_DEPTH, _first_hit
from ._scene import AnalyticScene


@njit(cache=True, parallel=True)
def _render_kernel(
    boxes, spheres, cylinders, bounds, links, solids, T_W_S, origins_S, directions_S, t_max,
    kind, params, table, out,
):  # fmt: skip
    """Range ``out[i]`` of pixel ray ``i`` (sensor frame): the hit point's distance in the
    sensor's convention, inf on a miss or beyond ``max_range``, NaN closer than ``min_range``."""
    min_range = params[_k.P_MIN_RANGE]
    max_range = params[_k.P_MAX_RANGE]
    T = T_W_S
    n_rays = origins_S.shape[0]
    n_tasks = (n_rays + _ITEMS_PER_TASK - 1) // _ITEMS_PER_TASK
    for task in prange(n_tasks):
        stack = np.empty(_STACK_DEPTH, np.int64)
        stop = min(n_rays, (task + 1) * _ITEMS_PER_TASK)
        for i in range(task * _ITEMS_PER_TASK, stop):
            sx, sy, sz = origins_S[i, 0], origins_S[i, 1], origins_S[i, 2]
            ex, ey, ez = directions_S[i, 0], directions_S[i, 1], directions_S[i, 2]
            ray_W = (
                T[0, 0] * sx + T[0, 1] * sy + T[0, 2] * sz + T[0, 3],
                T[1, 0] * sx + T[1, 1] * sy + T[1, 2] * sz + T[1, 3],
                T[2, 0] * sx + T[2, 1] * sy + T[2, 2] * sz + T[2, 3],
                T[0, 0] * ex + T[0, 1] * ey + T[0, 2] * ez,
                T[1, 0] * ex + T[1, 1] * ey + T[1, 2] * ez,
                T[2, 0] * ex + T[2, 1] * ey + T[2, 2] * ez,
            )
            t = _first_hit(boxes, spheres, cylinders, bounds, links, solids, ray_W, t_max[i], stack)
            if t == math.inf:
                out[i] = math.inf
                continue
            # The hit point in the sensor frame, straight from the sensor-frame ray.
            d = _k.project_point(kind, params, table, sx + t * ex, sy + t * ey, sz + t * ez)[2]
            if d > max_range:
                out[i] = math.inf
            elif d < min_range or math.isnan(d):
                out[i] = math.nan
            else:
                out[i] = d


@functools.lru_cache(maxsize=4)
def _sensor_rays(sensor: Sensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel rays ``(origins_S, directions_S)`` (H*W, 3) and the ray length ``t_max`` (H*W,)
    beyond which the range exceeds ``max_range``.

    Every model's range grows linearly along its pixel rays, so two points fix the rate; where
    that fails ``t_max`` is inf (render still tests the range of every hit).
    """
    origins, directions = sensor.pixel_rays()
    origins = np.ascontiguousarray(origins.reshape(-1, 3))
    directions = np.ascontiguousarray(directions.reshape(-1, 3))
    d1 = sensor.project(origins + directions)[2]
    d2 = sensor.project(origins + 2.0 * directions)[2]
    rate = d2 - d1
    with np.errstate(invalid="ignore", divide="ignore"):
        t_max = 1.0 + (sensor.max_range - d1) / rate
    t_max = np.where(np.isfinite(t_max) & (rate > 0.0), t_max * (1.0 + 1e-6) + 1e-6, math.inf)
    for array in (origins, directions, t_max):
        array.setflags(write=False)
    return origins, directions, t_max


def render(scene: AnalyticScene, sensor: Sensor, T_W_S: np.ndarray) -> np.ndarray:
    """Range map of a scene seen by a sensor (the encoding of ``docs/formats.md``).

    Parameters
    ----------
    scene : AnalyticScene
    sensor : Sensor
        Any sensor model; its pixel rays (:meth:`Sensor.pixel_rays`) are cast into the scene.
    T_W_S : array (4, 4)
        Sensor-to-world pose, rigid.

    Returns
    -------
    float32 array (H, W)
        Distance of the first hit in the sensor's range convention (``sensor.project`` of the
        hit point, e.g. z-depth for a ``"z"`` pinhole camera); ``+inf`` for a miss or a hit
        beyond ``max_range`` (no return), NaN for a hit closer than ``min_range`` (invalid).
    """
    if not isinstance(scene, AnalyticScene):
        raise InvalidInputError("scene", f"must be an AnalyticScene, got {type(scene).__name__}")
    if not isinstance(sensor, Sensor):
        raise InvalidInputError("sensor", f"must be a Sensor, got {type(sensor).__name__}")
    T = check_pose(T_W_S, "T_W_S")
    origins_S, directions_S, t_max = _sensor_rays(sensor)
    kind, params, table = sensor.kernel_args()
    out = np.empty(origins_S.shape[0], np.float32)
    _render_kernel(*scene._kernel_args, T, origins_S, directions_S, t_max, kind, params, table, out)
    return out.reshape(sensor.shape)
