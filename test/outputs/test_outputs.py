"""Nav2 map_server maps (PGM + YAML) and mcap bags of a map, read back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml  # type: ignore[import-untyped]

from mfp_mapper.cli import main
from mfp_mapper.core.gridmap import unobserved_hit_probability
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapio.loading import save_map
from mfp_mapper.outputs.mcap_export import DOO_TOPIC, GRID_TOPIC, STD_TOPIC, export_mcap
from mfp_mapper.outputs.nav2_map import read_pgm, write_nav2_map


@pytest.fixture
def ring_map() -> Mapper:
    """Rays from (0, 0, 1) to a ring wall of radius 3 m at z = 1, 30 times: free inside,
    a wall (its hit probability grows with the returns: 5 give about 0.5)."""
    mapper = Mapper(0.1, frame_id="odom")
    angles = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    points = np.stack([3 * np.cos(angles), 3 * np.sin(angles), np.ones_like(angles)], axis=1)
    for k in range(30):
        mapper.integrate(points, np.array([0.0, 0.0, 1.0]), 10.0 + k)
    return mapper


def _map_server_decode(pixels: np.ndarray, meta: dict) -> np.ndarray:  # type: ignore[type-arg]
    """nav2_map_server's trinary rule (map_io.cpp), rows flipped to y-up."""
    occ = (255 - pixels.astype(np.float64)) / 255.0
    if meta["negate"]:
        occ = 1.0 - occ
    out = np.full(pixels.shape, -1, dtype=np.int8)
    out[occ > meta["occupied_thresh"]] = 100
    out[occ < meta["free_thresh"]] = 0
    return np.flipud(out)


def test_nav2_map_reads_back_as_the_thresholded_grid(ring_map: Mapper, tmp_path: Path) -> None:
    nav = write_nav2_map(ring_map, tmp_path / "map.yaml", 0.5, 1.5, 0.65, 0.25)
    meta = yaml.safe_load(nav.yaml.read_text())
    assert meta["image"] == "map.pgm" and meta["mode"] == "trinary"
    assert meta["resolution"] == 0.1 and meta["negate"] == 0
    grid = ring_map.hit_probability_grid(0.5, 1.5)
    assert meta["origin"] == [grid.origin[0], grid.origin[1], 0.0]
    pixels = read_pgm(tmp_path / meta["image"])
    assert pixels.shape == grid.data.shape
    decoded = _map_server_decode(pixels, meta)
    np.testing.assert_array_equal(decoded, nav.occupancy)
    trinary = ring_map.hit_probability_grid(0.5, 1.5, trinary=(0.65, 0.25)).data
    np.testing.assert_array_equal(decoded, trinary)
    # the wall ring is occupied, the inside free, the corners unknown
    row, col = grid.cell_of(3.0, 0.05)
    assert (decoded[row, col - 1 : col + 2] == 100).any()
    row, col = grid.cell_of(1.0, 0.5)
    assert decoded[row, col] == 0
    row, col = grid.cell_of(2.9, 2.9)
    assert decoded[row, col] == -1
    # the percentages are rounded: away from the thresholds they decide alike
    known = (grid.data >= 0) & (abs(grid.data - 65) > 1) & (abs(grid.data - 25) > 1)
    assert np.all((decoded == 100)[known] == (grid.data >= 65)[known])
    assert np.all((decoded == 0)[known] == (grid.data < 25)[known])


def test_thresholds_are_checked(ring_map: Mapper, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="free <= occupied"):
        write_nav2_map(ring_map, tmp_path / "m.yaml", 0.5, 1.5, 0.2, 0.6)


def test_mcap_holds_the_clouds_and_the_grid(ring_map: Mapper, tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out = tmp_path / "map_bag"
    counts = export_mcap(ring_map, out, 0.5, 1.5, min_doo=0.1)
    assert list(out.glob("*.mcap")) and (out / "metadata.yaml").exists()
    stats = ring_map.voxels(min_doo=0.1)
    grid = ring_map.hit_probability_grid(0.5, 1.5)
    seen = {}
    with AnyReader([out], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, stamp, raw in reader.messages():
            seen[conn.topic] = (conn.msgtype, stamp, reader.deserialize(raw, conn.msgtype))
    assert set(seen) == {DOO_TOPIC, STD_TOPIC, GRID_TOPIC}
    for topic, field in ((DOO_TOPIC, "degree_of_occupancy"), (STD_TOPIC, "std")):
        msgtype, stamp, msg = seen[topic]
        assert msgtype == "sensor_msgs/msg/PointCloud2" and stamp == 39 * 10**9
        assert msg.header.frame_id == "odom" and msg.width == len(stats) == counts[topic]
        assert [f.name for f in msg.fields] == ["x", "y", "z", field]
        values = np.frombuffer(bytes(msg.data), dtype="<f4").reshape(msg.width, 4)
        order = np.lexsort(values[:, :3].T)
        ref = np.column_stack(
            [stats.centers, getattr(stats, "most_likely_doo" if field != "std" else "std")]
        )
        ref_order = np.lexsort(ref[:, :3].T)
        np.testing.assert_allclose(values[order], ref[ref_order], rtol=1e-6, atol=1e-6)
    msgtype, _, msg = seen[GRID_TOPIC]
    assert msgtype == "nav_msgs/msg/OccupancyGrid"
    assert (msg.info.width, msg.info.height) == (grid.width, grid.height)
    assert msg.info.origin.position.x == grid.origin[0]
    np.testing.assert_array_equal(np.asarray(msg.data).reshape(grid.data.shape), grid.data)
    with pytest.raises(FileExistsError):
        export_mcap(ring_map, out, 0.5, 1.5)


def test_export_cli_formats(
    ring_map: Mapper, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "ring.npz"
    save_map(ring_map, path)
    assert (
        main(
            [
                "export",
                str(path),
                "-o",
                str(tmp_path / "nav.yaml"),
                "--z-min",
                "0.5",
                "--z-max",
                "1.5",
            ]
        )
        == 0
    )
    assert (tmp_path / "nav.pgm").exists()
    assert (
        main(["export", str(path), "-o", str(tmp_path / "bag"), "--z-min", "0.5", "--z-max", "1.5"])
        == 0
    )
    assert (tmp_path / "bag" / "metadata.yaml").exists()
    assert main(["export", str(path), "-o", str(tmp_path / "v.ply")]) == 0
    out = capsys.readouterr().out
    assert "occupied" in out and "mcap" in out and "voxels" in out


def test_nav2_map_defaults_are_the_nodes_projected_map(ring_map: Mapper, tmp_path: Path) -> None:
    """Without thresholds, the PGM holds exactly what ~/projected_map would (the schema's
    projected_map.* defaults: occupied 0.25, free that of a never-observed voxel)."""
    from mfp_mapper.config.schema import BY_NAME

    nav = write_nav2_map(ring_map, tmp_path / "default.yaml", 0.5, 1.5)
    occupied = BY_NAME["projected_map.occupied_threshold"].default
    free = unobserved_hit_probability(ring_map.resolution)
    expected = ring_map.hit_probability_grid(0.5, 1.5, trinary=(occupied, free)).data
    np.testing.assert_array_equal(nav.occupancy, expected)
    assert (expected == 100).any() and (expected == 0).any()
