"""The map file contract: round trip, atomic writes, and clear errors on bad files."""

from __future__ import annotations

import io
import math
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import MapFileError, Mapper
from mfp_mapper.core.layout import bit_count
from mfp_mapper.mapio.loading import load_map, save_map


@pytest.fixture(scope="module")
def mapper() -> Mapper:
    m = Mapper(0.2, decay_time=30.0, frame_id="odom", max_range=40.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=300)):
        m.integrate(points, origin, 100.0 + k)
    return m


def test_round_trip_keeps_every_voxel(mapper: Mapper, tmp_path: Path) -> None:
    path = tmp_path / "map.npz"
    save_map(mapper, path)
    loaded = load_map(path)
    assert (loaded.resolution, loaded.decay_time, loaded.frame_id, loaded.max_range) == (
        0.2,
        30.0,
        "odom",
        40.0,
    )
    a, b = mapper.voxels(), loaded.voxels()
    order_a, order_b = np.lexsort(a.ijk.T), np.lexsort(b.ijk.T)
    assert np.array_equal(a.ijk[order_a], b.ijk[order_b])
    assert np.array_equal(a.s[order_a], b.s[order_b])
    assert np.array_equal(a.n[order_a], b.n[order_b])
    assert np.array_equal(a.t_last[order_a], b.t_last[order_b])
    assert loaded.num_voxels == mapper.num_voxels
    assert loaded.last_stamp == 101.0
    # a loaded map keeps integrating
    points, origin = anchors_scene(n_scans=1, azimuths=50)[0]
    loaded.integrate(points, origin, 102.0)


def test_file_holds_the_documented_arrays(mapper: Mapper, tmp_path: Path) -> None:
    path = tmp_path / "map.npz"
    save_map(mapper, path)
    with np.load(path, allow_pickle=False) as f:
        assert int(f["version"]) == 4 and str(f["format"]) == "mfp_mapper.map"
        assert f["hi_block"].shape == (0,) and f["hi_s"].shape == f["hi_n"].shape == (0,)
        block_ijk, observed, hit = f["block_ijk"], f["observed"], f["hit"]
        assert block_ijk.dtype == np.int32 and observed.dtype == np.uint64
        assert f["s"].dtype == np.float32 and f["n"].dtype == np.float32  # as in memory
        assert f["s"].shape == (mapper.num_voxels,)
        assert bit_count(observed).sum() == mapper.num_voxels
        assert np.array_equal(np.diff(f["block_start"]), bit_count(observed).sum(1))
        assert np.all(hit & ~observed[f["hit_block"]] == 0)
        assert f["n"].shape == (np.count_nonzero(mapper.voxels().n),)
        assert float(f["resolution"]) == 0.2 and str(f["frame_id"]) == "odom"
        assert float(f["decay_time"]) == 30.0
        # the documented decoding gives back every voxel: block index * 8 + Morton offsets
        rows, place = np.nonzero(np.unpackbits(observed.view(np.uint8), axis=1, bitorder="little"))
        bits = [(place >> (2 - axis)) & 1 | (place >> (4 - axis)) & 2 | (place >> (6 - axis)) & 4
                for axis in range(3)]  # fmt: skip
        ijk = block_ijk[rows].astype(np.int64) * 8 + np.stack(bits, axis=1)
        s, t_last = f["s"], f["block_t"][rows]
    v = mapper.stored_voxels()
    order_a, order_b = np.lexsort(v.ijk.T), np.lexsort(ijk.T)
    assert np.array_equal(v.ijk[order_a], ijk[order_b])
    assert np.array_equal(v.s[order_a], s[order_b])
    assert np.array_equal(v.t_last[order_a], t_last[order_b])


LEGACY = Path(__file__).parent / "data"
"""A map and a tiled map written by the version 2 writer (commit e8b3188): 2,899 voxels of
``anchors_scene(n_scans=2, azimuths=6)`` at 0.5 m, max_range 15 m, decay 30 s, frame odom."""


