"""Pictures: the top-down band between floor and ceiling, outliers cropped, a std picture
that does not depend on storage order, mean DoO and minimum evidence."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.replay import ReplayOptions, replay
from mfp_mapper.outputs.render import floor_and_ceiling, render_map
from mfp_mapper.sources.simulate import preset, simulate

pytestmark = pytest.mark.slow

HALL = replace(preset("demo"), scans=4, azimuths=360)  # 28 x 22 m hall, ceiling at 5 m
RES = 0.2


@pytest.fixture(scope="module")
def hall_rays(
    tmp_path_factory: pytest.TempPathFactory,
) -> list[tuple[float, np.ndarray, np.ndarray]]:
    bag = simulate(tmp_path_factory.mktemp("hall") / "bag", HALL, "mcap").bag
    rays: list[tuple[float, np.ndarray, np.ndarray]] = []
    replay(bag, ReplayOptions.of(resolution=RES), progress=False,
           on_scan=lambda t, p, o: rays.append((t, p.copy(), np.array(o))))  # fmt: skip
    return rays


def _map(rays, order: np.ndarray | None = None, outlier: bool = False) -> Mapper:  # type: ignore[no-untyped-def]
    mapper = Mapper(RES)
    for stamp, points, origins in rays:
        pick = order[: len(points)] % len(points) if order is not None else slice(None)
        mapper.integrate(points[pick], origins if origins.ndim == 1 else origins[pick], stamp)
    if outlier:  # a few stray returns far above and far away
        o = rays[-1][2] if rays[-1][2].ndim == 1 else rays[-1][2][0]
        mapper.integrate(np.array([[60.0, 40.0, 55.0], [-45.0, 5.0, 30.0]]), o, rays[-1][0])
    return mapper


def test_band_between_floor_and_ceiling(hall_rays, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    mapper = _map(hall_rays, outlier=True)
    floor, ceiling = floor_and_ceiling(mapper.voxels())
    assert floor == pytest.approx(0.0 + RES, abs=RES + 1e-9)  # floor top: z = 0 .. 0.2
    assert ceiling == pytest.approx(5.0, abs=RES + 1e-9)
    result = render_map(mapper, tmp_path)
    lo, hi = result.band
    assert floor < lo < 1.0 and 2.0 < hi < ceiling
    # the walls are drawn: the hall's outline columns are occupied in the picture
    assert result.top_down is not None
    assert np.nanmax(result.top_down) > 0.9
    # cropped to the hall, not stretched to the outliers 45-60 m away
    x0, x1, y0, y1 = result.extent
    assert -16 < x0 < -13 and 13 < x1 < 16 and -13 < y0 < -10 and 10 < y1 < 13


def test_std_picture_does_not_depend_on_storage_order(hall_rays, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    a = render_map(_map(hall_rays), tmp_path / "a")
    shuffled = [(t, p[::-1].copy(), o if o.ndim == 1 else o[::-1].copy()) for t, p, o in hall_rays]
    b = render_map(_map(shuffled), tmp_path / "b")
    # equal up to the float32 rounding of s summed in another order: no storage-order tiles
    np.testing.assert_allclose(a.top_down, b.top_down, rtol=1e-6, atol=1e-7, equal_nan=True)
    np.testing.assert_allclose(a.top_down_std, b.top_down_std, rtol=1e-6, equal_nan=True)


def test_mean_and_min_evidence(hall_rays, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    mapper = _map(hall_rays)
    top = render_map(mapper, tmp_path / "max")
    mean = render_map(mapper, tmp_path / "mean", value="mean")
    seen = ~np.isnan(top.top_down)
    np.testing.assert_array_equal(np.isnan(mean.top_down), ~seen)
    # free columns: the most likely DoO is 0, the posterior mean stays above it
    free = seen & (top.top_down == 0.0)
    assert free.sum() > 100
    assert np.all(mean.top_down[free] > 0.0)
    strict = render_map(mapper, tmp_path / "strict", min_evidence=1.0)
    assert np.isnan(strict.top_down).sum() > np.isnan(top.top_down).sum()
    with pytest.raises(ValueError, match="most-likely' or 'mean"):
        render_map(mapper, tmp_path / "bad", value="median")


def test_reflectivity_view_shows_the_ground_s_intensity(tmp_path: Path) -> None:
    """A floor whose left half returns intensity 3 and right half 100, under a roof of
    intensity 200: the view draws the floor (the lowest voxel with returns per column)."""
    from mfp_mapper.core.reflectivity import ReflectivityBins, ScanReflectivity

    bins = ReflectivityBins("intensity", (2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0))
    rng = np.random.default_rng(2)
    floor = np.column_stack([rng.uniform(-4, 4, 4000), rng.uniform(-4, 4, 4000), np.zeros(4000)])
    roof = floor + [0.0, 0.0, 3.0]
    points = np.vstack([floor, roof])
    values = np.concatenate([np.where(floor[:, 0] < 0, 3.0, 100.0), np.full(4000, 200.0)])
    mapper = Mapper(0.5)
    mapper.integrate(
        points, np.array([0.0, 0.0, 1.5]), 0.0, reflectivity=ScanReflectivity(values, bins)
    )
    result = render_map(mapper, tmp_path, z_min=-1.0, z_max=4.0)
    assert tmp_path / "reflectivity_topdown.png" in result.files
    grid = result.reflectivity
    assert grid is not None
    x0 = result.extent[0]
    columns = x0 + (np.arange(grid.shape[0]) + 0.5) * (result.extent[1] - x0) / grid.shape[0]
    left, right = grid[columns < -0.5], grid[columns > 0.5]
    assert np.nanmax(left) == pytest.approx(np.sqrt(8.0))
    assert np.nanmin(left) == pytest.approx(np.sqrt(8.0))
    assert np.nanmin(right) == pytest.approx(np.sqrt(64.0 * 128.0))
    plain = Mapper(0.5)
    plain.integrate(points, np.array([0.0, 0.0, 1.5]), 0.0)
    assert render_map(plain, tmp_path / "plain").reflectivity is None
