"""The scan likelihood (core/likelihood.py) against a brute-force pure-Python reference."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import pytest
from likelihood_reference import reference as _reference

from mfp_mapper.core.likelihood import scan_log_likelihood, total_log_likelihood
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.traversal import RETURN_CHORD_FLOOR


def _scene(decay_time: float = math.inf) -> tuple[Mapper, np.random.Generator]:
    rng = np.random.default_rng(7)
    mapper = Mapper(0.25, max_range=6.0, decay_time=decay_time)
    for k in range(4):
        origin = rng.uniform(-0.5, 0.5, 3)
        pts = origin + rng.normal(size=(400, 3)) * rng.uniform(0.5, 4.0, (400, 1))
        flags = rng.random(400) < 0.2
        mapper.integrate(pts, origin, stamp=float(k), no_return=flags)
    return mapper, rng


@pytest.mark.parametrize(
    ("decay_time", "shape", "rate"), [(math.inf, 1.0, 1.0), (3.0, 0.3, 0.05), (math.inf, 2.5, 0.01)]
)
def test_matches_brute_force(decay_time: float, shape: float, rate: float) -> None:
    mapper, rng = _scene(decay_time)
    origin = np.array([0.13, -0.21, 0.07])
    pts = origin + rng.normal(size=(150, 3)) * rng.uniform(0.3, 5.0, (150, 1))
    pts[:5] = origin + rng.normal(size=(5, 3)) * 10.0  # beyond max_range: cut, no return
    flags = rng.random(150) < 0.15
    stamp = 5.5
    got = scan_log_likelihood(
        mapper, pts, origin, stamp, no_return=flags, shape=shape, rate=rate, events=True
    )
    want, events = _reference(mapper, pts, origin, stamp, flags, shape, rate)
    assert got.rays == 150
    np.testing.assert_array_equal(got.ray_source, np.arange(150))
    np.testing.assert_allclose(got.ray_log_likelihood, want, rtol=1e-9, atol=1e-12)
    assert got.total == pytest.approx(want.sum(), rel=1e-10)
    ev = got.event_arrays
    assert ev is not None
    assert got.events == len(ev) == len(events)
    ref = np.array([e[:3] for e in events])
    np.testing.assert_allclose(np.c_[ev.s, ev.n, ev.chord], ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(ev.hit, [e[3] for e in events])
    np.testing.assert_allclose(
        np.bincount(ev.ray, ev.log_probability(shape, rate), minlength=150),
        want,
        rtol=1e-9,
        atol=1e-12,
    )
    # a ray returns at most once, and only at its end
    assert np.bincount(ev.ray[ev.hit], minlength=150).max() == 1


def test_same_chords_as_integration() -> None:
    """The read-only walk's chords are the integrating walk's: rays without returns score
    passes whose chords, summed per voxel, are what integrating them adds to s."""
    rng = np.random.default_rng(3)
    origin = np.array([0.31, 0.02, -0.4])
    pts = origin + rng.normal(size=(300, 3)) * 3.0
    flags = np.ones(300, dtype=bool)
    empty = Mapper(0.2, max_range=50.0)
    got = scan_log_likelihood(empty, pts, origin, 0.0, no_return=flags, events=True)
    ev = got.event_arrays
    assert ev is not None and not ev.hit.any()
    assert np.all(ev.s == 0.0) and np.all(ev.n == 0.0)  # an empty map: the prior alone
    built = Mapper(0.2, max_range=50.0)
    built.integrate(pts, origin, 0.0, no_return=flags)
    voxels = built.voxels()
    keys, inverse = np.unique(ev.ijk, axis=0, return_inverse=True)
    sums = np.bincount(inverse.ravel(), ev.chord)
    order = np.lexsort(voxels.ijk.T[::-1])
    np.testing.assert_array_equal(keys, voxels.ijk[order])
    np.testing.assert_allclose(sums, voxels.s[order], rtol=2e-6)


def test_empty_map_is_the_prior() -> None:
    """Never-observed voxels: a pass over l has probability (beta/(beta+l))^alpha."""
    mapper = Mapper(0.5)
    got = scan_log_likelihood(
        mapper, [[0.2, 0.1, 0.3]], [0.1, 0.1, 0.3], 0.0, shape=2.0, rate=0.5, events=True
    )
    # one ray inside one voxel, ends with a return: the full chord is 0.5 - 0.1 = 0.4 m
    assert got.events == 1
    assert got.total == pytest.approx(math.log(1.0 - (0.5 / 0.9) ** 2.0), rel=1e-12)


def test_return_on_a_voxel_edge_is_finite() -> None:
    """A return exactly on a voxel's edge or corner (coordinates rounded to 1 mm, a wall at
    x = 2.0 m) floors to a voxel the ray only touches: its chord there is 0, and was
    p_hit 0, log-likelihood -inf. The return event's chord is at least RETURN_CHORD_FLOOR,
    as in the brute force; every other event is exact."""
    res = 0.1
    mapper = Mapper(res, max_range=20.0)
    origin = np.zeros(3)
    # the tls_conifers case: x on a face entered at the end, y on a face left at the end
    edge = np.array([[2.0, -1.0, -1.353], [-1.0, 0.5, 1.495], [2.0, 1.0, 0.3], [2.0, -1.0, -1.0]])
    for k in range(3):
        mapper.integrate(edge, origin, float(k))
    got = scan_log_likelihood(mapper, edge, origin, 3.0, shape=0.0033, rate=0.0016, events=True)
    ev = got.event_arrays
    assert ev is not None
    assert np.all(np.isfinite(got.ray_log_likelihood))
    assert ev.chord[ev.hit].min() == RETURN_CHORD_FLOOR  # the edge cases hit the floor
    want, events = _reference(mapper, edge, origin, 3.0, np.zeros(4, bool), 0.0033, 0.0016)
    np.testing.assert_allclose(got.ray_log_likelihood, want, rtol=1e-9, atol=1e-12)
    # the return events (rays along grid diagonals also cross voxels over chords of 1e-16 m,
    # which the brute force merges with their neighbours)
    ref = np.array([e[:3] for e in events if e[3]])
    got_hits = np.c_[ev.s, ev.n, ev.chord][ev.hit]
    np.testing.assert_allclose(got_hits, ref, rtol=1e-9, atol=1e-12)


def test_read_only_and_threads() -> None:
    mapper, rng = _scene()
    before = mapper.voxels()
    version = mapper.version
    origin = np.zeros(3)
    pts = rng.normal(size=(500, 3)) * 3.0
    want = total_log_likelihood(mapper, pts, origin, 4.0)
    results: list[float] = []

    def score(shift: float) -> None:
        results.append(total_log_likelihood(mapper, pts + shift * 0.0, origin, 4.0))

    threads = [threading.Thread(target=score, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results == [want] * 4
    after = mapper.voxels()
    assert mapper.version == version
    np.testing.assert_array_equal(before.s, after.s)
    np.testing.assert_array_equal(before.n, after.n)


def test_dropped_rays_and_bad_prior() -> None:
    mapper, _ = _scene()
    pts = np.array([[1.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [0.0, 2.0, 0.0]])
    got = scan_log_likelihood(mapper, pts, np.zeros(3), 1.0)
    assert got.rays == 2 and got.dropped["nonfinite"] == 1
    np.testing.assert_array_equal(got.ray_source, [0, 2])
    with pytest.raises(ValueError, match="shape and rate"):
        scan_log_likelihood(mapper, pts, np.zeros(3), 1.0, shape=0.0)


def test_shards_and_origin() -> None:
    """Two shards and a map origin far from zero (not on the voxel grid): still exact."""
    rng = np.random.default_rng(11)
    base = np.array([5000.0, -3000.0, 20.0])
    mapper = Mapper(0.25, max_range=6.0, threads=2, origin=base - 0.37)
    for k in range(3):
        origin = base + rng.normal(size=3)
        mapper.integrate(base + rng.normal(size=(500, 3)) * 3.0, origin, float(k))
    pts = base + rng.normal(size=(100, 3)) * 3.0
    flags = np.zeros(100, dtype=bool)
    got = scan_log_likelihood(mapper, pts, base, 3.0)
    offset = np.asarray(mapper.origin)
    shifted = Mapper(0.25, max_range=6.0)  # the reference reads ``mapper`` at shifted points
    shifted.query = lambda p, stamp=None: mapper.query(np.asarray(p) + offset, stamp)  # type: ignore[method-assign]
    prior = mapper.prior  # the default: the family
    want, _ = _reference(shifted, pts - offset, base - offset, 3.0, flags, prior.shape, prior.rate)
    np.testing.assert_allclose(got.ray_log_likelihood, want, rtol=1e-9, atol=1e-12)
    mapper.close()


def test_every_held_out_ray_of_the_tls_scan_is_finite(shared_data: Path) -> None:
    """tls_conifers at 0.1 m, even shots mapped and odd shots scored (what `score --split
    shots` does): its coordinates are rounded to 1 mm, so some returns lie on voxel edges
    (2 of them scored -inf before the return chord's floor)."""
    from mfp_mapper.sources.scan_files import read_ply

    cols = read_ply(shared_data / "tls_conifers" / "scan.ply")
    pts = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
    mapper = Mapper(0.1, max_range=100.0)
    mapper.integrate(pts[::2], np.zeros(3), 0.0)
    got = scan_log_likelihood(mapper, pts[1::2], np.zeros(3), 0.0, events=True)
    ev = got.event_arrays
    assert ev is not None
    assert np.all(np.isfinite(got.ray_log_likelihood))
    assert np.count_nonzero(ev.hit & (ev.chord == RETURN_CHORD_FLOOR)) >= 2
