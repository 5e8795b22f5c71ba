"""Queries from a map file read by block (``MapFileQueries``): the same answers as the map
loaded whole, from only the blocks they need."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import MapFileError, Mapper
from mfp_mapper.core.layout import FLUSH_EDGES, N_LIMIT
from mfp_mapper.core.voxel_stats import VoxelStats
from mfp_mapper.mapio.loading import load_map, save_map
from mfp_mapper.mapio.mapfile import map_arrays, write_map_arrays
from mfp_mapper.mapio.queries import MapFileQueries, segment_block_keys

LEGACY = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def mapper() -> Mapper:
    m = Mapper(0.1, decay_time=30.0, max_range=30.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=200)):
        m.integrate(points, origin, 100.0 + k)
    return m


def _queries(m: Mapper, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    centres = m.voxels().centers
    points = np.concatenate([centres[rng.choice(len(centres), 300)], rng.normal(0, 8, (200, 3))])
    starts = centres[rng.choice(len(centres), 100)] + rng.normal(0, 0.3, (100, 3))
    ends = starts + rng.normal(0, 6.0, (100, 3))
    return points, starts, ends


@pytest.mark.parametrize("tiled", [False, True], ids=["file", "tiled"])
def test_answers_equal_the_whole_map(mapper: Mapper, tiled: bool, tmp_path: Path) -> None:
    path = tmp_path / ("tiled" if tiled else "map.npz")
    save_map(mapper, path, tile_blocks=2)
    points, starts, ends = _queries(mapper)
    from mfp_mapper.cli.common import load_map_arg

    q = load_map_arg(str(path), lazy_tiles=True, queries=True)
    for stamp in (None, 130.0):
        _assert_same_stats(mapper.query(points, stamp), q.query(points, stamp))
    if not tiled:
        a, b = mapper.query_segments(starts, ends), q.query_segments(starts, ends)
        assert np.array_equal(a.clear_probability, b.clear_probability)
        assert np.array_equal(a.unknown_length, b.unknown_length)


ESTIMATES = ("most_likely_doo", "mean_doo", "std", "hit_probability", "mean_free_path")


def _assert_same_stats(a: VoxelStats, b: VoxelStats) -> None:
    """Every field and estimate equal, bit for bit (-0 and +0 apart)."""
    for key in ("ijk", "centers", "s", "n", "t_last", "observed", *ESTIMATES):
        x, y = getattr(a, key), getattr(b, key)
        assert x.dtype == y.dtype, key
        np.testing.assert_array_equal(x, y, err_msg=key, strict=True)
        assert np.array_equal(np.signbit(x), np.signbit(y)), key
    for x, y in zip(a.doo_interval(0.9), b.doo_interval(0.9), strict=True):
        np.testing.assert_array_equal(x, y, strict=True)
    assert (a.resolution, a.prior) == (b.resolution, b.prior)


def _hard_points(m: Mapper, rng: np.random.Generator) -> np.ndarray:
    """Observed voxels, their neighbours (unobserved voxels of stored blocks, block edges),
    random points in and around the map, far and non-finite ones, points beyond the index
    range."""
    centres = m.voxels().centers
    picks = centres[rng.choice(len(centres), 400)]
    edge = m.resolution * 8
    lo, hi = centres.min(axis=0) - edge, centres.max(axis=0) + edge
    origin = np.asarray(m.origin or (0.0, 0.0, 0.0))
    odd = [[np.nan, 0, 0], [np.inf, 1, 1], [0, -np.inf, 0], [1e30, 0, 0], [-1e12, 5, 5]]
    return np.concatenate([
        picks, picks + rng.integers(-2, 3, picks.shape) * m.resolution,
        rng.uniform(lo, hi, (600, 3)), rng.normal(0, 1e3, (50, 3)),
        origin + (np.floor(rng.uniform(lo, hi, (100, 3)) / edge) * edge - origin),
        np.asarray(odd) + origin,
    ])  # fmt: skip


@pytest.mark.parametrize("kind", ["decaying", "merged_float64", "prior_and_origin"])
def test_the_numpy_point_path_equals_the_compiled_one(
    mapper: Mapper, kind: str, tmp_path: Path
) -> None:
    """``MapFileQueries.query`` (numpy, the blocks read) against ``Mapper.query`` of the
    whole map (the compiled store), on random points: every statistic and estimate equal.
    Maps: a decaying one of real integrations (float32 sums), one of float64 sums (merged
    files keep them) and one with a prior and an origin of its own."""
    rng = np.random.default_rng(7)
    path = tmp_path / "map.npz"
    if kind == "merged_float64":  # sums no float32 holds, as a merge of files writes them
        arrays = map_arrays(mapper)
        s, n = arrays["s"], arrays["n"]
        s *= 1.0 + rng.uniform(1e-9, 2e-9, s.shape)
        far = rng.random(s.shape) < 0.02  # at and beyond the store's float32 limits
        s[far] = FLUSH_EDGES * 0.1 * rng.choice([0.999, 1.0, 1.5], int(far.sum()))
        n[rng.random(n.shape) < 0.01] = N_LIMIT * rng.choice([0.5, 1.0, 1.25])
        write_map_arrays(path, arrays)
        with np.load(path) as f:  # the blocks holding them kept in float64 parts
            assert f["hi_s"].size > 0 and f["hi_n"].size > 0
    else:
        m = mapper
        if kind == "prior_and_origin":
            v = mapper.stored_voxels()
            m = Mapper.from_arrays(
                v, resolution=0.1, decay_time=30.0, prior_shape=0.3, prior_rate=0.15,
                origin=(0.37, -12.5, 1.0e4),
            )  # fmt: skip
        save_map(m, path)
    whole = load_map(path)
    q = MapFileQueries(path)
    points = _hard_points(whole, rng)
    for stamp in (None, 99.0, 101.5, 400.0):
        _assert_same_stats(whole.query(points, stamp), q.query(points, stamp))
    _assert_same_stats(whole.query(points[:0]), q.query(points[:0]))
    assert q._whole is None  # answered by block, in numpy


def test_a_query_reads_only_its_blocks(mapper: Mapper, tmp_path: Path) -> None:
    """Values of a block far from the query are damaged on disk: the query, which never
    reads that block, answers; loading the whole file refuses it (CRC, then the value)."""
    path = tmp_path / "map.npz"
    save_map(mapper, path)
    with np.load(path) as f:
        block_ijk, start = f["block_ijk"], f["block_start"]
        s = f["s"]
    far = int(np.argmax(block_ijk[:, 0]))  # the block farthest along +x
    raw = bytearray(path.read_bytes())
    s_data = raw.find(b"\n", raw.find(b"'descr': '<f4'")) + 1
    first = s_data + 4 * int(start[far])
    assert np.frombuffer(bytes(raw[first : first + 4]), "<f4")[0] == s[start[far]]
    raw[first : first + 4] = np.float32(-1.0).tobytes()
    path.write_bytes(bytes(raw))
    near = block_ijk[np.argmin(block_ijk[:, 0])] * 8 * 0.1 + 0.05
    answer = MapFileQueries(path).query(near[None, :])
    assert np.array_equal(answer.s, mapper.query(near[None, :]).s)
    with pytest.raises(MapFileError, match="CRC-32"):
        load_map(path)
    far_point = block_ijk[far] * 8 * 0.1 + 0.05
    with pytest.raises(MapFileError, match="s holds negative"):
        MapFileQueries(path).query(far_point[None, :])


def test_files_of_the_version_2_writer_are_queried_whole(tmp_path: Path) -> None:
    whole = load_map(LEGACY / "legacy_v2.npz")
    points = whole.voxels().centers[::50]
    q = MapFileQueries(LEGACY / "legacy_v2.npz")
    assert np.array_equal(q.query(points).s, whole.query(points).s)
    assert q.num_voxels == whole.num_voxels


def test_segment_blocks_cover_every_voxel_the_walk_visits() -> None:
    """Every block holding a voxel that a segment crosses (brute force: points every
    1/50 voxel along it) is among the blocks read."""
    rng = np.random.default_rng(4)
    va = rng.uniform(-40, 40, (50, 3))
    vb = va + rng.normal(0, 30, (50, 3))
    keys = segment_block_keys(va, vb)
    assert keys is not None
    from mfp_mapper.core.packed import sort_keys

    t = np.linspace(0, 1, 5000)[:, None]
    for a, b in zip(va, vb, strict=True):
        dense = np.floor(a + (b - a) * t).astype(np.int64) >> 3
        assert np.isin(sort_keys(dense), keys).all()


def test_histograms_are_read_by_block_too(tmp_path: Path, histogram_map: Mapper) -> None:
    """A map with reflectivity histograms is queried by block: the same histograms as the
    map loaded whole; a damaged histogram far from the query is never read (loading the
    whole file refuses it), the query that reads it refuses it."""
    import zipfile

    from mfp_mapper.core.reflectivity import ROW_KEYS
    from mfp_mapper.mapio.blockfile import BLOCK_MEMBERS, TABLE_MEMBERS, locate_members

    assert TABLE_MEMBERS == ROW_KEYS  # the file's names, kept numba-free in mapio
    m = histogram_map
    path = tmp_path / "map.npz"
    save_map(m, path)
    table = m.stored_reflectivity()
    assert table is not None and len(table) > 100
    centres = (table.ijk + 0.5) * m.resolution + np.asarray(m.origin)
    q = MapFileQueries(path)
    for stamp in (None, 130.0):
        a, b = m.reflectivity(centres, stamp), q.reflectivity(centres, stamp)
        assert a is not None and b is not None and a[0] == b[0]
        np.testing.assert_array_equal(a[1], b[1])
    far, near = int(np.argmax(table.ijk[:, 0])), int(np.argmin(table.ijk[:, 0]))
    with open(path, "rb") as f, zipfile.ZipFile(f) as archive:
        member = locate_members(f, archive, (*BLOCK_MEMBERS, *ROW_KEYS), path.stat().st_size)
    raw = bytearray(path.read_bytes())
    at = member["reflectivity_counts"].offset + 8 * table.counts.shape[1] * far
    raw[at : at + 8] = np.float64(-1.0).tobytes()
    path.write_bytes(bytes(raw))
    got = MapFileQueries(path).reflectivity(centres[near][None, :])
    assert got is not None
    np.testing.assert_array_equal(got[1], m.reflectivity(centres[near][None, :])[1])  # type: ignore[index]
    with pytest.raises(MapFileError, match="CRC-32"):
        load_map(path)
    with pytest.raises(MapFileError, match="reflectivity_counts holds negative"):
        MapFileQueries(path).reflectivity(centres[far][None, :])
    assert MapFileQueries(LEGACY / "legacy_v2.npz").reflectivity(centres[:3]) is None


def test_histograms_of_other_dtypes_are_read_too(tmp_path: Path) -> None:
    """int64 indices and float32 counts and times (a file written by other tools) read as
    the usual int32 and float64 ones, whole or by block."""
    from mfp_mapper.core.reflectivity import ScanReflectivity
    from mfp_mapper.mapio.mapfile import map_arrays, write_map_arrays
    from mfp_mapper.sensing.reflectivity import bins_for

    bins = bins_for("reflectivity", 8)
    assert bins is not None
    rng = np.random.default_rng(3)
    m = Mapper(0.2, decay_time=30.0, max_range=30.0)
    points, origin = anchors_scene(n_scans=1, azimuths=100)[0]
    m.integrate(
        points, origin, 5.0, reflectivity=ScanReflectivity(rng.uniform(0, 255, len(points)), bins)
    )
    arrays = map_arrays(m)
    other = dict(
        arrays,
        reflectivity_ijk=arrays["reflectivity_ijk"].astype(np.int64),
        reflectivity_counts=arrays["reflectivity_counts"].astype(np.float32),
        reflectivity_t_last=arrays["reflectivity_t_last"].astype(np.float32),
    )
    write_map_arrays(tmp_path / "other.npz", other)
    centres = (arrays["reflectivity_ijk"] + 0.5) * m.resolution + np.asarray(m.origin)
    want = m.reflectivity(centres)
    for got in (load_map(tmp_path / "other.npz").reflectivity(centres),
                MapFileQueries(tmp_path / "other.npz").reflectivity(centres)):  # fmt: skip
        assert want is not None and got is not None
        np.testing.assert_array_equal(want[1], got[1])


@pytest.fixture(scope="module")
def histogram_map() -> Mapper:
    """A decaying map of two scans with a reflectivity histogram per return voxel."""
    from mfp_mapper.core.reflectivity import ScanReflectivity
    from mfp_mapper.sensing.reflectivity import bins_for

    bins = bins_for("reflectivity", 8)
    assert bins is not None
    rng = np.random.default_rng(11)
    m = Mapper(0.1, decay_time=30.0, max_range=30.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=200)):
        values = ScanReflectivity(rng.uniform(0, 255, len(points)), bins)
        m.integrate(points, origin, 100.0 + k, reflectivity=values)
    return m


@pytest.mark.parametrize("kind", ["decaying", "static", "rows_of_other_times", "tiled"])
def test_the_numpy_histograms_equal_the_compiled_ones(
    histogram_map: Mapper, kind: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``MapFileQueries.reflectivity`` (numpy, the rows of the blocks read) against
    ``Mapper.reflectivity`` of the whole map loaded (the compiled table), bit for bit, with
    and without a stamp, on the voxels holding histograms, their neighbours and the hard
    points: a decaying map, a static one, one whose rows refer to other times (as merges
    write them: float64 counts, each brought to the latest time of the whole file, held
    as float32, then decayed to the stamp, also when one block is read) and a tiled map
    (each tile read by block)."""
    from mfp_mapper.mapio import queries

    rng = np.random.default_rng(12)
    path = tmp_path / ("tiled" if kind == "tiled" else "map.npz")
    arrays = map_arrays(histogram_map)
    if kind == "static":
        arrays["decay_time"] = np.float64(np.inf)
    if kind == "rows_of_other_times":
        rows = arrays["reflectivity_t_last"].shape[0]
        arrays["reflectivity_t_last"] = arrays["reflectivity_t_last"] - rng.uniform(0, 40, rows)
        arrays["reflectivity_counts"] = arrays["reflectivity_counts"] * rng.uniform(
            0.3, 1.7, arrays["reflectivity_counts"].shape
        )
    if kind == "tiled":
        save_map(histogram_map, path, tile_blocks=2)
    else:
        write_map_arrays(path, arrays)
    whole = load_map(path)
    table = whole.stored_reflectivity()
    assert table is not None and len(table) > 100
    centres = (table.ijk + 0.5) * whole.resolution + np.asarray(whole.origin)
    points = np.concatenate([
        centres, centres + rng.integers(-1, 2, centres.shape) * whole.resolution,
        _hard_points(whole, rng),
    ])  # fmt: skip
    from mfp_mapper.cli.common import load_map_arg

    q = load_map_arg(str(path), lazy_tiles=True, queries=True)
    if kind != "tiled":  # answered without a Mapper
        monkeypatch.setattr(queries, "mapper_from_contents", None)
    for stamp in (None, 99.0, 101.5, 400.0):
        a, b = whole.reflectivity(points, stamp), q.reflectivity(points, stamp)
        assert a is not None and b is not None and a[0] == b[0]
        np.testing.assert_array_equal(a[1], b[1], strict=True)
        assert (a[1][: len(centres)].sum(axis=1) > 0).all()  # every row found
        for one in centres[:: len(centres) // 6]:  # one block read: the file's latest time
            a, b = whole.reflectivity(one[None, :], stamp), q.reflectivity(one[None, :], stamp)
            assert a is not None and b is not None
            np.testing.assert_array_equal(a[1], b[1], strict=True)
    if kind != "tiled":  # (a tiled map reads no tile for no point: None)
        a, b = whole.reflectivity(points[:0]), q.reflectivity(points[:0])
        assert a is not None and b is not None
        np.testing.assert_array_equal(a[1], b[1], strict=True)


def test_a_voxel_whose_histogram_is_listed_twice_is_refused(
    histogram_map: Mapper, tmp_path: Path
) -> None:
    """A file listing one voxel's histogram twice: loading it whole refuses it, and so does
    a query of its block, with the same words."""
    arrays = map_arrays(histogram_map)
    for key in ("reflectivity_ijk", "reflectivity_counts", "reflectivity_t_last"):
        arrays[key] = np.concatenate([arrays[key], arrays[key][:1]])
    path = tmp_path / "twice.npz"
    write_map_arrays(path, arrays)
    voxel = arrays["reflectivity_ijk"][0]
    point = (voxel + 0.5) * histogram_map.resolution + np.asarray(histogram_map.origin)
    with pytest.raises(MapFileError, match="more than once") as whole:
        load_map(path)
    with pytest.raises(MapFileError, match="more than once") as by_block:
        MapFileQueries(path).reflectivity(point[None, :])
    assert str(whole.value) == str(by_block.value)
    assert f"lists voxel {voxel.tolist()} more than once" in str(whole.value)
