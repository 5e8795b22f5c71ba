"""KISS-ICP poses (``--odometry kiss-icp``) against recordings with known poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from odometry_scenes import lidar_truth, pose_errors, structured_recording

from mfp_mapper.mapping.replay import ReplayOptions, replay
from mfp_mapper.sensing.poses import quaternion_to_matrix
from mfp_mapper.sources.bags import ReplayError
from mfp_mapper.sources.lidar_odometry import MAP_FRAME, kiss_icp_available
from mfp_mapper.sources.opener import open_recording
from mfp_mapper.sources.pose_files import read_odometry_csv
from mfp_mapper.sources.scan_folder import folder_poses, open_scan_folder
from mfp_mapper.sources.simulate import simulate

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not kiss_icp_available(), reason="kiss-icp is not installed"),
]
RES = 0.1


@pytest.fixture(scope="module")
def structured(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    cfg = structured_recording(scans=20)
    return cfg, simulate(tmp_path_factory.mktemp("kiss") / "bag", cfg, "mcap").bag


def _world_from_first_lidar(cfg, stamp: float) -> np.ndarray:  # type: ignore[no-untyped-def]
    return lidar_truth(cfg, np.array([stamp]))[0]


def test_walls_within_a_voxel(structured) -> None:  # type: ignore[no-untyped-def]
    """Mapped with KISS-ICP's poses, the hall's walls land within a voxel of the truth."""
    cfg, bag = structured
    result = replay(bag, ReplayOptions.of(resolution=RES, odometry="kiss-icp"), progress=False)
    assert result.mapper.frame_id == MAP_FRAME
    assert result.summary.scans_used == cfg.scans and "KISS-ICP" in result.summary.pose_source
    # KISS-ICP's map frame is the lidar at the end of the first (de-skewed) scan
    first_end = result.summary.first_stamp + cfg.scan_period * (1 - 1 / cfg.azimuths)
    to_world = _world_from_first_lidar(cfg, first_end)
    v = result.mapper.voxels(min_doo=0.5)
    centres = v.centers @ to_world[:3, :3].T + to_world[:3, 3]
    lo, hi = np.array(cfg.scene.room_lo), np.array(cfg.scene.room_hi)
    errors = []
    for axis, plane in ((0, lo[0]), (0, hi[0]), (1, lo[1]), (1, hi[1])):
        other = 1 - axis
        near = (
            (np.abs(centres[:, axis] - plane) < 0.6)
            & (centres[:, other] > lo[other] + 1.5)
            & (centres[:, other] < hi[other] - 1.5)
            & (centres[:, 2] > 1.0)
            & (centres[:, 2] < 3.5)
        )
        assert near.sum() > 50
        errors.append(np.abs(centres[near, axis] - plane))
    distance = np.concatenate(errors)
    # a voxel centre of a wall voxel is at most half a voxel inside: allow one voxel more
    assert np.median(distance) <= RES
    assert np.percentile(distance, 90) <= 1.5 * RES


def test_pose_error_on_the_structured_hall(structured) -> None:  # type: ignore[no-untyped-def]
    from mfp_mapper.sources.bags import open_reader
    from mfp_mapper.sources.lidar_odometry import estimate_poses

    cfg, bag = structured
    reader = open_reader(bag)
    try:
        conns = [c for c in reader.connections if c.msgtype == "sensor_msgs/msg/PointCloud2"]
        clouds = (
            (None, lambda c=c, r=r: reader.deserialize(r, c.msgtype))
            for c, _, r in reader.messages(connections=conns)
        )
        # max range 30 m: KISS-ICP's voxel (max range / 100) 0.3 m, as fits a 20 m hall
        stamps, poses = estimate_poses(clouds, ReplayOptions.of(max_range=30.0))
    finally:
        reader.close()
    translation, rotation = pose_errors(poses, lidar_truth(cfg, stamps))
    assert translation.max() < 0.1  # measured 0.062 m over a 3.2 m path
    assert np.degrees(rotation.max()) < 2.0  # measured 1.09 deg


def test_norlab_sequence_against_its_icp_odometry(shared_data: Path) -> None:
    """Real scans: KISS-ICP's poses agree with the recording's ICP odometry (the robot
    barely moves: a real-geometry, real-noise check)."""
    sequence = shared_data / "norlab_sequence"
    if not sequence.is_dir():
        pytest.skip(f"{sequence} is absent")
    folder = open_scan_folder(sequence / "scans")
    found = folder_poses(folder, None, ReplayOptions.of(odometry="kiss-icp"))
    odometry = read_odometry_csv(sequence / "icp_odom.csv")
    stamps = np.array([scan.stamp for scan in folder.scans])
    est_p, est_r = found.buffer.interpolate(stamps)
    ref = np.tile(np.eye(4), (len(stamps), 1, 1))
    est = ref.copy()
    order = np.argsort(odometry["stamp"])
    for k, stamp in enumerate(stamps):
        j = order[np.argmin(np.abs(odometry["stamp"][order] - stamp))]
        ref[k, :3, :3] = quaternion_to_matrix(odometry["quaternion"][j])
        ref[k, :3, 3] = odometry["position"][j]
        est[k, :3, :3], est[k, :3, 3] = est_r[k], est_p[k]
    translation, rotation = pose_errors(est, ref)
    assert translation.max() < 0.05
    assert np.degrees(rotation.max()) < 0.5


def test_a_clear_error_without_poses_or_with_both(tmp_path: Path) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    np.zeros((10, 4), "<f4").tofile(folder / "000000.bin")
    with pytest.raises(ReplayError, match="either --poses or --odometry"):
        open_recording(folder, ReplayOptions.of(odometry="kiss-icp"), "identity")
