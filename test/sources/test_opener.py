"""One way to open a recording (``open_recording``): a bag, a bag with a pose file, a scan
folder with a pose file, KISS-ICP poses, the simulator; what each says about its poses."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from folder_helpers import write_pcd

from mfp_mapper.config.replay_options import ReplayError, ReplayOptions
from mfp_mapper.sensing.pipeline import scan_stamp
from mfp_mapper.sources.lidar_odometry import MAP_FRAME, kiss_icp_available
from mfp_mapper.sources.opener import open_recording, opened
from mfp_mapper.sources.recording import Recording
from mfp_mapper.sources.simulate import TruthPoses, preset, simulate

SMALL = replace(preset("small"), scans=4, azimuths=120)


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate(tmp_path_factory.mktemp("opener") / "bag", SMALL, "mcap").bag


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    scans = tmp_path / "scans"
    scans.mkdir()
    for k in range(3):
        xyz = np.array([[4.0, 0.0, 0.0], [0.0, 4.0, 0.5]], dtype="<f4")
        write_pcd(scans / f"cloud_{100 + k}_0.pcd", {"x": xyz[:, 0], "y": xyz[:, 1],
                                                      "z": xyz[:, 2]})  # fmt: skip
    return scans


def test_a_bag_with_its_own_poses(bag: Path) -> None:
    with open_recording(bag) as recording:
        assert isinstance(recording, Recording)
        assert recording.map_frame == "odom" and "nav_msgs/Odometry" in recording.poses.source
        assert len(list(recording.clouds())) == SMALL.scans


def test_a_bag_with_a_pose_file(bag: Path, tmp_path: Path) -> None:
    tum = tmp_path / "poses.tum"
    tum.write_text("1699999999 0 0 0 0 0 0 1\n1700000001 0 0 0 0 0 0 1\n")
    with open_recording(bag, ReplayOptions.of(odom_max_gap=5.0), poses=tum) as recording:
        assert recording.map_frame == "world" and recording.poses.source.startswith(str(tum))


def test_a_scan_folder_with_a_pose_file(folder: Path, tmp_path: Path) -> None:
    tum = tmp_path / "poses.tum"
    tum.write_text("99 0 0 0 0 0 0 1\n103 1 0 0 0 0 0 1\n")
    with open_recording(folder, poses=tum) as recording:
        assert recording.cloud_source == "3 .pcd files (stamps: file names)"
        assert recording.map_frame == "world" and "TUM" in recording.poses.source
        stamps = [scan_stamp(cloud.load()) for cloud in recording.clouds()]
        assert stamps == [100.0, 101.0, 102.0]


@pytest.mark.skipif(not kiss_icp_available(), reason="kiss-icp is not installed")
def test_kiss_icp_estimated_poses(bag: Path) -> None:
    with open_recording(bag, ReplayOptions.of(odometry="kiss-icp")) as recording:
        assert recording.map_frame == MAP_FRAME and recording.poses.body == "velodyne"
        assert recording.poses.source.startswith("KISS-ICP on the clouds")
        assert recording.extrinsic_source.startswith("identity")
        assert len(recording.poses.buffer) >= SMALL.scans


def test_the_simulator_with_its_true_poses(bag: Path) -> None:
    with open_recording(SMALL) as recording:
        assert isinstance(recording.pose_source, TruthPoses)
        assert recording.map_frame == "odom" and recording.poses.body == "base_link"
        assert recording.cloud_frame == "velodyne" and recording.cloud_count == SMALL.scans
        clouds = [cloud.load() for cloud in recording.clouds()]
    # the clouds the bag of the same configuration holds, byte for byte
    with open_recording(bag) as from_bag:
        recorded = [cloud.load() for cloud in from_bag.clouds()]
    assert len(clouds) == len(recorded)
    for made, read in zip(clouds, recorded, strict=True):
        assert scan_stamp(made) == pytest.approx(scan_stamp(read), abs=1e-9)
        assert (made.height, made.width, made.point_step) == (read.height, read.width,
                                                              read.point_step)  # fmt: skip
        assert bytes(made.data) == bytes(read.data)
        assert [f.name for f in made.fields] == [f.name for f in read.fields]
    # the true pose is the odometry the bag recorded at its samples
    with open_recording(bag) as from_bag, open_recording(SMALL) as simulated:
        stamps = SMALL.start_time + np.array([0.0, 0.1, 0.22])
        odom_p, odom_r = from_bag.pose_source.interpolate(stamps)
        true_p, true_r = simulated.pose_source.interpolate(stamps)
        np.testing.assert_allclose(true_p, odom_p, atol=1e-3)
        np.testing.assert_allclose(true_r, odom_r, atol=1e-3)


def test_flags_that_do_not_fit_the_recording(bag: Path, folder: Path, tmp_path: Path) -> None:
    times = tmp_path / "times.txt"
    times.write_text("0\n")
    with pytest.raises(ReplayError, match="--times is for folders of scan files"):
        open_recording(bag, times=times)
    with pytest.raises(ReplayError, match="either --poses or --odometry"):
        open_recording(folder, ReplayOptions.of(odometry="kiss-icp"), poses="identity")
    with pytest.raises(ReplayError, match="true poses"):
        open_recording(SMALL, poses="identity")
    with pytest.raises(ReplayError, match="no such file"):
        open_recording(tmp_path / "absent")


def test_opened_closes_only_what_it_opened(bag: Path) -> None:
    closed: list[str] = []
    with open_recording(SMALL) as recording:
        recording.release = lambda: closed.append("given")
        with opened(recording) as same:
            assert same is recording
        assert closed == []
    assert closed == ["given"]
    with opened(bag) as own:
        assert own.map_frame == "odom"
