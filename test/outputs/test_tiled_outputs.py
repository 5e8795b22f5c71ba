"""Export and pictures of tiled maps: the same as of the map they were cut from."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import Mapper
from mfp_mapper.mapio.loading import load_map
from mfp_mapper.mapio.mapfile import map_arrays
from mfp_mapper.mapio.tiles import TiledMap, write_tiled
from mfp_mapper.outputs.export import export_ply, export_ply_tiled, read_ply


@pytest.fixture(scope="module")
def mapper() -> Mapper:
    m = Mapper(0.2, max_range=30.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=3, azimuths=180)):
        m.integrate(points, origin, float(k))
    return m


def _rows(ply: dict[str, np.ndarray]) -> np.ndarray:
    rows = np.stack([ply[k] for k in ("x", "y", "z", "n", "s", "std")], axis=1)
    return rows[np.lexsort(rows[:, :3].T)]


@pytest.mark.parametrize("min_doo", [0.0, 0.3])
def test_tiled_export_equals_the_export_of_the_map(
    mapper: Mapper, tmp_path: Path, min_doo: float
) -> None:
    write_tiled(tmp_path / "tiles", map_arrays(mapper), tile_blocks=4)
    one = export_ply(mapper, tmp_path / "one.ply", min_doo=min_doo)
    tiled = export_ply_tiled(TiledMap(tmp_path / "tiles"), tmp_path / "tiled.ply", min_doo=min_doo)
    assert one == tiled > 0
    np.testing.assert_array_equal(
        _rows(read_ply(tmp_path / "one.ply")), _rows(read_ply(tmp_path / "tiled.ply"))
    )
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no scratch left


def test_render_of_a_tiled_region(mapper: Mapper, tmp_path: Path) -> None:
    from mfp_mapper.outputs.render import render_map

    write_tiled(tmp_path / "tiles", map_arrays(mapper), tile_blocks=4)
    region = load_map(tmp_path / "tiles", bounds=((-5.0, -5.0, -1.0), (5.0, 5.0, 4.0)))
    assert 0 < region.num_voxels < mapper.num_voxels
    result = render_map(region, tmp_path / "pictures")
    assert {p.name for p in result.files} >= {"doo_topdown.png", "histogram.png"}
