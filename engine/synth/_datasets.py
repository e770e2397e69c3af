"""The datasets of ``rangefuse synth``: a scene, its sensor and the scans that sensor takes.

:func:`make_dataset` builds one of the three scenes (:mod:`._object`, :mod:`._room`,
:mod:`._street`) with its sensor and poses, renders every scan (:func:`~._render.render`) and
adds the noise asked for (:func:`~._noise.apply_noise`). Geometry and poses are deterministic;
only the noise depends on the seed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InvalidInputError
from ..scans import Scan
from ..sensors import Sensor
from ._noise import NoiseSpec, apply_noise
from ._object import (
    _OBJECT_BOUNDS_MARGIN_M,
    _OBJECT_CAMERA,
    _OBJECT_VIEWS,
    _object_poses,
    _object_scene,
)
from ._render import render
from ._room import _ROOM_BOUNDS_MARGIN_M, _ROOM_CAMERA, _ROOM_VIEWS, _room_poses, _room_scene
from ._scene import AnalyticScene
from ._street import (
    _STREET_BOUNDS_MARGIN_M,
    _STREET_LENGTH_M,
    _STREET_LIDAR,
    _STREET_MAX_LENGTH_M,
    _STREET_SCAN_SPACING_M,
    _street_poses,
    _street_scene,
)

SCENES: tuple[str, ...] = ("object", "room", "street")


@dataclass(frozen=True, eq=False)
class SyntheticDataset:
    """A rendered scene: the solids, the sensor and the scans (see :func:`make_dataset`).

    Parameters
    ----------
    name : str
        One of :data:`SCENES`.
    scene : AnalyticScene
        The true geometry.
    sensor : Sensor
        The sensor of every scan.
    scans : list of (str, Scan)
        ``("scan_0000", Scan), ...`` in order.
    bounds : (x0, y0, z0, x1, y1, z1)
        Region of interest for closed-mode fusion: the scene's solids plus a small margin.
    """

    name: str
    scene: AnalyticScene
    sensor: Sensor
    scans: list[tuple[str, Scan]]
    bounds: tuple[float, float, float, float, float, float]


def _check_views(views: Any) -> int | None:
    if views is None:
        return None
    if isinstance(views, bool) or not isinstance(views, (int, np.integer)):
        raise InvalidInputError("views", f"must be an integer, got {views!r}")
    if views < 1:
        raise InvalidInputError("views", f"must be at least 1, got {views}")
    return int(views)


def _check_length(name: str, length_m: Any) -> float:
    if length_m is None:
        return _STREET_LENGTH_M
    if name != "street":
        raise InvalidInputError("length_m", f"applies to the street scene only, not {name!r}")
    if isinstance(length_m, bool) or not isinstance(length_m, (int, float, np.number)):
        raise InvalidInputError("length_m", f"must be a number of metres, got {length_m!r}")
    value = float(length_m)
    if not (math.isfinite(value) and 0.0 < value <= _STREET_MAX_LENGTH_M):
        raise InvalidInputError(
            "length_m", f"must be > 0 and at most {_STREET_MAX_LENGTH_M:g} m, got {length_m!r}"
        )
    return value


def make_dataset(
    name: str,
    views: int | None = None,
    noise: NoiseSpec | None = None,
    seed: int = 0,
    length_m: float | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SyntheticDataset:
    """Render one of the synthetic scenes.

    Parameters
    ----------
    name : {"object", "room", "street"}
        ``object``: a robot arm about 0.9 m across seen by a 640x480 ray-range pinhole camera
        from ``views`` (default 12) directions on a 2 m sphere; ``room``: a furnished
        5 x 4 x 2.6 m room seen by a 640x480 z-depth RGB-D camera on a closed loop (default 100
        views); ``street``: a street seen by a 64-beam spherical LiDAR 1.8 m above the road,
        one scan every 2 m by default.
    views : int or None
        Number of scans (>= 1); None for the scene's default.
    noise : NoiseSpec or None
        Noise added to every scan (see :func:`apply_noise`); None for none.
    seed : int
        Seed of the noise (``np.random.default_rng(seed)``); geometry and poses do not depend
        on it.
    length_m : float or None
        Street length in metres (default 40); street only.
    progress : callable or None
        ``progress(done, total)`` is called after each scan is rendered.

    Returns
    -------
    SyntheticDataset

    Raises
    ------
    InvalidInputError
        Naming ``name``, ``views``, ``noise`` or ``length_m``.
    """
    if name not in SCENES:
        raise InvalidInputError(
            "name", f"unknown scene {name!r}; expected one of {', '.join(SCENES)}"
        )
    n_views = _check_views(views)
    length = _check_length(name, length_m)
    if noise is None:
        noise = NoiseSpec()
    if not isinstance(noise, NoiseSpec):
        raise InvalidInputError("noise", f"must be a NoiseSpec, got {type(noise).__name__}")
    sensor: Sensor
    if name == "object":
        scene = _object_scene()
        sensor = _OBJECT_CAMERA
        poses = _object_poses(n_views or _OBJECT_VIEWS, scene)
        margin = _OBJECT_BOUNDS_MARGIN_M
    elif name == "room":
        scene = _room_scene()
        sensor = _ROOM_CAMERA
        poses = _room_poses(n_views or _ROOM_VIEWS)
        margin = _ROOM_BOUNDS_MARGIN_M
    else:
        scene = _street_scene(length)
        sensor = _STREET_LIDAR
        default = max(1, round(length / _STREET_SCAN_SPACING_M))
        poses = _street_poses(n_views or default, length)
        margin = _STREET_BOUNDS_MARGIN_M
    rng = np.random.default_rng(seed)
    scans = []
    for k, T_W_S in enumerate(poses):
        range_m = render(scene, sensor, T_W_S)
        if noise != NoiseSpec():
            range_m = apply_noise(range_m, noise, sensor, rng)
        scans.append((f"scan_{k:04d}", Scan(range_m=range_m, T_W_S=T_W_S, sensor=sensor)))
        if progress is not None:
            progress(k + 1, len(poses))
    x0, y0, z0, x1, y1, z1 = scene.bounds()
    bounds = (x0 - margin, y0 - margin, z0 - margin, x1 + margin, y1 + margin, z1 + margin)
    return SyntheticDataset(name=name, scene=scene, sensor=sensor, scans=scans, bounds=bounds)
