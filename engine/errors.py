"""Errors raised by the engine.

Every error caused by bad input is an :class:`InvalidInputError` (a
``ValueError``) whose message starts with the name of the offending field, so
the service and the command line can show it to the user unchanged.
"""

from __future__ import annotations

__all__ = [
    "FarRangesError",
    "InvalidGridError",
    "InvalidInputError",
    "InvalidNoiseError",
    "InvalidScanError",
    "InvalidSensorError",
    "ScanNotFoundError",
]


class InvalidInputError(ValueError):
    """Bad input: ``field`` names what is wrong, ``problem`` says why."""

    def __init__(self, field: str, problem: str) -> None:
        self.field = field
        self.problem = problem
        super().__init__(f"{field}: {problem}")


class InvalidSensorError(InvalidInputError):
    """A sensor model that is unknown or whose parameters make no sense."""


class InvalidScanError(InvalidInputError):
    """A range map or pose that cannot be fused."""


class FarRangesError(InvalidScanError):
    """A range map whose measured ranges mostly lie beyond the sensor's ``max_range`` or look
    like millimetres: refused unless accepted explicitly (``accept_far_ranges``)."""


class InvalidNoiseError(InvalidInputError):
    """Noise-model or fusion parameters out of range."""


class InvalidGridError(InvalidInputError):
    """Voxel size, tile size, mode or bounds that make no sense."""


class ScanNotFoundError(LookupError):
    """A scan id that the volume does not hold."""
