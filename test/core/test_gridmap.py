"""The 2D hit-probability projection (mfp_mapper.core.gridmap), without ROS."""

from __future__ import annotations

import numpy as np
import pytest
from box_world import BoxWorld
from grid_reference import hit_probability_grid

from mfp_mapper import Mapper
from mfp_mapper.core import gridmap, model
from mfp_mapper.core.gridmap import (
    DEFAULT_OCCUPIED_THRESHOLD,
    UNKNOWN,
    band_mask,
    unobserved_hit_probability,
)
from mfp_mapper.sources.scan_pattern import scan_directions


def test_band_uses_voxel_centres() -> None:
    ijk = np.array([[0, 0, -1], [0, 0, 0], [0, 0, 1], [0, 0, 9], [0, 0, 10]])
    # res 0.2: centres -0.1, 0.1, 0.3, 1.9, 2.1
    assert band_mask(ijk, 0.2, 0.1, 2.0).tolist() == [False, True, True, True, False]


def test_max_over_band_unknown_elsewhere_and_layout() -> None:
    res = 0.5
    ijk = np.array(
        [
            [2, 1, 1],  # in band, p 0.3
            [2, 1, 2],  # in band, p 0.8: the column keeps the max
            [2, 1, 9],  # above the band: ignored
            [0, 0, 1],  # in band, p 0.004 -> 0
            [3, 3, 1],  # not observed: unknown
        ]
    )
    prob = np.array([0.3, 0.8, 1.0, 0.004, 0.9])
    observed = np.array([True, True, True, True, False])
    grid = hit_probability_grid(ijk, prob, observed, res, 0.2, 1.5)
    # extent of the observed voxels: i 0..2, j 0..1
    assert (grid.width, grid.height) == (3, 2)
    assert grid.origin == (0.0, 0.0)
    assert grid.data.dtype == np.int8
    assert grid.data[1, 2] == 80  # row = j, col = i
    assert grid.data[0, 0] == 0
    assert grid.value_at(1.2, 0.7) == 80
    assert (grid.data == UNKNOWN).sum() == 4
    assert grid.value_at(100.0, 0.0) == UNKNOWN


def test_window_around_robot_has_fixed_size_and_origin() -> None:
    ijk = np.array([[10, -4, 2]])
    grid = hit_probability_grid(ijk, [0.5], [True], 0.25, 0.0, 2.0, center=(2.6, -1.0), radius=1.0)
    # floor((2.6-1)/0.25)=6 .. floor(3.6/0.25)=14 -> 9 columns; j -8..0 -> 9 rows
    assert (grid.width, grid.height) == (9, 9)
    assert grid.origin == pytest.approx((1.5, -2.0))
    assert grid.value_at(2.6, -0.9) == 50
    assert (grid.data == UNKNOWN).sum() == 80


def test_empty_inputs() -> None:
    grid = hit_probability_grid(np.zeros((0, 3), int), [], [], 0.1, 0.0, 1.0)
    assert (grid.width, grid.height) == (0, 0)
    with pytest.raises(ValueError):
        hit_probability_grid(np.zeros((0, 3), int), [], [], 0.1, 1.0, 1.0)


def test_projection_of_a_real_map_sees_the_box_and_free_space() -> None:
    res = 0.2
    mapper = Mapper(res, max_range=30.0)
    world = BoxWorld()
    dirs = scan_directions(azimuths=360)
    for k in range(3):
        origin = np.array([0.5 * k, 0.0, 1.8])
        rng = world.cast(origin, dirs)
        keep = np.isfinite(rng) & (rng < 30.0)
        mapper.integrate(origin + dirs[keep] * rng[keep, None], origin, float(k))
    vox = mapper.voxels()
    prob = model.hit_probability(vox.s, vox.n, res)
    grid = hit_probability_grid(vox.ijk, prob, vox.observed, res, 0.3, 2.0)
    # the face x = 5 of the box (5..7, 3..5, height 3): one of the two cells at the face
    face = max(grid.value_at(4.9, 4.0), grid.value_at(5.1, 4.0))
    assert face >= 30
    free = grid.value_at(2.0, 0.5)  # crossed by rays, never a return
    assert 0 <= free <= 20 and free < face / 2
    assert grid.value_at(6.5, 4.5) == UNKNOWN  # inside the box
    assert grid.data.min() >= -1 and grid.data.max() <= 100


