"""``Mapper.query_segments``: clear line-of-sight probabilities against a brute-force walk."""

from __future__ import annotations

import math

import numpy as np
import pytest
from likelihood_reference import segments as brute_force_pieces

from mfp_mapper.core.mapper import MAX_RAY_VOXELS, Mapper
from mfp_mapper.core.store import VoxelArrays


def _scene(decay_time: float = math.inf) -> Mapper:
    rng = np.random.default_rng(11)
    mapper = Mapper(0.25, max_range=8.0, decay_time=decay_time, prior_shape=0.4, prior_rate=0.2)
    for k in range(4):
        origin = rng.uniform(-0.5, 0.5, 3)
        pts = origin + rng.normal(size=(500, 3)) * rng.uniform(0.5, 4.0, (500, 1))
        mapper.integrate(pts, origin, stamp=float(k))
    return mapper


def _brute_force(
    mapper: Mapper, a: np.ndarray, b: np.ndarray, stamp: float | None
) -> tuple[float, float]:
    """Product of the pass probabilities over independently found pieces, statistics read
    one voxel at a time at each piece's midpoint; metres through never-observed voxels."""
    log_clear, unknown = 0.0, 0.0
    length = float(np.linalg.norm(b - a))
    shape, rate = mapper.prior.shape, mapper.prior.rate
    for _, t0, t1 in brute_force_pieces(a, b, mapper.resolution):
        chord = (t1 - t0) * length
        stats = mapper.query((a + (b - a) * (0.5 * (t0 + t1)))[None], stamp)
        s, n = float(stats.s[0]), float(stats.n[0])
        log_clear += (n + shape) * math.log((s + rate) / (s + rate + chord))
        if not stats.observed[0]:
            unknown += chord
    return math.exp(log_clear), unknown


@pytest.mark.parametrize(("decay_time", "stamp"), [(math.inf, None), (2.0, 5.0)])
def test_segments_match_a_brute_force_walk(decay_time: float, stamp: float | None) -> None:
    mapper = _scene(decay_time)
    rng = np.random.default_rng(3)
    starts = rng.uniform(-3, 3, (60, 3))
    ends = starts + rng.normal(size=(60, 3)) * rng.uniform(0.05, 5.0, (60, 1))
    ends[:3] = starts[:3] + [[1.0, 0, 0], [0, -2.0, 0], [0, 0, 0.5]]  # along the axes
    got = mapper.query_segments(starts, ends, stamp)
    for i in range(len(starts)):
        clear, unknown = _brute_force(mapper, starts[i], ends[i], stamp)
        assert got.clear_probability[i] == pytest.approx(clear, rel=1e-9, abs=1e-300)
        assert got.unknown_length[i] == pytest.approx(unknown, rel=1e-9, abs=1e-9)
        assert got.length[i] == pytest.approx(np.linalg.norm(ends[i] - starts[i]))
    assert 0.0 < got.clear_probability.min() < got.clear_probability.max() < 1.0
    assert (got.unknown_length > 0).any() and (got.unknown_length < got.length).any()


def test_a_medium_of_known_extinction_passes_as_exp_minus_its_optical_depth() -> None:
    """Well-observed voxels with 0.5 returns per metre of ray: 1 m through them is clear with
    probability close to e^-0.5, 2 m e^-1."""
    res = 0.1
    ijk = np.array([(i, 0, 0) for i in range(40)], dtype=np.int32)
    s = np.full(40, 1.0e4)  # metres of ray seen in each voxel
    voxels = VoxelArrays(ijk, s, 0.5 * s, np.zeros(40))
    mapper = Mapper.from_arrays(voxels, resolution=res)
    got = mapper.query_segments([[0.5, 0.05, 0.05]] * 2, [[1.5, 0.05, 0.05], [2.5, 0.05, 0.05]])
    assert got.clear_probability == pytest.approx([math.exp(-0.5), math.exp(-1.0)], rel=1e-3)
    assert got.unknown_length == pytest.approx([0.0, 0.0])


def test_an_empty_map_is_all_unknown_and_uses_the_prior() -> None:
    mapper = Mapper(0.2, prior_shape=0.5, prior_rate=0.25)
    got = mapper.query_segments([[0.03, 0.07, 0.11]], [[3.03, 0.07, 0.11]])
    # 3 m through never-observed voxels: each chord l passes with (rate / (rate + l))^shape
    want = math.prod(
        (0.25 / (0.25 + (t1 - t0) * 3.0)) ** 0.5
        for _, t0, t1 in brute_force_pieces(
            np.array([0.03, 0.07, 0.11]), np.array([3.03, 0.07, 0.11]), 0.2
        )
    )
    assert got.clear_probability[0] == pytest.approx(want, rel=1e-12)
    assert got.unknown_length[0] == pytest.approx(3.0)


def test_a_zero_length_segment_is_clear_and_bad_segments_are_refused() -> None:
    mapper = _scene()
    got = mapper.query_segments([[1.0, 1.0, 1.0]], [[1.0, 1.0, 1.0]])
    assert (got.clear_probability, got.unknown_length, got.length) == ([1.0], [0.0], [0.0])
    empty = mapper.query_segments(np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(empty) == 0
    with pytest.raises(ValueError, match="finite"):
        mapper.query_segments([[0.0, 0.0, math.nan]], [[1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="starts but"):
        mapper.query_segments([[0.0, 0.0, 0.0]], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="voxels"):
        mapper.query_segments([[0.0, 0.0, 0.0]], [[(MAX_RAY_VOXELS + 1) * 0.25, 0.0, 0.0]])
    with pytest.raises(ValueError, match="index range"):
        mapper.query_segments([[1e12, 0.0, 0.0]], [[1e12 + 1.0, 0.0, 0.0]])