@pytest.mark.parametrize("name", ["legacy_v2.npz", "legacy_v2_tiled"])
def test_files_of_the_version_2_writer_still_load(name: str, tmp_path: Path) -> None:
    loaded = load_map(LEGACY / name)
    v = loaded.stored_voxels()
    assert (loaded.num_voxels, loaded.frame_id, loaded.decay_time) == (2899, "odom", 30.0)
    assert v.s.sum() == pytest.approx(2508.773651440628, rel=1e-6)
    assert v.n.sum() == pytest.approx(62.983698189258575, rel=1e-6)
    assert np.count_nonzero(v.n) == 58
    # and saved again (version 3), they hold the same voxels
    save_map(loaded, tmp_path / "again.npz")
    again = load_map(tmp_path / "again.npz").stored_voxels()
    order_a, order_b = np.lexsort(v.ijk.T), np.lexsort(again.ijk.T)
    for key in ("ijk", "s", "n", "t_last"):
        assert np.array_equal(getattr(v, key)[order_a], getattr(again, key)[order_b]), key


@pytest.mark.parametrize("name", ["legacy_v3.npz", "legacy_v3_tiled"])
def test_files_of_the_version_3_writer_still_load(name: str, tmp_path: Path) -> None:
    """Written by the version 3 writer (commit 3218d3c) from ``legacy_v2.npz`` with a third
    of its blocks flushed into float64 and one more scan (``anchors_scene(n_scans=1,
    azimuths=6)`` at 200 s): ``s`` and ``n`` in float64, the sums as they were."""
    loaded = load_map(LEGACY / name)
    v = loaded.stored_voxels()
    assert (loaded.num_voxels, loaded.last_stamp) == (2899, 200.0)
    assert v.s.sum() == pytest.approx(1380.5398396084365, rel=1e-12)
    assert v.n.sum() == pytest.approx(37.28252745567036, rel=1e-12)
    assert np.count_nonzero(v.n) == 58
    if name.endswith(".npz"):
        with np.load(LEGACY / name) as f:
            assert int(f["version"]) == 3 and f["s"].dtype == np.float64
            s_file = np.sort(f["s"])
        assert np.array_equal(np.sort(v.s), s_file)  # float64 values kept (none < limit cast)
    save_map(loaded, tmp_path / "again.npz")  # version 4: the same voxels
    again = load_map(tmp_path / "again.npz").stored_voxels()
    order_a, order_b = np.lexsort(v.ijk.T), np.lexsort(again.ijk.T)
    for key in ("ijk", "s", "n", "t_last"):
        assert np.array_equal(getattr(v, key)[order_a], getattr(again, key)[order_b]), key


