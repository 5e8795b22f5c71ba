"""The reflectivity field (Appendix B): histograms of return intensity per voxel, checked
against brute force, under decay and late scans, through eviction, files, tiles and merges."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mfp_mapper.core import reflectivity
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.merge import MergeError, merge_map_arrays
from mfp_mapper.core.reflectivity import (
    ReflectivityArrays,
    ReflectivityBins,
    ReflectivityTable,
    ScanReflectivity,
    block_order,
    mean_value,
    merge_reflectivity,
    most_likely_bin,
    smoothed,
)
from mfp_mapper.mapio.loading import load_map, save_map
from mfp_mapper.mapio.mapfile import map_arrays, mapper_from_arrays
from mfp_mapper.sensing.reflectivity import bins_for

BINS = ReflectivityBins("intensity", (2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0))


def _scan(rng: np.random.Generator, count: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Points on a few surfaces 2-6 m from the origin, and intensities 0-255."""
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = directions * rng.choice([2.0, 3.5, 6.0], size=(count, 1))
    return points, rng.integers(0, 256, count).astype(np.float32)


def _brute(
    returns: list[tuple[np.ndarray, np.ndarray, float]], stamp: float, decay: float
) -> dict[tuple[int, int, int], np.ndarray]:
    """Every return's weight exp(-(stamp - t) / T) summed per voxel and bin."""
    out: dict[tuple[int, int, int], np.ndarray] = {}
    for ijk, bins, t in returns:
        w = 1.0 if math.isinf(decay) else math.exp(-(stamp - t) / decay)
        for (x, y, z), b in zip(ijk.tolist(), bins.tolist(), strict=True):
            if b >= 0:
                out.setdefault((x, y, z), np.zeros(BINS.count))[b] += w
    return out


def test_bins_are_log_spaced_per_field() -> None:
    bins = bins_for("reflectivity", 8)
    assert bins is not None and bins.edges == (2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0)
    assert bins_for("intensity", 4) == ReflectivityBins("intensity", (4.0, 16.0, 64.0))
    assert bins_for("intensity", 0) is None and bins_for("ambient", 8) is None
    values = [0.0, 1.9, 2.0, 7.99, 100.0, 128.0, 255.0, 65535.0, np.nan]
    assert bins.bin_of(values).tolist() == [0, 0, 1, 2, 6, 7, 7, 7, -1]
    with pytest.raises(ValueError, match="increasing"):
        ReflectivityBins("x", (3.0, 2.0))


@pytest.mark.parametrize("decay", [math.inf, 2.0])
def test_table_is_the_decayed_sum_of_its_returns_in_any_order(decay: float) -> None:
    rng = np.random.default_rng(3)
    returns = []
    for stamp in rng.permutation(np.arange(8.0)):  # late scans included
        ijk = rng.integers(-3, 3, size=(200, 3))
        returns.append((ijk, rng.integers(-1, BINS.count, 200), float(stamp)))
    table = ReflectivityTable(BINS, capacity=4)  # grows several times
    for ijk, bins, stamp in returns:
        table.add(ijk, bins, stamp, decay)
    expected = _brute(returns, 9.0, decay)
    keys = np.array(sorted(expected))
    counts, _ = table.histograms(keys, 9.0, decay)
    np.testing.assert_allclose(counts, [expected[tuple(k)] for k in keys.tolist()], rtol=1e-5)
    assert len(table) == len(expected)
    absent, t = table.histograms(np.array([[50, 50, 50]]), 9.0, decay)
    assert absent.sum() == 0.0 and t[0] == -np.inf


def test_decay_over_many_decay_times_and_far_apart_voxels_keep_the_sums() -> None:
    """Stamps up to 96 decay times apart, late ones included (counts decay to float32's
    subnormal range); one add with voxels farther apart than a packed sort key holds takes
    the other sort; voxels beyond the map's range are skipped."""
    rng = np.random.default_rng(4)
    decay = 1.0
    far = np.array([[600_000, -3, 1], [-600_000, 2, 0], [5, 5, 5]])
    returns = []
    for stamp in (0.0, 40.0, 41.0, 95.0, 90.0, 96.0):
        ijk = np.concatenate([rng.integers(-20, 20, size=(300, 3)), far])
        returns.append((ijk, rng.integers(0, BINS.count, ijk.shape[0]), stamp))
    table = ReflectivityTable(BINS)
    for ijk, bins, stamp in returns:
        table.add(ijk, bins, stamp, decay)
    table.add(np.array([[1 << 24, 0, 0]]), np.array([1]), 96.0, decay)  # beyond the range
    expected = _brute(returns, 97.0, decay)
    assert len(table) == len(expected)
    keys = np.array(sorted(expected))
    counts, t = table.histograms(keys, 97.0, decay)
    # counts decayed below float32's normal range (1e-38, ~87 decay times) keep less
    # precision, as the voxels' n does
    want = [expected[tuple(k)] for k in keys.tolist()]
    np.testing.assert_allclose(counts, want, rtol=1e-5, atol=1e-36)
    assert np.all(t == 97.0)
    np.testing.assert_array_equal(table.lookup(np.array([[1 << 24, 0, 0]])), [-1])
    with pytest.raises(ValueError, match="decay time"):
        table.add(keys[:1], np.array([0]), 98.0, 2.0)


