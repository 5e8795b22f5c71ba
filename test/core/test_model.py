"""The model's statistics against docs/model.md's values and numerical integration of Eq. 25."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, stats

from mfp_mapper.core import model
from mfp_mapper.core.gridmap import hit_probability_one

# s, n, most likely DoO (nan = unknown), E[m], std(DoO), p_hit with s0 = 0.1  (docs/model.md)
VECTORS = [
    (0.0, 0.0, math.nan, 0.500000, 0.288675, 0.090909),
    (1.0, 0.0, 0.0, 0.666667, 0.235702, 0.047619),
    (2.0, 3.0, 0.776870, 0.316406, 0.171718, 0.122922),
    (10.0, 10.0, 0.632121, 0.383995, 0.108386, 0.094754),
    (100.0, 0.0, 0.0, 0.990196, 0.009708, 0.000989),
]


@pytest.mark.parametrize(("s", "n", "doo", "mean_m", "std", "p_hit"), VECTORS)
def test_model_md_vectors(
    s: float, n: float, doo: float, mean_m: float, std: float, p_hit: float
) -> None:
    expected_doo = model.UNKNOWN_DOO if math.isnan(doo) else doo
    assert model.most_likely_doo(s, n) == pytest.approx(expected_doo, abs=1e-6)
    assert model.moment_m(s, n, 1.0) == pytest.approx(mean_m, abs=1e-6)
    assert model.mean_doo(s, n) == pytest.approx(1.0 - mean_m, abs=1e-6)
    assert model.std_doo(s, n) == pytest.approx(std, abs=1e-6)
    assert model.hit_probability(s, n, 0.1) == pytest.approx(p_hit, abs=1e-6)
    assert bool(model.observed(s, n)) == (s > 0 or n > 0)


def test_unknown_voxel_reports_the_uniform_prior() -> None:
    assert model.std_doo(0.0, 0.0) == pytest.approx(model.UNKNOWN_STD)
    assert pytest.approx(0.288675, abs=1e-6) == model.UNKNOWN_STD


def test_return_on_a_face_with_zero_length_is_fully_occupied_without_division_error() -> None:
    with np.errstate(all="raise"):
        assert model.most_likely_doo(0.0, 2.0) == 1.0
        assert model.mean_free_path(0.0, 2.0) == 0.0
        assert np.isfinite(model.std_doo(0.0, 2.0))


def _posterior(m: float, s: float, n: float) -> float:
    """Eq. 25: p(m | s, n) = (-log m)^n m^s (s+1)^(n+1) / Gamma(n+1)."""
    if m <= 0.0 or m >= 1.0:
        return 0.0
    log_p = (
        n * math.log(-math.log(m))
        + s * math.log(m)
        + (n + 1) * math.log(s + 1)
        - math.lgamma(n + 1)
    )
    return math.exp(log_p)


@pytest.mark.parametrize(
    ("s", "n"), [(0.3, 0.0), (2.0, 3.0), (10.0, 10.0), (4.5, 1.7), (40.0, 25.0)]
)
def test_moments_and_hit_probability_match_integration_of_eq25(s: float, n: float) -> None:
    def moment(z: float) -> float:
        return integrate.quad(lambda m: m**z * _posterior(m, s, n), 0.0, 1.0, limit=200)[0]

    assert moment(0.0) == pytest.approx(1.0, abs=1e-7)
    m1, m2 = moment(1.0), moment(2.0)
    assert model.moment_m(s, n, 1.0) == pytest.approx(m1, rel=1e-6)
    assert model.std_doo(s, n) == pytest.approx(math.sqrt(m2 - m1 * m1), rel=1e-5)
    for length in (0.05, 0.1, 1.0):
        # probability that a ray travelling `length` in the voxel is reflected: 1 - E[m^length]
        assert model.hit_probability(s, n, length) == pytest.approx(1.0 - moment(length), rel=1e-6)


def test_path_probability_is_the_product_over_independent_voxels() -> None:
    s, n, lengths = np.array([1.0, 5.0, 0.2]), np.array([0.0, 3.0, 1.0]), np.array([0.1, 0.3, 0.05])
    expected = np.prod(1.0 - model.hit_probability(s, n, lengths))
    assert model.path_pass_probability(s, n, lengths) == pytest.approx(expected)


@pytest.mark.parametrize(
    ("s", "n"), [(0.0, 0.0), (1.0, 0.0), (2.0, 3.0), (50.0, 12.5), (1e4, 300.0)]
)
def test_credible_interval_matches_gamma_quantiles(s: float, n: float) -> None:
    lo, hi = model.extinction_interval(s, n, 0.9)
    dist = stats.gamma(n + 1.0, scale=1.0 / (s + 1.0))
    assert lo == pytest.approx(dist.ppf(0.05), rel=1e-6)
    assert hi == pytest.approx(dist.ppf(0.95), rel=1e-6)
    doo_lo, doo_hi = model.doo_interval(s, n, 0.9)
    assert doo_lo == pytest.approx(1.0 - math.exp(-dist.ppf(0.05)), rel=1e-6)
    assert doo_lo < doo_hi


def test_credible_level_must_be_a_probability() -> None:
    with pytest.raises(ValueError, match="credible level"):
        model.extinction_interval(1.0, 1.0, 1.5)


def test_decay_vector_of_model_md() -> None:
    n, s = model.decay(5.0, 10.0, 5.0, 10.0)[::-1]
    # n=10, s=5 at t'=0, T=10 s, one ray crossing 0.1 m at t=5 -> n=6.065307, s=3.132653
    assert n == pytest.approx(6.065307, abs=1e-6)
    assert s + 0.1 == pytest.approx(3.132653, abs=1e-6)
    # decay keeps the most likely value and widens the uncertainty
    assert model.mean_free_path(s, n) == pytest.approx(0.5)
    assert model.std_doo(s, n) > model.std_doo(5.0, 10.0)
    assert model.decay_factor(1e9, math.inf) == 1.0


def test_classic_occupancy_vectors() -> None:
    assert model.classic_occupancy(10, 0) == pytest.approx(0.999805, abs=1e-6)
    assert model.classic_occupancy(10, 40) == pytest.approx(0.000361, abs=1e-6)
    assert model.classic_occupancy(10, 20) > 0.5 > model.classic_occupancy(10, 21)


def test_compiled_hit_probability_is_the_vectorised_one() -> None:
    rng = np.random.default_rng(3)
    s = np.concatenate([[0.0, 0.0, 1e-6], rng.exponential(3.0, 200)])
    n = np.concatenate([[0.0, 2.0, 0.0], rng.poisson(2.0, 200).astype(float)])
    for length in (0.05, 0.2, 1.0):
        compiled = [hit_probability_one(a, b, length) for a, b in zip(s, n, strict=True)]
        # numba's and numpy's log1p/log may differ in the last bits
        np.testing.assert_allclose(compiled, model.hit_probability(s, n, length), rtol=1e-13)