def _parked_scan() -> tuple[np.ndarray, np.ndarray]:
    """4000 returns on the walls of a small box around a parked sensor."""
    rng = np.random.default_rng(7)
    origin = np.array([0.0123, 0.0271, 0.0347])
    directions = rng.normal(size=(4000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    reach = np.min(np.abs(np.array([0.5, 0.4, 0.3]) / directions), axis=1)
    return origin + directions * reach[:, None] * 0.999, origin


@pytest.mark.parametrize("threads", [1, 2])
def test_flushed_blocks_load_back_bit_for_bit(tmp_path: Path, threads: int) -> None:
    """A parked sensor: the voxels around it pass the float32 limits and their blocks are
    flushed into float64 (``shard.flush``). The file keeps the float32 and float64 parts
    apart (``hi_*``: only those blocks in float64) and loads back the same store: every
    voxel's sums bit for bit, and the same sums after more scans added to both."""
    points, origin = _parked_scan()
    m = Mapper(0.1, max_range=10.0, min_range=0.0, decay_time=600.0, threads=threads)
    for k in range(150):
        m.integrate(points, origin, 0.1 * k)
    wide, wide_origin = anchors_scene(n_scans=1, azimuths=60)[0]
    m.integrate(wide, wide_origin, 15.0)  # blocks that were never flushed, too
    path = tmp_path / "parked.npz"
    save_map(m, path)
    with np.load(path) as f:
        assert f["s"].dtype == np.float32 and f["hi_block"].shape[0] > 0
        assert f["hi_s"].shape[0] < f["s"].shape[0]
    loaded = load_map(path, threads=threads)
    for step in range(2):
        a, b = m.stored_voxels(), loaded.stored_voxels()
        order_a, order_b = np.lexsort(a.ijk.T), np.lexsort(b.ijk.T)
        for key in ("ijk", "s", "n", "t_last"):
            assert np.array_equal(getattr(a, key)[order_a], getattr(b, key)[order_b]), key
        assert loaded.num_voxels == m.num_voxels
        for mapper in (m, loaded) if step == 0 else ():
            for k in range(3):
                mapper.integrate(points, origin, 15.1 + 0.1 * k)


def test_static_map_round_trips_infinite_decay_time(tmp_path: Path) -> None:
    m = Mapper(0.5)
    m.integrate(np.array([[3.0, 0.2, 0.2]]), np.zeros(3), 1.0)
    save_map(m, tmp_path / "static.npz")
    assert math.isinf(load_map(tmp_path / "static.npz").decay_time)


def test_save_is_atomic_and_leaves_no_temporary_file(
    mapper: Mapper, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "map.npz"
    save_map(mapper, path)
    before = path.read_bytes()

    write_header = np.lib.format.write_array_header_1_0
    written: list[str] = []

    def fail_on_third_array(member: Any, header: dict, **kwargs: Any) -> None:
        written.append(header["descr"])
        if len(written) == 3:
            raise OSError("disk full")
        write_header(member, header, **kwargs)

    monkeypatch.setattr(np.lib.format, "write_array_header_1_0", fail_on_third_array)
    with pytest.raises(OSError, match="disk full"):
        save_map(mapper, path)
    assert len(written) == 3  # failed part way, with arrays already in the archive
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["map.npz"]


def _write_npz(path: Path, **arrays: np.ndarray) -> Path:
    np.savez(path, **arrays)
    return path


def _valid_arrays() -> dict[str, np.ndarray]:
    return {
        "ijk": np.array([[0, 0, 0], [1, 0, 0]], dtype=np.int32),
        "s": np.array([1.0, 2.0]),
        "n": np.array([0.0, 1.0]),
        "t_last": np.array([0.0, 0.0]),
        "resolution": np.float64(0.1),
        "decay_time": np.float64(np.inf),
        "frame_id": np.str_("map"),
    }


def test_minimal_foreign_writer_is_accepted(tmp_path: Path) -> None:
    loaded = load_map(_write_npz(tmp_path / "ok.npz", **_valid_arrays()))
    q = loaded.query(np.array([[0.15, 0.05, 0.05]]))
    assert q.s[0] == 2.0 and q.n[0] == 1.0


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"s": np.array([1.0, -2.0])}, "negative, NaN or infinite"),
        ({"n": np.array([np.nan, 1.0])}, "negative, NaN or infinite"),
        ({"ijk": np.zeros((2, 2), dtype=np.int32)}, r"integer \(N, 3\)"),
        ({"s": np.array([1.0])}, "float array of length 2"),
        ({"resolution": np.float64(-1.0)}, "resolution must be positive"),
        ({"ijk": np.zeros((2, 3), dtype=np.int32)}, "more than once"),
        ({"t_last": np.array([np.nan, 0.0])}, "t_last"),
    ],
)
def test_invalid_contents_name_the_file_and_the_problem(
    tmp_path: Path, change: dict, message: str
) -> None:
    path = _write_npz(tmp_path / "bad.npz", **{**_valid_arrays(), **change})
    with pytest.raises(MapFileError, match=message) as err:
        load_map(path)
    assert str(path) in str(err.value)


def test_missing_keys_say_it_is_not_a_map(tmp_path: Path) -> None:
    arrays = _valid_arrays()
    del arrays["s"], arrays["frame_id"]
    with pytest.raises(MapFileError, match="not an mfp_mapper map: missing s, frame_id"):
        load_map(_write_npz(tmp_path / "foreign.npz", **arrays))


