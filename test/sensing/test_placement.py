"""Placing a cloud from odometry, TF or both (sensing.placement), and the live worker's
clock and stamp handling — without ROS."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
from live_helpers import drain, odom_sample
from scipy.spatial.transform import Rotation

from mfp_mapper.config.sections import PlacementSection
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.live import LiveIntegrator, LiveSettings
from mfp_mapper.sensing.deskew import cloud_to_map
from mfp_mapper.sensing.pipeline import ScanDropped
from mfp_mapper.sensing.placement import Odometry, resolve_placement
from mfp_mapper.sensing.pointcloud import ParsedCloud
from mfp_mapper.sensing.poses import Extrinsic, PoseBuffer, StampGuard
from mfp_mapper.sensing.tf_tree import TfTree
from mfp_mapper.sources.scan_files import cloud_message_from_columns

T0 = 100.0
MAP_ODOM = (np.array([10.0, -5.0, 0.0]), Rotation.from_euler("z", 0.5).as_quat())
ODOM_BASE = (np.array([2.0, 1.0, 0.0]), Rotation.from_euler("z", -0.3).as_quat())
BASE_LIDAR = (np.array([0.3, 0.0, 1.2]), Rotation.from_euler("xyz", [0.0, 0.1, 0.2]).as_quat())


def matrix(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat(q).as_matrix()
    out[:3, 3] = t
    return out


def robot_tree(with_map: bool = True, with_odom: bool = True) -> TfTree:
    tree = TfTree()
    tree.add("base_link", "lidar", 0.0, *BASE_LIDAR, static=True)
    for stamp in (T0 - 1.0, T0 + 1.0):
        if with_map:
            tree.add("map", "odom", stamp, *MAP_ODOM)
        if with_odom:
            tree.add("odom", "base_link", stamp, *ODOM_BASE)
    return tree


def odometry() -> Odometry:
    buffer = PoseBuffer(max_gap=5.0)
    for stamp in (T0 - 1.0, T0 + 1.0):
        buffer.add(stamp, *ODOM_BASE)
    return Odometry("odom", "base_link", buffer)


POINT = np.array([[4.0, 1.0, -0.5]])


def place(placement: Any) -> np.ndarray:
    cloud = ParsedCloud(POINT.copy(), None, None, 1)
    points, _ = cloud_to_map(cloud, T0, placement.poses, placement.extrinsic)
    return points[0]


def expected(*transforms: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    m = np.eye(4)
    for t in transforms:
        m = m @ matrix(*t)
    return (m @ np.append(POINT[0], 1.0))[:3]


def test_tf_only_places_the_lidar_through_the_whole_chain() -> None:
    placement = resolve_placement("lidar", robot_tree(), None)
    assert placement.map_frame == "map"  # the root of the tree
    np.testing.assert_allclose(place(placement), expected(MAP_ODOM, ODOM_BASE, BASE_LIDAR))
    in_odom = resolve_placement("lidar", robot_tree(), None, frame_id="odom")
    np.testing.assert_allclose(place(in_odom), expected(ODOM_BASE, BASE_LIDAR))


def test_odometry_with_map_above_it_and_extrinsic_from_tf_static() -> None:
    tree = robot_tree(with_odom=False)  # odom -> base_link comes from the odometry topic
    placement = resolve_placement("lidar", tree, odometry(), frame_id="map")
    np.testing.assert_allclose(place(placement), expected(MAP_ODOM, ODOM_BASE, BASE_LIDAR))
    assert "map -> odom from TF" in placement.source and "/tf_static" in placement.source
    in_odom = resolve_placement("lidar", tree, odometry())
    np.testing.assert_allclose(place(in_odom), expected(ODOM_BASE, BASE_LIDAR))


def test_a_cloud_already_in_the_map_or_odometry_frame_is_not_moved_twice() -> None:
    tree = robot_tree(with_odom=False)
    in_odom = resolve_placement("odom", tree, odometry(), frame_id="map")
    np.testing.assert_allclose(place(in_odom), expected(MAP_ODOM))
    in_map = resolve_placement("map", tree, odometry(), frame_id="map")
    np.testing.assert_allclose(place(in_map), POINT[0])
    odom_only = resolve_placement("odom", tree, odometry())
    np.testing.assert_allclose(place(odom_only), POINT[0])


def test_never_a_silent_wrong_extrinsic() -> None:
    tree = TfTree()
    with pytest.raises(ScanDropped) as err:
        resolve_placement("velodyne", tree, odometry())
    assert err.value.reason == "no_extrinsic"
    assert "'velodyne'" in err.value.detail and "'base_link'" in err.value.detail
    override = Extrinsic(np.array([0.0, 0.0, 2.0]))
    placed = resolve_placement("velodyne", tree, odometry(), param_extrinsic=override)
    np.testing.assert_allclose(
        place(placed), expected(ODOM_BASE, (override.translation, override.quaternion))
    )
    # the odometry child itself: identity even with lidar.* set
    own = resolve_placement("base_link", tree, odometry(), param_extrinsic=override)
    np.testing.assert_allclose(place(own), expected(ODOM_BASE))


def test_missing_transforms_name_the_frames() -> None:
    with pytest.raises(ScanDropped) as err:
        resolve_placement("lidar", TfTree(), None)
    assert err.value.reason == "no_poses" and "'lidar'" in err.value.detail
    with pytest.raises(ScanDropped) as err:
        resolve_placement("lidar", robot_tree(with_map=False), odometry(), frame_id="map")
    assert err.value.reason == "no_poses"
    assert "'odom'" in err.value.detail and "'map'" in err.value.detail
    assert "set frame_id to 'odom'" in err.value.detail


def test_stamp_guard_rejects_one_outlier_and_follows_a_real_jump() -> None:
    guard = StampGuard(max_jump=5.0, max_future=10.0)
    assert guard.check(100.0, now=100.0) is None
    assert guard.check(3700.0, now=100.5) == "ahead_of_clock"
    assert guard.check(3700.0) == "future_outlier"  # no clock: held back
    assert guard.check(100.2) is None and guard.latest == 100.2
    assert guard.check(80.0) == "past_outlier"
    assert guard.check(80.1) is None and guard.jumped  # confirmed: the stream restarted
    assert guard.latest == 80.1


# --- the live worker ---------------------------------------------------------------------


def worker_and_logs(now: list[float], **changes: Any) -> tuple[LiveIntegrator, list[str]]:
    logs: list[str] = []
    settings = LiveSettings(
        PlacementSection(**{"cloud_queue_size": 5, "odom_wait": 0.2, **changes})
    )
    worker = LiveIntegrator(
        Mapper(0.2),
        settings,
        PoseBuffer(max_age=10.0, max_gap=0.5),
        log=lambda key, text, error: logs.append(f"{key}: {text}"),
        now=lambda: now[0],
    )
    return worker, logs


def cloud(stamp: float, frame: str = "base_link", time_field: str | None = None) -> Any:
    xyz = np.random.default_rng(1).uniform(1.0, 4.0, (20, 3)).astype(np.float32)
    columns: dict[str, Any] = {a: xyz[:, k] for k, a in enumerate("xyz")}
    if time_field is not None:
        columns[time_field] = np.linspace(0.0, 0.05, 20).astype(np.float32)
    return cloud_message_from_columns(columns, stamp, frame)


def test_one_poisoned_odometry_stamp_does_not_stop_mapping() -> None:
    now = [T0]
    worker, logs = worker_and_logs(now)
    for k in range(5):
        assert worker.add_odometry(odom_sample(T0 - 0.5 + 0.1 * k))
    assert not worker.add_odometry(odom_sample(T0 + 3600.0))  # one hour ahead
    assert worker.counters.odom_rejected["ahead_of_clock"] == 1
    assert worker.add_odometry(odom_sample(T0 + 0.1))
    worker.submit(cloud(T0))
    drain(worker)
    assert worker.counters.clouds_integrated == 1
    assert any("ahead_of_clock" in line for line in logs)


def test_clock_jump_back_clears_buffers_and_mapping_resumes() -> None:
    now = [T0]
    worker, logs = worker_and_logs(now)
    worker.add_odometry(odom_sample(T0 - 0.1))
    worker.add_odometry(odom_sample(T0 + 0.1))
    worker.submit(cloud(T0))
    drain(worker)
    now[0] = T0 - 20.0  # bag loop
    worker.submit(cloud(T0 - 20.0))
    assert worker.observe_clock(T0) is False  # first observation: no jump
    assert worker.observe_clock(T0 - 20.0) is True
    assert worker.counters.clouds_dropped["clock_jump"] == 1 and len(worker.pose_inputs.poses) == 0
    assert sum("clock jumped back" in line for line in logs) == 1
    t0 = time.monotonic()
    worker.add_odometry(odom_sample(T0 - 20.1))
    worker.add_odometry(odom_sample(T0 - 19.9))
    worker.submit(cloud(T0 - 20.0))
    drain(worker)
    assert worker.counters.clouds_integrated == 2 and time.monotonic() - t0 < 1.0


def test_tf_only_worker_maps_in_the_root_frame() -> None:
    now = [T0]
    worker, logs = worker_and_logs(now)
    worker.pose_inputs.tree = robot_tree()
    worker.submit(cloud(T0, frame="lidar"))
    drain(worker)
    assert worker.counters.clouds_integrated == 1
    assert worker.map_frame == "map" and worker.mapper.frame_id == "map"
    assert any("TF map <- lidar" in line for line in logs)


def test_unknown_time_field_warns_once() -> None:
    now = [T0]
    worker, logs = worker_and_logs(now)
    worker.add_odometry(odom_sample(T0 - 0.1))
    worker.add_odometry(odom_sample(T0 + 0.2))
    for k in range(3):
        worker.submit(cloud(T0 + 0.01 * k, time_field="offset_time"))
    drain(worker)
    assert worker.counters.clouds_integrated == 3
    assert sum("'offset_time'" in line and "de-skew is off" in line for line in logs) == 1
