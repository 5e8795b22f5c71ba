"""The built-in example simulator: geometry, free-path statistics, bags and ground truth."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mfp_mapper.sensing.pointcloud import parse_pointcloud2
from mfp_mapper.sources.simulate import (
    SURFACE_FLOOR,
    SURFACE_MEDIUM,
    SURFACE_WALL,
    Medium,
    Scene,
    SimulationError,
    Solid,
    generate_scans,
    load_truth,
    preset,
    simulate,
    truth_path_for,
)


def test_cast_hits_floor_walls_and_solids() -> None:
    scene = Scene(
        room_lo=(-5, -5, 0), room_hi=(5, 5, 3), solids=(Solid("s", (2, -1, 0), (3, 1, 2)),)
    )
    o = np.array([0.0, 0.0, 1.0])
    d = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, -1.0], [0, 0, 1.0]])
    r, code = scene.cast(o, d, np.random.default_rng(0))
    np.testing.assert_allclose(r, [2.0, 5.0, 1.0, 2.0])
    assert code[1] == SURFACE_WALL and code[2] == SURFACE_FLOOR


def test_first_returns_follow_the_exponential_free_path() -> None:
    lam = 0.8
    scene = Scene(room_lo=(-50, -50, -50), room_hi=(50, 50, 50),
                  media=(Medium("m", (1, -5, -5), (21, 5, 5), lam),))  # fmt: skip
    n = 200_000
    d = np.tile([1.0, 0.0, 0.0], (n, 1))
    r, code = scene.cast(np.zeros(3), d, np.random.default_rng(1))
    inside = code == SURFACE_MEDIUM
    depth = r[inside] - 1.0
    # truncated exponential on [0, 20]: the share returning and the mean depth
    p_return = 1 - np.exp(-lam * 20)
    assert abs(inside.mean() - p_return) < 0.005
    assert abs(depth.mean() - (1 / lam - 20 * np.exp(-lam * 20) / p_return)) < 0.01
    assert np.all(r[~inside] == pytest.approx(50.0))  # the rest reach the far wall


def test_overlapping_media_are_rejected() -> None:
    scene = Scene(
        media=(Medium("a", (0, 0, 0), (2, 2, 2), 1.0), Medium("b", (1, 1, 1), (3, 3, 3), 1.0))
    )
    with pytest.raises(SimulationError, match="overlap"):
        scene.validate()


def test_closed_scene_returns_every_ray_open_scene_does_not() -> None:
    closed = replace(preset("small"), scans=2, azimuths=180)
    opened = replace(preset("open"), scans=2, azimuths=180)
    for scan in generate_scans(closed):
        assert scan.omitted == 0 and scan.xyz.shape[0] == scan.rays
    lost = [s for s in generate_scans(opened)]
    assert sum(s.omitted for s in lost) > 0
    assert sum(s.omitted_through_media for s in lost) > 0


def test_scans_are_seeded() -> None:
    cfg = replace(preset("small"), scans=1, azimuths=90)
    a = next(generate_scans(cfg)).xyz
    b = next(generate_scans(cfg)).xyz
    c = next(generate_scans(replace(cfg, seed=1))).xyz
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize(("fmt", "name"), [("mcap", "b"), ("sqlite3", "b"), ("ros1", "b.bag")])
def test_bag_holds_odometry_tf_static_and_velodyne_clouds(
    tmp_path: Path, fmt: str, name: str
) -> None:
    from rosbags.highlevel import AnyReader

    cfg = replace(preset("small"), scans=3, azimuths=120, write_tf=True)
    result = simulate(tmp_path / name, cfg, fmt)
    assert result.truth_path == truth_path_for(result.bag)
    truth = load_truth(result.truth_path)
    assert truth["storage"] == fmt
    assert truth["rays"]["omitted"] == 0
    with AnyReader([result.bag]) as reader:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        assert topics["/velodyne_points"] == ("sensor_msgs/msg/PointCloud2", 3)
        assert topics["/odom"][0] == "nav_msgs/msg/Odometry"
        assert topics["/tf_static"] == ("tf2_msgs/msg/TFMessage", 1)
        assert topics["/tf"][0] == "tf2_msgs/msg/TFMessage"
        conn = next(c for c in reader.connections if c.topic == "/velodyne_points")
        _, stamp_ns, raw = next(reader.messages(connections=[conn]))
        msg = reader.deserialize(raw, conn.msgtype)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "ring", "time"]
    assert msg.point_step == 22 and msg.fields[4].datatype == 4  # ring: UINT16
    assert msg.header.frame_id == "velodyne"
    cloud = parse_pointcloud2(msg)
    assert len(cloud) == 16 * 120
    assert cloud.time_offset is not None
    assert cloud.time_offset.min() >= 0.0 and cloud.time_offset.max() < 0.1
    # the cloud is recorded once its rotation is complete
    stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
    assert stamp_ns * 1e-9 == pytest.approx(stamp + 0.1, abs=1e-6)


def test_simulate_refuses_to_overwrite_and_checks_format(tmp_path: Path) -> None:
    cfg = replace(preset("small"), scans=1, azimuths=60)
    simulate(tmp_path / "b", cfg)
    with pytest.raises(SimulationError, match="exists"):
        simulate(tmp_path / "b", cfg)
    simulate(tmp_path / "b", cfg, overwrite=True)
    with pytest.raises(SimulationError, match="ROS 1"):
        simulate(tmp_path / "c", cfg, "ros1")


def test_truth_json_describes_the_scene(tmp_path: Path) -> None:
    result = simulate(tmp_path / "b", replace(preset("demo"), scans=1, azimuths=60))
    data = json.loads(result.truth_path.read_text())
    names = {m["name"]: m for m in data["scene"]["media"]}
    assert names["bush"]["extinction"] == 1.0 and names["hedge"]["mean_free_path"] == 2.5
    assert data["scene"]["enclosed"] is True
    assert data["frames"] == {
        "odom": "odom",
        "base": "base_link",
        "lidar": "velodyne",
        "cloud": "velodyne",
    }
    bad = tmp_path / "x.json"
    bad.write_text("{}")
    with pytest.raises(SimulationError):
        load_truth(bad)
