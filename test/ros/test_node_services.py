"""Services during a long scan, saving at shutdown and in the background, clean stops: the
node as a user runs it (``python -m mfp_mapper.node``), over real DDS on loopback.

- a hit-probability query, GetMap and ``~/save_map`` answer while a scan of a million
  points (``MFP_TEST_BIG_SCAN_POINTS``) is being integrated, and GetMap and the saved file
  hold the map before that scan (whole scans);
- a map of ``MFP_TEST_SHUTDOWN_VOXELS`` voxels (20 M by default) loaded at start is saved
  intact under ``ros2 launch``'s escalation: SIGINT, SIGTERM 5 s later, SIGKILL 5 s after;
- ``autosave_period`` saves in the background; a directory ``map_path`` saves a tiled map;
- SIGINT during a burst of GetMap calls: exit code 0, no traceback.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_helpers import (
    ROOT,
    Feeder,
    NodeProcess,
    cloud_from_columns,
    domain_id,
    odom_msg,
    ros_context,
)

pytestmark = pytest.mark.ros

T0 = 1_700_000_000.0
RES = 0.05
DDS_PROFILE = ROOT / "config" / "fastdds_large_data.xml"
BIG_SCAN_POINTS = int(float(os.environ.get("MFP_TEST_BIG_SCAN_POINTS", "1e6")))
SHUTDOWN_VOXELS = int(float(os.environ.get("MFP_TEST_SHUTDOWN_VOXELS", "20e6")))
PARAMS = {
    "resolution": RES,
    "frame_id": "odom",
    "publish_rate": 0.0,
    "status_period": 0.2,
    "odom_wait": 5.0,
    "sensor_model.max_range": 100.0,
    "point_cloud_min_z": -100.0,
    "point_cloud_max_z": 100.0,
}


@pytest.fixture(scope="module")
def ros_domain() -> Iterator[int]:
    """rclpy on a private domain, with the large-data profile (clouds of 12 MB) for the nodes
    it starts (they inherit the environment)."""
    with ros_context(domain_id(), {"FASTRTPS_DEFAULT_PROFILES_FILE": str(DDS_PROFILE)}) as d:
        yield d


def _room_scan(count: int, seed: int) -> dict[str, np.ndarray]:
    """About ``count`` returns of a lidar (elevations -30..30 deg, 2048 azimuths) at the
    base_link origin in a box room 30 x 30 m, floor 2 m below, ceiling 6 m above."""
    rows = max(1, count // 2048)
    el = np.radians(np.linspace(-30.0, 30.0, rows))
    az = np.linspace(-np.pi, np.pi, 2048, endpoint=False) + seed * 1e-3
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        up = np.where(d[:, 2] > 0, 6.0 / d[:, 2], 2.0 / np.abs(d[:, 2]))
        t = np.minimum(np.minimum(15.0 / np.abs(d[:, 0]), 15.0 / np.abs(d[:, 1])), up)
    xyz = (d * t[:, None]).astype(np.float32)
    return {a: xyz[:, k] for k, a in enumerate("xyz")}


def _odom(f: Feeder, start: float, end: float) -> None:
    for t in np.arange(start, end, 0.05):
        f.odom_pub.publish(odom_msg(float(t), np.zeros(3), 0.0))


PUBLISHER = """
import sys, time
import numpy as np, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
sys.path.insert(0, sys.argv[4])
from ros_helpers import cloud_from_columns
rclpy.init(domain_id=int(sys.argv[1]))
node = rclpy.create_node("big_cloud_publisher")
reliable = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
pub = node.create_publisher(PointCloud2, "cloud_in", reliable)
cols = dict(np.load(sys.argv[2]))
end = time.monotonic() + 20.0
while pub.get_subscription_count() == 0 and time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
pub.publish(cloud_from_columns(cols, "base_link", float(sys.argv[3])))
end = time.monotonic() + 2.0
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
node.destroy_node()
rclpy.shutdown()
"""
"""Publishes one cloud from a child process: Fast DDS reads its XML profile once per process,
so this test process may have started DDS without the large-data profile (an earlier test
module) while a child always has it (the fixture's environment)."""


def _send(f: Feeder, cols: dict[str, np.ndarray], stamp: float) -> None:
    """Publish from a child process with the large-data profile until the node counts the
    cloud (its cloud_in is best effort)."""
    import tempfile

    with tempfile.TemporaryDirectory() as scratch:
        columns = Path(scratch) / "cloud.npz"
        np.savez(columns, **cols)
        for _ in range(3):
            seen = (f.status or {}).get("clouds_in", 0)
            child = subprocess.Popen(
                [sys.executable, "-c", PUBLISHER, str(domain_id()), str(columns), str(stamp),
                 str(Path(__file__).parent)],
            )  # fmt: skip
            try:
                if f.wait(lambda seen=seen: (f.status or {}).get("clouds_in", 0) > seen, 30.0):
                    return
            finally:
                try:
                    child.wait(timeout=30.0)
                except subprocess.TimeoutExpired:
                    child.kill()
                    child.wait()
    raise AssertionError("the node never received the cloud")


def _grid(response: Any) -> np.ndarray:
    info = response.map.info
    return np.array(response.map.data, dtype=np.int8).reshape(info.height, info.width)


def test_services_answer_during_a_long_scan_and_see_whole_scans(
    ros_domain: int, tmp_path: Path
) -> None:
    from nav_msgs.srv import GetMap
    from std_srvs.srv import Trigger

    from mfp_mapper.mapio.mapfile import read_map_file

    path = tmp_path / "map.npz"
    node = NodeProcess(ros_domain, {**PARAMS, "map_path": str(path)}, tmp_path / "node.log")
    f = Feeder()
    try:
        assert f.wait_connected(30.0), node.log()
        assert f.wait(lambda: f.status is not None, 10.0)
        _odom(f, T0 - 1.0, T0 + 3.0)
        _send(f, _room_scan(20_000, 1), T0)
        status = f.wait_status(lambda s: s["clouds_integrated"] == 1, 60.0)
        assert status["clouds_integrated"] == 1, (status, node.log()[-3000:])
        before = _grid(f.call(f.get_map, GetMap.Request()))
        voxels_before = f.status["voxels"]

        _send(f, _room_scan(BIG_SCAN_POINTS, 2), T0 + 1.0)
        t_sent = time.monotonic()
        query_cols = _room_scan(10, 3)
        f.query_pub.publish(cloud_from_columns(query_cols, "odom", T0 + 1.0))
        get_map = f.get_map.call_async(GetMap.Request())
        save = f.save.call_async(Trigger.Request())
        answered: dict[str, float] = {}
        integrated_at: list[float] = []

        def progress() -> bool:
            now = time.monotonic() - t_sent
            if f.results and "query" not in answered:
                answered["query"] = now
            for name, fut in (("get_map", get_map), ("save_map", save)):
                if fut.done() and name not in answered:
                    answered[name] = now
            if (f.status or {}).get("clouds_integrated", 0) >= 2 and not integrated_at:
                integrated_at.append(now)
            return len(answered) == 3 and bool(integrated_at)

        assert f.wait(progress, 300.0), (answered, integrated_at, node.log()[-3000:])
        print(f"answered after {answered} s; the scan integrated after {integrated_at[0]:.2f} s")
        # every service answered before the scan was in the map, with the map before it
        assert max(answered.values()) < integrated_at[0], (answered, integrated_at)
        assert np.array_equal(_grid(get_map.result()), before)
        assert save.result().success, save.result().message
        assert read_map_file(path).voxels.s.shape[0] == voxels_before
        assert f.results[0].width == len(query_cols["x"])
        status = f.wait_status(lambda s: s["voxels"] > voxels_before, 10.0)
        assert status["voxels"] > voxels_before and node.alive()
    finally:
        f.destroy()
        assert node.stop() == 0, node.log()[-3000:]
    assert "Traceback" not in node.log()


def _write_box_map(path: Path, voxels: float) -> tuple[int, np.ndarray]:
    """A map file of a dense box of about ``voxels`` voxels; returns the voxel count and
    their ``s``."""
    from mfp_mapper import Mapper
    from mfp_mapper.core.store import VoxelArrays
    from mfp_mapper.mapio.mapfile import write_map

    side = round(voxels ** (1 / 3))
    grid = np.stack(np.meshgrid(*(np.arange(side),) * 3, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(0)
    ijk = (grid - side // 2).astype(np.int32)
    count = len(ijk)
    s = rng.uniform(0.01, 5.0, count)
    mapper = Mapper.from_arrays(
        VoxelArrays(ijk, s, np.ones(count), np.full(count, T0)), resolution=RES, frame_id="odom"
    )
    write_map(path, mapper)
    return count, s


def _launch_escalation(proc: subprocess.Popen[bytes]) -> int:
    """What ``ros2 launch`` does on Ctrl-C: SIGINT, SIGTERM 5 s later, SIGKILL 5 s after."""
    for sig, wait in ((signal.SIGINT, 5.0), (signal.SIGTERM, 5.0)):
        proc.send_signal(sig)
        try:
            return proc.wait(wait)
        except subprocess.TimeoutExpired:
            continue
    proc.kill()
    return proc.wait(10.0)


@pytest.mark.slow
def test_large_map_saved_intact_under_launch_escalation(ros_domain: int, tmp_path: Path) -> None:
    """A map of ``SHUTDOWN_VOXELS`` voxels loaded at start, ``save_on_shutdown``: after the
    escalation the file holds that map, and no temporary file is left."""
    from mfp_mapper.mapio.mapfile import read_map_file

    path = tmp_path / "big.npz"
    count, s = _write_box_map(path, SHUTDOWN_VOXELS)
    os.utime(path, (1.0, 1.0))
    params = {**PARAMS, "map_path": str(path), "save_on_shutdown": True, "status_period": 1.0}
    node = NodeProcess(ros_domain, params, tmp_path / "node.log")
    f = Feeder()
    try:
        assert f.wait(lambda: f.status is not None and f.status["voxels"] == count, 120.0), (
            node.log()[-3000:]
        )
    finally:
        f.destroy()
    t0 = time.monotonic()
    rc = _launch_escalation(node.proc)
    took = time.monotonic() - t0
    node.stop()
    log = node.log()
    print(f"{count} voxels: node exited {rc} after {took:.1f} s")
    assert path.stat().st_mtime > 1.0, log[-3000:]  # saved at shutdown
    saved = read_map_file(path)
    assert saved.voxels.s.shape[0] == count
    np.testing.assert_allclose(np.sort(saved.voxels.s), np.sort(s), rtol=1e-6)
    assert not list(tmp_path.glob(".*mfp-tmp")), list(tmp_path.iterdir())
    assert rc == 0, log[-3000:]
    assert "Traceback" not in log


def test_sigterm_during_the_save_lets_it_finish(ros_domain: int, tmp_path: Path) -> None:
    """SIGINT starts the final save; a SIGTERM right after does not cut it short."""
    from mfp_mapper.mapio.mapfile import read_map_file

    path = tmp_path / "map.npz"
    count, _ = _write_box_map(path, 2e6)
    os.utime(path, (1.0, 1.0))
    params = {**PARAMS, "map_path": str(path), "save_on_shutdown": True}
    node = NodeProcess(ros_domain, params, tmp_path / "node.log")
    f = Feeder()
    try:
        assert f.wait(lambda: f.status is not None and f.status["voxels"] == count, 120.0), (
            node.log()
        )
    finally:
        f.destroy()
    node.proc.send_signal(signal.SIGINT)
    assert f.wait(lambda: "SIGINT: stopping" in node.log(), 10.0), node.log()
    node.proc.send_signal(signal.SIGTERM)
    rc = node.proc.wait(20.0)
    node.stop()
    assert rc == 0, node.log()
    assert path.stat().st_mtime > 1.0
    assert read_map_file(path).voxels.s.shape[0] == count
    assert not list(tmp_path.glob(".*mfp-tmp"))


def test_autosave_and_a_tiled_map_path(ros_domain: int, tmp_path: Path) -> None:
    """``autosave_period`` writes the map without a service call; ``map_path`` a directory:
    ``~/save_map`` and the autosave write a tiled map there, which a new node loads."""
    from mfp_mapper.mapio.loading import load_map

    tiled = tmp_path / "tiled"
    tiled.mkdir()
    params = {**PARAMS, "map_path": str(tiled), "autosave_period": 0.5}
    node = NodeProcess(ros_domain, params, tmp_path / "node.log")
    f = Feeder()
    try:
        assert f.wait_connected(30.0), node.log()
        assert f.wait(lambda: f.status is not None, 10.0)
        _odom(f, T0 - 1.0, T0 + 2.0)
        _send(f, _room_scan(5_000, 4), T0)
        status = f.wait_status(lambda s: s["clouds_integrated"] == 1, 30.0)
        assert status["clouds_integrated"] == 1, node.log()
        assert f.wait(lambda: (tiled / "index.json").is_file(), 10.0), node.log()
        assert "saved" in node.log()
        assert load_map(tiled).num_voxels == status["voxels"]
        index_mtime = (tiled / "index.json").stat().st_mtime
        f.wait(lambda: False, 1.5)  # three autosave periods with no new scan: not rewritten
        assert (tiled / "index.json").stat().st_mtime == index_mtime
    finally:
        f.destroy()
        assert node.stop() == 0, node.log()
    assert "Is a directory" not in node.log()


def test_sigint_during_a_get_map_burst_exits_cleanly(ros_domain: int, tmp_path: Path) -> None:
    from nav_msgs.srv import GetMap

    for k in range(3):
        log = tmp_path / f"node{k}.log"
        node = NodeProcess(ros_domain, {**PARAMS, "save_on_shutdown": False}, log)
        f = Feeder()
        try:
            assert f.wait(f.get_map.service_is_ready, 30.0), node.log()
            pending = [f.get_map.call_async(GetMap.Request()) for _ in range(30)]
            some = 5 + 5 * k
            f.wait(lambda p=pending, n=some: sum(x.done() for x in p) >= n, 5.0)
            node.proc.send_signal(signal.SIGINT)
            rc = node.proc.wait(15.0)
        finally:
            f.destroy()
            node.stop()
        text = node.log()
        assert rc == 0, text[-3000:]
        assert "Traceback" not in text and "take_message" not in text, text[-3000:]
        assert "[WARN]" not in text, text[-3000:]


@pytest.mark.parametrize("stop", ["cleanup", "shutdown", "sigterm"])
def test_a_save_racing_a_stop_answers_and_the_node_survives(
    ros_domain: int, tmp_path: Path, stop: str
) -> None:
    """Cleanup, shutdown or SIGTERM while ``~/save_map`` writes: the caller gets its answer,
    the file holds the map, no InvalidHandle (the answer used to be sent on a destroyed
    service, ending spin) and the node ends or goes on as asked."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    from std_srvs.srv import Trigger

    from mfp_mapper.mapio.mapfile import read_map_file

    path = tmp_path / "map.npz"
    count, _ = _write_box_map(path, 4e6)
    params = {**PARAMS, "map_path": str(path), "save_on_shutdown": False, "autostart": False}
    node = NodeProcess(ros_domain, params, tmp_path / "node.log")
    f = Feeder()
    change = f.node.create_client(ChangeState, "/mfp_mapper/change_state")
    rc = None
    try:
        assert change.wait_for_service(30.0), node.log()
        request = ChangeState.Request()
        request.transition.id = Transition.TRANSITION_CONFIGURE
        assert f.call(change, request, timeout=120.0).success, node.log()[-3000:]
        assert f.save.wait_for_service(10.0)
        loaded = path.stat().st_ino  # a save replaces the file (a new inode), never edits it
        saving = f.save.call_async(Trigger.Request())
        assert f.wait(lambda: bool(list(tmp_path.glob(".*mfp-tmp"))) or saving.done(), 60.0)
        assert not saving.done(), "the save ended before the stop: make the map larger"
        if stop == "sigterm":
            node.proc.send_signal(signal.SIGTERM)
        else:
            request.transition.id = (
                Transition.TRANSITION_CLEANUP
                if stop == "cleanup"
                else Transition.TRANSITION_INACTIVE_SHUTDOWN
            )
            moved = change.call_async(request)
            assert f.wait(moved.done, 60.0), node.log()[-3000:]
            assert moved.result().success, node.log()[-3000:]
        assert f.wait(saving.done, 60.0), node.log()[-3000:]
        assert saving.result().success, saving.result().message
        if stop == "sigterm":
            rc = node.proc.wait(30.0)
        else:
            f.wait(lambda: False, 1.0)  # the node would die right after the answer
            assert node.alive(), node.log()[-3000:]
    finally:
        f.destroy()
        code = node.stop()
    log = node.log()
    assert (rc if rc is not None else code) == 0, log[-3000:]
    assert "InvalidHandle" not in log and "Traceback" not in log, log[-3000:]
    assert path.stat().st_ino != loaded  # written by the save, whole
    assert read_map_file(path).voxels.s.shape[0] == count


def test_sigterms_after_the_shutdown_save_exit_0(ros_domain: int, tmp_path: Path) -> None:
    """SIGINT, then SIGTERM every few milliseconds until the process ends (launch's
    escalation, at its worst moment: after the save, before the exit): exit code 0."""
    path = tmp_path / "map.npz"
    params = {**PARAMS, "map_path": str(path), "save_on_shutdown": True}
    node = NodeProcess(ros_domain, params, tmp_path / "node.log")
    f = Feeder()
    try:
        assert f.wait(lambda: f.status is not None, 60.0), node.log()
    finally:
        f.destroy()
    node.proc.send_signal(signal.SIGINT)
    deadline = time.monotonic() + 30.0
    while node.proc.poll() is None and time.monotonic() < deadline:
        if "saved" in node.log():
            node.proc.send_signal(signal.SIGTERM)
        time.sleep(0.002)
    rc = node.proc.wait(10.0)
    node.stop()
    assert path.is_file(), node.log()
    assert rc == 0, node.log()[-3000:]


def test_autosave_without_a_map_path_and_a_failing_autosave_say_so_once(
    ros_domain: int, tmp_path: Path
) -> None:
    """``autosave_period`` with no ``map_path``: one warning at start. An autosave that
    fails every period (its folder is a file): one error line, not one per period."""
    quiet = NodeProcess(ros_domain, {**PARAMS, "autosave_period": 0.1}, tmp_path / "quiet.log")
    f = Feeder()
    try:
        assert f.wait(lambda: f.status is not None, 60.0), quiet.log()
        f.wait(lambda: False, 1.0)
    finally:
        f.destroy()
        assert quiet.stop() == 0, quiet.log()
    assert quiet.log().count("map_path is empty: nothing is autosaved") == 1, quiet.log()

    blocker = tmp_path / "afile"
    blocker.write_text("")
    params = {**PARAMS, "map_path": str(blocker / "map.npz"), "autosave_period": 0.1}
    node = NodeProcess(ros_domain, params, tmp_path / "node.log")
    f = Feeder()
    try:
        assert f.wait_connected(60.0), node.log()
        assert f.wait(lambda: f.status is not None, 10.0)
        _odom(f, T0 - 1.0, T0 + 2.0)
        _send(f, _room_scan(5_000, 4), T0)
        status = f.wait_status(lambda s: s["clouds_integrated"] == 1, 30.0)
        assert status["clouds_integrated"] == 1, node.log()
        assert f.wait(lambda: "failed" in node.log(), 10.0), node.log()
        f.wait(lambda: False, 2.0)  # twenty autosave periods
    finally:
        f.destroy()
        node.stop()
    failures = [line for line in node.log().splitlines() if "map.npz' failed" in line]
    assert len(failures) == 1, failures