@pytest.mark.parametrize("threads", [1, 2])
def test_mapper_grid_equals_the_projection_of_exported_voxels(threads: int) -> None:
    """Mapper.hit_probability_grid reads the blocks directly; it must give exactly the grid
    of the reference projection of the exported voxels, whole-map and windowed."""
    res, z_min, z_max = 0.2, 0.3, 2.0
    mapper = Mapper(res, max_range=30.0, threads=threads)
    world = BoxWorld()
    dirs = scan_directions(azimuths=360)
    for k in range(3):
        origin = np.array([0.5 * k, -0.3 * k, 1.8])
        rng = world.cast(origin, dirs)
        keep = np.isfinite(rng) & (rng < 30.0)
        mapper.integrate(origin + dirs[keep] * rng[keep, None], origin, float(k))
    band = ([-np.inf, -np.inf, z_min], [np.inf, np.inf, z_max])
    vox = mapper.voxels(bounds=band)
    reference = hit_probability_grid(vox.ijk, vox.hit_probability, vox.observed, res, z_min, z_max)
    grid = mapper.hit_probability_grid(z_min, z_max)
    assert grid.data.shape == reference.data.shape and grid.origin == reference.origin
    assert np.array_equal(grid.data, reference.data)
    assert (grid.data >= 0).sum() > 1000 and grid.data.max() > 50  # a real, varied map

    center, radius = (3.3, -1.1), 4.0
    windowed = mapper.hit_probability_grid(z_min, z_max, center=center, radius=radius)
    ref_windowed = hit_probability_grid(
        vox.ijk, vox.hit_probability, vox.observed, res, z_min, z_max, center=center, radius=radius
    )
    assert windowed.origin == ref_windowed.origin
    assert np.array_equal(windowed.data, ref_windowed.data)

    empty = Mapper(res).hit_probability_grid(z_min, z_max)
    assert empty.data.shape == (0, 0)


def test_trinary_cells_for_nav2() -> None:
    """100 at/above the occupied threshold, 0 observed below the free one, else -1."""
    ijk = np.array([[2, 1, 1], [2, 1, 2], [0, 0, 1], [1, 0, 1], [1, 1, 1], [3, 3, 1]])
    prob = np.array([0.3, 0.5, 0.004, 0.2, 0.09999, 0.9])
    observed = np.array([True, True, True, True, True, False])
    grid = hit_probability_grid(ijk, prob, observed, 0.5, 0.2, 1.5, trinary=(0.5, 0.1))
    assert grid.data[1, 2] == 100  # the column's max 0.5 is at the threshold
    assert grid.data[0, 0] == 0
    assert grid.data[0, 1] == UNKNOWN  # 0.2: observed but between the thresholds
    assert grid.data[1, 1] == 0  # 0.09999 < 0.1: exact comparison, not the rounded 10
    assert set(np.unique(grid.data)) <= {-1, 0, 100}
    with pytest.raises(ValueError):
        hit_probability_grid(ijk, prob, observed, 0.5, 0.2, 1.5, trinary=(0.1, 0.5))


def test_unobserved_hit_probability_bounds_every_unhit_voxel() -> None:
    res = 0.1
    prior = unobserved_hit_probability(res)
    assert prior == pytest.approx(0.090909, abs=1e-6)  # docs/model.md's worked values (s = n = 0)
    s = np.array([1e-6, 0.05, 1.0, 100.0])
    assert np.all(model.hit_probability(s, np.zeros_like(s), res) < prior)


@pytest.mark.parametrize(("threads", "free"), [(1, None), (2, None), (1, 0.02), (1, 0.2)])
def test_mapper_trinary_grid_marks_the_wall_and_matches_the_reference(
    threads: int, free: float | None
) -> None:
    """The compiled grid (with its shortcut for voxels surely free) against the per-voxel
    reference; ``free``: the free threshold (None: the unobserved voxel's probability)."""
    res, z_min, z_max = 0.1, 0.3, 2.0
    mapper = Mapper(res, max_range=30.0, threads=threads)
    world = BoxWorld()
    dirs = scan_directions(azimuths=720)
    for k in range(3):
        origin = np.array([0.02 * k, 0.0, 1.8])
        rng = world.cast(origin, dirs)
        keep = np.isfinite(rng) & (rng < 30.0)
        mapper.integrate(origin + dirs[keep] * rng[keep, None], origin, float(k))
    free_threshold = unobserved_hit_probability(res) if free is None else free
    thresholds = (DEFAULT_OCCUPIED_THRESHOLD, free_threshold)
    grid = mapper.hit_probability_grid(z_min, z_max, trinary=thresholds)
    band = ([-np.inf, -np.inf, z_min], [np.inf, np.inf, z_max])
    vox = mapper.voxels(bounds=band)
    reference = hit_probability_grid(
        vox.ijk, vox.hit_probability, vox.observed, res, z_min, z_max, trinary=thresholds
    )
    assert np.array_equal(grid.data, reference.data) and grid.origin == reference.origin
    # the face x = 5 of the box, y 3..5: every cell of it occupied (one of the two columns)
    for y in np.arange(3.05, 5.0, 0.1):
        assert max(grid.value_at(4.95, y), grid.value_at(5.05, y)) == 100, y
    if free is None:
        assert grid.value_at(2.0, 0.5) == 0  # crossed by rays, never a return
    assert grid.value_at(6.5, 4.5) == UNKNOWN  # inside the box
    assert set(np.unique(grid.data)) == {-1, 0, 100}
    raw = mapper.hit_probability_grid(z_min, z_max)
    assert np.all(grid.data[raw.data == UNKNOWN] == UNKNOWN)


