"""Packed blocks (``core.packed``): the store's voxels block by block, exactly."""

from __future__ import annotations

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import Mapper
from mfp_mapper.core import store as store_module
from mfp_mapper.core.layout import bit_count
from mfp_mapper.core.packed import (
    PackedBlocks,
    as_parts,
    as_values,
    pack_chunks,
    packed_problem,
    totals,
    voxel_arrays_of,
    voxel_starts,
)
from mfp_mapper.core.shard import FLUSH_EDGES, HI_USED, N_LIMIT, NCHUNK_USED, NREC_USED, S_USED
from mfp_mapper.core.store import BlockStore, VoxelArrays


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
                          bit_count(packed.observed).sum(1))  # fmt: skip
    assert not np.any(packed.hit & ~packed.observed[packed.hit_block])


def _store_arrays(store: BlockStore) -> list[np.ndarray]:
    """Every array of the store's shards as far as it is used, as raw bits."""
    out: list[np.ndarray] = []
    for sh in store.shards:
        used, pools = sh.used, sh.pools
        out += [
            sh.block_ijk[:used], sh.block_t[:used].view(np.uint64), sh.block_scan[:used],
            sh.block_hit[:used], sh.block_chunks[: 8 * (used + 1)],
            sh.s_pool[: pools[S_USED]].view(np.uint32), sh.chunk_owner[: pools[S_USED]],
            sh.block_nrec[:used], sh.n_recs[: pools[NREC_USED]],
            sh.n_pool[: pools[NCHUNK_USED]].view(np.uint32), sh.block_href[:used],
            sh.hi_pool[: pools[HI_USED]].view(np.uint64), pools[:4].copy(), sh.counters[:1],
        ]  # fmt: skip
    return out


@pytest.mark.parametrize("shards", [1, 2, 4])
def test_compiled_unpack_is_the_voxel_list_path_bit_for_bit(shards: int) -> None:
    """``BlockStore.assign_blocks`` (compiled, block by block) sets the same store as
    ``assign`` of the voxel lists: chunks, float64 parts (values at the float32 limits, in
    float64 in the file), -0 marks of voxels whose s is 0, in the same order."""
    m = Mapper(0.1, decay_time=20.0, max_range=30.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=120)):
        m.integrate(points, origin, 10.0 + 7.5 * k)
    p = as_values(m.stored_blocks())  # values, no float64 parts: ``assign``'s semantics
    assert not p.parts and p.s.dtype == np.float32
    s, n = p.s.astype(np.float64), p.n.astype(np.float64)
    s[::97] *= 1e4 * (1 + 1e-12)  # beyond the limit below, not float32 values
    s[5::89] = 0.0  # observed through n alone where it has a return, else dropped
    n[::7] += 0.25 + 1e-13
    n[3::41] = N_LIMIT * 3  # beyond float32's count limit
    varied = PackedBlocks(p.block_ijk, p.block_t, p.observed, s, p.hit_block, p.hit, n)
    assert packed_problem(varied) is None
    for packed in (p, varied):
        direct, listed = BlockStore(shards, flush_s=2.0), BlockStore(shards, flush_s=2.0)
        direct.assign_blocks(packed)
        ijk, vs, vn, vt = voxel_arrays_of(packed)
        listed.assign(VoxelArrays(ijk.astype(np.int32), vs, vn, vt), np.inf)
        assert direct.num_voxels == listed.num_voxels > 0
        if packed is varied:
            assert sum(int(sh.pools[HI_USED]) for sh in direct.shards) > 0
        for a, b in zip(_store_arrays(direct), _store_arrays(listed), strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b)
        again = as_values(direct.export_blocks())
        if packed is p:  # float32 values: exactly the file's blocks
            for key in ("block_ijk", "block_t", "observed", "s", "hit_block", "hit", "n"):
                assert np.array_equal(getattr(again, key), getattr(packed, key)), key
    assert BlockStore(1).assign_blocks(pack_chunks([])) is None


