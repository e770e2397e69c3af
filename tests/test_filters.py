"""Range-map filters (METHOD §4 step 2): NaN-aware, no-return aware."""

from __future__ import annotations

import numpy as np
import pytest
from rangefuse.engine import InvalidInputError, filter_range

from tests import reference


def _noisy(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = (2.0 + rng.normal(0, 0.01, (30, 40))).astype(np.float32)
    img[rng.random(img.shape) < 0.1] = np.nan
    img[rng.random(img.shape) < 0.1] = np.inf
    img[:, :5] = np.inf
    return img


@pytest.mark.parametrize("name", ["mean5", "median3"])
def test_filters_match_reference(name: str) -> None:
    img = _noisy()
    out = filter_range(img, name)
    ref = reference.filter_ref(img, name)
    assert out.dtype == np.float32
    assert np.array_equal(np.isnan(out), np.isnan(ref))
    assert np.array_equal(np.isposinf(out), np.isposinf(ref))
    ok = np.isfinite(ref)
    np.testing.assert_allclose(out[ok], ref[ok], rtol=1e-6)


def test_median_removes_lone_spike_on_no_return_background() -> None:
    img = np.full((9, 9), np.inf, np.float32)
    img[4, 4] = 1.5
    out = filter_range(img, "median3")
    assert np.all(np.isposinf(out))


def test_median_removes_spike_on_surface_and_keeps_invalid() -> None:
    img = np.full((9, 9), 2.0, np.float32)
    img[4, 4] = 0.3
    img[0, 0] = np.nan
    out = filter_range(img, "median3")
    assert out[4, 4] == 2.0
    assert np.isnan(out[0, 0])


def test_mean_does_not_smear_into_background() -> None:
    img = np.full((10, 10), np.inf, np.float32)
    img[:, :5] = 1.0
    out = filter_range(img, "mean5")
    assert np.all(out[:, :5] == 1.0)
    assert np.all(np.isposinf(out[:, 5:]))


def test_none_is_identity_and_unknown_refused() -> None:
    img = _noisy()
    assert filter_range(img, "none") is img
    with pytest.raises(InvalidInputError, match="^filter: must be one of"):
        filter_range(img, "gauss7")
