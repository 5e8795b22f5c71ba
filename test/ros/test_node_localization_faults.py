"""The node's localization mode under bad input, over real DDS (issue 20; the project's rule:
bad input gets one clear line and changes nothing, no callback takes the node down, never a
silent wrong pose): ``/initialpose`` that is not finite, not a rotation or beyond the map's
reach or stamped a year ahead; parameters set to edge values at run time; ``~/reset``
while localizing; SIGINT."""

from __future__ import annotations

import math
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest
from scipy.spatial.transform import Rotation
from test_node_lifecycle import Lifecycle, _set_parameters
from test_node_localization import LocFeeder, _aligned, _save_scene_map, _start

pytestmark = pytest.mark.ros
YEAR = 365 * 86400.0


def _raw_initial_pose(
    feeder: LocFeeder, position: Any, quaternion: Any, ahead: float = 0.0
) -> None:
    from ros_helpers import stamp_msg

    msg = feeder.PoseWithCovarianceStamped()
    msg.header.frame_id = "map"
    msg.header.stamp = stamp_msg(time.time() + ahead)
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = (float(v) for v in position)
    o.x, o.y, o.z, o.w = (float(v) for v in quaternion)
    feeder.initial_pub.publish(msg)


def test_bad_initial_poses_edge_parameters_and_reset_leave_the_node_standing(
    ros_domain: int, tmp_path: Path
) -> None:
    scene, poses = _save_scene_map("box", tmp_path / "hall.npz")
    node, feeder = _start(ros_domain, tmp_path, "faults", tmp_path / "hall.npz")
    try:
        # beyond what a map can hold (finite, a unit quaternion): refused, not claimed on /tf
        _raw_initial_pose(feeder, (1e12, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
        assert feeder.wait(lambda: "beyond the map's reach" in node.log(), 60.0), node.log()
        _raw_initial_pose(feeder, (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
        assert feeder.wait(lambda: "not finite or not a unit quaternion" in node.log(), 60.0)
        _raw_initial_pose(feeder, (1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0))
        feeder.spin(0.3)
        assert feeder.localization()["initial_poses"] == 0, feeder.localization()
        assert not feeder.tf  # nothing claimed
        t = time.time()
        for i, k in enumerate((1, 3, 5)):
            feeder.scan(scene, poses[k], t + i * 0.2, seed=k)
            loc = _aligned(feeder, i + 1, node)
        assert loc["state"] == "localized", loc
        assert all(abs(tf.transform.translation.x) < 10.0 for tf in feeder.tf)

        # stamped a year ahead (a clock gone wrong): map -> odom must not be stamped there
        truth = poses[5]
        quat = Rotation.from_matrix(truth.rotation).as_quat()
        _raw_initial_pose(feeder, truth.translation, quat, ahead=YEAR)
        assert feeder.wait(lambda: "/initialpose received" in node.log(), 60.0)
        seen = len(feeder.tf)
        assert feeder.wait(lambda: len(feeder.tf) >= seen + 3, 30.0)
        newest = feeder.tf[-1].header.stamp
        assert newest.sec + 1e-9 * newest.nanosec < time.time() + 5.0
        assert "ahead of the clock: taken as now" in node.log()

        # edge values at run time: the next clouds are aligned with them
        results = _set_parameters(
            feeder,
            "mfp_mapper",
            {
                "localization.max_rays": 10,
                "localization.tracking_levels": 3,
                "localization.update_min_d": 0.0,
                "localization.update_min_a": 0.0,
                "localization.lost_after": 1,
            },
        )
        assert all(r.successful for r in results), [r.reason for r in results]
        feeder.scan(scene, poses[7], time.time(), seed=7)
        loc = _aligned(feeder, 4, node)
        assert loc["last"]["rays"] <= 10 or not loc["last"]["accepted"], loc

        # ~/clear_bbox while localizing: the field is rebuilt from what is left; clouds go on
        from ros_helpers import clear_bbox

        clear_bbox(feeder, "mfp_mapper", (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
        feeder.scan(scene, poses[9], time.time(), seed=9)
        loc = _aligned(feeder, 5, node)
        assert loc["state"] in ("localized", "lost", "initializing"), loc

        # ~/reset while localizing: the field goes with the map; clouds still come through
        from std_srvs.srv import Empty

        feeder.call(feeder.reset, Empty.Request())
        assert feeder.wait(lambda: feeder.localization().get("state") == "waiting_for_map", 60.0), (
            feeder.localization()
        )
        localized = feeder.status["clouds_localized"] if feeder.status else 0
        feeder.scan(scene, poses[11], time.time(), seed=11)
        assert feeder.wait(
            lambda: (feeder.status or {}).get("clouds_localized", 0) > localized, 60.0
        ), feeder.status
        assert node.alive()
    finally:
        feeder.destroy()
        code = node.stop()
    log = node.log()
    assert code == 0 and "Traceback" not in log, log[-3000:]


def test_lifecycle_while_localizing(ros_domain: int, tmp_path: Path) -> None:
    """deactivate/activate keeps the correction; cleanup/configure starts over from the map
    file (a new field); clouds are localized after each; no traceback, a clean exit."""
    from lifecycle_msgs.msg import Transition
    from ros_helpers import NodeProcess
    from test_node_localization import PARAMS

    scene, poses = _save_scene_map("box", tmp_path / "hall.npz")
    params = {**PARAMS, "autostart": False, "map_path": str(tmp_path / "hall.npz")}
    node = NodeProcess(ros_domain, params, tmp_path / "life.log")
    feeder = LocFeeder()
    life = Lifecycle(feeder)
    try:
        assert feeder.wait(lambda: life.change.service_is_ready(), 30.0), node.log()
        stamp = time.time()

        def up(configure: bool) -> None:
            if configure:
                assert life.transition(Transition.TRANSITION_CONFIGURE), node.log()[-3000:]
            assert life.transition(Transition.TRANSITION_ACTIVATE), node.log()[-3000:]
            assert feeder.wait(
                lambda: (
                    feeder.cloud_pub.get_subscription_count() > 0
                    and feeder.localization().get("state") in ("initializing", "localized")
                ),
                30.0,
            ), feeder.localization()

        def localize(k: int, count: int) -> dict[str, Any]:
            nonlocal stamp
            stamp += 0.2
            feeder.scan(scene, poses[k], stamp, seed=k)
            return _aligned(feeder, count, node)

        up(configure=True)
        localize(1, 1)
        loc = localize(3, 2)
        assert loc["state"] == "localized", loc
        assert life.transition(Transition.TRANSITION_DEACTIVATE)
        up(configure=False)
        loc = localize(5, 3)  # the same localizer: its count goes on
        assert loc["state"] == "localized" and loc["initial_poses"] == 0, loc
        assert life.transition(Transition.TRANSITION_DEACTIVATE)
        assert life.transition(Transition.TRANSITION_CLEANUP)
        feeder.status = None
        up(configure=True)
        assert feeder.localization()["aligned"] == 0  # a new localizer
        localize(7, 1)
        assert life.transition(Transition.TRANSITION_DEACTIVATE)
        assert life.transition(Transition.TRANSITION_INACTIVE_SHUTDOWN)
    finally:
        feeder.destroy()
        code = node.stop()
    log = node.log()
    assert code == 0 and "Traceback" not in log, log[-3000:]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_the_field_build_exits_cleanly(
    sig: int, ros_domain: int, shared_data: Path, tmp_path: Path
) -> None:
    """A map of 2.3 million voxels (two real Ouster scans at 0.2 m): the signal comes while
    the alignment's field is built in the background, right after the map is loaded."""
    from ros_helpers import NodeProcess, wait_for

    from mfp_mapper.cli import main

    src = shared_data / "ouster_street"
    train = tmp_path / "train"
    train.mkdir()
    for name in ("000000.bin", "000002.bin"):
        (train / name).symlink_to(src / "scans" / name)
    lines = (src / "poses.txt").read_text().splitlines()
    (tmp_path / "train.kitti").write_text(lines[0] + "\n" + lines[2] + "\n")
    map_path = tmp_path / "street.npz"
    assert main(["replay", str(train), "--poses", str(tmp_path / "train.kitti"), "-o",
                 str(map_path), "--resolution", "0.2", "-q"]) == 0  # fmt: skip
    params = {"resolution": 0.2, "localization.enabled": True, "map_path": str(map_path)}
    node = NodeProcess(ros_domain, params, tmp_path / "node.log")
    try:
        loaded = wait_for(
            lambda: "loaded" in node.log() or not node.alive(), 60.0, lambda: time.sleep(0.01)
        )
        assert loaded, node.log()
        assert node.alive(), node.log()
        node.proc.send_signal(sig)
        node.proc.wait(30.0)
    finally:
        code = node.stop()
    log = node.log()
    assert code == 0 and "Traceback" not in log, log[-3000:]
    assert f"{signal.Signals(sig).name}: stopping" in log, log[-3000:]


def test_a_map_made_by_replay_is_localized_against_in_map(ros_domain: int, tmp_path: Path) -> None:
    """``mfp-mapper replay`` writes its map in the recording's odometry frame (``odom``): the
    node localizes against it as documented, with no frame setting (issue 32 items 4 and 5):
    the map frame is ``map`` (logged), ``map -> odom`` converges to the true offset of the
    odometry, and ``~/status``, ``/tf``, ``~/pose`` and the log all name ``map`` as the map
    frame and ``odom`` as the frame clouds are placed in."""
    import numpy as np
    from folder_helpers import bag_contents
    from ros_helpers import NodeProcess, cloud_from_columns, odom_msg
    from test_node_localization import OFFSET, PARAMS, LocFeeder, _tf_matrix

    from mfp_mapper.cli import main
    from mfp_mapper.mapio.loading import load_map
    from mfp_mapper.mapping.live_localization import pose_matrix

    bag, map_path = tmp_path / "sim", tmp_path / "site.npz"
    scans = ["--scans", "24", "--azimuths", "900", "--cloud-in-base-frame"]
    assert main(["simulate", str(bag), "--scene", "demo", *scans]) == 0
    replay = ["replay", str(bag), "-o", str(map_path), "--resolution", "0.2", "--no-deskew"]
    assert main([*replay, "-q"]) == 0  # placed as the node places them below
    assert load_map(map_path).frame_id == "odom"  # what replay writes
    clouds, odometry = bag_contents(bag)
    params = {**PARAMS, "map_path": str(map_path)}
    node = NodeProcess(ros_domain, params, tmp_path / "replayed.log")
    feeder = LocFeeder()
    try:
        ready = feeder.wait(lambda: feeder.localization().get("state") == "initializing", 60.0)
        assert ready, node.log()[-3000:]
        shift = time.time() - clouds[0][0] + 1.0  # the recording, stamped from now on
        for k in range(0, len(clouds), 3):
            stamp, records = clouds[k]
            for row in odometry[(odometry[:, 0] > stamp - 0.15) & (odometry[:, 0] < stamp + 0.25)]:
                truth = pose_matrix(row[1:4], Rotation.from_quat(row[4:8]).as_matrix())
                odom = np.linalg.inv(OFFSET) @ truth
                yaw = float(Rotation.from_matrix(odom[:3, :3]).as_euler("xyz")[2])
                feeder.odom_pub.publish(odom_msg(row[0] + shift, odom[:3, 3], yaw))
            columns = {name: np.ascontiguousarray(records[name]) for name in ("x", "y", "z")}
            feeder.cloud_pub.publish(cloud_from_columns(columns, "base_link", stamp + shift))
            feeder.spin(0.3)
        assert feeder.wait(lambda: feeder.localization().get("state") == "localized", 30.0), (
            str(feeder.localization()) + node.log()[-3000:]
        )

        def xy_error() -> float:  # z left out: the field's bias on this map is about 0.1 m
            d = np.linalg.inv(OFFSET) @ _tf_matrix(feeder.tf[-1])
            return float(np.linalg.norm(d[:2, 3]))

        assert feeder.wait(lambda: bool(feeder.tf) and xy_error() < 0.1), feeder.tf[-1:]
        last = feeder.tf[-1]
        assert last.header.frame_id == "map" and last.child_frame_id == "odom"
        status = feeder.status or {}
        assert status["map_frame"] == "map" and status["placement_frame"] == "odom", status
        assert status["localization"]["global_frame"] == "map"
        assert feeder.wait(lambda: bool(feeder.poses), 10.0), feeder.localization()
        assert all(p.header.frame_id == "map" for p in feeder.poses)
    finally:
        feeder.destroy()
        code = node.stop()
    log = node.log()
    assert code == 0 and "Traceback" not in log, log[-3000:]
    assert "the map was built in 'odom'" in log and "localizing in 'map'" in log, log[-3000:]
    assert "odometry received in frame 'odom' (child 'base_link'): the map frame" not in log


@pytest.mark.parametrize("freeze_map", [True, False])
def test_a_map_replaced_on_disk_is_never_overwritten(
    ros_domain: int, tmp_path: Path, freeze_map: bool
) -> None:
    """Localization with ``save_on_shutdown``; the operator replaces the map file while the
    node runs (issue 32 item 10): on shutdown the new file is left as it is, byte for byte.
    A frozen map (unchanged) is not written at all; a map the clouds changed is saved beside
    the file, with a warning saying why."""
    import re

    from ros_helpers import NodeProcess
    from test_node_localization import PARAMS, LocFeeder

    from mfp_mapper.mapio.loading import load_map, save_map

    scene, poses = _save_scene_map("box", tmp_path / "hall.npz")
    params = {
        **PARAMS,
        "map_path": str(tmp_path / "hall.npz"),
        "save_on_shutdown": True,
        "localization.freeze_map": freeze_map,
    }
    node = NodeProcess(ros_domain, params, tmp_path / "replaced.log")
    feeder = LocFeeder()
    try:
        ready = feeder.wait(lambda: feeder.localization().get("state") == "initializing", 60.0)
        assert ready, node.log()[-3000:]
        t = time.time()
        for i, k in enumerate((1, 3)):
            feeder.scan(scene, poses[k], t + i * 0.2, seed=k)
            _aligned(feeder, i + 1, node)
        new_map = load_map(tmp_path / "hall.npz")
        new_map.clear_box((-100.0, -100.0, -100.0), (0.0, 100.0, 100.0))  # the operator's map
        save_map(new_map, tmp_path / "new.npz")
        os.replace(tmp_path / "new.npz", tmp_path / "hall.npz")
        replaced = (tmp_path / "hall.npz").read_bytes()
        if not freeze_map:  # saved beside it, now and at shutdown: one file
            from std_srvs.srv import Trigger

            assert feeder.wait(lambda: (feeder.status or {}).get("clouds_integrated", 0) >= 1)
            answer = feeder.call(feeder.save, Trigger.Request())
            assert answer.success and "not overwritten" in answer.message, answer.message
            feeder.scan(scene, poses[5], time.time(), seed=5)
            assert feeder.wait(lambda: (feeder.status or {}).get("clouds_integrated", 0) >= 2)
    finally:
        feeder.destroy()
        code = node.stop()
    log = node.log()
    assert code == 0 and "Traceback" not in log, log[-3000:]
    assert (tmp_path / "hall.npz").read_bytes() == replaced, log[-3000:]
    beside = sorted(p.name for p in tmp_path.glob("hall.*.npz"))
    if freeze_map:
        assert "was changed on disk since the node loaded or wrote it: not written" in log
        assert not beside, beside
    else:
        assert "was changed on disk since the node loaded or wrote it: not overwritten" in log
        assert len(beside) == 1 and re.search(r"\[WARN\].*saved \d+ voxels", log), log[-3000:]
        assert load_map(tmp_path / beside[0]).num_voxels > 0


def test_an_initial_pose_2_m_off_never_ends_localized_off(ros_domain: int, tmp_path: Path) -> None:
    """Issue 32 item 3 over DDS: localized, then an ``/initialpose`` 2 m off the truth
    (outside the 1 m window): the state is never ``localized`` with map -> odom more than
    0.1 m off, and ``~/pose`` is never published there."""
    import numpy as np
    from localization_scenes import Pose
    from test_node_localization import _error, _tf_matrix

    scene, poses = _save_scene_map("box", tmp_path / "hall.npz")
    node, feeder = _start(ros_domain, tmp_path, "far", tmp_path / "hall.npz")
    try:
        t = time.time()
        for i, k in enumerate((1, 3)):
            feeder.scan(scene, poses[k], t + i * 0.2, seed=k)
            _aligned(feeder, i + 1, node)
        assert feeder.localization()["state"] == "localized"
        given = Pose(poses[5].rotation, poses[5].translation + np.array([2.0, 0.0, 0.0]))
        feeder.initial_pose(given)
        assert feeder.wait(lambda: feeder.localization().get("initial_poses") == 1, 10.0)
        published = len(feeder.poses)
        for i, k in enumerate((5, 7, 9, 11)):
            feeder.scan(scene, poses[k], time.time(), seed=k)
            loc = _aligned(feeder, 3 + i, node)
            feeder.spin(0.3)
            if loc["state"] == "localized":
                shift, _ = _error(_tf_matrix(feeder.tf[-1]))
                assert shift < 0.1, (shift, loc)
        for msg in feeder.poses[published:]:
            p = msg.pose.pose.position
            truths = [poses[k].translation for k in (5, 7, 9, 11)]
            assert min(np.linalg.norm(np.array([p.x, p.y, p.z]) - x) for x in truths) < 0.1
    finally:
        feeder.destroy()
        code = node.stop()
    assert code == 0 and "Traceback" not in node.log()


def test_clouds_keep_flowing_while_a_wide_search_runs(ros_domain: int, tmp_path: Path) -> None:
    """Issue 32 item 6 over DDS: the first wide search (and its 26 probe searches) runs
    while clouds keep coming at 10 Hz into a queue of 2. The search must not starve the
    queue: no cloud is dropped ``queue_full``; the clouds placed during the search but the
    newest are dropped ``superseded``, the newest is taken after it; every cloud received
    is accounted for; the node ends localized at the truth."""
    from ros_helpers import NodeProcess
    from test_node_localization import PARAMS, LocFeeder, _error, _tf_matrix

    scene, poses = _save_scene_map("box", tmp_path / "hall.npz")
    params = {**PARAMS, "map_path": str(tmp_path / "hall.npz"), "cloud_queue_size": 2}
    node = NodeProcess(ros_domain, params, tmp_path / "flow.log")
    feeder = LocFeeder()
    try:
        ok = feeder.wait(
            lambda: (
                feeder.cloud_pub.get_subscription_count() > 0
                and feeder.localization().get("state") == "initializing"
                and (feeder.status or {}).get("kernels") == "ready"
            ),
            120.0,
        )
        assert ok, f"node not ready ({feeder.localization()}):\n{node.log()[-3000:]}"
        sent, t0 = 0, time.time()
        while time.time() - t0 < 4.0:  # the robot stands at poses[1]; 10 clouds a second
            feeder.scan(scene, poses[1], time.time(), seed=sent)
            sent += 1
            feeder.spin(0.1)

        def settled(s: dict[str, Any]) -> bool:
            done = s["clouds_localized"] + sum(s["clouds_dropped"].values())
            return s["clouds_in"] >= sent and done >= sent and s["queued"] == 0

        status = feeder.wait_status(settled, 120.0)
        assert status is not None and settled(status), f"{feeder.status}\n{node.log()[-3000:]}"
        drops = status["clouds_dropped"]
        assert drops.get("queue_full", 0) == 0, (drops, status["localization"])
        assert drops.get("superseded", 0) >= 1, (drops, status["localization"])
        assert set(drops) <= {"superseded"}, drops
        loc = status["localization"]
        assert loc["state"] == "localized", loc
        # map -> odom is another topic than ~/status: wait for it (one spin_once may take
        # only a status message)
        assert feeder.wait(lambda: bool(feeder.tf), 10.0), loc
        shift, angle = _error(_tf_matrix(feeder.tf[-1]))
        assert shift < 0.05 and angle < 0.5, (shift, angle, loc)
        print(
            f"{sent} clouds sent in 4 s: {status['clouds_localized']} localized, drops {drops}; "
            f"{loc['aligned']} aligned, ms_max {loc['ms_max']}"
        )
    finally:
        feeder.destroy()
        code = node.stop()
    assert code == 0 and "Traceback" not in node.log()
