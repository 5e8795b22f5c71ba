"""``MapCloud``: the map clouds rebuilt from changed blocks equal a rebuild of the whole map."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from mfp_mapper import Mapper
from mfp_mapper.core.model import Prior
from mfp_mapper.core.reflectivity import ScanReflectivity
from mfp_mapper.mapping.map_cloud import CloudRows, MapCloud, rows_of
from mfp_mapper.sensing.reflectivity import bins_for


def _whole(mapper: Mapper, min_doo: float, min_evidence: float) -> CloudRows:
    vox = mapper.voxels(min_doo=min_doo, min_evidence=min_evidence)
    return rows_of(vox, mapper.reflectivity(vox.centers))


def _assert_same(got: CloudRows, want: CloudRows) -> None:
    """Equal bit for bit, except the reflectivity mean: with decay, a later scan rescales
    every histogram's float32 counts (``ReflectivityTable`` keeps them at the latest stamp),
    which leaves a block's mean unchanged up to float32 rounding, so kept rows may differ
    from a rebuild in the last bits."""
    assert len(got) == len(want)
    a, b = np.lexsort(got.centers.T), np.lexsort(want.centers.T)
    for x, y in zip(got.arrays(), want.arrays(), strict=True):
        assert (x is None) == (y is None)
        if x is None:
            continue
        if x is got.reflectivity:
            np.testing.assert_allclose(x[a], y[b], rtol=1e-6, atol=0.0)
        else:
            np.testing.assert_array_equal(x[a], y[b])


def _update(cloud: MapCloud, mapper: Mapper, min_doo: float, min_evidence: float) -> CloudRows:
    return cloud.apply(cloud.read(mapper, min_doo, min_evidence), min_evidence)


@pytest.mark.parametrize("decay_time", [math.inf, 2.0])
@pytest.mark.parametrize(("min_doo", "min_evidence"), [(0.1, 0.0), (0.1, 0.3), (0.0, 0.0)])
def test_rebuilt_from_changed_blocks_equals_the_whole_map(
    decay_time: float, min_doo: float, min_evidence: float
) -> None:
    """A robot driving along, 40 scans (two late), published every few scans: the rows
    equal a whole-map rebuild every time (decayed statistics included), and a publication
    after scans far away reads only the blocks they changed."""
    rng = np.random.default_rng(7)
    mapper = Mapper(0.2, decay_time=decay_time, reflectivity_bins=8)
    cloud = MapCloud()
    bins = bins_for("intensity", 8)
    stamps = [10.0 + 0.1 * k for k in range(40)]
    stamps[5], stamps[7] = stamps[7], stamps[5]
    for k, stamp in enumerate(stamps):
        origin = np.array([1.5 * k, 0.2 * k, 1.0])
        points = origin + rng.normal(0.0, 3.0, (1500, 3))
        intensity = rng.uniform(0.0, 100.0, len(points))
        mapper.integrate(points, origin, stamp, reflectivity=ScanReflectivity(intensity, bins))
        if k % 3 == 0:
            rows = _update(cloud, mapper, min_doo, min_evidence)
            _assert_same(rows, _whole(mapper, min_doo, min_evidence))
    assert rows.reflectivity is not None and np.isfinite(rows.reflectivity).any()
    held = len(np.unique(mapper.voxels(min_doo=min_doo).ijk >> 3, axis=0))
    mapper.integrate(np.array([[60.0, 8.0, 1.0]]), np.array([58.5, 7.8, 1.0]), 20.0)
    _assert_same(
        _update(cloud, mapper, min_doo, min_evidence), _whole(mapper, min_doo, min_evidence)
    )
    assert 0 < cloud.last_changed_blocks < held / 10


def test_reset_clear_box_eviction_and_filters_start_over() -> None:
    """Whatever changes voxels other than a scan (clear_box, reset, the memory bound), or
    a change of filter or prior: the next rows still equal the whole map's."""
    rng = np.random.default_rng(8)
    mapper = Mapper(0.2, max_voxels=80_000)
    cloud = MapCloud()

    def scan(k: int, at: float) -> None:
        origin = np.array([at, 0.0, 1.0])
        mapper.integrate(origin + rng.normal(0.0, 3.0, (2000, 3)), origin, 10.0 + k)

    def check(min_doo: float = 0.1) -> None:
        _assert_same(_update(cloud, mapper, min_doo, 0.0), _whole(mapper, min_doo, 0.0))

    for k in range(3):
        scan(k, 0.0)
    check()
    mapper.clear_box([-2.0, -2.0, 0.0], [2.0, 2.0, 3.0])
    check()
    epoch = mapper.epoch
    for k in range(3, 8):  # far away: the memory bound evicts the first blocks
        scan(k, 150.0)
    assert mapper.epoch > epoch
    check()
    check(0.4)
    mapper.prior = Prior(2.0, 1.0)
    check(0.4)
    mapper.reset()
    check()
    scan(9, 0.0)
    check()


