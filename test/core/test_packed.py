"""Packed blocks (``core.packed``): the store's voxels block by block, exactly."""

from __future__ import annotations

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import Mapper
from mfp_mapper.core.packed import PackedBlocks, pack_chunks, packed_problem, voxel_starts


def _sorted(m: Mapper) -> tuple[np.ndarray, ...]:
    v = m.stored_voxels()
    order = np.lexsort(v.ijk.T)
    return v.ijk[order], v.s[order], v.n[order], v.t_last[order]


@pytest.mark.parametrize("threads", [1, 2])
def test_blocks_round_trip_every_voxel_bit_for_bit(threads: int) -> None:
    m = Mapper(0.1, decay_time=20.0, max_range=30.0, threads=threads)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=3, azimuths=150)):
        m.integrate(points, origin, 10.0 + 7.5 * k)  # blocks of several times
    packed = m.stored_blocks()
    assert packed_problem(packed) is None
    assert packed.num_voxels == m.num_voxels and packed.s.dtype == np.float32
    assert 0 < len(packed.n) < m.num_voxels and np.all(packed.n > 0)
    again = Mapper.from_blocks(packed, resolution=0.1, decay_time=20.0)
    assert again.num_voxels == m.num_voxels and again.last_stamp == 25.0
    for a, b in zip(_sorted(m), _sorted(again), strict=True):
        assert np.array_equal(a, b)
    # the masks count the values; each voxel with a return is observed
    assert np.array_equal(np.diff(voxel_starts(packed.observed)),
                          np.bitwise_count(packed.observed).sum(1))  # fmt: skip
    assert not np.any(packed.hit & ~packed.observed[packed.hit_block])


def test_float64_statistics_pack_to_the_same_blocks() -> None:
    """A store exporting float64 statistics packs to the same file when they are float32
    values, and keeps float64 where they are not."""
    m = Mapper(0.2, max_range=20.0)
    points, origin = anchors_scene(n_scans=1, azimuths=100)[0]
    m.integrate(points, origin, 1.0)
    chunks = list(m._store.block_chunks())
    as_64 = pack_chunks([(a, t, sn.astype(np.float64)) for a, t, sn in chunks])
    packed = m.stored_blocks()
    for key in ("block_ijk", "block_t", "observed", "s", "hit_block", "hit", "n"):
        assert np.array_equal(getattr(as_64, key), getattr(packed, key)), key
    assert as_64.s.dtype == np.float32
    finer = [(a, t, sn.astype(np.float64) * (1 + 1e-12)) for a, t, sn in chunks]
    assert pack_chunks(finer).s.dtype == np.float64
    assert pack_chunks([]).num_voxels == 0


def test_bad_blocks_are_named() -> None:
    m = Mapper(0.2, max_range=20.0)
    points, origin = anchors_scene(n_scans=1, azimuths=50)[0]
    m.integrate(points, origin, 1.0)
    p = m.stored_blocks()

    def changed(**kw: object) -> PackedBlocks:
        return PackedBlocks(**{**p.__dict__, **kw})  # type: ignore[arg-type]

    swapped = np.r_[1, 0, 2 : len(p.block_ijk)]
    assert "not sorted" in str(packed_problem(changed(block_ijk=p.block_ijk[swapped])))
    assert "s holds" in str(packed_problem(changed(s=p.s[:-1])))
    assert "negative" in str(packed_problem(changed(s=-p.s)))
    hit = p.hit.copy()
    hit[0] |= ~p.observed[p.hit_block[0]]
    assert "not marked observed" in str(packed_problem(changed(hit=hit)))
    with pytest.raises(ValueError, match="NaN"):
        Mapper.from_blocks(changed(block_t=p.block_t * np.nan), resolution=0.2)
