"""The mean-free-path model of Berquin & Zell (2021): posterior statistics of one voxel.

Every function is vectorised over numpy arrays of the sufficient statistics:
``s`` — metres travelled by rays inside the voxel, ``n`` — first returns inside it (real
valued after decay). With a Gamma(shape alpha, rate beta) prior on the extinction
``u = -log m`` (``Prior``; alpha = beta = 1 is the paper's uniform prior on m, Eq. 24) the
posterior of u is Gamma(n + alpha, s + beta) (Eq. 25-26 generalised, docs/model.md); ``m``
is the probability of crossing one metre unreflected and the degree of occupancy (DoO) is
``1 - m``. The prior is applied when statistics are read, never stored in ``s`` and ``n``.
Numpy only (a query of map-file points loads no numba); ``gridmap.hit_probability_one`` is
the compiled kernels' copy of ``hit_probability``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Prior:
    """Gamma(``shape`` alpha, ``rate`` beta) prior on the extinction u = -log m (per metre).

    ``beta`` is in metres of ray and ``alpha`` in returns: the prior weighs as much as
    ``beta`` metres of ray with ``alpha`` returns. ``Prior()`` (1, 1) is the uniform prior
    on m of the paper (Eq. 24)."""

    shape: float = 1.0
    rate: float = 1.0

    def __post_init__(self) -> None:
        finite = math.isfinite(self.shape) and math.isfinite(self.rate)
        if not (finite and self.shape > 0 and self.rate > 0):
            raise ValueError(
                f"the prior's shape and rate must be finite and > 0, got shape={self.shape}, "
                f"rate={self.rate}"
            )

    @property
    def is_uniform(self) -> bool:
        return self.shape == 1.0 and self.rate == 1.0

    @property
    def unknown_doo(self) -> float:
        """Mean DoO of a never-observed voxel, ``1 - (beta / (beta + 1))^alpha``."""
        return float(1.0 - (self.rate / (self.rate + 1.0)) ** self.shape)

    @property
    def unknown_std(self) -> float:
        """Std of the DoO of a never-observed voxel."""
        m1 = (self.rate / (self.rate + 1.0)) ** self.shape
        m2 = (self.rate / (self.rate + 2.0)) ** self.shape
        return float(math.sqrt(max(m2 - m1 * m1, 0.0)))


UNIFORM = Prior()
"""The paper's uniform prior on m: Gamma(1, 1) on the extinction."""
ALIGNMENT_PRIOR = UNIFORM
"""The prior of the likelihood field that localization aligns scans on (offline and live),
whatever the map's own prior: the objective its scales and acceptance thresholds were tuned
on (the exact check of an accepted correction reads the map's prior). With the calibrated
default prior (``family_prior``) in the field, the live localizer's corrections on the
simulated hall came out 1 to 10 cm worse (issue 29); re-tuning it is future work."""
FAMILY_MEAN_EXTINCTION = 2.0
"""Mean extinction (per metre) of every prior of the family (``family_prior``): shape /
rate = 2, a mean free path of 0.5 m a priori."""


def family_prior(scale: float, resolution: float) -> Prior:
    """The prior of the family measured on real recordings (docs/scoring.md): shape
    ``scale * resolution`` returns and rate ``scale * resolution / 2`` metres of ray, so it
    weighs as much as ``scale * resolution`` returns: a fixed share of a voxel's evidence
    whatever the voxel's size. ``scale`` is ``prior.scale`` (per metre)."""
    shape = scale * resolution
    return Prior(shape, shape / FAMILY_MEAN_EXTINCTION)


def resolve_prior(resolution: float, shape: float, rate: float, scale: float) -> Prior:
    """The prior a map of ``resolution`` uses: ``shape`` and ``rate`` as given, except either
    one that is 0 (unset): the family's (``family_prior(scale, resolution)``). ValueError
    for a negative or non-finite value, or no usable ``scale`` when one is needed."""
    if shape != 0.0 and rate != 0.0:
        return Prior(shape, rate)
    if not (math.isfinite(scale) and scale > 0.0):
        raise ValueError(
            f"prior.scale must be finite and > 0 when prior.shape or prior.rate is 0 (from "
            f"the family), got {scale}"
        )
    family = family_prior(scale, resolution)
    return Prior(shape if shape != 0.0 else family.shape, rate if rate != 0.0 else family.rate)


UNKNOWN_DOO = 0.5
"""Degree of occupancy shown for voxels never observed (the uniform prior's mean)."""
UNKNOWN_STD = 1.0 / math.sqrt(12.0)
"""Standard deviation of the uniform prior: what an unobserved voxel reports."""