@pytest.mark.parametrize(("shards", "threaded"), [(1, False), (4, False), (1, True), (4, True)])
def test_parts_open_the_store_the_values_open(
    shards: int, threaded: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Blocks set from parts (``_open_parts``: no table search, chunks numbered from the
    masks, ``s`` written beside or after) and from values (``_set_blocks``: a probe and
    ``open_block`` a block) give the same store: every used array, the hash table too."""
    if threaded:
        monkeypatch.setattr(store_module, "_THREADED_WRITE_VOXELS", 0)
        monkeypatch.setattr(store_module.os, "cpu_count", lambda: 2)
    m = Mapper(0.1, decay_time=20.0, max_range=30.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=120)):
        m.integrate(points, origin, 10.0 + 7.5 * k)
    values = as_values(m.stored_blocks())
    assert values.s.dtype == np.float32 and not values.parts
    by_values, by_parts = BlockStore(shards), BlockStore(shards)
    by_values.assign_blocks(values)
    by_parts.assign_blocks(as_parts(values))
    assert by_parts.num_voxels == by_values.num_voxels == values.num_voxels
    for a, b in zip(_store_arrays(by_parts), _store_arrays(by_values), strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    for a_sh, b_sh in zip(by_parts.shards, by_values.shards, strict=True):
        assert np.array_equal(a_sh.table_keys, b_sh.table_keys)
        assert np.array_equal(a_sh.table_blocks, b_sh.table_blocks)
        assert np.array_equal(a_sh.counters, b_sh.counters)
        for key in ("block_scale", "block_flush"):
            assert np.array_equal(getattr(a_sh, key)[: a_sh.used], getattr(b_sh, key)[: b_sh.used])


def _parts_by_block(store: BlockStore) -> dict[tuple[int, int, int], tuple[bytes, ...]]:
    """Every block's time, float32 parts (raw bits: -0 marks too) and float64 part."""
    out = {}
    for ijk, t, s, n, hi_row, hi in store.block_chunks():
        for k in range(ijk.shape[0]):
            f = hi[hi_row[k]].tobytes() if hi_row[k] >= 0 else b""
            out[tuple(ijk[k].tolist())] = (t[k].tobytes(), s[k].tobytes(), n[k].tobytes(), f)
    return out


@pytest.mark.parametrize(("shards", "threaded"), [(1, False), (2, False), (1, True), (2, True)])
def test_parts_round_trip_with_the_float64_blocks_bit_for_bit(
    shards: int, threaded: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Blocks flushed into float64 (``shard.flush``) pack as float32 parts plus float64
    parts of those blocks only, and are set back as the store held them: every block's
    parts, bit for bit (``s`` written in a thread beside the opening, as for maps of a
    million voxels, or after it); values as in ``totals``; ``as_parts`` of the values is
    exact."""
    if threaded:
        monkeypatch.setattr(store_module, "_THREADED_WRITE_VOXELS", 0)
        monkeypatch.setattr(store_module.os, "cpu_count", lambda: 2)
    m = Mapper(0.1, max_range=30.0, threads=shards)
    scans = anchors_scene(n_scans=2, azimuths=120)
    for k, (points, origin) in enumerate(scans):
        m.integrate(points, origin, 10.0 + k)
    store = m._store
    for sh in store.shards:  # flush a third of the blocks, as a long run does
        sh.block_flush[: sh.used : 3] = True
        sh.pools[4] = 1  # FLUSH_PENDING
        sh.flush()
    p = m.stored_blocks()
    assert packed_problem(p) is None and p.parts and p.s.dtype == np.float32
    assert 0 < p.hi_block.shape[0] < p.block_ijk.shape[0]
    assert p.hi_s.shape[0] < p.s.shape[0] // 2  # the float64 part of the flushed blocks only
    back = BlockStore(shards, flush_s=FLUSH_EDGES * 0.1)
    back.assign_blocks(p)
    assert back.num_voxels == p.num_voxels
    packed_blocks = set(map(tuple, p.block_ijk.tolist()))
    expected = {k: v for k, v in _parts_by_block(store).items() if k in packed_blocks}
    assert _parts_by_block(back) == expected
    ijk, s, n, t = voxel_arrays_of(p)
    v = m.stored_voxels()
    order, mine = np.lexsort(v.ijk.T), np.lexsort(ijk.T)
    assert np.array_equal(v.s[order], s[mine]) and np.array_equal(v.n[order], n[mine])
    s_tot, n_tot = totals(p)
    again = as_parts(as_values(p))
    assert [a.tobytes() for a in totals(again)] == [s_tot.tobytes(), n_tot.tobytes()]
    assert pack_chunks([]).num_voxels == 0


@pytest.mark.parametrize("shards", [1, 2])
def test_export_in_two_threads_packs_as_one(shards: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """``export_blocks`` packing half the blocks in a thread of its own (large maps) gives
    the packing of ``block_chunks`` in one thread, bit for bit, flushed blocks included."""
    m = Mapper(0.1, max_range=30.0, threads=shards)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=120)):
        m.integrate(points, origin, 10.0 + k)
    store = m._store
    for sh in store.shards:  # flush some blocks: their float64 parts go with them
        sh.block_flush[: sh.used : 5] = True
        sh.pools[4] = 1  # FLUSH_PENDING
        sh.flush()
    one = pack_chunks(store.block_chunks(), store.num_voxels)
    monkeypatch.setattr(store_module, "_THREADED_PACK_BLOCKS", 0)
    monkeypatch.setattr(store_module.os, "cpu_count", lambda: 2)
    two = store.export_blocks()
    assert packed_problem(two) is None and two.hi_block.shape[0] > 0
    for key, value in one.__dict__.items():
        got = getattr(two, key)
        assert isinstance(got, bool) or got.dtype == value.dtype, key
        assert np.array_equal(np.asarray(got).view(np.uint8), np.asarray(value).view(np.uint8)), key


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
