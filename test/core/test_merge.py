"""Exact merge of maps: partial maps of disjoint scans add up to the sequential map."""

from __future__ import annotations

import math

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import Mapper
from mfp_mapper.core.merge import MergeError, merge_map_arrays, merge_voxels
from mfp_mapper.core.store import VoxelArrays
from mfp_mapper.mapio.mapfile import map_arrays, mapper_from_arrays, read_map_arrays

RES = 0.2


@pytest.fixture(scope="module")
def scans() -> list[tuple[np.ndarray, np.ndarray]]:
    return anchors_scene(n_scans=9, azimuths=180)


def _map(scans: list[tuple[np.ndarray, np.ndarray]], stamps: list[float], decay: float) -> Mapper:
    mapper = Mapper(RES, decay_time=decay, max_range=30.0)
    for (points, origin), stamp in sorted(zip(scans, stamps, strict=True), key=lambda x: x[1]):
        mapper.integrate(points, origin, stamp)
    return mapper


def _sorted(arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
    order = np.lexsort(arrays["ijk"].T)
    return tuple(np.asarray(arrays[k])[order] for k in ("ijk", "s", "n", "t_last"))


def _assert_same_map(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    ijk_a, s_a, n_a, t_a = _sorted(a)
    ijk_b, s_b, n_b, t_b = _sorted(b)
    np.testing.assert_array_equal(ijk_a, ijk_b)
    # the store sums in float32: partial sums round differently from one running sum
    np.testing.assert_allclose(s_a, s_b, rtol=2e-5, atol=1e-5)
    np.testing.assert_allclose(n_a, n_b, rtol=2e-5, atol=1e-5)
    np.testing.assert_array_equal(t_a, t_b)


@pytest.mark.parametrize("decay", [math.inf, 3.0])
def test_merge_of_partials_equals_the_sequential_map(scans, decay: float) -> None:  # type: ignore[no-untyped-def]
    stamps = [10.0 + 0.5 * k for k in range(len(scans))]
    sequential = map_arrays(_map(scans, stamps, decay))
    # interleaved subsets: each partial has gaps the others fill (late data for the merge)
    parts = [map_arrays(_map(scans[i::3], stamps[i::3], decay)) for i in range(3)]
    merged = merge_map_arrays(parts)
    _assert_same_map(merged, sequential)
    # merging in another order, or in two steps, gives the same map
    _assert_same_map(merge_map_arrays([merge_map_arrays(parts[1:]), parts[0]]), sequential)
    if math.isfinite(decay):  # decay really acts: the plain sum differs
        plain = merge_map_arrays([{**p, "decay_time": np.float64(math.inf)} for p in parts])
        assert not np.allclose(_sorted(plain)[1], _sorted(sequential)[1], rtol=1e-3)


def test_decay_brings_blocks_to_the_common_time_as_model_md_says() -> None:
    # docs/model.md's worked values: n=10, s=5 at t'=0 and a crossing of 0.1 m at t=5 (T = 10 s)
    a = VoxelArrays(np.array([[0, 0, 0]], np.int32), np.array([5.0]), np.array([10.0]), np.zeros(1))
    b = VoxelArrays(np.array([[0, 0, 0]], np.int32), np.array([0.1]), np.zeros(1), np.full(1, 5.0))
    for parts in ([a, b], [b, a]):
        m = merge_voxels(parts, 10.0)
        assert m.n[0] == pytest.approx(6.065307, abs=1e-6)
        assert m.s[0] == pytest.approx(3.132653, abs=1e-6)
        assert m.t_last[0] == 5.0
    # late data: n=10, s=5 at t'=5; a crossing of 0.1 m made at t=0
    a.t_last[:] = 5.0
    b.t_last[:] = 0.0
    m = merge_voxels([a, b], 10.0)
    assert (m.n[0], m.t_last[0]) == (10.0, 5.0)
    assert m.s[0] == pytest.approx(5.060653, abs=1e-6)


def test_voxels_of_one_block_share_the_latest_time() -> None:
    # voxel (0,0,0) seen at t=0 in one map; (1,0,0), same block, at t=4 in another
    a = VoxelArrays(np.array([[0, 0, 0]], np.int32), np.array([2.0]), np.array([1.0]), np.zeros(1))
    b = VoxelArrays(np.array([[1, 0, 0]], np.int32), np.ones(1), np.zeros(1), np.full(1, 4.0))
    far = VoxelArrays(np.array([[9, 0, 0]], np.int32), np.ones(1), np.zeros(1), np.full(1, 1.0))
    m = merge_voxels([a, b, far], 2.0)
    np.testing.assert_array_equal(m.ijk, [[0, 0, 0], [1, 0, 0], [9, 0, 0]])
    np.testing.assert_allclose(m.t_last, [4.0, 4.0, 1.0])
    np.testing.assert_allclose(m.s, [2.0 * math.exp(-2.0), 1.0, 1.0])


def test_wide_maps_and_negative_indices_merge_too() -> None:
    big = 2**22  # 2^19 blocks a side on each axis: more than one int64 key can pack
    ijk = np.array([[-big, 0, big], [big, -big, 0], [-big, 0, big], [0, 0, -1]], np.int32)
    parts = [
        VoxelArrays(ijk[:2], np.array([1.0, 2.0]), np.array([0.0, 1.0]), np.zeros(2)),
        VoxelArrays(ijk[2:], np.array([4.0, 8.0]), np.array([1.0, 0.0]), np.zeros(2)),
    ]
    m = merge_voxels(parts, math.inf)
    got = {tuple(v): (s, n) for v, s, n in zip(m.ijk.tolist(), m.s, m.n, strict=True)}
    assert got == {(-big, 0, big): (5.0, 1.0), (big, -big, 0): (2.0, 1.0), (0, 0, -1): (8.0, 0.0)}


def test_maps_of_other_settings_are_refused(scans) -> None:  # type: ignore[no-untyped-def]
    base = map_arrays(_map(scans[:2], [0.0, 1.0], math.inf))
    for key, value in (
        ("resolution", np.float64(0.1)),
        ("frame_id", np.str_("odom")),
        ("decay_time", np.float64(5.0)),
        ("origin", np.array([1.0, 0.0, 0.0])),
    ):
        with pytest.raises(MergeError, match=f"different {key.replace('_', ' ')}.*b.npz"):
            merge_map_arrays([base, {**base, key: value}], ["a.npz", "b.npz"])
    with pytest.raises(MergeError, match="no map"):
        merge_map_arrays([])


def test_merged_arrays_are_a_map_file(scans, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from mfp_mapper.mapio.mapfile import write_map_arrays

    parts = [map_arrays(_map(scans[i::2], [float(k) for k in range(i, 9, 2)], 5.0)) for i in (0, 1)]
    path = tmp_path / "merged.npz"
    write_map_arrays(path, merge_map_arrays(parts))
    back = read_map_arrays(path)
    assert back["s"].dtype == np.float64 and str(back["frame_id"]) == "map"
    mapper = mapper_from_arrays(back)
    assert mapper.num_voxels == len(back["s"]) and mapper.decay_time == 5.0
