"""Poses and frames a robot can trust (issue 17), over real DDS on loopback: stray and
conflicting transforms, late pose sources, a TF stream jumping back, churned frame names,
TF-only radii, sim time without /clock, and a future-stamped cloud in the queue.

The scene of ``test_node_tf``: a wall at x = WALL_X in the map frame seen by a lidar on
``map -> odom -> base_link -> lidar``. "The world once" is measured as the share of the
occupied voxels (DoO > 0.5), taken back into the map frame, that lie on the wall.
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_helpers import NodeProcess, odom_msg, read_cloud, stamp_msg
from test_node_tf import (
    BASE_LIDAR,
    MAP_LIDAR,
    MAP_ODOM,
    ODOM_BASE,
    PARAMS,
    RES,
    T0,
    WALL_X,
    TfFeeder,
    matrix,
    start,
    transform,
    wall_cloud,
)

pytestmark = pytest.mark.ros

ZERO = (np.zeros(3), 0.0)


def tf_message(feeder: TfFeeder, *tfs: Any) -> Any:
    return feeder.TFMessage(transforms=list(tfs))


def integrated(feeder: TfFeeder, at_least: int, timeout: float = 20.0) -> dict[str, Any]:
    status = feeder.wait_status(lambda s: s["clouds_integrated"] >= at_least, timeout)
    assert status is not None
    return status


def on_wall_share(feeder: TfFeeder, map_from_cloud: np.ndarray) -> tuple[float, int]:
    """Share of the occupied voxels of the latest DoO cloud on the wall (map frame)."""
    cloud = read_cloud(feeder.doo)
    occupied = cloud["degree_of_occupancy"] > 0.5
    pts = np.stack([cloud[a][occupied] for a in "xyz"] + [np.ones(occupied.sum())])
    x = (map_from_cloud @ pts)[0]
    return float(np.mean(np.abs(x - WALL_X) <= 1.5 * RES)), int(occupied.sum())


def wait_doo(feeder: TfFeeder, version_voxels: int = 50) -> None:
    def ok() -> bool:
        if feeder.doo is None:
            return False
        return int((read_cloud(feeder.doo)["degree_of_occupancy"] > 0.5).sum()) > version_voxels

    assert feeder.wait(ok, 20.0)


def odom_scans(feeder: TfFeeder, start_t: float, count: int, map_odom: bool) -> None:
    """Scans at 10 Hz placed by odometry (odom -> base_link), with /tf map -> odom or not."""
    pose, yaw = ODOM_BASE
    for k in range(count):
        t = start_t + 0.1 * k
        for dt in (-0.05, 0.0, 0.05, 0.1):
            feeder.odom_pub.publish(odom_msg(t + dt, pose, yaw))
            if map_odom:
                feeder.tf(t + dt, with_odom=False)
        feeder.cloud_pub.publish(wall_cloud(t))
        feeder.spin(0.06)  # about real time: the queue is not what is tested here


def stop(node: NodeProcess, feeder: TfFeeder) -> None:
    feeder.destroy()
    assert node.stop() == 0


def test_stray_loop_and_stray_parent_and_frame_names(ros_domain: int, tmp_path: Path) -> None:
    """One ``base_link -> odom`` message (a loop) is refused and never stored; one dynamic
    ``odom -> lidar`` beside the static ``base_link -> lidar`` is warned (both parents
    named) and mapping resumes within the TF cache time; an empty cloud frame_id is a drop
    with a reason, a leading slash is stripped with one warning."""
    node, f = start(ros_domain, tmp_path, "stray", tf_buffer=2.0)
    try:
        f.static_tf()
        f.scans(T0, 5, with_odom_tf=True)
        integrated(f, 5)
        f.tf_pub.publish(tf_message(f, transform("base_link", "odom", T0 + 0.5, ZERO)))
        f.scans(T0 + 0.5, 5, with_odom_tf=True)
        status = integrated(f, 10)
        assert status["clouds_integrated"] >= 10, f"{status}\n{node.log()[-3000:]}"
        assert status["tf_rejected"].get("loop") == 1
        assert "'base_link' -> 'odom' refused" in node.log()

        # the stray parent: 4 s of stream after it, cache time 2 s
        f.tf_pub.publish(tf_message(f, transform("odom", "lidar", T0 + 1.0, BASE_LIDAR)))
        f.scans(T0 + 1.0, 40, with_odom_tf=True)
        before = f.wait_status(lambda s: s["queued"] == 0, 10.0)["clouds_integrated"]
        f.scans(T0 + 5.0, 10, with_odom_tf=True)
        status = integrated(f, before + 10)
        assert status["clouds_integrated"] >= before + 10, f"{status}\n{node.log()[-3000:]}"
        log = node.log()
        assert re.search(r"frame 'lidar'.*'odom'.*'base_link'", log), log[-3000:]
        wait_doo(f)
        share, n = on_wall_share(f, np.eye(4))
        assert share > 0.95, (share, n)

        # frame names: "" is a drop with its reason; "/lidar" is read as "lidar", warned once
        f.tf(T0 + 6.0)
        f.tf(T0 + 6.1)
        f.cloud_pub.publish(wall_cloud(T0 + 6.05, frame=""))
        status = f.wait_status(lambda s: "no_frame" in s["clouds_dropped"], 10.0)
        assert status["clouds_dropped"].get("no_frame") == 1, status
        for k in range(3):
            t = T0 + 6.2 + 0.1 * k
            f.tf(t - 0.05)
            f.tf(t + 0.05)
            f.cloud_pub.publish(wall_cloud(t, frame="/lidar"))
            f.spin(0.05)
        status = integrated(f, status["clouds_integrated"] + 3)
        assert node.log().count("has a leading slash") == 1
        print(
            f"stray loop refused ({status['tf_rejected']}); after the stray parent "
            f"{status['clouds_integrated']} clouds integrated, wall share {share:.3f}"
        )
    finally:
        stop(node, f)


def test_late_map_to_odom_keeps_one_world(ros_domain: int, tmp_path: Path) -> None:
    """Odometry only for 3 s, then SLAM starts ``map -> odom``. frame_id "": the map frame
    is decided once (odom) and stays; frame_id map: clouds wait for map -> odom (dropped
    with a reason before it), then map in ``map``. Either way the wall is there once."""
    for frame_id, expected in (("", "odom"), ("map", "map")):
        node, f = start(ros_domain, tmp_path, f"late_map_{expected}", frame_id=frame_id)
        try:
            f.static_tf()
            odom_scans(f, T0, 30, map_odom=False)
            odom_scans(f, T0 + 3.0, 30, map_odom=True)
            status = f.wait_status(
                lambda s: (
                    s["clouds_integrated"] + sum(s["clouds_dropped"].values()) >= 55
                    and s["queued"] == 0
                ),
                20.0,
            )
            assert status["map_frame"] == expected, status
            wait_doo(f)
            assert f.doo.header.frame_id == expected
            to_map = matrix(*MAP_ODOM) if expected == "odom" else np.eye(4)
            share, n = on_wall_share(f, to_map)
            assert share > 0.95, (frame_id, share, n, status)
            if frame_id:  # waiting for map -> odom: dropped after odom_wait (or pushed out)
                drops = status["clouds_dropped"]
                assert status["clouds_integrated"] >= 25 and drops.get("no_poses", 0) >= 15, drops
            else:
                assert status["clouds_integrated"] >= 55, status["clouds_dropped"]
            assert f"map frame '{expected}'" in node.log()
            print(
                f"frame_id {frame_id!r}: map in {expected!r}, {status['clouds_integrated']} "
                f"integrated, drops {status['clouds_dropped']}, {share:.3f} of {n} occupied "
                "voxels on the wall"
            )
        finally:
            stop(node, f)


def test_late_odometry_topic_is_linked_through_tf(ros_domain: int, tmp_path: Path) -> None:
    """TF only first (the map frame is decided: map, the TF root), then an Odometry topic
    appears in odom: it is linked through map -> odom; the map is never relabelled."""
    node, f = start(ros_domain, tmp_path, "late_odom", frame_id="")
    try:
        f.static_tf()
        f.scans(T0, 10, with_odom_tf=True)
        integrated(f, 10)
        f.scans(T0 + 1.0, 20, with_odom_tf=True, odom=True)
        status = integrated(f, 30)
        assert status["clouds_integrated"] >= 30, f"{status}\n{node.log()[-3000:]}"
        assert status["map_frame"] == "map" and status["odom_frame"] == "odom"
        log = node.log()
        assert "loaded map" not in log
        assert "linked to the map frame 'map' through TF" in log
        assert "map -> odom from TF" in status["pose_source"], status["pose_source"]
        wait_doo(f)
        assert f.doo.header.frame_id == "map"
        share, n = on_wall_share(f, np.eye(4))
        assert share > 0.95, (share, n)
        print(f"late odometry: {status['pose_source']}; {share:.3f} of {n} on the wall")
    finally:
        stop(node, f)


def test_tf_stream_jumping_back_resumes(ros_domain: int, tmp_path: Path) -> None:
    """The TF publisher restarts with its clock 20 s back (the node clock unchanged): the
    jump is confirmed by the second message and mapping resumes at once."""
    node, f = start(ros_domain, tmp_path, "tf_jump")
    try:
        f.static_tf()
        f.scans(T0, 10, with_odom_tf=True)
        integrated(f, 10)
        f.scans(T0 - 20.0, 20, with_odom_tf=True)
        status = integrated(f, 27)
        assert status["clouds_integrated"] >= 27, f"{status}\n{node.log()[-3000:]}"
        assert "TF stamps jumped back" in node.log()
        print(f"TF 20 s back: {status['clouds_integrated']} of 30 integrated")
    finally:
        stop(node, f)


def test_two_localizers_are_reported_as_a_conflict(ros_domain: int, tmp_path: Path) -> None:
    """``base_link`` alternately in ``odom`` and in ``map`` (two localizers): a conflict
    naming both parents, in the log, ~/status and the drop reason; when one localizer
    stops, mapping resumes within the cache time."""
    node, f = start(ros_domain, tmp_path, "two_loc", tf_buffer=2.0)
    try:
        f.static_tf()
        for k in range(20):
            t = T0 + 0.1 * k
            for dt in (-0.05, 0.0, 0.05, 0.1):
                f.tf(t + dt)
                other = transform("map", "base_link", t + dt + 0.01, ODOM_BASE)
                f.tf_pub.publish(tf_message(f, other))
            f.cloud_pub.publish(wall_cloud(t))
            f.spin(0.01)
        status = f.wait_status(lambda s: s["clouds_dropped"].get("tf_conflict", 0) >= 5, 20.0)
        assert status["clouds_dropped"].get("tf_conflict", 0) >= 5, status
        assert "base_link" in status.get("tf_conflicts", ""), status
        assert re.search(
            r"frame 'base_link'.*alternately.*'(map|odom)' and '(map|odom)'", node.log()
        )
        before = f.wait_status(lambda s: s["queued"] == 0, 10.0)["clouds_integrated"]
        f.scans(T0 + 2.0, 30, with_odom_tf=True)  # 3 s of one localizer
        f.scans(T0 + 5.0, 10, with_odom_tf=True)
        status = integrated(f, before + 10)
        assert status["clouds_integrated"] >= before + 10, status
        assert "tf_conflicts" not in status
        print(f"two localizers: {status['clouds_dropped']}; then {status['clouds_integrated']}")
    finally:
        stop(node, f)


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def churn_message(feeder: TfFeeder, stamp: float, names: list[str]) -> Any:
    """One /tf message of identity transforms ``map -> name`` (built without scipy)."""
    from geometry_msgs.msg import TransformStamped

    tfs = []
    for name in names:
        tf = TransformStamped()
        tf.header.frame_id, tf.child_frame_id = "map", name
        tf.header.stamp = stamp_msg(stamp)
        tf.transform.rotation.w = 1.0
        tfs.append(tf)
    return feeder.TFMessage(transforms=tfs)


def test_churned_frame_names_keep_memory_flat(ros_domain: int, tmp_path: Path) -> None:
    """60,000 frame names, each published for a moment (100 per /tf message), beside the
    robot's TF: the node forgets them after the cache time; its memory stays flat between
    the first 20k and the last 40k names; an error line names a handful of frames."""
    node, f = start(ros_domain, tmp_path, "churn", tf_buffer=2.0)
    try:
        f.static_tf()
        f.scans(T0, 5, with_odom_tf=True)
        integrated(f, 5)
        t, sent, rss = T0 + 0.5, 0, []
        for k in range(600):
            f.tf_pub.publish(churn_message(f, t, [f"churn_{k}_{j}" for j in range(100)]))
            f.tf(t)
            sent += 102
            t += 0.02
            if k % 20 == 19:  # at the node's pace: /tf keeps the last 100 messages only
                assert f.wait_status(lambda s, n=sent: s["tf_in"] >= n, 30.0)["tf_in"] >= sent
            if k in (199, 599):
                time.sleep(0.5)
                rss.append(rss_mb(node.pid))
        for _ in range(150):  # 3 s more of the robot's TF: every churned name expires
            f.tf(t)
            t += 0.02
        status = f.wait_status(lambda s: s["tf_frames"] < 50, 30.0)
        assert status["tf_in"] >= sent and status["tf_frames"] < 50, status
        f.cloud_pub.publish(wall_cloud(t, frame="nowhere"))
        f.wait_status(lambda s: "no_poses" in s["clouds_dropped"], 10.0)
        time.sleep(0.3)
        longest = max(len(line) for line in node.log().splitlines())
        assert longest < 2000, longest
        assert rss[1] - rss[0] < 15.0, rss
        print(
            f"60k churned frame names: {status['tf_frames']} frames kept after, RSS "
            f"{rss[0]:.1f} MB after 20k -> {rss[1]:.1f} MB after 60k; longest log line "
            f"{longest} chars"
        )
    finally:
        stop(node, f)


def test_tf_only_radius_and_window(ros_domain: int, tmp_path: Path) -> None:
    """TF only: the sensor's position in the map frame is the robot's: publish_radius
    bounds the published voxels and hit_probability_map.radius the GetMap window."""
    from nav_msgs.srv import GetMap

    radius, window = 3.3, 1.5
    node, f = start(
        ros_domain,
        tmp_path,
        "tf_radius",
        publish_radius=radius,
        **{"hit_probability_map.radius": window},
    )
    try:
        f.static_tf()
        f.scans(T0, 10, with_odom_tf=True)
        integrated(f, 10)
        wait_doo(f, 20)
        cloud = read_cloud(f.doo)
        xyz = np.stack([cloud[a] for a in "xyz"], axis=1)
        lidar = MAP_LIDAR[:3, 3]
        dist = np.linalg.norm(xyz - lidar, axis=1)
        assert len(dist) > 20 and dist.max() <= radius + 1e-3, (len(dist), dist.max())
        # the wall reaches beyond the radius: without a robot position it would be there
        assert np.hypot(WALL_X - lidar[0], 2.0) > radius + 0.3
        grid = f.call(f.get_map, GetMap.Request()).map
        cells = int(np.ceil(2 * window / RES)) + 2
        assert 0 < grid.info.width <= cells and 0 < grid.info.height <= cells, grid.info
        centre = (
            grid.info.origin.position.x + grid.info.width * RES / 2,
            grid.info.origin.position.y + grid.info.height * RES / 2,
        )
        assert np.hypot(centre[0] - lidar[0], centre[1] - lidar[1]) < 2 * RES, centre
        print(
            f"TF only: {len(dist)} voxels published, farthest {dist.max():.2f} m "
            f"(publish_radius {radius}); GetMap {grid.info.width}x{grid.info.height}"
        )
    finally:
        stop(node, f)


def test_sim_time_without_clock_is_reported_and_status_keeps_going(
    ros_domain: int, tmp_path: Path
) -> None:
    """use_sim_time with no /clock (a bag played without --clock): one clear line within a
    few seconds, and ~/status and /diagnostics keep publishing (wall-clock timers)."""
    from diagnostic_msgs.msg import DiagnosticArray

    node = NodeProcess(ros_domain, {**PARAMS, "use_sim_time": True}, tmp_path / "noclock.log")
    f = TfFeeder()
    diags: list[Any] = []
    statuses: list[dict[str, Any]] = []
    f.node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    try:
        t0 = time.monotonic()
        assert f.wait(lambda: f.status is not None, 30.0), node.log()[-3000:]
        first = time.monotonic()
        while time.monotonic() - first < 6.0:
            f.spin(0.05)
            if f.status is not None and (not statuses or f.status is not statuses[-1]):
                statuses.append(f.status)
        log = node.log()
        assert log.count("use_sim_time is true and /clock has not been received") == 1, log
        stamps = {  # the node's own log times (wall clock): from its start to the line
            key: float(re.search(rf"\[(\d+\.\d+)\] \[mfp_mapper\]: {key}", log).group(1))
            for key in ("mfp_mapper ready", "use_sim_time is true")
        }
        after = stamps["use_sim_time is true"] - stamps["mfp_mapper ready"]
        assert after <= 5.0, after
        assert len(statuses) >= 5 and len(diags) >= 5, (len(statuses), len(diags))
        assert statuses[-1]["sim_time_without_clock"] is True
        print(
            f"no /clock: reported once, {after:.1f} s after the node was ready "
            f"({time.monotonic() - t0:.1f} s after launch, discovery included); "
            f"{len(statuses)} ~/status and {len(diags)} /diagnostics in 6 s"
        )
    finally:
        f.destroy()
        assert node.stop() == 0


def test_future_stamped_cloud_does_not_block_the_queue(ros_domain: int, tmp_path: Path) -> None:
    """Good clouds at 10 Hz with odometry, and at 1 Hz a cloud stamped 100 s ahead (never
    coverable): the future ones wait apart and are dropped after odom_wait (or pushed out
    first when the queue is full); no good cloud is lost (cloud_queue_size 5)."""
    node, f = start(
        ros_domain, tmp_path, "future", frame_id="odom", cloud_queue_size=5, odom_wait=1.0
    )
    try:
        f.static_tf()
        pose, yaw = ODOM_BASE
        good = 60
        for k in range(good):
            t = T0 + 0.1 * k
            for dt in (-0.05, 0.0, 0.05, 0.1):
                f.odom_pub.publish(odom_msg(t + dt, pose, yaw))
            if k % 10 == 0:
                f.cloud_pub.publish(wall_cloud(t + 100.0))
            f.cloud_pub.publish(wall_cloud(t))
            f.spin(0.1)  # real time: 10 Hz
        status = f.wait_status(
            lambda s: s["queued"] == 0 and s["clouds_integrated"] >= good - 3, 60.0
        )
        in_ = status["clouds_in"]
        assert status["clouds_integrated"] >= good - 3, f"{status}\n{node.log()[-3000:]}"
        # the future clouds are dropped: after odom_wait, or pushed out first when full;
        # beside the 6 future ones, at most the 3 good clouds the bound above allows (a
        # starved machine may overflow a queue of 5 at 10 Hz: not the fault this is about)
        drops = status["clouds_dropped"]
        assert drops.get("too_new", 0) + drops.get("queue_full", 0) <= 6 + 3, status
        assert drops.get("too_new", 0) >= 3, status
        print(
            f"future-stamped clouds at 1 Hz: {status['clouds_integrated']} of {good} good "
            f"clouds integrated ({in_} received), drops {status['clouds_dropped']}"
        )
    finally:
        stop(node, f)


def test_clouds_flow_under_a_tf_flood_after_a_churn(ros_domain: int, tmp_path: Path) -> None:
    """60,000 frame names churned, then 10,000 new frames a second beside the robot's TF:
    placeable clouds keep flowing (each placement copied the whole TF tree under the lock,
    300 ms at 20,000 frames, holding up the executor's TF: 7 of 15 clouds were kept)."""
    node, f = start(ros_domain, tmp_path, "flood", cloud_queue_size=5)
    try:
        f.static_tf()
        f.scans(T0, 5, with_odom_tf=True)
        integrated(f, 5)
        t = T0 + 0.5
        for k in range(600):  # the churn: 100 names a message, stamped with the robot's TF
            f.tf_pub.publish(churn_message(f, t, [f"churn_{k}_{j}" for j in range(100)]))
            if k % 50 == 49:
                f.spin(0.01)
        f.wait_status(lambda s: s["tf_frames"] > 10_000, 60.0)
        assert f.status is not None
        base = f.status["clouds_integrated"]
        settled = base + sum(f.status["clouds_dropped"].values())
        clouds = 15
        for k in range(clouds):  # 10 Hz clouds, 10,000 new frames a second
            for j in range(10):
                names = [f"flood_{k}_{j}_{i}" for i in range(100)]
                f.tf_pub.publish(churn_message(f, t + 0.01 * j, names))
            for dt in (-0.05, 0.0, 0.05, 0.1):
                f.tf(t + dt)
            f.cloud_pub.publish(wall_cloud(t))
            f.spin(0.1)
            t += 0.1
        kept = clouds * 3 // 5  # 11-12 of 15 measured on a loaded 2-core machine
        status = f.wait_status(
            lambda s: (  # every cloud integrated or dropped
                s["queued"] == 0
                and s["clouds_integrated"] + sum(s["clouds_dropped"].values()) >= settled + clouds
            ),
            60.0,
        )
        # before: 4 of 15 (too_new: the robot's TF held up behind whole-tree copies). /tf is
        # now read from its CDR bytes and inserted without numpy (0.8 CPU ms a message of
        # 100 transforms, was 4.1: benchmarks/bench_tf_flood.py). What is left on a loaded
        # 2-core machine: the churn's backlog (the wait above ends at 10,000 frames while
        # 150-200 churn messages are still queued); the robot's TF waits behind it, and the
        # first clouds fill the queue waiting (with the churn settled first: 15 of 15 in 2
        # of 3 runs). Interleaved A/B on a shared 2-core machine (load 3.3-4.9): 10, 10, 10
        # of 15 before, 14, 15, 15 after (29-37k of the ~76k transforms received before,
        # 63-68k after); 9-11 after when the load is 5-6
        assert status["clouds_integrated"] >= base + kept, f"{status}\n{node.log()[-2000:]}"
        print(
            f"TF flood: {status['clouds_integrated'] - base} of {clouds} clouds integrated, "
            f"drops {status['clouds_dropped']}, {status['tf_in']} transforms received, "
            f"{status['stage_s']['queued']:.2f} s queued in all"
        )
    finally:
        stop(node, f)
