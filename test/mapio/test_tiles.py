"""Tiled maps: round trip, region loads, queries over tiles, the per-tile merge, damage."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import Mapper
from mfp_mapper.core.merge import merge_map_arrays
from mfp_mapper.mapio.loading import load_map, save_map
from mfp_mapper.mapio.mapfile import MapFileError, map_arrays
from mfp_mapper.mapio.tiles import INDEX_NAME, TiledMap, merge_tile, write_tiled

RES = 0.2
TILE_BLOCKS = 4  # 6.4 m tiles: the scene spans many


@pytest.fixture(scope="module")
def mapper() -> Mapper:
    m = Mapper(RES, decay_time=20.0, max_range=30.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=3, azimuths=120)):
        m.integrate(points, origin, 100.0 + k)
    return m


def _table(stats) -> dict[tuple[int, ...], tuple[float, float, float]]:  # type: ignore[no-untyped-def]
    return {
        tuple(v): (s, n, t)
        for v, s, n, t in zip(stats.ijk.tolist(), stats.s, stats.n, stats.t_last, strict=True)
    }


def test_tiles_round_trip(mapper: Mapper, tmp_path) -> None:  # type: ignore[no-untyped-def]
    entries = write_tiled(tmp_path / "map", map_arrays(mapper), TILE_BLOCKS)
    assert len(entries) > 10
    index = json.loads((tmp_path / "map" / INDEX_NAME).read_text())
    assert index["format"] == "mfp_mapper.tiles" and index["voxels"] == mapper.num_voxels
    assert index["decay_time"] == 20.0 and index["tile_blocks"] == TILE_BLOCKS
    back = load_map(tmp_path / "map")
    assert _table(back.voxels()) == _table(mapper.voxels())
    assert (back.resolution, back.decay_time, back.frame_id) == (RES, 20.0, "map")
    # every tile is an ordinary map file, inside its block range
    for entry in index["tiles"]:
        tile = load_map(tmp_path / "map" / entry["file"])
        blocks = tile.voxels().ijk // 8
        assert np.all(blocks >= entry["blocks"][0]) and np.all(blocks < entry["blocks"][1])


def test_tiles_of_blocks_load_the_map_bit_for_bit(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """A tiled map of the store's blocks (flushed blocks too) loads, its tiles taken in tile
    order and not sorted together, to the blocks of the map file of the same map, bit for
    bit; a tile holding a block of another tile is refused (blocks would be twice)."""
    m = Mapper(RES, decay_time=20.0, max_range=30.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=3, azimuths=120)):
        m.integrate(points, origin, 100.0 + k)
    for sh in m._store.shards:  # flush some blocks: their float64 parts go with them
        sh.block_flush[: sh.used : 4] = True
        sh.pools[4] = 1  # FLUSH_PENDING
        sh.flush()
    assert save_map(m, tmp_path / "tiles", tile_blocks=TILE_BLOCKS) > 10
    save_map(m, tmp_path / "map.npz")
    tiled, whole = load_map(tmp_path / "tiles"), load_map(tmp_path / "map.npz")
    a, b = tiled.stored_blocks(), whole.stored_blocks()
    assert a.hi_block.shape[0] > 0
    for key, value in b.__dict__.items():
        got = getattr(a, key)
        assert isinstance(got, bool) or got.tobytes() == value.tobytes(), key
    index = TiledMap(tmp_path / "tiles")
    first, second = sorted(index.tiles)[:2]
    (tmp_path / "tiles" / index.tiles[second].file).write_bytes(
        (tmp_path / "tiles" / index.tiles[first].file).read_bytes()
    )
    with pytest.raises(MapFileError, match="does not hold"):
        load_map(tmp_path / "tiles")


def test_rewriting_a_tiled_map_leaves_only_the_new_files(mapper: Mapper, tmp_path) -> None:  # type: ignore[no-untyped-def]
    arrays = map_arrays(mapper)
    write_tiled(tmp_path / "map", arrays, TILE_BLOCKS)
    write_tiled(tmp_path / "map", arrays, TILE_BLOCKS * 2)
    files = sorted(p.name for p in (tmp_path / "map" / "tiles").iterdir())
    listed = sorted(e.file.split("/")[-1] for e in TiledMap(tmp_path / "map").tiles.values())
    assert files == listed


def test_a_region_loads_only_its_voxels(mapper: Mapper, tmp_path) -> None:  # type: ignore[no-untyped-def]
    write_tiled(tmp_path / "map", map_arrays(mapper), TILE_BLOCKS)
    bounds = ((-2.0, -1.0, 0.0), (3.0, 2.5, math.inf))
    want = _table(mapper.voxels(bounds=bounds))
    assert 0 < len(want) < mapper.num_voxels
    tiled = TiledMap(tmp_path / "map")
    assert len(tiled.keys_in(bounds)) < len(tiled.tiles)
    assert _table(load_map(tmp_path / "map", bounds=bounds).voxels()) == want
    save_map(mapper, tmp_path / "map.npz")  # the same for one map file
    assert _table(load_map(tmp_path / "map.npz", bounds=bounds).voxels()) == want


def test_queries_over_tiles_match_the_map(mapper: Mapper, tmp_path) -> None:  # type: ignore[no-untyped-def]
    write_tiled(tmp_path / "map", map_arrays(mapper), TILE_BLOCKS)
    rng = np.random.default_rng(1)
    points = np.concatenate(
        [mapper.voxels().centers[::7], rng.uniform(-20, 20, (200, 3)), [[np.nan, 0, 0]]]
    )
    for stamp in (None, 130.0):
        got = TiledMap(tmp_path / "map").query(points, stamp)
        want = mapper.query(points, stamp)
        for name in ("ijk", "s", "n", "t_last", "observed"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


def test_tile_by_tile_merge_equals_the_whole_merge(tmp_path) -> None:  # type: ignore[no-untyped-def]
    scans = anchors_scene(n_scans=4, azimuths=90)
    parts = []
    for i in range(2):
        m = Mapper(RES, decay_time=5.0, max_range=30.0)
        for k in range(i, 4, 2):
            m.integrate(*scans[k], float(k))
        parts.append(map_arrays(m))
        write_tiled(tmp_path / f"p{i}", parts[-1], TILE_BLOCKS)
    tiled = [TiledMap(tmp_path / f"p{i}") for i in range(2)]
    keys = sorted(set(tiled[0].tiles) | set(tiled[1].tiles))
    by_tile = [merge_tile(tiled, k) for k in keys]
    got = {k: np.concatenate([t[k] for t in by_tile]) for k in ("ijk", "s", "n", "t_last")}
    whole = merge_map_arrays(parts)
    a, b = np.lexsort(got["ijk"].T), np.lexsort(whole["ijk"].T)
    for k in ("ijk", "s", "n", "t_last"):
        np.testing.assert_array_equal(got[k][a], whole[k][b])


def test_damaged_tiled_maps_are_clear_errors(mapper: Mapper, tmp_path) -> None:  # type: ignore[no-untyped-def]
    root = tmp_path / "map"
    (root).mkdir()
    with pytest.raises(MapFileError, match="not a tiled map"):
        load_map(root)
    write_tiled(root, map_arrays(mapper), TILE_BLOCKS)
    tiled = TiledMap(root)
    key = sorted(tiled.tiles)[0]
    (root / tiled.tiles[key].file).unlink()
    with pytest.raises(MapFileError, match="no such file"):
        load_map(root)
    (root / INDEX_NAME).write_text("{not json")
    with pytest.raises(MapFileError, match="unreadable tile index"):
        TiledMap(root)
    # a tile file from another map (other resolution) is refused
    other = Mapper(0.1)
    other.integrate(np.array([[1.0, 0.0, 0.0]]), np.zeros(3), 0.0)
    write_tiled(root, map_arrays(mapper), TILE_BLOCKS)
    tiled = TiledMap(root)
    entry = tiled.tiles[sorted(tiled.tiles)[0]]
    save_map(other, root / entry.file)
    with pytest.raises(MapFileError, match="different resolution"):
        load_map(root)


@pytest.mark.parametrize("output", ["merged.npz", "merged_tiles"])
def test_merging_tiled_maps_merges_their_reflectivity_exactly(tmp_path, output: str) -> None:  # type: ignore[no-untyped-def]
    """``mfp-mapper merge`` of two tiled maps (scans split between them, out of order, with
    decay) holds the histograms of one map of all the scans."""
    from mfp_mapper.cli import main
    from mfp_mapper.core.reflectivity import ScanReflectivity
    from mfp_mapper.sensing.reflectivity import bins_for

    bins = bins_for("intensity", 8)
    assert bins is not None
    scans = list(anchors_scene(n_scans=4, azimuths=120))
    rng = np.random.default_rng(4)
    values = [rng.integers(0, 256, len(points)).astype(np.float32) for points, _ in scans]
    stamps = [100.0, 103.0, 101.0, 102.0]

    def map_of(picks: list[int]) -> Mapper:
        m = Mapper(RES, decay_time=20.0, max_range=30.0, origin=(0.0, 0.0, 0.0))
        for k in picks:
            points, origin = scans[k]
            m.integrate(points, origin, stamps[k], reflectivity=ScanReflectivity(values[k], bins))
        return m

    both = map_of([0, 1, 2, 3])
    save_map(map_of([0, 1]), tmp_path / "a", tile_blocks=TILE_BLOCKS)
    save_map(map_of([2, 3]), tmp_path / "b", tile_blocks=TILE_BLOCKS)
    out = tmp_path / output
    assert main(["merge", str(tmp_path / "a"), str(tmp_path / "b"), "-o", str(out)]) == 0
    merged = load_map(out)
    want, got = both.stored_reflectivity(), merged.stored_reflectivity()
    assert want is not None and got is not None and len(want) == len(got) and got.bins == bins
    centers = (want.ijk + 0.5) * RES
    a, b = both.reflectivity(centers, 104.0), merged.reflectivity(centers, 104.0)
    assert a is not None and b is not None
    np.testing.assert_allclose(a[1], b[1], rtol=1e-5)
    np.testing.assert_allclose(
        b[1].sum(axis=1), merged.query(centers, 104.0).n, rtol=1e-5
    )  # totals are still the voxels' n