def test_a_publication_without_changed_blocks_keeps_the_rows() -> None:
    """A map version with no block holding a return changed (a scan of free space far from
    every return): the rows stay the whole map's."""
    rng = np.random.default_rng(9)
    mapper = Mapper(0.2)
    cloud = MapCloud()
    origin = np.array([0.0, 0.0, 1.0])
    mapper.integrate(origin + rng.normal(0.0, 3.0, (2000, 3)), origin, 10.0)
    first = _update(cloud, mapper, 0.1, 0.0)
    far = np.array([300.0, 0.0, 1.0])
    mapper.integrate(far + [[5.0, 0.0, 0.0]], far, 11.0, no_return=np.array([True]))
    rows = _update(cloud, mapper, 0.1, 0.0)
    assert cloud.last_changed_blocks == 0
    _assert_same(rows, first)
    _assert_same(rows, _whole(mapper, 0.1, 0.0))


@pytest.mark.parametrize("threads", [1, 2])
def test_a_read_in_slices_with_scans_between_then_the_next_equals_the_whole_map(
    threads: int,
) -> None:
    """``MapCloud.read`` a few blocks at a time (the node lets go of the map lock between
    slices): without scans in between, the rows of one read; with scans integrated between
    the slices, the rows hold every voxel once and the next publication equals the whole
    map (it reads again the blocks those scans changed), also when the map's first
    histograms came between two slices; a clear_box between two slices starts the read
    again."""
    rng = np.random.default_rng(13)
    mapper = Mapper(0.2, threads=threads, reflectivity_bins=8)
    bins = bins_for("intensity", 8)

    def scan(k: int) -> None:  # the first four without an intensity: no histograms yet
        origin = np.array([2.0 * k, 0.3 * k, 1.0])
        points = origin + rng.normal(0.0, 3.0, (1500, 3))
        values = ScanReflectivity(rng.uniform(0.0, 100.0, len(points)), bins)
        mapper.integrate(points, origin, 10.0 + k, reflectivity=values if k >= 4 else None)

    def sliced(cloud: MapCloud, between: Callable[[], None] | None = None) -> CloudRows:
        changes = cloud.read(mapper, 0.1, 0.0, 30)
        count = 1
        while not changes.complete:
            if between is not None:
                between()
            changes = cloud.read(mapper, 0.1, 0.0, 30, changes)
            count += 1
        assert count > 3
        return cloud.apply(changes, 0.0)

    for k in range(4):
        scan(k)
    cloud = MapCloud()
    _assert_same(sliced(cloud), _whole(mapper, 0.1, 0.0))
    later = iter(range(4, 100))
    rows = sliced(cloud, lambda: scan(next(later)))  # the histograms begin in between
    assert next(later) > 6 and rows.reflectivity is not None
    assert len(np.unique(rows.centers, axis=0)) == len(rows), "a voxel twice"
    _assert_same(_update(cloud, mapper, 0.1, 0.0), _whole(mapper, 0.1, 0.0))
    cleared = []
    rows = sliced(
        cloud,
        lambda: (
            cleared.append(mapper.clear_box([-1.0, -1.0, 0.0], [1.0, 1.0, 2.0]))
            if not cleared
            else None
        ),
    )
    _assert_same(rows, _whole(mapper, 0.1, 0.0))
