"""Queries from a map file read by block (``MapFileQueries``): the same answers as the map
loaded whole, from only the blocks they need."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import MapFileError, Mapper
from mfp_mapper.mapio.loading import load_map, save_map
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
        a, b = mapper.query(points, stamp), q.query(points, stamp)
        for key in ("ijk", "s", "n", "t_last", "observed"):
            assert np.array_equal(getattr(a, key), getattr(b, key)), key
    if not tiled:
        a, b = mapper.query_segments(starts, ends), q.query_segments(starts, ends)
        assert np.array_equal(a.clear_probability, b.clear_probability)
        assert np.array_equal(a.unknown_length, b.unknown_length)


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


def test_histograms_are_read_by_block_too(tmp_path: Path) -> None:
    """A map with reflectivity histograms is queried by block: the same histograms as the
    map loaded whole; a damaged histogram far from the query is never read (loading the
    whole file refuses it), the query that reads it refuses it."""
    import zipfile

    from mfp_mapper.core.reflectivity import ROW_KEYS, ScanReflectivity
    from mfp_mapper.mapio.blockfile import BLOCK_MEMBERS, TABLE_MEMBERS, locate_members
    from mfp_mapper.sensing.reflectivity import bins_for

    assert TABLE_MEMBERS == ROW_KEYS  # the file's names, kept numba-free in mapio
    bins = bins_for("reflectivity", 8)
    assert bins is not None
    rng = np.random.default_rng(2)
    m = Mapper(0.1, decay_time=30.0, max_range=30.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=200)):
        values = ScanReflectivity(rng.uniform(0, 255, len(points)), bins)
        m.integrate(points, origin, 100.0 + k, reflectivity=values)
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
    at = member["reflectivity_counts"].offset + 8 * bins.count * far
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