def test_truncated_and_garbage_files_are_reported(mapper: Mapper, tmp_path: Path) -> None:
    path = tmp_path / "map.npz"
    save_map(mapper, path)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(MapFileError, match="unreadable or truncated"):
        load_map(truncated)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a map at all" * 10)
    with pytest.raises(MapFileError, match="unreadable or truncated"):
        load_map(garbage)
    with pytest.raises(MapFileError, match="no such file"):
        load_map(tmp_path / "absent.npz")


def test_pickled_objects_are_never_loaded(tmp_path: Path) -> None:
    arrays = _valid_arrays()
    arrays["frame_id"] = np.array([{"evil": "object"}], dtype=object)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path = tmp_path / "pickle.npz"
    path.write_bytes(buf.getvalue())
    with zipfile.ZipFile(path) as z:
        assert "frame_id.npy" in z.namelist()
    with pytest.raises(MapFileError, match="pickles are never loaded"):
        load_map(path)


def _v1_file(mapper: Mapper, path: Path) -> Path:
    """A version-1 file as the code before the origin wrote it (no origin, version 1)."""
    from hostile_maps import write_legacy_map

    from mfp_mapper.mapio.mapfile import map_arrays

    arrays = map_arrays(mapper)
    del arrays["origin"]
    arrays["version"] = np.int64(1)
    write_legacy_map(path, arrays)
    return path


def test_version_1_files_still_load(mapper: Mapper, tmp_path: Path) -> None:
    loaded = load_map(_v1_file(mapper, tmp_path / "v1.npz"))
    assert loaded.origin == (0.0, 0.0, 0.0)
    a, b = mapper.voxels(), loaded.voxels()
    assert len(a) == len(b) and a.s.sum() == pytest.approx(b.s.sum())


def test_geo_referenced_map_round_trips_its_origin(tmp_path: Path) -> None:
    utm = np.array([512_345.6, 5_412_345.7, 250.0])
    m = Mapper(0.1)
    points, origin = anchors_scene(n_scans=1, azimuths=100)[0]
    summary = m.integrate(points + utm, origin + utm, 1.0)
    assert summary.integrated and summary.rays_unindexable == 0
    assert m.origin is not None and np.abs(np.array(m.origin) - utm).max() < 6553.6 / 2
    save_map(m, tmp_path / "geo.npz")
    with np.load(tmp_path / "geo.npz") as f:
        assert int(f["version"]) == 4 and np.array_equal(f["origin"], np.array(m.origin))
        ijk = m.stored_voxels().ijk
        centers = np.asarray(f["origin"]) + (ijk + 0.5) * float(f["resolution"])
    loaded = load_map(tmp_path / "geo.npz")
    assert loaded.origin == m.origin
    q = loaded.query(centers)
    assert q.observed.all() and q.s.sum() == pytest.approx(m.voxels().s.sum())


def test_huge_array_claimed_by_a_header_is_refused_before_reading(tmp_path: Path) -> None:
    arrays = _valid_arrays()
    path = _write_npz(tmp_path / "huge.npz", **arrays)
    # rewrite the s member with a header claiming 10^12 elements and no data
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": (10**12,)}
    )
    raw = header.getvalue()  # magic and header, no data
    with zipfile.ZipFile(path) as src:
        members = {n: src.read(n) for n in src.namelist()}
    members["s.npy"] = raw
    with zipfile.ZipFile(path, "w") as out:
        for name, data in members.items():
            out.writestr(name, data)
    with pytest.raises(MapFileError, match="s claims 8000000000000 bytes") as err:
        load_map(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"resolution": np.float64(1e-300)}, r"resolution must be positive, within"),
        ({"ijk": np.array([[0, 0, 0], [2**30, 0, 0]], dtype=np.int32)}, "beyond"),
        ({"origin": np.array([0.0, np.nan, 0.0])}, "origin must be 3 finite metres"),
        ({"origin": np.zeros(2)}, "origin must be a float array of 3"),
        ({"version": np.int64(2)}, "needs origin"),
        ({"ijk": np.array([[5, 6, 7], [5, 6, 7]], dtype=np.int32)}, r"\[5, 6, 7\] more than"),
    ],
)
def test_ranges_are_checked(tmp_path: Path, change: dict, message: str) -> None:
    path = _write_npz(tmp_path / "bad.npz", **{**_valid_arrays(), **change})
    with pytest.raises(MapFileError, match=message):
        load_map(path)


