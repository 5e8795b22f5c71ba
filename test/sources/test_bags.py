"""Bags as recordings (``open_bag``): topics, poses from odometry, /tf or a pose file,
extrinsics, and a clear error for every bag that cannot be used."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mfp_mapper.config.replay_options import ReplayError, ReplayOptions
from mfp_mapper.config.schema import xyz_rpy
from mfp_mapper.sensing.poses import quaternion_to_matrix
from mfp_mapper.sources.bags import bag_extent, open_bag
from mfp_mapper.sources.simulate import VELODYNE_DTYPE, VELODYNE_FIELDS, BagSink, preset, simulate

SMALL = replace(preset("small"), scans=4, azimuths=120)
OPTS = ReplayOptions()


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    return {
        "mcap": simulate(root / "mcap", SMALL, "mcap").bag,
        "tf_only": simulate(root / "tf", replace(SMALL, odom_topic=None, write_tf=True)).bag,
        "no_static": simulate(root / "ns", replace(SMALL, write_tf_static=False)).bag,
        "base_frame": simulate(
            root / "base", replace(SMALL, cloud_in_base_frame=True, write_tf_static=False)
        ).bag,
    }


def test_a_bag_with_odometry(bags: dict[str, Path]) -> None:
    with open_bag(bags["mcap"], OPTS) as recording:
        assert recording.name == str(bags["mcap"])
        assert recording.cloud_source == "/velodyne_points" and recording.cloud_count == 4
        assert recording.cloud_frame == "velodyne" and recording.map_frame == "odom"
        assert recording.poses.body == "base_link" and "/odom" in recording.poses.source
        assert recording.extrinsic_source.startswith("/tf_static base_link <- velodyne")
        extrinsic = recording.extrinsic_of("velodyne")
        np.testing.assert_allclose(extrinsic.translation, SMALL.lidar_translation)
        clouds = list(recording.clouds())
        assert [c.position for c in clouds] == [0, 1, 2, 3]
        stamps = [c.load().header.stamp.sec for c in clouds]
        assert stamps == [c.load().header.stamp.sec for c in recording.clouds()]  # again


def test_poses_from_the_tf_chain(bags: dict[str, Path]) -> None:
    with open_bag(bags["tf_only"], OPTS) as recording:
        assert recording.poses.source == "/tf chain odom -> base_link"
        assert recording.map_frame == "odom"
    with pytest.raises(ReplayError, match="no /tf transforms"):  # use_tf: not its odometry
        open_bag(bags["mcap"], OPTS.but(use_tf_poses=True))


def test_poses_from_a_tum_file_matched_by_stamp(bags: dict[str, Path], tmp_path: Path) -> None:
    tum = tmp_path / "lidar.tum"
    tum.write_text("1699999990 1 2 3 0 0 0 1\n1700000010 1 2 3 0 0 0 1\n")
    with open_bag(bags["mcap"], OPTS.but(odom_max_gap=30.0), tum) as recording:
        assert recording.map_frame == "world" and recording.poses.body == "velodyne"
        assert recording.extrinsic_source.startswith("identity")  # the poses are the lidar's
        position, _ = recording.pose_source.interpolate([1700000000.0])
        np.testing.assert_allclose(position, [[1.0, 2.0, 3.0]])
    with open_bag(bags["mcap"], OPTS, "identity") as recording:
        assert recording.map_frame == "velodyne" and recording.poses.source == "identity"
    kitti = tmp_path / "poses.txt"
    kitti.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(ReplayError, match="KITTI poses have no stamps"):
        open_bag(bags["mcap"], OPTS, kitti)


def test_extrinsics(bags: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(ReplayError, match="no lidar extrinsic"):
        open_bag(bags["no_static"], OPTS)
    mount = xyz_rpy(SMALL.lidar_translation, SMALL.lidar_rpy)
    with open_bag(bags["no_static"], OPTS.but(config_extrinsic=mount)) as recording:
        assert "configuration" in recording.extrinsic_source
        rotation = quaternion_to_matrix(recording.extrinsic_of("velodyne").quaternion)
        assert np.arctan2(rotation[1, 0], rotation[0, 0]) == pytest.approx(SMALL.lidar_rpy[2])
    with open_bag(bags["mcap"], OPTS.but(extrinsic=xyz_rpy([0, 0, 1], [0, 0, 0]))) as rec:
        assert rec.extrinsic_source == "given on the command line"
        np.testing.assert_allclose(rec.extrinsic_of("velodyne").translation, [0, 0, 1])
    with open_bag(bags["base_frame"], OPTS) as recording:
        assert recording.extrinsic_source.startswith("identity")


def test_missing_or_wrong_topic(bags: dict[str, Path]) -> None:
    with pytest.raises(ReplayError, match="/points is not in the bag"):
        open_bag(bags["mcap"], OPTS.but(cloud_topic="/points"))
    with pytest.raises(ReplayError, match="expected sensor_msgs/msg/PointCloud2"):
        open_bag(bags["mcap"], OPTS.but(cloud_topic="/odom"))


def test_several_cloud_topics_need_a_choice(tmp_path: Path) -> None:
    bag = tmp_path / "two"
    with BagSink(bag, "mcap") as sink:
        for topic in ("/a", "/b"):
            sink.add(topic, "sensor_msgs/msg/PointCloud2")
    with pytest.raises(ReplayError, match="several PointCloud2 topics"):
        open_bag(bag, OPTS)


def test_unreadable_and_missing_bags(tmp_path: Path) -> None:
    with pytest.raises(ReplayError, match="no such file"):
        open_bag(tmp_path / "nope.bag", OPTS)
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + b"\x00garbage" * 50)
    with pytest.raises(ReplayError, match="cannot read the bag"):
        open_bag(junk, OPTS)
    folder = tmp_path / "folder"
    folder.mkdir()
    with pytest.raises(ReplayError, match="metadata.yaml"):
        open_bag(folder, OPTS)
    (folder / "metadata.yaml").write_text("this: is not a bag\n")
    with pytest.raises(ReplayError, match="cannot read the bag"):
        open_bag(folder, OPTS)


def test_a_bag_damaged_part_way_names_the_message_reached(tmp_path: Path) -> None:
    bag = simulate(tmp_path / "sq", replace(preset("small"), scans=20), "sqlite3").bag
    db = next(bag.glob("*.db3"))
    raw = bytearray(db.read_bytes())
    raw[len(raw) // 2 : len(raw) // 2 + 8192] = b"\xab" * 8192
    db.write_bytes(bytes(raw))
    with pytest.raises(ReplayError, match="cannot read the bag"), open_bag(bag, OPTS) as recording:
        for cloud in recording.clouds():
            cloud.load()


def test_bag_without_poses(tmp_path: Path) -> None:
    bag = tmp_path / "nopose"
    with BagSink(bag, "mcap") as sink:
        sink.add("/cloud", "sensor_msgs/msg/PointCloud2")
        records = np.zeros(4, dtype=VELODYNE_DTYPE)
        sink.write("/cloud", 1.0, sink.pointcloud(1.0, "velodyne", records, VELODYNE_FIELDS))
    with pytest.raises(ReplayError, match="no poses"):
        open_bag(bag, OPTS)


def test_ros2_file_path_means_its_folder_and_the_extent(bags: dict[str, Path]) -> None:
    mcap_file = next(bags["mcap"].glob("*.mcap"))
    with open_bag(mcap_file, OPTS) as recording:
        assert recording.name == str(bags["mcap"])
    first, last, clouds = bag_extent(mcap_file)
    assert clouds == 4 and first < SMALL.start_time < last


def test_an_undecodable_first_cloud_is_a_replay_error_for_every_pose_source(
    tmp_path: Path,
) -> None:
    """KISS-ICP and a pose file read the first cloud's frame first: a cloud that cannot be
    deserialized says so (with KISS-ICP it was a traceback)."""
    bag = tmp_path / "garbage"
    with BagSink(bag, "mcap") as sink:
        sink.add("/cloud", "sensor_msgs/msg/PointCloud2")
        sink.writer.write(sink.connections["/cloud"], 1_000_000_000, b"\x00\x01\x00\x00bad")
    with pytest.raises(ReplayError, match="cannot read the first cloud"):
        open_bag(bag, OPTS.but(odometry="kiss-icp"))
    with pytest.raises(ReplayError, match="cannot read the first cloud"):
        open_bag(bag, OPTS, "identity")