def _stats(s: ArrayLike, n: ArrayLike) -> tuple[FloatArray, FloatArray]:
    s_arr = np.maximum(np.asarray(s, dtype=np.float64), 0.0)
    n_arr = np.maximum(np.asarray(n, dtype=np.float64), 0.0)
    return s_arr, n_arr


def observed(s: ArrayLike, n: ArrayLike) -> NDArray[np.bool_]:
    """True where the voxel holds any evidence (s > 0 or n > 0)."""
    s_arr, n_arr = _stats(s, n)
    return (s_arr > 0.0) | (n_arr > 0.0)


def _log_moment(s: ArrayLike, n: ArrayLike, z: ArrayLike, prior: Prior = UNIFORM) -> FloatArray:
    """log E[m^z] = (n+alpha) (log(s+beta) - log(s+beta+z)) (Eq. 26, Gamma prior)."""
    s_arr, n_arr = _stats(s, n)
    z_arr = np.asarray(z, dtype=np.float64)
    return -(n_arr + prior.shape) * np.log1p(z_arr / (s_arr + prior.rate))


def moment_m(s: ArrayLike, n: ArrayLike, z: ArrayLike, prior: Prior = UNIFORM) -> FloatArray:
    """E[m^z] = ((s+beta)/(s+beta+z))^(n+alpha) (Eq. 26; alpha = beta = 1: uniform prior)."""
    return np.exp(_log_moment(s, n, z, prior))


