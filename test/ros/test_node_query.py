"""``~/query`` (mfp_mapper_msgs/srv/QueryMap) and ``mfp-mapper call``, over real DDS.

A robot drives through a hall the other tests do not use: a solid wall, and a box of medium
returning 0.5 per metre of ray. Once its scans are integrated, the node's service says a
segment through free air is clear, one through the wall is not, one running 1 m inside the
medium is clear with probability near e^-0.5; the same questions asked offline of the map it
saved get the same answers; every service of the node answers ``mfp-mapper call``.
"""

from __future__ import annotations

import json
import math
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
    Trajectory,
    cloud_from_columns,
    domain_id,
    odom_msg,
    ros_env,
    simulate_scan,
    stamp_msg,
    tf_publishers,
)

from mfp_mapper.sources.scan_pattern import scan_directions
from mfp_mapper.sources.sim_scene import Medium, Scene, Solid

pytestmark = pytest.mark.ros

T0 = 2000.0
RES = 0.2
LIDAR_HEIGHT = 1.2
AZIMUTHS = 720
N_SCANS = 30
NODE = "mfp_query_test"
NODE_PARAMS: dict[str, Any] = {
    "resolution": RES,
    "frame_id": "odom",
    "sensor_model.max_range": 30.0,
    "cloud_queue_size": 40,
    "publish_rate": 0.0,
    "status_period": 0.25,
    "lidar.translation": [0.0, 0.0, LIDAR_HEIGHT],
    "odom_wait": 2.0,
    "odom_buffer": 10.0,
}
FREE_AIR = ((-1.0, -1.1, 1.3), (-7.0, -1.1, 1.3))
THROUGH_WALL = ((8.5, 0.5, 1.3), (11.5, 0.5, 1.3))
INSIDE_MEDIUM = ((3.9, 0.3, 1.3), (4.9, 0.3, 1.3))
SEGMENTS = (FREE_AIR, THROUGH_WALL, INSIDE_MEDIUM)


class HallWorld:
    """A closed hall with a solid wall across it at x = 10 m and, nearer, a box of medium
    (extinction 0.5 /m) from x = 3 to 6 m."""

    scene = Scene(
        room_lo=(-15.0, -10.0, 0.0),
        room_hi=(15.0, 10.0, 4.0),
        solids=(Solid("wall", (10.0, -10.0, 0.0), (10.5, 10.0, 4.0)),),
        media=(Medium("fog", (3.0, -3.0, 0.0), (6.0, 3.0, 3.0), extinction=0.5),),
    )

    def __init__(self) -> None:
        self._rng = np.random.default_rng(5)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        ranges, _ = self.scene.cast(origins, directions, self._rng)
        return ranges


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("query")


@pytest.fixture(scope="module")
def node(ros_domain: int, workdir: Path) -> Iterator[NodeProcess]:
    params = {**NODE_PARAMS, "map_path": str(workdir / "map.npz")}
    proc = NodeProcess(ros_domain, params, workdir / "node.log", name=NODE)
    try:
        yield proc
    finally:
        proc.stop()


@pytest.fixture(scope="module")
def feeder(node: NodeProcess) -> Iterator[Feeder]:
    f = Feeder(node_name=NODE, feeder_name="query_feeder")
    try:
        assert f.wait_connected(30.0), f"node not discovered:\n{node.log()[-3000:]}"
        yield f
    finally:
        f.destroy()


@pytest.fixture(scope="module")
def mapped(feeder: Feeder, node: NodeProcess) -> Feeder:
    """The robot drove N_SCANS sweeps (0.1 s each, 32 beams x 720 azimuths) slowly around the
    middle of the hall; all of them are integrated."""
    world = HallWorld()
    dirs = scan_directions(np.linspace(-30.0, 25.0, 32), azimuths=AZIMUTHS)
    traj = Trajectory(T0, velocity=(0.25, 0.08, 0.0), yaw_rate=0.2)
    assert feeder.wait(lambda: feeder.status is not None, 10.0)
    t = T0 - 0.05
    for k in range(N_SCANS):
        start = T0 + 0.1 + 0.2 * k
        while t <= start + 0.3:
            feeder.odom_pub.publish(odom_msg(t, traj.position(t), float(traj.yaw(t))))
            t += 0.05
        xyz, offsets = simulate_scan(world, dirs, AZIMUTHS, traj, start, LIDAR_HEIGHT)
        cols = {a: xyz[:, j].astype(np.float32) for j, a in enumerate("xyz")}
        cols["time"] = offsets.astype(np.float32)
        msg = cloud_from_columns(cols, "lidar", start)
        seen = (feeder.status or {}).get("clouds_in", 0)
        for _ in range(3):  # cloud_in is best effort: publish until the node counts it
            feeder.cloud_pub.publish(msg)
            if feeder.wait(lambda s=seen: (feeder.status or {}).get("clouds_in", 0) > s, 3.0):
                break
    status = feeder.wait_status(lambda st: st["clouds_integrated"] >= N_SCANS, 90.0)
    assert status is not None and status["clouds_integrated"] == N_SCANS, (
        f"status {status}\n{node.log()[-3000:]}"
    )
    return feeder


