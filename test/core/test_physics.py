"""docs/model.md's physics check: in a medium of uniform extinction the map recovers it."""

from __future__ import annotations

import numpy as np
import pytest

from mfp_mapper import Mapper
from mfp_mapper.core import model

EXTINCTION = 0.8  # returns per metre
RES = 0.5
HALF = 2.0  # voxels judged: the cube [-HALF, HALF]^3


def _medium_rays(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from random origins in random directions, first return after Exp(EXTINCTION)."""
    origins = rng.uniform(-HALF, HALF, size=(count, 3))
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    distance = rng.exponential(1.0 / EXTINCTION, size=count)
    return origins + directions * distance[:, None], origins


def _judged_voxels(mapper: Mapper) -> tuple[np.ndarray, np.ndarray]:
    vox = mapper.voxels()
    inside = (np.abs(vox.centers) < HALF).all(axis=1)
    return vox.s[inside], vox.n[inside]


def test_uniform_medium_recovers_extinction_and_intervals_cover() -> None:
    rng = np.random.default_rng(7)
    mapper = Mapper(RES, max_range=1e3)
    for k in range(6):
        points, origins = _medium_rays(rng, 20_000)
        summary = mapper.integrate(points, origins, float(k))
        assert summary.rays_truncated == 0  # every ray returns
    s, n = _judged_voxels(mapper)
    assert len(s) == (2 * HALF / RES) ** 3
    pooled = n.sum() / s.sum()
    assert pooled == pytest.approx(EXTINCTION, rel=0.03)
    lo, hi = model.extinction_interval(s, n, 0.9)
    coverage = np.mean((lo <= EXTINCTION) & (hi >= EXTINCTION))
    assert 0.85 <= coverage <= 0.95


def test_rays_cut_at_max_range_still_clear_space_and_keep_the_estimate_unbiased() -> None:
    """Rays with no return within range add their length and no return: n/s stays λ."""
    rng = np.random.default_rng(11)
    kept = Mapper(RES, max_range=1.0)
    dropped = Mapper(RES, max_range=1.0)
    for k in range(6):
        points, origins = _medium_rays(rng, 20_000)
        kept.integrate(points, origins, float(k))
        returned = np.linalg.norm(points - origins, axis=1) <= 1.0
        # what a mapper that silently drops the no-return rays would see
        dropped.integrate(points[returned], origins[returned], float(k))
    s, n = _judged_voxels(kept)
    assert n.sum() / s.sum() == pytest.approx(EXTINCTION, rel=0.03)
    s_biased, n_biased = _judged_voxels(dropped)
    assert n_biased.sum() / s_biased.sum() > 1.3 * EXTINCTION