def _float32_reference(
    scans: list[tuple[np.ndarray, np.ndarray, float]], decay: float
) -> tuple[dict[tuple[int, int, int], np.ndarray], float]:
    """The table's arithmetic, one voxel at a time: float32 counts referring to one time,
    every count scaled by float32(exp(-dt / T)) and the time moved to a later stamp only
    when that stamp is more than ``REFERENCE_DECAY_TIMES`` decay times later, a return
    adding its weight exp((stamp - time) / T) (float64) rounded to float32; then brought
    to the latest stamp (float32), as reads and exports do: the counts and that stamp."""
    rows: dict[tuple[int, int, int], np.ndarray] = {}
    time = latest = -math.inf
    for ijk, bins, stamp in scans:
        if not rows:
            time = latest = stamp
        latest = max(latest, stamp)
        if math.isfinite(decay) and stamp - time > reflectivity.REFERENCE_DECAY_TIMES * decay:
            factor = np.float32(math.exp(-(stamp - time) / decay))
            for counts in rows.values():
                counts *= factor
            time = stamp
        w = 1.0 if math.isinf(decay) else 1.0 / math.exp(-(stamp - time) / decay)
        for voxel, b in zip(map(tuple, ijk.tolist()), bins.tolist(), strict=True):
            if b >= 0:
                counts = rows.setdefault(voxel, np.zeros(BINS.count, dtype=np.float32))
                counts[b] = np.float32(np.float64(counts[b]) + w)
    if math.isfinite(decay) and time != latest:
        factor = np.exp(np.array([time - latest]) / decay)[0]  # (numpy's exp, as the table)
        rows = {v: (c.astype(np.float64) * factor).astype(np.float32) for v, c in rows.items()}
    return rows, latest


