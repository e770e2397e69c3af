"""Certainty shapes (METHOD §1) and the fixed-point log-odds encoding (§2)."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rangefuse.engine import InvalidNoiseError, NoiseModel, decode_count, decode_logodds
from rangefuse.engine.certainty import contribution, log, logit, pack, quantise
from rangefuse.engine.defaults import LOGIT_SCALE

from tests import reference


def test_linear_shape_matches_method() -> None:
    noise = NoiseModel(eps=0.01, rho=0.1)
    alpha = np.array([-1.0, -0.011, -0.01, -0.005, 0.0, 0.005, 0.01, 0.015, 0.02, 0.0201])
    c = noise.certainty(alpha, np.ones_like(alpha))
    expected = [0.1, 0.1, 0.1, 0.3, 0.5, 0.7, 0.9, 0.7, 0.5, np.nan]
    np.testing.assert_allclose(c, expected, atol=1e-12)


def test_falloff_and_range_dependent_eps() -> None:
    noise = NoiseModel(eps=0.01, eps_per_m=0.01, rho=0.1, falloff=0.05)
    r = 2.0  # eps = 0.03
    c = noise.certainty(np.array([-0.03, 0.0, 0.03, 0.055, 0.08, 0.0801]), np.full(6, r))
    np.testing.assert_allclose(c, [0.1, 0.5, 0.9, 0.7, 0.5, np.nan], atol=1e-12)


def test_erf_shape_is_continuous_monotone_and_symmetric() -> None:
    noise = NoiseModel(eps=0.02, rho=0.05, shape="erf")
    alpha = np.linspace(-0.1, 0.02, 2001)
    c = noise.certainty(alpha, np.ones_like(alpha))
    assert np.all(np.diff(c) > 0)
    assert c[0] == pytest.approx(0.05, abs=1e-6)
    assert noise.certainty(np.array([0.0]), np.array([1.0]))[0] == pytest.approx(0.5)
    # the same slope at the surface as the linear ramp
    lin = NoiseModel(eps=0.02, rho=0.05)
    h = 1e-6
    slope_erf = np.diff(noise.certainty(np.array([-h, h]), np.ones(2)))[0] / (2 * h)
    slope_lin = np.diff(lin.certainty(np.array([-h, h]), np.ones(2)))[0] / (2 * h)
    assert slope_erf == pytest.approx(slope_lin, rel=1e-4)
    # symmetric: C(-a) + C(a) = 1 inside the band
    a = np.linspace(0, 0.02, 11)
    np.testing.assert_allclose(
        noise.certainty(-a, np.ones_like(a)) + noise.certainty(a, np.ones_like(a)), 1.0
    )
    # continuous at the start of the fall-off, 1/2 at its end
    e = 0.02
    left, right = noise.certainty(np.array([e - 1e-9, e + 1e-9]), np.ones(2))
    assert left == pytest.approx(right, abs=1e-6)
    assert noise.certainty(np.array([0.04]), np.array([1.0]))[0] == pytest.approx(0.5)


@pytest.mark.parametrize("shape", ["linear", "erf"])
def test_kernel_certainty_matches_reference(shape: str) -> None:
    noise = NoiseModel(eps=0.01, eps_per_m=0.003, rho=0.07, falloff=0.02, shape=shape)
    rng = np.random.default_rng(0)
    r = rng.uniform(0.5, 5, 1000)
    alpha = rng.uniform(-0.05, 0.05, 1000)
    eps = 0.01 + 0.003 * r
    c = noise.certainty(alpha, r)
    ref = reference.certainty(alpha, eps, np.full_like(r, 0.02), noise)
    informed = alpha <= eps + 0.02
    np.testing.assert_allclose(c[informed], ref[informed], atol=1e-12)
    assert np.all(np.isnan(c[~informed]))


@settings(max_examples=200, deadline=None)
@given(alpha=st.floats(-1, 1), r=st.floats(0.1, 50), rho=st.floats(0.001, 0.49))
def test_contribution_is_quantised_logit(alpha, r, rho) -> None:
    noise = NoiseModel(eps=0.02, eps_per_m=0.001, rho=rho)
    eps0, eps1, rho_, falloff, shape, q_rho = noise.kernel_args()
    q, informed = contribution(alpha, r, eps0, eps1, rho_, falloff, shape, q_rho)
    c = noise.certainty(np.array([alpha]), np.array([r]))[0]
    assert informed == (not np.isnan(c))
    if informed:
        assert abs(q / LOGIT_SCALE - math.log(c / (1 - c))) <= 0.5 / LOGIT_SCALE + 1e-9


def test_half_certainty_changes_nothing_but_informs() -> None:
    # at the end of the fall-off C = 1/2 exactly: logit 0, but the voxel is informed
    noise = NoiseModel(eps=0.01, rho=0.1)
    q, informed = contribution(0.02, 1.0, *noise.kernel_args())
    assert informed and q == 0
    packed = np.array([pack(q)], np.int64)
    assert decode_logodds(packed)[0] == 0.0
    assert decode_count(packed)[0] == 1


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(-(10**6), 10**6), min_size=1, max_size=50))
def test_packing_sums_decode_exactly(qs) -> None:
    total = np.int64(0)
    for q in qs:
        total += pack(np.int64(q))
    assert decode_count(np.array([total]))[0] == len(qs)
    assert decode_logodds(np.array([total]))[0] == np.float32(sum(qs) / LOGIT_SCALE)
    # removing every contribution returns to unknown
    for q in qs:
        total -= pack(np.int64(q))
    assert total == 0 and np.isnan(decode_logodds(np.array([total]))[0])


def test_unknown_differs_from_balanced_evidence() -> None:
    balanced = pack(quantise(1.5)) + pack(quantise(-1.5))
    assert decode_logodds(np.array([balanced]))[0] == 0.0
    assert np.isnan(decode_logodds(np.array([0]))[0])


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"eps": 0.0}, "eps"),
        ({"eps": -0.01}, "eps"),
        ({"eps": float("nan")}, "eps"),
        ({"eps": 0.01, "rho": 0.0}, "rho"),
        ({"eps": 0.01, "rho": 0.5}, "rho"),
        ({"eps": 0.01, "rho": 0.7}, "rho"),
        ({"eps": 0.01, "eps_per_m": -0.1}, "eps_per_m"),
        ({"eps": 0.01, "falloff": 0.0}, "falloff"),
        ({"eps": 0.01, "shape": "cubic"}, "shape"),
        ({"eps": "small"}, "eps"),
        ({"eps": True}, "eps"),
    ],
)
def test_invalid_noise(kwargs: dict, field: str) -> None:
    with pytest.raises(InvalidNoiseError) as info:
        NoiseModel(**kwargs)
    assert str(info.value).startswith(field + ":")


def test_noise_dict_round_trip() -> None:
    noise = NoiseModel(eps=0.01, eps_per_m=0.002, rho=0.1, falloff=0.03, shape="erf")
    assert NoiseModel.from_dict(noise.to_dict()) == noise
    with pytest.raises(InvalidNoiseError, match="unknown noise parameter"):
        NoiseModel.from_dict({"eps": 0.01, "sigma": 2})


@given(st.floats(min_value=5e-324, max_value=1.7e308, allow_nan=False, allow_infinity=False))
@settings(max_examples=500, deadline=None)
def test_log_is_within_a_few_ulps_of_math_log(x):
    """The kernels' own log (plain arithmetic, so that loops vectorise) matches the library's
    to a few units in the last place over every positive float, subnormals included."""
    expected = math.log(x)
    assert abs(log(x) - expected) <= 4 * np.spacing(max(abs(expected), 1e-300))


def test_quantised_logit_agrees_with_the_library_log():
    """On a million certainties the quantised contributions equal those of ``math.log``."""
    c = np.random.default_rng(3).uniform(1e-4, 1.0 - 1e-4, 1_000_000)
    expected = np.floor(np.log(c / (1.0 - c)) * LOGIT_SCALE + 0.5).astype(np.int64)
    got = _quantised_logits(c)
    assert np.array_equal(got, expected)


def _quantised_logits(c: np.ndarray) -> np.ndarray:
    out = np.empty(len(c), np.int64)
    _logits_kernel(c, out)
    return out


@numba.njit(cache=True)
def _logits_kernel(c, out):
    for i in range(c.shape[0]):
        out[i] = quantise(logit(c[i]))