def _point(xyz: Any) -> Any:
    from geometry_msgs.msg import Point

    return Point(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


def _query(feeder: Feeder, points: Any = (), segments: Any = (), frame: str = "") -> Any:
    from mfp_mapper_msgs.srv import QueryMap

    client = feeder.node.create_client(QueryMap, f"/{NODE}/query")
    try:
        assert client.wait_for_service(10.0)
        request = QueryMap.Request()
        request.points = [_point(p) for p in points]
        request.segment_starts = [_point(a) for a, _ in segments]
        request.segment_ends = [_point(b) for _, b in segments]
        request.frame_id = frame
        return feeder.call(client, request, timeout=20.0)
    finally:
        feeder.node.destroy_client(client)


def _call(
    domain: int, *args: str, node: str = NODE, wait: float = 20.0
) -> subprocess.CompletedProcess[str]:
    """``mfp-mapper call ...`` exactly as a user types it, through the .venv's launcher when
    there is one (else the module), from a directory of its own."""
    launcher = ROOT / ".venv" / "bin" / "mfp-mapper"
    head = [str(launcher)] if launcher.is_file() else [sys.executable, "-m", "mfp_mapper.cli"]
    return subprocess.run(
        [*head, "call", *args, "--node", node, "--timeout", str(wait)],
        env=ros_env(domain), capture_output=True, text=True, timeout=wait + 60.0, cwd="/",
    )  # fmt: skip


def test_segments_say_clear_blocked_and_partly_clear(mapped: Feeder) -> None:
    r = _query(mapped, points=[(0.1, 0.1, 1.3), (10.1, 0.5, 1.3)], segments=SEGMENTS)
    assert r.success, r.message
    assert r.map_frame_id == "odom"
    free, wall, medium = r.segment_clear_probability
    assert free >= 0.9, free
    assert wall <= 0.1, wall
    assert medium == pytest.approx(math.exp(-0.5), abs=0.08), medium
    assert r.segment_unknown_length[0] == 0.0 and r.segment_unknown_length[2] == 0.0
    assert r.segment_unknown_length[1] > 0.5  # behind the wall's face: never seen
    assert list(r.observed) == [True, True]
    assert r.degree_of_occupancy[1] > 0.5 and r.hit_probability[1] > r.hit_probability[0]


def test_online_answers_equal_offline_answers(
    mapped: Feeder, workdir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from std_srvs.srv import Trigger

    from mfp_mapper.cli import main

    saved = mapped.call(mapped.save, Trigger.Request(), timeout=30.0)
    assert saved.success, saved.message
    online = _query(mapped, points=[(0.1, 0.1, 1.3)], segments=SEGMENTS)
    argv = ["query", str(workdir / "map.npz"), "0.1", "0.1", "1.3", "--json"]
    for a, b in SEGMENTS:
        argv += ["--segment", *map(str, (*a, *b))]
    capsys.readouterr()
    assert main(argv) == 0
    offline = json.loads(capsys.readouterr().out)
    assert [s["clear_probability"] for s in offline["segments"]] == pytest.approx(
        list(online.segment_clear_probability), rel=1e-9
    )
    assert [s["unknown_length"] for s in offline["segments"]] == pytest.approx(
        list(online.segment_unknown_length), abs=1e-9
    )
    assert offline["points"][0]["hit_probability"] == pytest.approx(online.hit_probability[0])


def test_bad_requests_get_a_message_and_the_node_stays(mapped: Feeder) -> None:
    r = _query(mapped, points=[(0.0, math.nan, 1.0)])
    assert not r.success and "not finite" in r.message and len(r.hit_probability) == 0
    r = _query(mapped, segments=[((0.0, 0.0, 1.0), (0.0, 0.0, 1.0e4))])
    assert not r.success and "query.max_segment_length" in r.message
    r = _query(mapped, points=[(0.0, 0.0, 1.0)], frame="no_such_frame")
    assert not r.success and "no_such_frame" in r.message
    r = _query(mapped, segments=[((0.0, 0.0, 1.0), (1.0, 0.0, 1.0))])
    assert r.success and len(r.segment_clear_probability) == 1
    st = mapped.wait_status(lambda s: s["query_service"]["refused"] >= 3, 5.0)
    assert st is not None and st["query_service"]["refused"] >= 3


def test_bulk_fields_answer_after_the_point_messages(mapped: Feeder) -> None:
    """points_xyz and segments_xyz (flat float64[]) are answered after points and the
    segment pairs, with the same numbers; a flat field of the wrong length is refused."""
    import array

    from mfp_mapper_msgs.srv import QueryMap

    one = _query(mapped, points=[(0.1, 0.1, 1.3)], segments=[FREE_AIR])
    client = mapped.node.create_client(QueryMap, f"/{NODE}/query")
    try:
        assert client.wait_for_service(10.0)
        request = QueryMap.Request()
        request.points = [_point((0.1, 0.1, 1.3))]
        request.points_xyz = array.array("d", [10.1, 0.5, 1.3, 0.1, 0.1, 1.3])
        request.segment_ends = [_point(INSIDE_MEDIUM[1])]
        request.segment_starts = [_point(INSIDE_MEDIUM[0])]
        request.segments_xyz = array.array("d", [*FREE_AIR[0], *FREE_AIR[1]])
        r = mapped.call(client, request, timeout=20.0)
        assert r.success, r.message
        assert len(r.hit_probability) == 3 and len(r.segment_clear_probability) == 2
        assert r.hit_probability[2] == r.hit_probability[0] == one.hit_probability[0]
        assert r.segment_clear_probability[1] == one.segment_clear_probability[0]
        request.points_xyz = array.array("d", [1.0, 2.0])
        bad = mapped.call(client, request, timeout=20.0)
        assert not bad.success and "points_xyz holds 2 numbers" in bad.message
    finally:
        mapped.node.destroy_client(client)


def test_a_point_in_the_robot_frame_is_moved_through_tf(mapped: Feeder) -> None:
    """With odom -> base_link on /tf, a point given in base_link is answered where it is in
    the map: 1.3 m above the robot the air is free; ahead of it, at x = 10.1 m, the wall."""
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    tf_pub, _ = tf_publishers(mapped.node)
    x, y = 1.0, 0.3
    tf = TransformStamped()
    tf.header.stamp = stamp_msg(time.time())  # the node takes /tf near its own clock
    tf.header.frame_id, tf.child_frame_id = "odom", "base_link"
    tf.transform.translation.x, tf.transform.translation.y = x, y
    tf.transform.rotation.w = 1.0
    assert mapped.wait(lambda: tf_pub.get_subscription_count() > 0, 10.0)
    for _ in range(10):
        tf_pub.publish(TFMessage(transforms=[tf]))
        here = _query(
            mapped, points=[(0.0, 0.0, 1.3), (10.1 - x, 0.5 - y, 1.3)], frame="/base_link"
        )
        if here.success:
            break
        mapped.wait(lambda: False, 0.2)
    assert here.success, f"{here.message}; status {mapped.status}"
    assert list(here.observed) == [True, True]
    assert here.degree_of_occupancy[0] < 0.1 < 0.5 < here.degree_of_occupancy[1]


def test_the_docs_python_client_example_runs(mapped: Feeder) -> None:
    """docs/examples/query_client.py, as node.md shows it, against the running node."""
    example = ROOT / "docs" / "examples" / "query_client.py"
    run = subprocess.run(
        [sys.executable, str(example), NODE],
        env=ros_env(domain_id()), capture_output=True, text=True, timeout=120, cwd="/",
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert "DoO" in run.stdout and "clear with probability" in run.stdout


def test_every_service_answers_mfp_mapper_call(mapped: Feeder, workdir: Path) -> None:
    domain = domain_id()
    status = _call(domain, "status", "--json")
    assert status.returncode == 0, status.stderr
    assert json.loads(status.stdout)["clouds_integrated"] >= N_SCANS
    query = _call(domain, "query", "0.1", "0.1", "1.3", "--json")
    assert query.returncode == 0, query.stderr
    (row,) = json.loads(query.stdout)["results"]
    assert row["observed"] is True
    segment = _call(domain, "segment", *map(str, (*FREE_AIR[0], *FREE_AIR[1])))
    assert segment.returncode == 0 and "clear with probability" in segment.stdout, segment.stderr
    grid = _call(domain, "getmap", "-o", str(workdir / "office"))
    assert grid.returncode == 0, grid.stderr
    assert (workdir / "office.pgm").read_bytes()[:2] == b"P5"
    assert "resolution:" in (workdir / "office.yaml").read_text()
    saved = _call(domain, "save", "--json")
    assert saved.returncode == 0 and json.loads(saved.stdout)["success"], saved.stderr
    box = _call(domain, "clear-bbox", "-14", "-9", "0", "-13", "-8", "1", "--json")
    assert box.returncode == 0 and json.loads(box.stdout)["cleared"] > 0, box.stderr
    life = _call(domain, "lifecycle", "--json")
    assert life.returncode == 0 and json.loads(life.stdout)["state"] == "active", life.stderr
    wrong = _call(domain, "lifecycle", "configure")
    assert wrong.returncode == 1 and "not allowed" in wrong.stderr
    assert "Traceback" not in wrong.stderr
    bad = _call(domain, "segment", "1", "2", "3")
    assert bad.returncode == 1 and "groups of 6" in bad.stderr
    # reset last: it empties the map
    reset = _call(domain, "reset")
    assert reset.returncode == 0, reset.stderr
    after = _query(mapped, points=[(0.1, 0.1, 1.3)])
    assert after.success and list(after.observed) == [False]
    assert math.isnan(after.degree_of_occupancy[0])


def test_calling_a_node_that_is_not_there_says_so(ros_domain: int) -> None:
    gone = _call(ros_domain, "status", node="nobody_here", wait=1.0)
    assert gone.returncode == 1 and "no /nobody_here/status message" in gone.stderr
    assert "Traceback" not in gone.stderr
