"""Sensor models: pinhole, spherical, cylindrical, orthographic (FORMAT.md).

A sensor maps a point ``p_S`` in its own frame to continuous pixel
coordinates ``(u, v)`` (pixel centres at integers: column ``u`` in
``0..W-1``, row ``v`` in ``0..H-1``) and a line-of-sight distance ``d`` in the
sensor's range convention, and back (METHOD.md "Inputs"). Each model is a
frozen dataclass with ``to_dict``/``from_dict`` in the FORMAT.md JSON layout;
kernels receive it as ``kernel_args()``: a kind code, a float64 parameter
vector and an elevation table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import numpy as np

from . import _sensor_kernels as _k
from .errors import InvalidSensorError

__all__ = [
    "CylindricalSensor",
    "OrthographicSensor",
    "PinholeSensor",
    "Sensor",
    "SphericalSensor",
    "sensor_from_dict",
]

_TWO_PI = 2.0 * math.pi
#: A full turn may be given to 5 decimals (FORMAT.md writes -3.14159 .. 3.14159).
_FULL_TURN_TOLERANCE = 1e-4


def _require_finite(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InvalidSensorError(f"sensor.{name}", f"must be a number, got {value!r}") from None
    if not math.isfinite(value):
        raise InvalidSensorError(f"sensor.{name}", f"must be finite, got {value}")
    return value


def _require_positive(name: str, value: float) -> float:
    value = _require_finite(name, value)
    if value <= 0.0:
        raise InvalidSensorError(f"sensor.{name}", f"must be > 0, got {value}")
    return value


@dataclass(frozen=True, kw_only=True)
class Sensor:
    """Common fields of every sensor model.

    Parameters
    ----------
    width, height : int
        Image size in pixels (at least 2 each, so that bilinear interpolation has four pixels).
    min_range, max_range : float
        Metres. ``max_range`` is where a no-return pixel (``+inf``) is taken to end (METHOD §1).
    """

    model: ClassVar[str] = ""
    kind: ClassVar[int] = -1
    conventions: ClassVar[tuple[str, ...]] = ("ray",)

    width: int
    height: int
    max_range: float
    min_range: float = 0.0
    range_convention: str = "ray"

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise InvalidSensorError(f"sensor.{name}", f"must be an integer, got {value!r}")
            if value < 2:
                raise InvalidSensorError(f"sensor.{name}", f"must be at least 2, got {value}")
            object.__setattr__(self, name, int(value))
        min_range = _require_finite("min_range", self.min_range)
        max_range = _require_finite("max_range", self.max_range)
        if min_range < 0.0:
            raise InvalidSensorError("sensor.min_range", f"must be >= 0, got {min_range}")
        if max_range <= min_range:
            raise InvalidSensorError(
                "sensor.max_range", f"must be greater than min_range ({min_range}), got {max_range}"
            )
        object.__setattr__(self, "min_range", min_range)
        object.__setattr__(self, "max_range", max_range)
        if self.range_convention not in self.conventions:
            raise InvalidSensorError(
                "sensor.range_convention",
                f"{self.model} sensors take one of {', '.join(map(repr, self.conventions))}, "
                f"got {self.range_convention!r}",
            )

    # --- kernel form -------------------------------------------------------------------------
    def _fill_params(self, params: np.ndarray) -> None:
        raise NotImplementedError

    def kernel_args(self) -> tuple[int, np.ndarray, np.ndarray]:
        """``(kind, params, table)`` as kernels take them (see ``engine._sensor_kernels``)."""
        params = np.zeros(_k.N_PARAMS, dtype=np.float64)
        params[_k.P_W] = self.width
        params[_k.P_H] = self.height
        params[_k.P_MIN_RANGE] = self.min_range
        params[_k.P_MAX_RANGE] = self.max_range
        self._fill_params(params)
        return self.kind, params, self._table()

    def _table(self) -> np.ndarray:
        return _k.empty_table()

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``: the shape of this sensor's range maps."""
        return (self.height, self.width)

    # --- geometry ----------------------------------------------------------------------------
    def project(self, p_S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project sensor-frame points.

        Parameters
        ----------
        p_S : array (..., 3)
            Points in the sensor frame, metres.

        Returns
        -------
        u, v, d : arrays (...)
            Continuous column and row (pixel centres at integers) and the distance in
            this sensor's range convention; ``u`` is NaN where a point has no pixel.
            Whether ``(u, v)`` lies inside the image is tested by :meth:`in_image`.
        """
        pts = np.ascontiguousarray(np.asarray(p_S, dtype=np.float64).reshape(-1, 3))
        out = np.empty_like(pts)
        kind, params, table = self.kernel_args()
        _k.project_many(kind, params, table, pts, out)
        shape = np.shape(p_S)[:-1]
        return out[:, 0].reshape(shape), out[:, 1].reshape(shape), out[:, 2].reshape(shape)

    def unproject(self, u: np.ndarray, v: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`project`: points ``p_S`` (..., 3) at distance ``d`` on ``(u, v)``."""
        u, v, d = np.broadcast_arrays(
            np.asarray(u, np.float64), np.asarray(v, np.float64), np.asarray(d, np.float64)
        )
        uvd = np.ascontiguousarray(np.stack([u, v, d], axis=-1).reshape(-1, 3))
        out = np.empty_like(uvd)
        kind, params, table = self.kernel_args()
        _k.unproject_many(kind, params, table, uvd, out)
        return out.reshape((*u.shape, 3))

    def in_image(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Boolean mask of pixel coordinates that can be interpolated (METHOD exact conventions)."""
        u = np.asarray(u, np.float64)
        v = np.asarray(v, np.float64)
        ok = (v >= 0.0) & (v <= self.height - 1)
        if getattr(self, "wrap", False):
            return ok & (u >= 0.0) & (u < self.width)
        return ok & (u >= 0.0) & (u <= self.width - 1)

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Ray origin and unit direction of every pixel, sensor frame, each (H, W, 3).

        The point at distance ``d`` of pixel ``(u, v)`` lies on that ray; used to render
        scenes into range maps.
        """
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        origin = self.unproject(u, v, np.zeros_like(u))
        direction = self.unproject(u, v, np.ones_like(u)) - origin
        direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
        return origin, direction

    # --- (de)serialisation ---------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The FORMAT.md ``sensor.json`` form of this sensor."""
        out: dict[str, Any] = {"model": self.model}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            out[f.name] = list(value) if isinstance(value, tuple) else value
        return out

    @staticmethod
    def from_dict(data: dict[str, Any]) -> Sensor:
        """Build a sensor from its FORMAT.md JSON form; see :func:`sensor_from_dict`."""
        return sensor_from_dict(data)


@dataclass(frozen=True, kw_only=True)
class PinholeSensor(Sensor):
    """Pinhole camera, OpenCV frame (x right, y down, z forward).

    ``u = fx x / z + cx``, ``v = fy y / z + cy`` for ``z > 0``; range is ``|p|`` (``"ray"``)
    or ``z`` (``"z"``, what most RGB-D cameras write).
    """

    model: ClassVar[str] = "pinhole"
    kind: ClassVar[int] = _k.PINHOLE
    conventions: ClassVar[tuple[str, ...]] = ("ray", "z")

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("fx", "fy"):
            object.__setattr__(self, name, _require_positive(name, getattr(self, name)))
        for name in ("cx", "cy"):
            object.__setattr__(self, name, _require_finite(name, getattr(self, name)))

    def _fill_params(self, params: np.ndarray) -> None:
        params[_k.P_FX] = self.fx
        params[_k.P_FY] = self.fy
        params[_k.P_CX] = self.cx
        params[_k.P_CY] = self.cy
        params[_k.P_Z_CONV] = 1.0 if self.range_convention == "z" else 0.0


def _check_azimuths(az_min: float, az_max: float, wrap: bool) -> tuple[float, float]:
    az_min = _require_finite("az_min", az_min)
    az_max = _require_finite("az_max", az_max)
    span = az_max - az_min
    if span <= 0.0:
        raise InvalidSensorError("sensor.az_max", f"must be greater than az_min ({az_min})")
    if span > _TWO_PI + _FULL_TURN_TOLERANCE:
        raise InvalidSensorError(
            "sensor.az_max", f"az_max - az_min is {span:.6f} rad, more than a full turn (2 pi)"
        )
    if wrap and abs(span - _TWO_PI) > _FULL_TURN_TOLERANCE:
        raise InvalidSensorError(
            "sensor.wrap",
            f"wrap needs a full turn (az_max - az_min = 2 pi), got {span:.6f} rad",
        )
    return az_min, az_max


def _azimuth_step(sensor: SphericalSensor | CylindricalSensor) -> float:
    span = sensor.az_max - sensor.az_min
    return span / sensor.width if sensor.wrap else span / (sensor.width - 1)


def _check_wrap(value: Any) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise InvalidSensorError("sensor.wrap", f"must be true or false, got {value!r}")
    return bool(value)


@dataclass(frozen=True, kw_only=True)
class SphericalSensor(Sensor):
    """Rotating LiDAR / scanning LADAR, frame x forward, y left, z up.

    ``az = atan2(y, x)``, ``el = atan2(z, hypot(x, y))``; column ``c`` has azimuth
    ``az_min + c * daz``; row ``r`` has elevation ``el_max - r * (el_max - el_min) / (H - 1)``,
    or ``elevations[r]`` when that table (H values, decreasing) is given. Range is ``|p|``.
    """

    model: ClassVar[str] = "spherical"
    kind: ClassVar[int] = _k.SPHERICAL

    az_min: float = -math.pi
    az_max: float = math.pi
    el_min: float | None = None
    el_max: float | None = None
    wrap: bool = False
    elevations: tuple[float, ...] | None = field(default=None)

    def __post_init__(self) -> None:
        super().__post_init__()
        wrap = _check_wrap(self.wrap)
        object.__setattr__(self, "wrap", wrap)
        az_min, az_max = _check_azimuths(self.az_min, self.az_max, wrap)
        object.__setattr__(self, "az_min", az_min)
        object.__setattr__(self, "az_max", az_max)
        if self.elevations is not None:
            table = np.asarray(self.elevations, dtype=np.float64)
            if table.ndim != 1 or table.shape[0] != self.height:
                raise InvalidSensorError(
                    "sensor.elevations",
                    f"needs one angle per row ({self.height}), got {table.size}",
                )
            if not np.all(np.isfinite(table)) or np.any(np.abs(table) >= math.pi / 2):
                raise InvalidSensorError(
                    "sensor.elevations", "angles must be finite and within (-pi/2, pi/2)"
                )
            if np.any(np.diff(table) >= 0.0):
                raise InvalidSensorError(
                    "sensor.elevations", "must be strictly decreasing (row 0 is the top beam)"
                )
            object.__setattr__(self, "elevations", tuple(float(e) for e in table))
            if self.el_min is None:
                object.__setattr__(self, "el_min", float(table[-1]))
            if self.el_max is None:
                object.__setattr__(self, "el_max", float(table[0]))
        if self.el_min is None or self.el_max is None:
            raise InvalidSensorError(
                "sensor.el_min", "el_min and el_max are needed unless an elevations table is given"
            )
        el_min = _require_finite("el_min", self.el_min)
        el_max = _require_finite("el_max", self.el_max)
        if not -math.pi / 2 <= el_min < el_max <= math.pi / 2:
            raise InvalidSensorError(
                "sensor.el_max",
                f"needs -pi/2 <= el_min < el_max <= pi/2, got el_min={el_min}, el_max={el_max}",
            )
        object.__setattr__(self, "el_min", el_min)
        object.__setattr__(self, "el_max", el_max)

    def _fill_params(self, params: np.ndarray) -> None:
        assert self.el_min is not None and self.el_max is not None
        params[_k.P_AZ_MIN] = self.az_min
        params[_k.P_DAZ] = _azimuth_step(self)
        params[_k.P_WRAP] = 1.0 if self.wrap else 0.0
        params[_k.P_EL_MAX] = self.el_max
        params[_k.P_DEL] = (self.el_max - self.el_min) / (self.height - 1)
        params[_k.P_HAS_TABLE] = 1.0 if self.elevations is not None else 0.0

    def _table(self) -> np.ndarray:
        if self.elevations is None:
            return _k.empty_table()
        return _k.elevation_table(np.asarray(self.elevations, dtype=np.float64))


@dataclass(frozen=True, kw_only=True)
class CylindricalSensor(Sensor):
    """Cylindrical sensor, frame x forward, y left, z up, axis along z.

    Columns are azimuths as for :class:`SphericalSensor`. Rows are
    ``v = cy - fy * z / hypot(x, y)`` (``axial="perspective"``, a cylindrical panorama) or
    ``v = cy - fy * z`` (``axial="linear"``, ``fy`` in rows per metre: a line-scan sensor that
    moves along its axis, such as the Stanford bunny's triangulation scanner). Range is
    ``|p|`` (``"ray"``) or ``hypot(x, y)`` (``"radial"``, the distance from the axis; the
    only convention a linear sensor has).
    """

    model: ClassVar[str] = "cylindrical"
    kind: ClassVar[int] = _k.CYLINDRICAL
    conventions: ClassVar[tuple[str, ...]] = ("ray", "radial")

    az_min: float = -math.pi
    az_max: float = math.pi
    wrap: bool = False
    fy: float
    cy: float
    axial: str = "perspective"

    def __post_init__(self) -> None:
        super().__post_init__()
        wrap = _check_wrap(self.wrap)
        object.__setattr__(self, "wrap", wrap)
        az_min, az_max = _check_azimuths(self.az_min, self.az_max, wrap)
        object.__setattr__(self, "az_min", az_min)
        object.__setattr__(self, "az_max", az_max)
        object.__setattr__(self, "fy", _require_positive("fy", self.fy))
        object.__setattr__(self, "cy", _require_finite("cy", self.cy))
        if self.axial not in ("perspective", "linear"):
            raise InvalidSensorError(
                "sensor.axial", f"must be 'perspective' or 'linear', got {self.axial!r}"
            )
        if self.axial == "linear" and self.range_convention != "radial":
            raise InvalidSensorError(
                "sensor.range_convention",
                "a linear (line-scan) cylindrical sensor measures 'radial' range "
                "(distance from its axis)",
            )

    def _fill_params(self, params: np.ndarray) -> None:
        params[_k.P_AZ_MIN] = self.az_min
        params[_k.P_DAZ] = _azimuth_step(self)
        params[_k.P_WRAP] = 1.0 if self.wrap else 0.0
        params[_k.P_CYL_FY] = self.fy
        params[_k.P_CYL_CY] = self.cy
        params[_k.P_LINEAR] = 1.0 if self.axial == "linear" else 0.0
        params[_k.P_RADIAL] = 1.0 if self.range_convention == "radial" else 0.0


@dataclass(frozen=True, kw_only=True)
class OrthographicSensor(Sensor):
    """Orthographic sensor, frame x right, y down, z forward: ``u = x/sx + cx``, ``v = y/sy + cy``,
    range ``z`` (points with ``z < 0`` have no pixel)."""

    model: ClassVar[str] = "orthographic"
    kind: ClassVar[int] = _k.ORTHOGRAPHIC
    conventions: ClassVar[tuple[str, ...]] = ("z",)

    range_convention: str = "z"
    sx: float
    sy: float
    cx: float = 0.0
    cy: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("sx", "sy"):
            object.__setattr__(self, name, _require_positive(name, getattr(self, name)))
        for name in ("cx", "cy"):
            object.__setattr__(self, name, _require_finite(name, getattr(self, name)))

    def _fill_params(self, params: np.ndarray) -> None:
        params[_k.P_SX] = self.sx
        params[_k.P_SY] = self.sy
        params[_k.P_OCX] = self.cx
        params[_k.P_OCY] = self.cy


_MODELS: dict[str, type[Sensor]] = {
    cls.model: cls
    for cls in (PinholeSensor, SphericalSensor, CylindricalSensor, OrthographicSensor)
}
#: Fields that must be present in a sensor.json for each model (the others have defaults).
_REQUIRED: dict[str, tuple[str, ...]] = {
    "pinhole": ("width", "height", "max_range", "fx", "fy", "cx", "cy", "range_convention"),
    "spherical": ("width", "height", "max_range", "az_min", "az_max"),
    "cylindrical": (
        "width",
        "height",
        "max_range",
        "az_min",
        "az_max",
        "fy",
        "cy",
        "range_convention",
    ),
    "orthographic": ("width", "height", "max_range", "sx", "sy", "cx", "cy"),
}


def sensor_from_dict(data: dict[str, Any]) -> Sensor:
    """Build a sensor from its FORMAT.md ``sensor.json`` form.

    Raises
    ------
    InvalidSensorError
        For an unknown model, a missing or unknown field, or parameters that make no sense;
        the message names the field.
    """
    if not isinstance(data, dict):
        raise InvalidSensorError("sensor", f"must be a JSON object, got {type(data).__name__}")
    model = data.get("model")
    if not isinstance(model, str) or model not in _MODELS:
        raise InvalidSensorError(
            "sensor.model",
            f"unknown sensor model {model!r}; expected one of {', '.join(sorted(_MODELS))}",
        )
    cls = _MODELS[model]
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known - {"model"})
    if unknown:
        raise InvalidSensorError(
            f"sensor.{unknown[0]}", f"unknown field for a {model} sensor (known: {sorted(known)})"
        )
    missing = [name for name in _REQUIRED[model] if name not in data]
    if model == "spherical" and "elevations" not in data:
        missing += [name for name in ("el_min", "el_max") if name not in data]
    if missing:
        raise InvalidSensorError(f"sensor.{missing[0]}", f"missing (a {model} sensor needs it)")
    kwargs = {k: v for k, v in data.items() if k != "model"}
    if "elevations" in kwargs and kwargs["elevations"] is not None:
        try:
            kwargs["elevations"] = tuple(float(e) for e in kwargs["elevations"])
        except (TypeError, ValueError):
            raise InvalidSensorError("sensor.elevations", "must be a list of numbers") from None
    try:
        return cls(**kwargs)
    except TypeError as exc:  # e.g. a list where a number belongs
        raise InvalidSensorError("sensor", str(exc)) from None
