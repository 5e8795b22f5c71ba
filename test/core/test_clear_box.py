"""Mapper.clear_box (the node's ~/clear_bbox): voxels in the box become unknown, others stay."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import Mapper
from mfp_mapper.mapio import load_map, save_map


def _scene(threads: int = 1) -> Mapper:
    mapper = Mapper(0.2, threads=threads)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=300)):
        mapper.integrate(points, origin, float(k))
    return mapper


@pytest.mark.parametrize("threads", [1, 4])
def test_clear_box_resets_exactly_the_voxels_whose_centres_are_inside(threads: int) -> None:
    mapper = _scene(threads)
    before = mapper.voxels()
    # corners in any order; a box crossing block boundaries and holding walls and free space
    a, b = np.array([4.013, 3.021, 2.117]), np.array([-2.271, -1.737, 0.331])
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    inside = np.all((before.centers >= lo) & (before.centers <= hi), axis=1)
    assert 0 < inside.sum() < len(before)
    v0 = mapper.version

    cleared = mapper.clear_box(a, b)

    assert cleared == int(inside.sum())
    assert mapper.version > v0
    assert mapper.num_voxels == len(before) - cleared
    after = mapper.voxels()
    assert len(after) == mapper.num_voxels
    # the voxels outside keep their exact statistics (brute force: the full export, filtered)
    order = np.lexsort(after.ijk.T)
    kept = before.select(~inside)
    kept_order = np.lexsort(kept.ijk.T)
    assert np.array_equal(after.ijk[order], kept.ijk[kept_order])
    assert np.array_equal(after.s[order], kept.s[kept_order])
    assert np.array_equal(after.n[order], kept.n[kept_order])
    # those inside are unknown again: the prior of a never-observed voxel
    q = mapper.query(before.centers[inside])
    assert not q.observed.any()
    assert np.allclose(q.most_likely_doo, 0.5)
    # clearing again finds nothing; an empty box clears nothing and keeps the version
    v1 = mapper.version
    assert mapper.clear_box(a, b) == 0 and mapper.version == v1


def test_cleared_space_maps_again_and_the_clearing_is_saved(tmp_path: Path) -> None:
    mapper = _scene()
    box = (np.array([-np.inf, -np.inf, 1.013]), np.array([np.inf, np.inf, 1.417]))
    cleared = mapper.clear_box(*box)
    assert cleared > 0
    path = tmp_path / "map.npz"
    save_map(mapper, path)
    loaded = load_map(path)
    assert loaded.num_voxels == mapper.num_voxels
    centers = loaded.voxels().centers
    assert not np.any((centers[:, 2] >= 1.013) & (centers[:, 2] <= 1.417))
    # new rays through the cleared band observe it again
    points, origin = anchors_scene(n_scans=1, azimuths=300)[0]
    loaded.integrate(points, origin, 5.0)
    z = loaded.voxels().centers[:, 2]
    assert np.any((z >= 1.013) & (z <= 1.417))


def test_clear_box_refuses_nan_corners() -> None:
    mapper = _scene()
    n = mapper.num_voxels
    with pytest.raises(ValueError, match="corners"):
        mapper.clear_box([0.0, float("nan"), 0.0], [1.0, 1.0, 1.0])
    assert mapper.num_voxels == n
