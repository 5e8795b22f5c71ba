"""``save_map`` writes what ``load_map`` reads: one map file (``*.npz``) or a tiled map."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import MapFileError, Mapper
from mfp_mapper.mapio.loading import is_map_file_name, load_map, save_map
from mfp_mapper.mapio.tiles import TiledMap, is_tiled


@pytest.fixture(scope="module")
def mapper() -> Mapper:
    m = Mapper(0.2, decay_time=30.0, frame_id="odom", max_range=40.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=300)):
        m.integrate(points, origin, 100.0 + k)
    return m


def _sorted(m: Mapper) -> tuple[np.ndarray, np.ndarray]:
    v = m.voxels()
    order = np.lexsort(v.ijk.T)
    return v.ijk[order], np.stack([v.s[order], v.n[order], v.t_last[order]])


@pytest.mark.parametrize("name", ["map.npz", "tiled", "tiled.d"])
def test_save_map_writes_what_load_map_reads(mapper: Mapper, tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    tiles = save_map(mapper, path, tile_blocks=2)
    assert is_map_file_name(path) == (name == "map.npz") == (tiles == 0)
    assert path.is_file() if name == "map.npz" else is_tiled(path)
    if tiles:
        assert TiledMap(path).tile_blocks == 2 and len(TiledMap(path).tiles) == tiles > 1
    loaded = load_map(path)
    assert (loaded.resolution, loaded.frame_id, loaded.decay_time) == (0.2, "odom", 30.0)
    ijk, values = _sorted(loaded)
    ref_ijk, ref_values = _sorted(mapper)
    np.testing.assert_array_equal(ijk, ref_ijk)
    np.testing.assert_array_equal(values, ref_values)


def test_a_tiled_map_is_replaced_but_no_other_folder(mapper: Mapper, tmp_path: Path) -> None:
    path = tmp_path / "tiled"
    save_map(mapper, path)
    save_map(mapper, path)  # a tiled map: replaced
    assert load_map(path).num_voxels == mapper.num_voxels
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("keep me\n")
    with pytest.raises(MapFileError, match="not replaced"):
        save_map(mapper, other)
    assert (other / "notes.txt").read_text() == "keep me\n"
