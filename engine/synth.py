"""Synthetic range data: analytic scenes rendered into range maps (FORMAT.md encoding).

An :class:`AnalyticScene` is a union of convex solids (oriented boxes, spheres and capped
cylinders) with exact ray casting and exact signed distances, so that tests and benchmarks
know the true surface of everything they fuse (STYLE.md 17). :func:`render` turns a scene,
a sensor and a pose ``T_W_S`` into the range map the sensor would measure (``+inf``: no
return within ``max_range``, NaN: closer than ``min_range``); :func:`apply_noise` adds
range noise, spikes, dropouts and an invalid background; :func:`make_dataset` builds the
three scenes of ``rangefuse synth`` (``object``, ``room``, ``street``) with their sensors
and poses.

This module holds rendering, noise and datasets; the solids, their bounding-volume hierarchy
and the ray-casting kernels are in :mod:`engine._raycast`, :class:`SceneBuilder` and the three
scenes in :mod:`engine._scenes`. Geometry and poses are deterministic; only the noise depends
on the seed.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ._raycast import AnalyticScene, _render_kernel
from ._scenes import (
    _OBJECT_BOUNDS_MARGIN_M,
    _OBJECT_CAMERA,
    _OBJECT_VIEWS,
    _ROOM_BOUNDS_MARGIN_M,
    _ROOM_CAMERA,
    _ROOM_VIEWS,
    _STREET_BOUNDS_MARGIN_M,
    _STREET_LENGTH_M,
    _STREET_LIDAR,
    _STREET_MAX_LENGTH_M,
    _STREET_SCAN_SPACING_M,
    SceneBuilder,
    _object_poses,
    _object_scene,
    _room_poses,
    _room_scene,
    _street_poses,
    _street_scene,
)
from .errors import InvalidInputError
from .scans import Scan, check_pose
from .sensors import Sensor

__all__ = [
    "SCENES",
    "AnalyticScene",
    "NoiseSpec",
    "SceneBuilder",
    "SyntheticDataset",
    "apply_noise",
    "make_dataset",
    "parse_noise",
    "render",
]

SCENES: tuple[str, ...] = ("object", "room", "street")

# --- rendering ---------------------------------------------------------------------------------


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
    """Range map of a scene seen by a sensor (FORMAT.md encoding).

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


# --- noise -------------------------------------------------------------------------------------

_NOISE_KINDS = ("uniform", "gaussian", "spikes", "dropouts", "background")
_NOISE_FIELDS = {
    "uniform": "uniform_m",
    "gaussian": "gaussian_m",
    "spikes": "spikes",
    "dropouts": "dropouts",
    "background": "background",
}
_NOISE_GRAMMAR = (
    "valid kinds: uniform:<metres>, gaussian:<metres>, spikes:<fraction>, dropouts:<fraction>, "
    "background:inf|nan, or 'none'"
)
_BACKGROUNDS = ("inf", "nan")
#: Noisy ranges are clipped to at least max(min_range, this), so that they stay positive.
_MIN_NOISY_RANGE_M = 1e-3


