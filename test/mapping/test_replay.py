"""Replaying bags: formats, topic detection, poses from Odometry or /tf, extrinsics, bad bags."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mfp_mapper.config.schema import xyz_rpy
from mfp_mapper.mapping.replay import (
    Progress,
    ReplayError,
    ReplayOptions,
    options_from_yaml,
    replay,
)
from mfp_mapper.sensing.poses import rpy_to_quaternion
from mfp_mapper.sources.simulate import VELODYNE_DTYPE, VELODYNE_FIELDS, BagSink, preset, simulate

SMALL = replace(preset("small"), scans=6, azimuths=240)
RES = 0.25


def _bag(root: Path, name: str, fmt: str | None = None, **changes: object) -> Path:
    return simulate(root / name, replace(SMALL, **changes), fmt).bag


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    return {
        "mcap": _bag(root, "mcap", "mcap"),
        "sqlite3": _bag(root, "sqlite3", "sqlite3"),
        "ros1": _bag(root, "run.bag", "ros1"),
        "tf_only": _bag(root, "tf_only", odom_topic=None, write_tf=True),
        "base_frame": _bag(root, "base_frame", cloud_in_base_frame=True, write_tf_static=False),
        "no_static": _bag(root, "no_static", write_tf_static=False),
    }


def _stats(bag: Path, **opts: object) -> tuple[np.ndarray, np.ndarray, object]:
    result = replay(bag, ReplayOptions.of(resolution=RES, **opts), progress=False)
    v = result.mapper.voxels()
    order = np.lexsort(v.ijk.T)
    return v.ijk[order], np.stack([v.s[order], v.n[order]]), result.summary


@pytest.fixture(scope="module")
def reference(bags: dict[str, Path]) -> tuple[np.ndarray, np.ndarray, object]:
    return _stats(bags["mcap"])


@pytest.mark.parametrize("fmt", ["sqlite3", "ros1"])
def test_all_storage_formats_give_the_same_map(bags, reference, fmt: str) -> None:  # type: ignore[no-untyped-def]
    ijk, sn, summary = _stats(bags[fmt])
    np.testing.assert_array_equal(ijk, reference[0])
    np.testing.assert_allclose(sn, reference[1], rtol=1e-9, atol=1e-9)
    assert summary.scans_used == SMALL.scans


def test_summary_of_a_replay(bags, reference) -> None:  # type: ignore[no-untyped-def]
    summary = reference[2]
    assert summary.cloud_topic == "/velodyne_points"
    assert summary.map_frame == "odom" and summary.cloud_frame == "velodyne"
    assert "/odom" in summary.pose_source
    assert summary.extrinsic_source.startswith("/tf_static")
    assert summary.deskew
    assert summary.scans_total == summary.scans_used == SMALL.scans
    assert summary.points_in == summary.rays_used == SMALL.scans * SMALL.azimuths * 16
    assert summary.voxels > 0 and 0.0 <= summary.share_outside_core <= 1.0
    text = summary.format()
    assert "rays/s" in text and "outside the core" in text


def test_explicit_topics_match_auto_detection(bags, reference) -> None:  # type: ignore[no-untyped-def]
    ijk, sn, _ = _stats(bags["mcap"], cloud_topic="/velodyne_points", odom_topic="/odom")
    np.testing.assert_array_equal(ijk, reference[0])
    np.testing.assert_allclose(sn, reference[1])


def test_poses_from_the_tf_chain(bags, reference) -> None:  # type: ignore[no-untyped-def]
    ijk, sn, summary = _stats(bags["tf_only"])
    assert summary.pose_source.startswith("/tf chain odom -> base_link")
    np.testing.assert_array_equal(ijk, reference[0])
    np.testing.assert_allclose(sn, reference[1], rtol=1e-6, atol=1e-6)


def test_extrinsic_from_tf_static_matters(bags, reference) -> None:  # type: ignore[no-untyped-def]
    # the bag's /tf_static holds the true mount; a wrong one given explicitly moves the map
    wrong = xyz_rpy([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    ijk, _, summary = _stats(bags["mcap"], extrinsic=wrong)
    assert summary.extrinsic_source == "given on the command line"
    assert ijk.shape != reference[0].shape or not np.array_equal(ijk, reference[0])
    # the true one given explicitly reproduces the /tf_static map
    t, rpy = SMALL.lidar_translation, SMALL.lidar_rpy
    ijk2, sn2, _ = _stats(bags["no_static"], extrinsic=xyz_rpy(t, rpy))
    np.testing.assert_array_equal(ijk2, reference[0])
    np.testing.assert_allclose(sn2, reference[1], rtol=1e-6, atol=1e-6)


def test_identity_when_the_cloud_is_in_the_odometry_child_frame(bags, reference) -> None:  # type: ignore[no-untyped-def]
    ijk, sn, summary = _stats(bags["base_frame"])
    assert summary.extrinsic_source.startswith("identity")
    # same returns (rays now start at the base_link origin, so the crossed voxels differ)
    hit_ref = {tuple(v): n for v, n in zip(reference[0], reference[1][1], strict=True) if n > 0}
    hit = {tuple(v): n for v, n in zip(ijk, sn[1], strict=True) if n > 0}
    assert sum(hit.values()) == sum(hit_ref.values())
    same = sum(1 for k in hit if k in hit_ref and hit[k] == hit_ref[k])
    assert same >= 0.97 * len(hit_ref)  # float32 points on the floor z = 0 may change voxel


def test_missing_extrinsic_is_an_error_unless_configured(bags, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ReplayError, match="no lidar extrinsic"):
        replay(bags["no_static"], ReplayOptions.of(resolution=RES), progress=False)
    cfg = tmp_path / "node.yaml"
    t, rpy = SMALL.lidar_translation, SMALL.lidar_rpy
    cfg.write_text(
        "mfp_mapper:\n  ros__parameters:\n    resolution: 0.25\n"
        "    sensor_model:\n      max_range: 0.0\n"
        f"    lidar.translation: {list(t)}\n    lidar.rpy: {list(rpy)}\n"
    )
    opts = options_from_yaml(cfg)
    assert opts["resolution"] == 0.25 and opts["max_range"] == 0.0  # no limit to the core
    result = replay(bags["no_static"], ReplayOptions.of(**opts), progress=False)
    assert "configuration" in result.summary.extrinsic_source


def test_unknown_config_parameter_is_an_error(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("/**:\n  ros__parameters:\n    resolution: 0.2\n    resolutoin: 0.1\n")
    with pytest.raises(ReplayError, match="resolutoin"):
        options_from_yaml(cfg)
    # rcl cannot read a file without a node section: neither can --config (a former leniency)
    cfg.write_text("resolution: 0.2\n")
    with pytest.raises(ReplayError, match="ros__parameters"):
        options_from_yaml(cfg)


def test_missing_or_wrong_topic(bags) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ReplayError, match="/points is not in the bag"):
        replay(bags["mcap"], ReplayOptions.of(cloud_topic="/points"), progress=False)
    with pytest.raises(ReplayError, match="expected sensor_msgs/msg/PointCloud2"):
        replay(bags["mcap"], ReplayOptions.of(cloud_topic="/odom"), progress=False)


def test_several_cloud_topics_need_a_choice(tmp_path: Path) -> None:
    bag = tmp_path / "two"
    with BagSink(bag, "mcap") as sink:
        for topic in ("/a", "/b"):
            sink.add(topic, "sensor_msgs/msg/PointCloud2")
    with pytest.raises(ReplayError, match="several PointCloud2 topics"):
        replay(bag, progress=False)


def test_unreadable_and_missing_bags(tmp_path: Path) -> None:
    with pytest.raises(ReplayError, match="no such file"):
        replay(tmp_path / "nope.bag", progress=False)
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + b"\x00garbage" * 50)
    with pytest.raises(ReplayError, match="cannot read the bag"):
        replay(junk, progress=False)
    folder = tmp_path / "folder"
    folder.mkdir()
    with pytest.raises(ReplayError, match="metadata.yaml"):
        replay(folder, progress=False)
    (folder / "metadata.yaml").write_text("this: is not a bag\n")
    with pytest.raises(ReplayError, match="cannot read the bag"):
        replay(folder, progress=False)


def _bag_with_late_clouds(path: Path) -> Path:
    """Odometry for t in [0, 1] s, clouds at t = 100 s: no pose covers them."""
    records = np.zeros(10, dtype=VELODYNE_DTYPE)
    records["x"] = 2.0
    with BagSink(path, "sqlite3") as sink:
        sink.add("/odom", "nav_msgs/msg/Odometry")
        sink.add("/cloud", "sensor_msgs/msg/PointCloud2")
        q = rpy_to_quaternion(0, 0, 0)
        for t in np.arange(0.0, 1.0, 0.1):
            sink.write("/odom", t, sink.odometry(t, "odom", "base_link", np.zeros(3), q, 0, 0))
        for t in (100.0, 100.1):
            sink.write("/cloud", t, sink.pointcloud(t, "base_link", records, VELODYNE_FIELDS))
    return path


def test_no_pose_covering_the_clouds(tmp_path: Path) -> None:
    bag = _bag_with_late_clouds(tmp_path / "late")
    with pytest.raises(ReplayError, match="No pose covers the clouds") as info:
        replay(bag, progress=False)
    assert "too_new 2" in str(info.value)


def test_bag_without_poses(tmp_path: Path) -> None:
    bag = tmp_path / "nopose"
    with BagSink(bag, "mcap") as sink:
        sink.add("/cloud", "sensor_msgs/msg/PointCloud2")
        records = np.zeros(4, dtype=VELODYNE_DTYPE)
        sink.write("/cloud", 1.0, sink.pointcloud(1.0, "velodyne", records, VELODYNE_FIELDS))
    with pytest.raises(ReplayError, match="no poses"):
        replay(bag, progress=False)


def test_ros2_file_path_means_its_folder(bags) -> None:  # type: ignore[no-untyped-def]
    mcap_file = next(bags["mcap"].glob("*.mcap"))
    result = replay(mcap_file, ReplayOptions.of(resolution=RES, max_scans=2), progress=False)
    assert result.summary.scans_used == 2


def test_progress_line_reports_rate_and_time_left() -> None:
    import io

    stream = io.StringIO()
    bar = Progress(10, stream=stream, interval=0.0)
    bar.update(5, 50_000, force=True)
    text = stream.getvalue()
    assert "5/10 scans" in text and "rays/s" in text and "left" in text


def test_keep_radius_reaches_the_mapper(bags) -> None:  # type: ignore[no-untyped-def]
    full = replay(bags["mcap"], ReplayOptions.of(resolution=RES), progress=False).mapper
    near = replay(bags["mcap"], ReplayOptions.of(resolution=RES, keep_radius=1.0), progress=False)
    assert near.mapper.keep_radius == 1.0 and full.keep_radius is None
    assert 0 < near.mapper.num_voxels < full.num_voxels
