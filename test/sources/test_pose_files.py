"""Pose files (``--poses``): one reader, ``read_poses``, for scan folders and bags."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mfp_mapper.config.replay_options import ReplayError
from mfp_mapper.sensing.poses import quaternion_to_matrix
from mfp_mapper.sources.pose_files import FixedPose, matrix_to_quaternion, read_poses

QUARTER_TURN = [0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)]  # xyzw, 90 deg about z


def test_matrix_to_quaternion_round_trip() -> None:
    rng = np.random.default_rng(1)
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[:4] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    back = matrix_to_quaternion(quaternion_to_matrix(q))
    np.testing.assert_allclose(np.abs(np.sum(back * q, axis=1)), 1.0, atol=1e-12)


def test_identity_is_every_scan_at_the_origin_of_its_frame() -> None:
    poses = read_poses("identity", "lidar", 0.5)
    assert isinstance(poses.buffer, FixedPose)
    assert poses.body == poses.map_frame == "lidar" and poses.source == "identity"
    position, rotation = poses.buffer.interpolate([1.0, 1e9])
    np.testing.assert_array_equal(position, np.zeros((2, 3)))
    np.testing.assert_array_equal(rotation, np.broadcast_to(np.eye(3), (2, 3, 3)))


def test_tum_poses_are_matched_by_stamp(tmp_path: Path) -> None:
    tum = tmp_path / "poses.tum"
    tum.write_text("# t x y z qx qy qz qw\n10 0 0 0 0 0 0 1\n12 2 0 0 " +
                   " ".join(map(str, QUARTER_TURN)) + "\n")  # fmt: skip
    poses = read_poses(tum, "velodyne", 5.0)
    assert poses.map_frame == "world" and poses.body == "velodyne"
    assert poses.source == f"{tum} (TUM, T_world_lidar)"
    position, rotation = poses.buffer.interpolate([11.0])
    np.testing.assert_allclose(position, [[1.0, 0.0, 0.0]])
    yaw = math.atan2(rotation[0, 1, 0], rotation[0, 0, 0])
    assert yaw == pytest.approx(math.pi / 4)


def test_odometry_csv_is_matched_by_stamp(tmp_path: Path) -> None:
    csv = tmp_path / "odom.csv"
    columns = ["header.stamp.sec", "header.stamp.nanosec"]
    columns += [f"pose.pose.position.{a}" for a in "xyz"]
    columns += [f"pose.pose.orientation.{a}" for a in "xyzw"]
    csv.write_text(",".join(columns) + "\n5,0,0,0,0,0,0,0,1\n5,500000000,1,0,0,0,0,0,1\n")
    poses = read_poses(csv, "lidar", 1.0)
    assert poses.source == f"{csv} (odometry CSV, T_map_body)"
    position, _ = poses.buffer.interpolate([5.25])
    np.testing.assert_allclose(position, [[0.5, 0.0, 0.0]])


def test_kitti_poses_need_the_scans_stamps(tmp_path: Path) -> None:
    kitti = tmp_path / "poses.txt"
    kitti.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 3 0 1 0 0 0 0 1 0\n")
    poses = read_poses(kitti, "lidar", 1.0, scan_stamps=[0.0, 0.1])
    assert poses.source == f"{kitti} (KITTI, T_world_lidar)"
    np.testing.assert_allclose(poses.buffer.interpolate([0.1])[0], [[3.0, 0.0, 0.0]])
    with pytest.raises(ReplayError, match="KITTI poses have no stamps"):
        read_poses(kitti, "lidar", 1.0)
    with pytest.raises(ReplayError, match="2 KITTI poses for 3 scans.*skipped: x"):
        read_poses(kitti, "lidar", 1.0, scan_stamps=[0.0, 0.1, 0.2], note="; skipped: x")


def test_bad_pose_files_are_replay_errors(tmp_path: Path) -> None:
    with pytest.raises(ReplayError, match="No such file"):
        read_poses(tmp_path / "absent.tum", "lidar", 1.0)
    bad = tmp_path / "bad.tum"
    bad.write_text("0 0 0 0 0 0 0 1\n0 1 0 0 0 0 0 1\n")
    with pytest.raises(ReplayError, match="repeated stamp"):
        read_poses(bad, "lidar", 1.0)
    odd = tmp_path / "odd.txt"
    odd.write_text("1 2 3\n")
    with pytest.raises(ReplayError, match="cannot tell the pose format"):
        read_poses(odd, "lidar", 1.0)