@dataclass(frozen=True)
class NoiseSpec:
    """Measurement noise added to rendered range maps (see :func:`apply_noise`).

    Parameters
    ----------
    uniform_m : float
        Half-width of additive uniform noise, metres (>= 0).
    gaussian_m : float
        Standard deviation of additive Gaussian noise, metres (>= 0).
    spikes : float
        Fraction of valid (finite) pixels replaced by a uniform random range in
        ``[min_range, max_range]`` (outliers), in [0, 1].
    dropouts : float
        Fraction of all pixels set to NaN (invalid), in [0, 1].
    background : {"inf", "nan"}
        How misses are written: ``"inf"`` (no return) or ``"nan"`` (invalid).
    """

    uniform_m: float = 0.0
    gaussian_m: float = 0.0
    spikes: float = 0.0
    dropouts: float = 0.0
    background: str = "inf"

    def __post_init__(self) -> None:
        for name in ("uniform_m", "gaussian_m", "spikes", "dropouts"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise InvalidInputError(f"noise.{name}", f"must be a number, got {value!r}")
            value = float(value)
            if not math.isfinite(value) or value < 0.0:
                raise InvalidInputError(f"noise.{name}", f"must be finite and >= 0, got {value}")
            if name in ("spikes", "dropouts") and value > 1.0:
                raise InvalidInputError(f"noise.{name}", f"is a fraction in [0, 1], got {value}")
            object.__setattr__(self, name, value)
        if self.background not in _BACKGROUNDS:
            raise InvalidInputError(
                "noise.background", f"must be 'inf' or 'nan', got {self.background!r}"
            )

    def to_spec(self) -> str:
        """The :func:`parse_noise` form of this noise (``"none"`` when it adds nothing)."""
        items = [
            f"{kind}:{getattr(self, _NOISE_FIELDS[kind]):g}"
            for kind in _NOISE_KINDS[:4]
            if getattr(self, _NOISE_FIELDS[kind]) > 0.0
        ]
        if self.background != "inf":
            items.append(f"background:{self.background}")
        return ",".join(items) if items else "none"

    def to_dict(self) -> dict[str, Any]:
        return {
            "uniform_m": self.uniform_m,
            "gaussian_m": self.gaussian_m,
            "spikes": self.spikes,
            "dropouts": self.dropouts,
            "background": self.background,
        }

    @staticmethod
    def from_dict(data: dict[str, Any]) -> NoiseSpec:
        if not isinstance(data, dict):
            raise InvalidInputError("noise", f"must be a JSON object, got {type(data).__name__}")
        unknown = sorted(set(data) - set(_NOISE_FIELDS.values()))
        if unknown:
            raise InvalidInputError(f"noise.{unknown[0]}", "unknown field")
        return NoiseSpec(**data)


def _noise_error(item: str, problem: str) -> InvalidInputError:
    return InvalidInputError("noise", f"item {item!r}: {problem} ({_NOISE_GRAMMAR})")


def parse_noise(spec: str) -> NoiseSpec:
    """Parse a noise specification such as ``"gaussian:0.005,dropouts:0.05"``.

    Parameters
    ----------
    spec : str
        ``"none"`` (or empty), or comma-separated ``kind:value`` items: ``uniform:M`` and
        ``gaussian:M`` (metres, >= 0), ``spikes:F`` and ``dropouts:F`` (fractions in [0, 1]),
        ``background:inf`` or ``background:nan``. Each kind at most once.

    Returns
    -------
    NoiseSpec

    Raises
    ------
    InvalidInputError
        Field ``"noise"``; the message names the offending item and lists the valid kinds.
    """
    if not isinstance(spec, str):
        raise InvalidInputError("noise", f"must be a string, got {type(spec).__name__}")
    text = spec.strip()
    if text.lower() in ("", "none"):
        return NoiseSpec()
    values: dict[str, Any] = {}
    for raw in text.split(","):
        item = raw.strip()
        if not item:
            raise _noise_error(raw, "empty item")
        kind, sep, value_text = item.partition(":")
        kind = kind.strip().lower()
        value_text = value_text.strip()
        if kind not in _NOISE_KINDS:
            raise _noise_error(item, f"unknown kind {kind!r}")
        if not sep or not value_text:
            raise _noise_error(item, f"{kind} needs a value after ':'")
        if _NOISE_FIELDS[kind] in values:
            raise _noise_error(item, f"{kind} is given twice")
        if kind == "background":
            if value_text.lower() not in _BACKGROUNDS:
                raise _noise_error(item, f"background must be inf or nan, got {value_text!r}")
            values["background"] = value_text.lower()
            continue
        try:
            value = float(value_text)
        except ValueError:
            raise _noise_error(item, f"{value_text!r} is not a number") from None
        if not math.isfinite(value):
            raise _noise_error(item, f"{value_text!r} is not a finite number")
        if value < 0.0:
            raise _noise_error(item, f"{kind} must be >= 0, got {value:g}")
        if kind in ("spikes", "dropouts") and value > 1.0:
            raise _noise_error(item, f"{kind} is a fraction in [0, 1], got {value:g}")
        values[_NOISE_FIELDS[kind]] = value
    return NoiseSpec(**values)


def apply_noise(
    range_m: np.ndarray, noise: NoiseSpec, sensor: Sensor, rng: np.random.Generator
) -> np.ndarray:
    """Noisy copy of a range map.

    Parameters
    ----------
    range_m : array (H, W)
        Range map in the FORMAT.md encoding (finite, ``+inf`` no return, NaN invalid).
    noise : NoiseSpec
    sensor : Sensor
        Gives ``min_range`` and ``max_range``; ``sensor.shape`` must match the map.
    rng : numpy.random.Generator
        Source of all randomness (same state, same result).

    Returns
    -------
    float32 array (H, W)
        Uniform and Gaussian noise are added to the finite pixels, which then stay at least
        ``max(min_range, 1 mm)``; a ``spikes`` fraction of the finite pixels is replaced by a
        range drawn uniformly in that floor .. ``max_range``; a ``dropouts`` fraction of all
        pixels becomes NaN; with ``background="nan"`` every ``+inf`` becomes NaN.
    """
    if not isinstance(noise, NoiseSpec):
        raise InvalidInputError("noise", f"must be a NoiseSpec, got {type(noise).__name__}")
    values = np.array(range_m, dtype=np.float64)
    if values.shape != sensor.shape:
        raise InvalidInputError(
            "range", f"shape {values.shape} does not match the sensor's {sensor.shape}"
        )
    floor_m = max(sensor.min_range, _MIN_NOISY_RANGE_M)
    hit = np.flatnonzero(np.isfinite(values))
    flat = values.reshape(-1)
    measured = flat[hit]
    if noise.uniform_m > 0.0:
        measured += rng.uniform(-noise.uniform_m, noise.uniform_m, hit.size)
    if noise.gaussian_m > 0.0:
        measured += rng.normal(0.0, noise.gaussian_m, hit.size)
    np.maximum(measured, floor_m, out=measured)
    if noise.spikes > 0.0:
        spike = rng.random(hit.size) < noise.spikes
        measured[spike] = rng.uniform(floor_m, max(sensor.max_range, floor_m), int(spike.sum()))
    flat[hit] = measured
    if noise.dropouts > 0.0:
        flat[rng.random(flat.size) < noise.dropouts] = math.nan
    if noise.background == "nan":
        flat[np.isposinf(flat)] = math.nan
    return flat.reshape(sensor.shape).astype(np.float32)


# --- datasets ----------------------------------------------------------------------------------


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
    x0, y0, z0, x1, y1, z1 = scene.bounds()
    bounds = (x0 - margin, y0 - margin, z0 - margin, x1 + margin, y1 + margin, z1 + margin)
    return SyntheticDataset(name=name, scene=scene, sensor=sensor, scans=scans, bounds=bounds)
