"""Measurement noise for rendered range maps: its specification and how it is applied.

:class:`NoiseSpec` holds the noise of ``rangefuse synth --noise``: additive uniform and Gaussian
range noise, spikes (outliers), dropouts (invalid pixels) and how misses are written;
:func:`parse_noise` reads its text form (``"gaussian:0.005,dropouts:0.05"``) and
:func:`apply_noise` adds it to a range map with a seeded generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InvalidInputError
from ..sensors import Sensor

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
        Range map in the dataset encoding of ``docs/formats.md`` (finite, ``+inf`` no
        return, NaN invalid).
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