@pytest.mark.parametrize("decay", [math.inf, 4.0])
@pytest.mark.parametrize("fresh_rows", [1, 10**9], ids=["merged_often", "never_merged"])
@pytest.mark.parametrize("reference", [22.0, 0.3], ids=["time_kept", "time_moved_often"])
def test_a_scan_copies_its_new_rows_not_the_table(
    decay: float, fresh_rows: int, reference: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """New voxels go into a small table of fresh rows, merged into the settled rows when
    they outgrow ``FRESH_ROWS_MIN``'s bound (every scan copied the whole table: 31.7
    ms a scan at 1.2 M rows). Whether the fresh rows are merged after every scan or never, reads
    between the scans (which do not merge them) and the export at the end hold the same
    float32 counts, bit for bit, as the table's arithmetic done one voxel at a time; late
    scans and repeats included. Nor does a later scan scale every count (with decay it
    did: 18.7-20.8 ms a scan at 4.4 M rows, now 11.1-16.7): the counts keep referring to
    one time until a scan comes ``REFERENCE_DECAY_TIMES`` decay times later (here kept, or
    moved every few scans)."""
    monkeypatch.setattr(reflectivity, "FRESH_ROWS_MIN", fresh_rows)
    monkeypatch.setattr(reflectivity, "REFERENCE_DECAY_TIMES", reference)
    rng = np.random.default_rng(11)
    scans = []
    for k, stamp in enumerate([0.0, 1.0, 2.0, 1.5, 3.0, 2.5, 4.0, 5.0, 6.0, 5.5]):
        grown = 4 + 3 * k  # each scan reaches a little further: new voxels every scan
        ijk = rng.integers(-grown, grown, size=(300, 3))
        scans.append((ijk, rng.integers(-1, BINS.count, 300), stamp))
    table = ReflectivityTable(BINS)
    for k, (ijk, bins, stamp) in enumerate(scans):
        table.add(ijk, bins, stamp, decay)
        expected, time = _float32_reference(scans[: k + 1], decay)
        voxels = np.array(sorted(expected))
        counts, _ = table.histograms(voxels, time, decay)  # at the latest stamp: as exported
        want = np.array([expected[tuple(v)] for v in voxels.tolist()], dtype=np.float64)
        np.testing.assert_array_equal(counts, want)
        assert len(table) == len(expected)
    held = table.export()
    expected, time = _float32_reference(scans, decay)
    order = np.lexsort(held.ijk.T[::-1])
    voxels = held.ijk[order].astype(np.int64)
    assert sorted(map(tuple, voxels.tolist())) == sorted(expected)
    want = np.array([expected[tuple(v)] for v in voxels.tolist()], dtype=np.float64)
    np.testing.assert_array_equal(held.counts[order], want)
    assert np.all(held.t_last == time)
    np.testing.assert_array_equal(table.lookup(held.ijk), np.arange(len(table)))


@pytest.mark.parametrize("decay", [math.inf, 3.0])
def test_files_of_rows_with_their_own_times_load_and_round_trip_exactly(decay: float) -> None:
    """A map file whose rows refer to different times (as the table with a time per row
    wrote them) reads the same histograms; a table exports its rows at one time, and
    loading that export and exporting again gives the same arrays."""
    rng = np.random.default_rng(9)
    ijk = rng.permutation(np.unique(rng.integers(-40, 40, size=(500, 3)), axis=0))
    counts = rng.integers(0, 5, size=(ijk.shape[0], BINS.count)).astype(np.float64)
    t_last = rng.uniform(0.0, 10.0, ijk.shape[0])
    old = ReflectivityArrays(BINS, ijk.astype(np.int32), counts, t_last)
    table = ReflectivityTable(BINS)
    table.assign(old, decay)
    got, _ = table.histograms(ijk, 12.0, decay)
    f = 1.0 if math.isinf(decay) else np.exp(-(12.0 - t_last) / decay)
    np.testing.assert_allclose(got, counts * np.reshape(f, (-1, 1)), rtol=1e-6)
    first = table.export()
    assert np.all(first.t_last == t_last.max())
    again = ReflectivityTable(BINS)
    again.assign(first, decay)
    second = again.export()
    for a, b in ((first.ijk, second.ijk), (first.counts, second.counts)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(first.t_last, second.t_last)


def test_histogram_totals_equal_n_and_follow_eviction_clear_and_reset() -> None:
    rng = np.random.default_rng(5)
    mapper = Mapper(0.25, decay_time=5.0)
    for stamp in (1.0, 3.0, 2.0):
        points, values = _scan(rng)
        mapper.integrate(points, np.zeros(3), stamp, reflectivity=ScanReflectivity(values, BINS))
    table = mapper.stored_reflectivity()
    assert table is not None and len(table)
    centers = (table.ijk + 0.5) * mapper.resolution
    _, counts = mapper.reflectivity(centers, 4.0) or (None, None)
    stats = mapper.query(centers, 4.0)
    np.testing.assert_allclose(counts.sum(axis=1), stats.n, rtol=1e-5)
    assert np.count_nonzero(mapper.stored_voxels().n > 0) == len(table)
    # clear_box drops the histograms of the cleared voxels
    mapper.clear_box((0.0, -10.0, -10.0), (10.0, 10.0, 10.0))
    left = mapper.stored_reflectivity()
    assert left is not None and 0 < len(left) < len(table)
    assert np.all((left.ijk[:, 0] + 0.5) * mapper.resolution < 0.0)
    assert np.count_nonzero(mapper.stored_voxels().n > 0) == len(left)
    mapper.reset()
    empty = mapper.stored_reflectivity()
    assert empty is not None and len(empty) == 0 and empty.bins == BINS


def test_eviction_drops_the_histograms_of_evicted_blocks() -> None:
    rng = np.random.default_rng(6)
    mapper = Mapper(0.1, keep_radius=2.0)
    points, values = _scan(rng, 2000)
    mapper.integrate(points, np.zeros(3), 0.0, reflectivity=ScanReflectivity(values, BINS))
    table = mapper.stored_reflectivity()
    assert table is not None and len(table)
    assert np.count_nonzero(mapper.stored_voxels().n > 0) == len(table)
    assert len(table) < np.unique(np.floor(points / 0.1), axis=0).shape[0]  # far ones evicted


def test_staged_scans_give_the_integrated_histograms() -> None:
    rng = np.random.default_rng(7)
    scans = [(*_scan(rng), float(t)) for t in (0.0, 2.0, 1.0)]
    direct, staged = Mapper(0.2, decay_time=3.0), Mapper(0.2, decay_time=3.0)
    for points, values, stamp in scans:
        direct.integrate(points, np.zeros(3), stamp, reflectivity=ScanReflectivity(values, BINS))
        staged.commit(
            staged.stage(points, np.zeros(3), stamp, None, ScanReflectivity(values, BINS))
        )
    a, b = direct.stored_reflectivity(), staged.stored_reflectivity()
    assert a is not None and b is not None
    np.testing.assert_array_equal(a.ijk, b.ijk)
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_array_equal(a.t_last, b.t_last)


def test_other_bins_are_refused_with_the_map_unchanged() -> None:
    rng = np.random.default_rng(8)
    mapper = Mapper(0.2)
    points, values = _scan(rng)
    mapper.integrate(points, np.zeros(3), 0.0, reflectivity=ScanReflectivity(values, BINS))
    other = bins_for("reflectivity", 8)
    assert other is not None and not mapper.takes_reflectivity(other)
    version = mapper.version
    with pytest.raises(ValueError, match="binned as"):
        mapper.integrate(points, np.zeros(3), 1.0, reflectivity=ScanReflectivity(values, other))
    with pytest.raises(ValueError, match="shape"):
        mapper.integrate(points, np.zeros(3), 1.0, reflectivity=ScanReflectivity(values[:3], BINS))
    assert mapper.version == version
    assert Mapper(0.2, reflectivity_bins=0).takes_reflectivity(BINS) is False


def _map_of(scans: list[tuple[np.ndarray, np.ndarray, float]], decay: float) -> Mapper:
    mapper = Mapper(0.2, decay_time=decay, origin=(0.0, 0.0, 0.0))
    for points, values, stamp in scans:
        mapper.integrate(points, np.zeros(3), stamp, reflectivity=ScanReflectivity(values, BINS))
    return mapper


def _table_dict(arrays: dict[str, np.ndarray]) -> dict[tuple[int, ...], tuple[np.ndarray, float]]:
    rows = zip(
        arrays["reflectivity_ijk"].tolist(),
        arrays["reflectivity_counts"],
        arrays["reflectivity_t_last"].tolist(),
        strict=True,
    )
    return {tuple(k): (c, t) for k, c, t in rows}


@pytest.mark.parametrize("decay", [math.inf, 4.0])
def test_merge_of_two_maps_tables_is_the_table_of_one_map_of_both(decay: float) -> None:
    rng = np.random.default_rng(11)
    scans = [(*_scan(rng), float(t)) for t in (0.0, 3.0, 1.0, 5.0, 2.0)]
    both = map_arrays(_map_of(scans, decay))
    merged = merge_map_arrays(
        [map_arrays(_map_of(scans[::2], decay)), map_arrays(_map_of(scans[1::2], decay))]
    )
    want, got = _table_dict(both), _table_dict(merged)
    assert want.keys() == got.keys()
    # rows are written by block (a reader finds a block's rows together), merged ones too
    for arrays in (both, merged):
        assert block_order(arrays["reflectivity_ijk"]) == slice(None)
    assert block_order(np.array([[8, 0, 0], [0, 0, 1], [0, 0, 0]])).tolist() == [2, 1, 0]  # type: ignore[union-attr]
    for key, (counts, t) in want.items():
        # one map's row refers to its last return's time; bring both to a common one
        other_counts, other_t = got[key]
        at = max(t, other_t)
        f = 1.0 if math.isinf(decay) else math.exp(-(at - t) / decay)
        g = 1.0 if math.isinf(decay) else math.exp(-(at - other_t) / decay)
        np.testing.assert_allclose(counts * f, other_counts * g, rtol=1e-5)
    # and the merged map reads the same histograms at any time
    centers = (np.array(list(want)) + 0.5) * 0.2
    a = mapper_from_arrays(both).reflectivity(centers, 6.0)
    b = mapper_from_arrays(merged).reflectivity(centers, 6.0)
    assert a is not None and b is not None
    np.testing.assert_allclose(a[1], b[1], rtol=1e-5)


def test_merge_refuses_other_bins() -> None:
    rng = np.random.default_rng(12)
    points, values = _scan(rng)
    a = _map_of([(points, values, 0.0)], math.inf)
    b = Mapper(0.2, origin=(0.0, 0.0, 0.0))
    other = bins_for("reflectivity", 8)
    assert other is not None
    b.integrate(points, np.zeros(3), 0.0, reflectivity=ScanReflectivity(values, other))
    with pytest.raises(MergeError, match="reflectivity bins"):
        merge_map_arrays([map_arrays(a), map_arrays(b)])
    with pytest.raises(ValueError, match="bins differ"):
        merge_reflectivity([a.stored_reflectivity(), b.stored_reflectivity()], math.inf)  # type: ignore[list-item]
    # a map without histograms merges with one that has them: its returns have no intensity
    plain = Mapper(0.2, origin=(0.0, 0.0, 0.0))
    plain.integrate(points, np.zeros(3), 1.0)
    merged = merge_map_arrays([map_arrays(plain), map_arrays(a)])
    np.testing.assert_allclose(
        merged["reflectivity_counts"].sum(),
        a.stored_reflectivity().counts.sum(),  # type: ignore[union-attr]
    )


@pytest.mark.parametrize("suffix", ["map.npz", "tiled"])
def test_files_and_tiles_keep_the_histograms(tmp_path, suffix: str) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(13)
    scans = [(*_scan(rng, 1500), float(t)) for t in (0.0, 1.0)]
    mapper = _map_of(scans, 10.0)
    path = tmp_path / suffix
    if suffix == "tiled":
        save_map(mapper, path, tile_blocks=1)  # many tiles
    else:
        save_map(mapper, path)
    loaded = load_map(path)
    a, b = mapper.stored_reflectivity(), loaded.stored_reflectivity()
    assert a is not None and b is not None and b.bins == BINS
    assert _table_dict(map_arrays(mapper)).keys() == _table_dict(map_arrays(loaded)).keys()
    centers = (a.ijk + 0.5) * 0.2
    np.testing.assert_allclose(
        mapper.reflectivity(centers, 3.0)[1],  # type: ignore[index]
        loaded.reflectivity(centers, 3.0)[1],  # type: ignore[index]
        rtol=1e-6,
    )
    # bounds read only the histograms inside
    part = load_map(path, bounds=((0.0, -10.0, -10.0), (10.0, 10.0, 10.0)))
    kept = part.stored_reflectivity()
    assert kept is not None and 0 < len(kept) < len(a)
    assert np.all((kept.ijk[:, 0] + 0.5) * 0.2 >= 0.0)
    # and the map then keeps its own bins for new scans
    assert loaded.takes_reflectivity(BINS) and not loaded.takes_reflectivity(
        bins_for("reflectivity", 8)  # type: ignore[arg-type]
    )


def test_damaged_histograms_are_refused_with_the_file_named(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from mfp_mapper.mapio.mapfile import MapFileError, write_map_arrays

    rng = np.random.default_rng(14)
    arrays = map_arrays(_map_of([(*_scan(rng), 0.0)], math.inf))
    bad = dict(arrays, reflectivity_counts=-arrays["reflectivity_counts"])
    write_map_arrays(tmp_path / "neg.npz", bad)
    with pytest.raises(MapFileError, match="neg.npz.*reflectivity_counts"):
        load_map(tmp_path / "neg.npz")
    short = dict(arrays, reflectivity_counts=arrays["reflectivity_counts"][:, :3])
    write_map_arrays(tmp_path / "short.npz", short)
    with pytest.raises(MapFileError, match="short.npz.*reflectivity_counts"):
        load_map(tmp_path / "short.npz")
    twice = dict(
        arrays,
        reflectivity_ijk=np.repeat(
            arrays["reflectivity_ijk"][:1], len(arrays["reflectivity_ijk"]), 0
        ),
    )
    write_map_arrays(tmp_path / "twice.npz", twice)
    with pytest.raises(MapFileError, match="twice.npz.*more than once"):
        load_map(tmp_path / "twice.npz")


def test_summaries_of_histograms() -> None:
    counts = np.array([[0.0, 0, 0, 0, 0, 0, 0, 0], [0, 3, 1, 0, 0, 0, 0, 0]])
    assert most_likely_bin(counts).tolist() == [-1, 1]
    mean = mean_value(counts, BINS)
    centers = BINS.centers()
    assert np.isnan(mean[0]) and mean[1] == pytest.approx((3 * centers[1] + centers[2]) / 4)
    assert centers[1] == pytest.approx(math.sqrt(8.0))
    background = np.full(8, 1 / 8)
    p = smoothed(counts, background, 1.0)
    np.testing.assert_allclose(p.sum(axis=1), 1.0)
    np.testing.assert_allclose(p[0], background)
    assert p[1, 1] == pytest.approx((3 + 1 / 8) / 5)
