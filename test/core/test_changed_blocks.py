"""``Mapper.changed_voxels``: the returns of the blocks scans changed, equal to ``voxels``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mfp_mapper import Mapper


def _scan(rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray]:
    origin = np.array([0.4 * k, 0.1 * k, 1.0])
    return origin + rng.normal(0.0, 3.0, (2500, 3)), origin


def _sorted(ijk: np.ndarray, *columns: np.ndarray) -> list[np.ndarray]:
    order = np.lexsort(ijk.T)
    return [ijk[order], *(c[order] for c in columns)]


@pytest.mark.parametrize("min_doo", [0.0, 0.05, 0.3, 0.9])
@pytest.mark.parametrize("threads", [1, 2])
def test_every_block_equals_voxels(min_doo: float, threads: int) -> None:
    """From scan -1 on: the voxels ``voxels(min_doo=...)`` exports, bit for bit, with
    flushed (float64) blocks among them (``min_doo`` 0: every observed voxel, free space
    included)."""
    rng = np.random.default_rng(3)
    mapper = Mapper(0.25, threads=threads, decay_time=5.0)
    for k in range(6):
        points, origin = _scan(rng, k)
        mapper.integrate(points, origin, 10.0 + k)
    for _ in range(300):  # one spot hit until its block goes to float64 (n > 2**20 in all)
        mapper.integrate(np.tile([[2.0, 2.0, 1.0]], (4000, 1)), np.zeros(3), 20.0)
    full = mapper.voxels(min_doo=min_doo)
    got, blocks, since = mapper.changed_voxels(-1, min_doo)
    assert len(got) == len(full) > 0
    for a, b in zip(
        _sorted(full.ijk, full.s, full.n, full.t_last),
        _sorted(got.ijk, got.s, got.n, got.t_last),
        strict=True,
    ):
        np.testing.assert_array_equal(a, b)
    assert since == 306
    held = {tuple(b) for b in np.unique(full.ijk >> 3, axis=0)}
    assert held <= {tuple(b) for b in blocks}


def test_only_blocks_a_later_scan_opened() -> None:
    """Since scan k: the blocks the scans from k on opened (and their returns), none else;
    nothing when no scan came."""
    rng = np.random.default_rng(4)
    mapper = Mapper(0.25)
    for k in range(4):
        mapper.integrate(*_scan(rng, k), 10.0 + k)
    _, _, since = mapper.changed_voxels(-1, 0.1)
    empty, no_blocks, again = mapper.changed_voxels(since, 0.1)
    assert len(empty) == len(no_blocks) == 0 and again == since
    before = mapper.voxels(min_doo=0.1)
    mapper.integrate(np.array([[5.0, 0.5, 1.0], [5.0, 0.6, 1.2]]), np.array([4.0, 0.5, 1.0]), 20.0)
    changed, blocks, _ = mapper.changed_voxels(since, 0.1)
    after = mapper.voxels(min_doo=0.1)
    touched = {tuple(b) for b in blocks}
    assert 0 < len(touched) < len(np.unique(after.ijk >> 3, axis=0))
    in_changed = np.array([tuple(b) in touched for b in after.ijk >> 3])
    np.testing.assert_array_equal(*_sorted_pair(after.ijk[in_changed], changed.ijk))
    # every voxel outside the changed blocks is as it was
    keep_before = np.array([tuple(b) not in touched for b in before.ijk >> 3])
    np.testing.assert_array_equal(*_sorted_pair(before.ijk[keep_before], after.ijk[~in_changed]))


def _sorted_pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return a[np.lexsort(a.T)], b[np.lexsort(b.T)]


def test_epoch_moves_when_voxels_change_other_than_by_scans() -> None:
    rng = np.random.default_rng(5)
    mapper = Mapper(0.25, max_voxels=60_000)
    epochs = [mapper.epoch]
    for k in range(3):
        mapper.integrate(*_scan(rng, k), 10.0 + k)
    assert mapper.epoch == epochs[0]
    assert mapper.clear_box([-1.0, -1.0, -1.0], [1.0, 1.0, 2.0]) > 0
    epochs.append(mapper.epoch)
    far = np.array([200.0, 0.0, 1.0])  # the memory bound evicts the first scans' blocks
    for k in range(3):
        mapper.integrate(far + rng.normal(0.0, 3.0, (2500, 3)), far, 20.0 + k)
    epochs.append(mapper.epoch)
    mapper.reset()
    epochs.append(mapper.epoch)
    assert epochs == sorted(set(epochs)), epochs
    with pytest.raises(ValueError):
        mapper.changed_voxels(-1, -0.1)
    assert math.isfinite(mapper.epoch)