@pytest.mark.parametrize("trinary", [None, (0.25, 0.01)])
def test_grid_continued_from_the_last_equals_one_from_scratch(
    trinary: tuple[float, float] | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A robot driving out of the first grid (the extent grows, on both sides), with decay
    and a late scan: each grid continued from the previous one's cells (only the columns
    of blocks the scans since opened) equals the grid computed from the whole band; after
    clear_box and reset too."""
    continued = []  # grids computed from the changed columns only
    dirty_columns = gridmap._dirty_columns
    monkeypatch.setattr(
        gridmap, "_dirty_columns", lambda *a: (continued.append(1), dirty_columns(*a))[1]
    )
    rng = np.random.default_rng(11)
    mapper = Mapper(0.2, decay_time=1.0)
    band = (0.1, 2.0)
    previous = None
    changed_columns = []
    stamps = [10.0 + 0.1 * k for k in range(24)]
    stamps[6], stamps[8] = stamps[8], stamps[6]
    for k, stamp in enumerate(stamps):
        origin = np.array([2.5 * k * (-1) ** k, 0.7 * k, 1.0])
        points = origin + rng.normal(0.0, 3.0, (1200, 3))
        mapper.integrate(points, origin, stamp)
        if k == 15:
            mapper.clear_box([-5.0, -5.0, 0.0], [5.0, 5.0, 3.0])
        if k == 20:
            mapper.reset()
        got = mapper.hit_probability_grid(*band, trinary=trinary, previous=previous)
        want = mapper.hit_probability_grid(*band, trinary=trinary)
        assert got.origin == want.origin
        np.testing.assert_array_equal(got.data, want.data)
        previous = got.cells
        changed_columns.append(got.cells is not None)
    assert all(changed_columns)
    assert len(continued) >= 15  # all but the first, and those after clear_box and reset
    # a scan in a corner: the continued grid reads a few columns, same cells as from scratch
    mapper.integrate(np.array([[0.0, 0.0, 1.0]]), np.array([0.5, 0.5, 1.0]), 20.0)
    got = mapper.hit_probability_grid(*band, trinary=trinary, previous=previous)
    want = mapper.hit_probability_grid(*band, trinary=trinary)
    np.testing.assert_array_equal(got.data, want.data)
    # a window is never continued
    window = mapper.hit_probability_grid(*band, center=(0.0, 0.0), radius=3.0, previous=previous)
    assert window.cells is None


@pytest.mark.parametrize("threads", [1, 2])
def test_grid_read_in_slices_equals_one_read_and_the_next_catches_up(threads: int) -> None:
    """``Mapper.start_grid`` + ``read_grid`` a few blocks at a time (the node lets go of the
    map lock between slices): with nothing integrated in between, the grid of one read;
    with scans integrated between the slices, a grid continued from it equals the grid
    from scratch (the scans' columns are computed again); a map whose epoch changed (a
    clear_box) refuses the next slice."""
    rng = np.random.default_rng(12)
    mapper = Mapper(0.2, threads=threads)
    band, trinary = (0.1, 2.0), (0.25, 0.02)

    def scan(k: int) -> None:
        origin = np.array([3.0 * k, 0.5 * k, 1.0])
        mapper.integrate(origin + rng.normal(0.0, 4.0, (1500, 3)), origin, 10.0 + k)

    for k in range(4):
        scan(k)
    reading = mapper.start_grid(*band, trinary=trinary)
    slices = 1
    while (grid := mapper.read_grid(reading, 40)) is None:
        slices += 1
    assert slices > 5 and mapper.num_blocks > 40 * 5
    np.testing.assert_array_equal(
        grid.data, mapper.hit_probability_grid(*band, trinary=trinary).data
    )
    reading = mapper.start_grid(*band, trinary=trinary, previous=grid.cells)
    k = 4
    while (grid := mapper.read_grid(reading, 40)) is None:
        scan(k)  # between two slices, as the node's walker may (new blocks: the next read's)
        k += 1
    assert k > 6
    assert grid.cells is not None
    got = mapper.hit_probability_grid(*band, trinary=trinary, previous=grid.cells)
    want = mapper.hit_probability_grid(*band, trinary=trinary)
    assert got.origin == want.origin
    np.testing.assert_array_equal(got.data, want.data)
    reading = mapper.start_grid(*band, trinary=trinary)
    assert mapper.read_grid(reading, 40) is None
    mapper.clear_box([-1.0, -1.0, 0.0], [1.0, 1.0, 2.0])
    assert not mapper.grid_still_valid(reading)
    with pytest.raises(ValueError, match="changed under the grid"):
        mapper.read_grid(reading, 40)
