"""Range-map filters of the paper's step 2 (METHOD.md §4): 5x5 mean and 3x3 median.

Both are NaN-aware and keep the pixel encoding of FORMAT.md: an invalid pixel
(NaN) stays invalid, and no-return pixels (``+inf``) are ordered after every
finite range. The median therefore removes a lone spike on a no-return
background (eight ``+inf`` neighbours outvote it), and the mean averages only
the finite ranges of its window, so a silhouette is not smeared into the
background.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .errors import InvalidInputError

__all__ = ["FILTERS", "filter_range"]

FILTERS = ("none", "mean5", "median3")


@njit(cache=True, parallel=True)
def _mean5(src, out):
    H, W = src.shape
    for v in prange(H):
        for u in range(W):
            centre = src[v, u]
            if not math.isfinite(centre):
                out[v, u] = centre
                continue
            total = 0.0
            count = 0
            for dv in range(-2, 3):
                vv = v + dv
                if vv < 0 or vv >= H:
                    continue
                for du in range(-2, 3):
                    uu = u + du
                    if uu < 0 or uu >= W:
                        continue
                    value = src[vv, uu]
                    if math.isfinite(value):
                        total += value
                        count += 1
            out[v, u] = total / count


@njit(cache=True, parallel=True)
def _median3(src, out):
    H, W = src.shape
    for v in prange(H):
        window = np.empty(9, np.float64)
        for u in range(W):
            centre = src[v, u]
            if math.isnan(centre):
                out[v, u] = centre
                continue
            n = 0
            for dv in range(-1, 2):
                vv = v + dv
                if vv < 0 or vv >= H:
                    continue
                for du in range(-1, 2):
                    uu = u + du
                    if uu < 0 or uu >= W:
                        continue
                    value = src[vv, uu]
                    if not math.isnan(value):
                        # insertion sort; +inf sorts last
                        k = n
                        while k > 0 and window[k - 1] > value:
                            window[k] = window[k - 1]
                            k -= 1
                        window[k] = value
                        n += 1
            if n % 2 == 1:
                out[v, u] = window[n // 2]
            else:
                out[v, u] = 0.5 * (window[n // 2 - 1] + window[n // 2])


def filter_range(range_m: np.ndarray, name: str) -> np.ndarray:
    """Filter a range map.

    Parameters
    ----------
    range_m : float32 array (H, W)
        Range map in the FORMAT.md encoding (finite, ``+inf`` no return, NaN invalid).
    name : {"none", "mean5", "median3"}

    Returns
    -------
    float32 array (H, W), a new array (the input for ``"none"``).
    """
    if name not in FILTERS:
        raise InvalidInputError("filter", f"must be one of {', '.join(FILTERS)}, got {name!r}")
    if name == "none":
        return range_m
    src = np.ascontiguousarray(range_m, dtype=np.float32)
    out = np.empty_like(src)
    (_mean5 if name == "mean5" else _median3)(src, out)
    return out
