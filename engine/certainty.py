"""Certainty of one scan at one point, and its fixed-point log-odds (METHOD.md §1-2).

For a point at signed distance ``alpha = d(p) - r`` behind the measured range
``r`` (paper Eq. 1, 3, 4), with ``eps = eps0 + eps1 * r`` and fall-off ``f``
(default ``eps``)::

    C(alpha) = rho                                   alpha < -eps
             = rho + (1/2 - rho) (alpha + eps) / eps     -eps <= alpha <= eps
             = (1 - rho) - (1/2 - rho) (alpha - eps) / f  eps < alpha <= eps + f
             (not informed)                          alpha > eps + f

The ``"erf"`` shape replaces the front part by the certainty of a Gaussian
range error, ``rho + (1 - 2 rho) Phi(alpha / sigma)`` with
``sigma = eps * sqrt(2 / pi)`` (the same slope at the surface as the linear
ramp), and falls off linearly from ``C(eps)`` to 1/2 behind it.

Scans fuse by adding ``logit(C)`` (super-Bayesian fusion, Eq. 5-6). Each
contribution is quantised to ``q = floor(logit(C) * LOGIT_SCALE + 1/2)`` and
stored packed with a count of informing scans (see :func:`pack`), so sums are
exact integers: order-free and exactly removable.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numba import njit

from .defaults import COUNT_BITS, LOGIT_SCALE
from .errors import InvalidNoiseError
from .params import PARAMS, current_names, params_of

__all__ = [
    "COUNT_MASK",
    "SHAPES",
    "NoiseModel",
    "decode_count",
    "decode_logodds",
    "pack",
]

SHAPES = PARAMS["shape"].choices
SHAPE_LINEAR = 0
SHAPE_ERF = 1
COUNT_MASK = (1 << COUNT_BITS) - 1
_SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)


@dataclass(frozen=True)
class NoiseModel:
    """Range-noise model of METHOD §1.

    Parameters
    ----------
    eps : float
        Noise half-width at zero range, metres (``eps0``, > 0).
    eps_per_m : float
        Growth of the half-width with range (``eps1``, >= 0, < 1): ``eps = eps0 + eps1 * r``.
    rho : float
        Outlier probability, ``0 < rho < 1/2``.
    falloff : float or None
        Distance behind the noise band over which certainty returns to 1/2; ``None`` means
        ``eps`` at that range (the paper's choice).
    shape : {"linear", "erf"}
        Piecewise-linear ramp (the paper's default) or a Gaussian (erf) ramp.
    """

    eps: float
    eps_per_m: float = PARAMS["eps_per_m"].default
    rho: float = PARAMS["rho"].default
    falloff: float | None = None
    shape: str = PARAMS["shape"].default

    def __post_init__(self) -> None:
        # each field as declared in engine/params.py
        for param in params_of("noise"):
            value = param.validate(getattr(self, param.name), InvalidNoiseError)
            object.__setattr__(self, param.name, value)

    @property
    def shape_code(self) -> int:
        return SHAPES.index(self.shape)

    def kernel_args(self) -> tuple[float, float, float, float, int, int]:
        """``(eps0, eps1, rho, falloff or -1, shape code, q_rho)`` as kernels take them."""
        falloff = -1.0 if self.falloff is None else self.falloff
        return (
            self.eps,
            self.eps_per_m,
            self.rho,
            falloff,
            self.shape_code,
            quantise(logit(self.rho)),
        )

    def certainty(self, alpha: np.ndarray, r: np.ndarray) -> np.ndarray:
        """C(alpha) at signed distances ``alpha`` behind measured ranges ``r`` (metres).

        NaN where the point is not informed (``alpha > eps + falloff``).
        """
        alpha, r = np.broadcast_arrays(np.asarray(alpha, np.float64), np.asarray(r, np.float64))
        out = np.empty(alpha.shape, np.float64)
        eps0, eps1, rho, falloff, shape, _ = self.kernel_args()
        _certainty_many(alpha.ravel(), r.ravel(), eps0, eps1, rho, falloff, shape, out.reshape(-1))
        return out

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(data: dict[str, Any]) -> NoiseModel:
        data = current_names(data)
        known = {p.name for p in params_of("noise")}
        unknown = sorted(set(data) - known)
        if unknown:
            raise InvalidNoiseError(unknown[0], f"unknown noise parameter (known: {sorted(known)})")
        if "eps" not in data:
            raise InvalidNoiseError("eps", "missing")
        return NoiseModel(**data)


_LN2 = math.log(2.0)
_SQRT2 = math.sqrt(2.0)
_MANTISSA = np.int64((1 << 52) - 1)
_ONE_BITS = np.int64(1023 << 52)


@njit(cache=True, inline="always")
def log(x):
    """Natural logarithm of a positive finite ``x``, in plain arithmetic so that loops calling
    it vectorise (``math.log`` is a library call). ``x = m 2^e`` with ``m`` in
    ``[sqrt(2)/2, sqrt(2))`` from the bits, then ``log m = 2 atanh(f)``,
    ``f = (m - 1) / (m + 1)``, ``|f| < 0.172``, by its series to ``f^21`` (the next term is
    below 1e-18): within a few units in the last place of ``math.log``."""
    tiny = x < 2.2250738585072014e-308  # subnormal: scale into the normal range
    x = x * 4503599627370496.0 if tiny else x
    bits = np.float64(x).view(np.int64)
    e = ((bits >> 52) & 0x7FF) - (1023 + 52 if tiny else 1023)
    m = np.int64((bits & _MANTISSA) | _ONE_BITS).view(np.float64)
    big = m > _SQRT2
    m = 0.5 * m if big else m
    e = e + 1 if big else e
    f = (m - 1.0) / (m + 1.0)
    f2 = f * f
    p = 1.0 / 21.0
    p = p * f2 + 1.0 / 19.0
    p = p * f2 + 1.0 / 17.0
    p = p * f2 + 1.0 / 15.0
    p = p * f2 + 1.0 / 13.0
    p = p * f2 + 1.0 / 11.0
    p = p * f2 + 1.0 / 9.0
    p = p * f2 + 1.0 / 7.0
    p = p * f2 + 1.0 / 5.0
    p = p * f2 + 1.0 / 3.0
    p = p * f2 + 1.0
    return 2.0 * f * p + e * _LN2


@njit(cache=True, inline="always")
def logit(c):
    return log(c / (1.0 - c))


@njit(cache=True, inline="always")
def quantise(x):
    return np.int64(math.floor(x * LOGIT_SCALE + 0.5))


@njit(cache=True, inline="always")
def certainty(alpha, eps, falloff, rho, shape):
    """C(alpha) for ``alpha <= eps + falloff`` (the caller tests that the point is informed)."""
    if shape == SHAPE_LINEAR:
        if alpha < -eps:
            return rho
        if alpha <= eps:
            return rho + (0.5 - rho) * (alpha + eps) / eps
        return (1.0 - rho) - (0.5 - rho) * (alpha - eps) / falloff
    sigma = eps * _SQRT_2_OVER_PI
    if alpha <= eps:
        return rho + (1.0 - 2.0 * rho) * 0.5 * math.erfc(-alpha / (sigma * math.sqrt(2.0)))
    c_eps = rho + (1.0 - 2.0 * rho) * 0.5 * math.erfc(-eps / (sigma * math.sqrt(2.0)))
    return c_eps - (c_eps - 0.5) * (alpha - eps) / falloff


@njit(cache=True, inline="always")
def contribution(alpha, r, eps0, eps1, rho, falloff, shape, q_rho):
    """Quantised ``logit(C)`` of one scan at one point, and whether the point is informed.

    ``q_rho`` is ``quantise(logit(rho))``, used for all free space of the linear shape
    (no logarithm there: most voxels are free).
    """
    eps = eps0 + eps1 * r
    f = falloff if falloff > 0.0 else eps
    if alpha > eps + f:
        return np.int64(0), False
    if shape == SHAPE_LINEAR and alpha < -eps:
        return q_rho, True
    return quantise(logit(certainty(alpha, eps, f, rho, shape))), True


@njit(cache=True)
def _certainty_many(alpha, r, eps0, eps1, rho, falloff, shape, out):
    for n in range(alpha.shape[0]):
        eps = eps0 + eps1 * r[n]
        f = falloff if falloff > 0.0 else eps
        if alpha[n] > eps + f:
            out[n] = math.nan
        else:
            out[n] = certainty(alpha[n], eps, f, rho, shape)


@njit(cache=True, inline="always")
def pack(q):
    """One informing scan's contribution as stored: ``q << COUNT_BITS | 1``."""
    return q * (1 << COUNT_BITS) + 1


def decode_count(voxels: np.ndarray) -> np.ndarray:
    """Number of scans that inform each voxel (0 means unknown)."""
    return (np.asarray(voxels, np.int64) & COUNT_MASK).astype(np.int32)


def decode_logodds(voxels: np.ndarray) -> np.ndarray:
    """Fused log-odds ``L`` (float32) of packed voxels; NaN where unknown."""
    voxels = np.asarray(voxels, np.int64)
    out = (voxels >> COUNT_BITS).astype(np.float64) / LOGIT_SCALE
    out[(voxels & COUNT_MASK) == 0] = np.nan
    return out.astype(np.float32)