def test_duplicates_far_apart_in_a_large_file_are_found(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    ijk = rng.integers(-5000, 5000, size=(200_000, 3), dtype=np.int32)
    ijk = np.unique(ijk, axis=0)
    rng.shuffle(ijk)
    count = len(ijk)
    base = {**_valid_arrays(), "s": np.ones(count), "n": np.zeros(count), "t_last": np.zeros(count)}
    ok = _write_npz(tmp_path / "ok.npz", **{**base, "ijk": ijk})
    assert load_map(ok).num_voxels == count
    twice = ijk.copy()
    twice[-1] = twice[0]
    with pytest.raises(MapFileError, match="more than once"):
        load_map(_write_npz(tmp_path / "twice.npz", **{**base, "ijk": twice}))


def test_from_arrays_builds_a_map_without_a_file() -> None:
    from mfp_mapper.core.store import VoxelArrays

    voxels = VoxelArrays(
        np.array([[1, 2, 3]], dtype=np.int32), np.array([2.0]), np.array([1.0]), np.array([4.0])
    )
    m = Mapper.from_arrays(voxels, resolution=0.5, origin=(10.0, 0.0, 0.0), decay_time=5.0)
    q = m.query(np.array([[10.0 + 0.75, 1.25, 1.75]]))
    assert q.s[0] == 2.0 and q.n[0] == 1.0 and m.last_stamp == 4.0
    assert q.centers[0] == pytest.approx([10.75, 1.25, 1.75])


@pytest.mark.parametrize("threads", [1, 2])
def test_s_read_by_two_threads_loads_the_same_and_is_checked(
    threads: int, mapper: Mapper, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``s`` read by two threads (``blockfile.read_all`` on large maps, forced here: the
    second reads from a point in the middle, the two CRCs combined) loads the same blocks
    as one read after the other, and one flipped bit anywhere in ``s`` (its first value,
    about where the second thread begins, its last) is still refused by its CRC."""
    from mfp_mapper.mapio import blockfile

    if threads == 2:
        monkeypatch.setattr(blockfile, "THREADED_READ_BYTES", 0)
        monkeypatch.setattr(blockfile, "_SPLIT_ALIGN", 4)
        monkeypatch.setattr(blockfile, "_PIECE", 4096)  # several pieces a thread
        monkeypatch.setattr(blockfile.os, "cpu_count", lambda: 2)
    path = tmp_path / "map.npz"
    save_map(mapper, path)
    a, b = load_map(path).stored_blocks(), mapper.stored_blocks()
    for key in ("block_ijk", "block_t", "observed", "s", "hit_block", "hit", "n"):
        assert getattr(a, key).tobytes() == getattr(b, key).tobytes(), key
    good = path.read_bytes()
    s_data = good.find(b"\n", good.find(b"'descr': '<f4'")) + 1
    size = 4 * b.s.shape[0]
    assert size > 3 * 4096
    for at in (0, size // 2 - 4, size // 2, size // 3, size - 1):
        raw = bytearray(good)
        raw[s_data + at] ^= 0x01
        path.write_bytes(bytes(raw))
        with pytest.raises(MapFileError, match="s fails its CRC-32"):
            load_map(path)


def test_crc32_combine_is_zlibs() -> None:
    """The CRC-32 of two pieces combined is zlib's of the whole, for empty, short and long
    pieces and any starting CRC."""
    import zlib

    from mfp_mapper.mapio.blockfile import crc32_combine

    rng = np.random.default_rng(5)
    for len_a, len_b in [
        (0, 0),
        (0, 5),
        (5, 0),
        (1, 1),
        (3, 4096),
        (70_000, 1 << 17),
        (9, 1_000_003),
    ]:
        a, b = rng.bytes(len_a), rng.bytes(len_b)
        start = int(rng.integers(0, 2**32))
        whole = zlib.crc32(a + b, start)
        assert crc32_combine(zlib.crc32(a, start), zlib.crc32(b), len_b) == whole