def most_likely_doo(s: ArrayLike, n: ArrayLike) -> FloatArray:
    """Most likely degree of occupancy ``1 - exp(-n/s)``; 0.5 where never observed.

    ``s == 0`` with ``n > 0`` (a return exactly on a voxel face) gives 1.
    """
    s_arr, n_arr = _stats(s, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        rate = np.where(s_arr > 0.0, n_arr / s_arr, np.inf)
    doo = -np.expm1(-rate)
    return np.where(observed(s_arr, n_arr), doo, UNKNOWN_DOO)


def mean_doo(s: ArrayLike, n: ArrayLike, prior: Prior = UNIFORM) -> FloatArray:
    """Posterior mean of the degree of occupancy, ``1 - E[m]``."""
    return 1.0 - moment_m(s, n, 1.0, prior)


def std_doo(s: ArrayLike, n: ArrayLike, prior: Prior = UNIFORM) -> FloatArray:
    """Posterior standard deviation of the degree of occupancy (equal to that of m)."""
    m1 = moment_m(s, n, 1.0, prior)
    m2 = moment_m(s, n, 2.0, prior)
    return np.sqrt(np.maximum(m2 - m1 * m1, 0.0))


def hit_probability(
    s: ArrayLike, n: ArrayLike, length: ArrayLike, prior: Prior = UNIFORM
) -> FloatArray:
    """Probability that a ray travelling ``length`` metres in the voxel is reflected (Eq. 34),
    ``1 - E[m^length]``.

    With ``length`` = the voxel edge this is the cell's p_hit (Eq. 31-33).
    """
    return -np.expm1(_log_moment(s, n, length, prior))


def path_pass_probability(
    s: ArrayLike, n: ArrayLike, lengths: ArrayLike, prior: Prior = UNIFORM
) -> FloatArray:
    """Probability that a ray crosses voxels (last axis) with chord ``lengths`` unreflected."""
    return np.exp(np.sum(_log_moment(s, n, lengths, prior), axis=-1))


def mean_free_path(s: ArrayLike, n: ArrayLike) -> FloatArray:
    """Most likely mean free path ``s/n`` in metres; inf where no return was seen."""
    s_arr, n_arr = _stats(s, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(n_arr > 0.0, s_arr / n_arr, np.inf)


def decay_factor(dt: ArrayLike, decay_time: float) -> FloatArray:
    """Scale applied to both statistics after ``|dt|`` seconds (Eq. 28-30); 1 when static."""
    dt_arr = np.abs(np.asarray(dt, dtype=np.float64))
    if not math.isfinite(decay_time):
        return np.ones_like(dt_arr)
    return np.exp(-dt_arr / decay_time)


def decay(
    s: ArrayLike, n: ArrayLike, dt: ArrayLike, decay_time: float
) -> tuple[FloatArray, FloatArray]:
    """Statistics after ``dt`` seconds of exponential forgetting (time constant ``decay_time``)."""
    f = decay_factor(dt, decay_time)
    s_arr, n_arr = _stats(s, n)
    return s_arr * f, n_arr * f


# --- Gamma credible intervals, without scipy ---------------------------------------------


def _regularized_gamma_p(a: FloatArray, x: FloatArray, log_gamma_a: FloatArray) -> FloatArray:
    """Regularised lower incomplete gamma P(a, x), series / continued fraction (vectorised).

    ``log_gamma_a`` = log Gamma(a), passed in so that a search over x computes it once.
    """
    out = np.zeros(a.shape)
    log_prefix = np.where(x > 0, -x + a * np.log(np.where(x > 0, x, 1.0)), -np.inf) - log_gamma_a
    series = x < a + 1.0
    # series: P = e^{-x} x^a / Gamma(a) * sum x^k / (a (a+1) ... (a+k))
    if np.any(series):
        aa, xx = a[series], x[series]
        term = 1.0 / aa
        total = term.copy()
        ap = aa.copy()
        for _ in range(500):
            ap = ap + 1.0
            term = term * xx / ap
            total = total + term
            if np.all(np.abs(term) < np.abs(total) * 1e-15):
                break
        out[series] = total * np.exp(log_prefix[series])
    frac = ~series
    if np.any(frac):
        aa, xx = a[frac], x[frac]
        tiny = 1e-300
        b = xx + 1.0 - aa
        c = np.full(aa.shape, 1.0 / tiny)
        d = 1.0 / b
        h = d.copy()
        for i in range(1, 500):
            an = -i * (i - aa)
            b = b + 2.0
            d = an * d + b
            d = np.where(np.abs(d) < tiny, tiny, d)
            c = b + an / c
            c = np.where(np.abs(c) < tiny, tiny, c)
            d = 1.0 / d
            delta = d * c
            h = h * delta
            if np.all(np.abs(delta - 1.0) < 1e-15):
                break
        out[frac] = 1.0 - np.exp(log_prefix[frac]) * h
    return np.clip(out, 0.0, 1.0)


_lgamma = np.vectorize(math.lgamma, otypes=[np.float64])


def gamma_quantile(shape: ArrayLike, rate: ArrayLike, q: float) -> FloatArray:
    """Quantile ``q`` of Gamma(shape, rate), by bisection on the regularised gamma function."""
    a = np.asarray(shape, dtype=np.float64)
    r = np.asarray(rate, dtype=np.float64)
    a, r = np.broadcast_arrays(a, r)
    log_gamma_a = _lgamma(a)
    lo = np.zeros(a.shape)
    hi = np.maximum(a + 20.0 * np.sqrt(a) + 40.0, 1.0)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        below = _regularized_gamma_p(a, mid, log_gamma_a) < q
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi) / r


def extinction_interval(
    s: ArrayLike, n: ArrayLike, level: float = 0.9, prior: Prior = UNIFORM
) -> tuple[FloatArray, FloatArray]:
    """Central credible interval of the extinction u = -log m (returns per metre):
    quantiles of Gamma(n + alpha, s + beta)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"credible level must lie in (0, 1), got {level}")
    s_arr, n_arr = _stats(s, n)
    tail = 0.5 * (1.0 - level)
    shape, rate = n_arr + prior.shape, s_arr + prior.rate
    return gamma_quantile(shape, rate, tail), gamma_quantile(shape, rate, 1.0 - tail)


def doo_interval(
    s: ArrayLike, n: ArrayLike, level: float = 0.9, prior: Prior = UNIFORM
) -> tuple[FloatArray, FloatArray]:
    """Central credible interval of the degree of occupancy (monotone in the extinction)."""
    u_lo, u_hi = extinction_interval(s, n, level, prior)
    return -np.expm1(-u_lo), -np.expm1(-u_hi)


# --- The classic binary occupancy model it is compared with (Eq. 5, Fig. 9) -------------

CLASSIC_P_HIT_OCCUPIED = 0.47
CLASSIC_P_HIT_FREE = 0.2


def classic_occupancy(
    returns: ArrayLike,
    pass_throughs: ArrayLike,
    prior: float = 0.5,
    p_hit_occupied: float = CLASSIC_P_HIT_OCCUPIED,
    p_hit_free: float = CLASSIC_P_HIT_FREE,
) -> FloatArray:
    """Posterior occupancy probability of the binary model after the given counts."""
    r = np.asarray(returns, dtype=np.float64)
    p = np.asarray(pass_throughs, dtype=np.float64)
    log_odds = (
        math.log(prior / (1.0 - prior))
        + r * math.log(p_hit_occupied / p_hit_free)
        + p * math.log((1.0 - p_hit_occupied) / (1.0 - p_hit_free))
    )
    return 1.0 / (1.0 + np.exp(-log_odds))
