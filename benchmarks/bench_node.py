"""End-to-end benchmark of the ROS 2 node: lidar streams through real DDS on loopback.

    .venv/bin/python benchmarks/bench_node.py                 # both streams, 15 s each
    .venv/bin/python benchmarks/bench_node.py --stream vlp16 --duration 30

The node runs in its own process (``python -m mfp_mapper.ros.node``); this process is the
driver: odometry at 50 Hz and one de-skewable sweep every 0.1 s, stamped with the wall
clock at the start of the sweep, from a robot driving and turning through
``synthetic.BoxWorld``. Subscribers to ``~/degree_of_occupancy`` and ``~/projected_map``
make the node publish them (1 Hz), so publishing is part of the bill. Both processes use
``config/fastdds_large_data.xml`` (``--dds all``) unless ``--dds mapper`` (the node only, as
the launch file does when the driver has no profile) or ``--dds none`` (Fast DDS's defaults;
``--default-dds``): clouds the middleware lost are ``clouds_lost_in_transport``
(``benchmarks/bench_transport.py`` compares the three).
Figures come from the node's ``~/status`` (its own counters) and from /proc for the node's
total CPU:

- latency: node clock when ``Mapper.integrate`` returned minus the cloud's header stamp
  (includes the 0.1 s sweep the de-skew has to wait odometry for, and DDS transport);
- rate: clouds integrated a second in a window of ``--duration`` s between two status
  messages, after ``WARMUP_S`` s of streaming; rays per second;
- integration CPU: CPU time of the integration thread (parse, place, integrate) over
  wall time, as a share of one core; node CPU: the whole node process;
- CPU ms per integrated cloud by thread, from ``~/status`` ``cpu_s`` (a node that has it):
  inputs (taking clouds, odometry, TF; a node that has the input thread), executor (the other
  ROS callbacks), worker (parse, place), walker (integrate), publisher (map outputs; also per
  publication), other (DDS and the rest of the process: with ``threads`` above 1, the core's
  own threads, which then walk the scan while the walker waits).

Streams: VLP-16 (16 x 1800 = 28.8k points, 0.1 m) and an OS1-128-like lidar
(128 x 1024 = 131k points, 0.2 m, elevations -22.5..22.5 deg), both simulated; ``--stream
ouster``: the real OS1-128 scans of ``../shared/data/ouster_street`` (0.2 m), sent in the
order 0 1 2 1 0 1 2 ... as the driver publishes them: organized 128 x 1024 clouds of 48-byte
points (the ouster-ros layout; firings with no return are zeros, ~24k of 131k; a per-point
time ``t`` from the column, so the node de-skews), odometry interpolated between the
recording's poses. The node's own timing per integrated scan is printed by stage (queued,
parse, place, walk, merge; ``~/status`` ``stage_s``) with the latency from the cloud's
arrival to the map (``received_latency``). ``--core`` (the default for ``ouster``) first
maps the same messages in a child process without ROS, through the same loop (parse,
place, ``Mapper.integrate``, and ``Mapper.stage`` + ``commit`` as the node does), so the
node's time per scan reads as a ratio of the core's, measured in the same run.

``--stream norlab``: the 14 real VLP-32C-like scans of ``../shared/data/norlab_sequence``
(~41k points, x y z, in base_link) looped at 10 Hz with the recording's odometry (the robot
barely moves: every scan reaches nearly the whole map); ``--resolution`` sets the map's
(0.2 m by default). ``--baseline REF`` runs the node of another commit too (``git archive``
into the log directory), alternating with this checkout's ``--repeat`` times, the same
stream and parameters (``--param NAME=VALUE``; ``--baseline-param`` for the baseline's own):
the ratio of the two under the same load is the figure to read on a shared machine.

    .venv/bin/python benchmarks/bench_node.py --stream norlab --resolution 0.1 --baseline main

``--big-scan 2e6``: service latency while one large scan integrates (item of issue 18).
A static robot in a 30 x 30 m room (0.1 m voxels) sends a small scan, then one of that
many points (1024 rows x 2048 azimuths, -30..30 deg); while the node integrates it, a
hit-probability query, a GetMap call and a ``~/save_map`` call go out every 0.5 s, each
once the previous one answered. Reported: the integration time (cloud received to
integrated, from ~/status) and each service's latency (max and median) during it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DDS_PROFILE = ROOT / "config" / "fastdds_large_data.xml"
sys.path[:0] = [str(ROOT / "test"), str(ROOT / "test" / "ros")]
sys.path.insert(0, str(ROOT))

from box_world import BoxWorld  # noqa: E402
from ros_helpers import (  # noqa: E402
    Feeder,
    NodeProcess,
    Trajectory,
    cloud_from_columns,
    odom_msg,
    set_ros_env,
    simulate_scan,
    stamp_msg,
    tf_publishers,
    yaw_quaternion,
)

from mfp_mapper.sensing.pointcloud import PackedCloud  # noqa: E402
from mfp_mapper.sources.scan_pattern import scan_directions  # noqa: E402

STREAMS: dict[str, dict[str, Any]] = {
    "vlp16": {
        "elevations": np.arange(-15.0, 16.0, 2.0),
        "azimuths": 1800,
        "resolution": 0.1,
        "time_field": "time",
    },
    "os1-128": {
        "elevations": np.linspace(-22.5, 22.5, 128),
        "azimuths": 1024,
        "resolution": 0.2,
        "time_field": "t",
    },
}
SCAN_PERIOD = 0.1
ODOM_PERIOD = 0.02
LIDAR_HEIGHT = 1.8
OUSTER = ROOT.parent / "shared" / "data" / "ouster_street"
NORLAB = ROOT.parent / "shared" / "data" / "norlab_sequence"
"""``--stream norlab``: 14 real VLP-32C-like scans (~41k points) looped at 10 Hz."""
OUSTER_SEQUENCE = (0, 1, 2, 1)
"""``--stream ouster``: the recording's three scans sent back and forth, one every 0.1 s."""
WARMUP_S = 3.0
"""Seconds of streaming before the measured window."""
CORE_SCANS = 12
"""Clouds the ``--core`` child maps (the medians leave the first out)."""
OUSTER_COLUMNS = 1024
OUSTER_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2", "<u2", "<u4"],
        "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32],
        "itemsize": 48,
    }
)
"""The point layout of the ouster-ros driver (x y z, padding, intensity, t in ns from the
sweep's start, reflectivity, ring, ambient, range in mm): 48 bytes a point."""


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _ouster_records(k: int) -> np.ndarray:
    """Scan ``k`` of ``ouster_street`` as the driver's organized (128, 1024) cloud.

    The files keep the firings that returned, beam after beam, each beam's along the sweep:
    a beam ends where the column index falls back by more than half a turn; a point's column
    is its azimuth from the sweep's start (kept increasing within a beam; the ~0.2% of
    points that would pass column 1023 are left out). Empty cells are zeros."""
    raw = np.fromfile(OUSTER / "scans" / f"{k:06d}.bin", dtype=np.float32).reshape(-1, 4)
    az = np.degrees(np.arctan2(raw[:, 1], raw[:, 0]))
    step = 360.0 / OUSTER_COLUMNS
    col = np.floor(((az[0] + step / 2 - az) % 360.0) / step).astype(np.int64)
    row = np.cumsum(np.r_[True, np.diff(col) < -OUSTER_COLUMNS // 2]) - 1
    for i in range(1, len(col)):
        if row[i] == row[i - 1] and col[i] <= col[i - 1]:
            col[i] = col[i - 1] + 1
    keep = (col < OUSTER_COLUMNS) & (row < 128)
    rec = np.zeros((128, OUSTER_COLUMNS), OUSTER_DTYPE)
    r, c, pts = row[keep], col[keep], raw[keep]
    for i, axis in enumerate("xyz"):
        rec[axis][r, c] = pts[:, i]
    rec["reflectivity"][r, c] = np.clip(pts[:, 3], 0, 65535).astype(np.uint16)
    rec["range"][r, c] = np.round(1000 * np.linalg.norm(pts[:, :3], axis=1)).astype(np.uint32)
    rec["ring"] = np.arange(128, dtype=np.uint16)[:, None]
    rec["t"] = np.round(np.arange(OUSTER_COLUMNS) * SCAN_PERIOD / OUSTER_COLUMNS * 1e9).astype(
        np.uint32
    )[None, :]
    return rec


class OusterPoses:
    """Poses of ``--stream ouster``: the recording's, ``OUSTER_SEQUENCE`` at 10 Hz,
    interpolated in between (position linearly, rotation by slerp)."""

    def __init__(self) -> None:
        from scipy.spatial.transform import Rotation

        m = np.loadtxt(OUSTER / "poses.txt").reshape(-1, 3, 4)
        self.positions = m[:, :, 3]
        self.rotations = Rotation.from_matrix(m[:, :, :3])

    def at(self, rel: float) -> tuple[np.ndarray, np.ndarray]:
        """Position and quaternion (x y z w) ``rel`` seconds into the stream."""
        from scipy.spatial.transform import Slerp

        i, frac = divmod(rel / SCAN_PERIOD, 1.0)
        a = OUSTER_SEQUENCE[int(i) % len(OUSTER_SEQUENCE)]
        b = OUSTER_SEQUENCE[(int(i) + 1) % len(OUSTER_SEQUENCE)]
        pos = (1 - frac) * self.positions[a] + frac * self.positions[b]
        rot = Slerp([0.0, 1.0], self.rotations[[a, b]])([frac])[0]
        return pos, rot.as_quat()


class NorlabPoses:
    """Poses of ``--stream norlab``: the recording's odometry of scan ``k % 14`` at
    ``k * 0.1`` s, linearly interpolated in between (the robot barely moves: ~1 cm)."""

    def __init__(self) -> None:
        from mfp_mapper.sources.pose_files import read_odometry_csv

        rows = read_odometry_csv(NORLAB / "trajectory.csv")
        self.positions = np.asarray(rows["position"], dtype=np.float64)
        self.quaternions = np.asarray(rows["quaternion"], dtype=np.float64)

    def at(self, rel: float) -> tuple[np.ndarray, np.ndarray]:
        """Position and quaternion (x y z w) ``rel`` seconds into the stream."""
        count = len(self.positions)
        i, frac = divmod(rel / SCAN_PERIOD, 1.0)
        a, b = int(i) % count, (int(i) + 1) % count
        pos = (1 - frac) * self.positions[a] + frac * self.positions[b]
        q = (1 - frac) * self.quaternions[a] + frac * self.quaternions[b]
        return pos, q / np.linalg.norm(q)


def _norlab_clouds() -> list[PackedCloud]:
    """The norlab scans as x y z float32 clouds in base_link (the lidar frame)."""
    from mfp_mapper.sensing.pointcloud import pack_columns
    from mfp_mapper.sources.scan_files import read_vtk_points

    clouds = []
    for path in sorted((NORLAB / "scans").glob("cloud_*.vtk")):
        xyz = read_vtk_points(path).astype(np.float32)
        clouds.append(pack_columns({a: xyz[:, i].copy() for i, a in enumerate("xyz")}))
    return clouds


def _precompute(stream: dict[str, Any], n_scans: int) -> tuple[Trajectory, list[dict]]:
    """Sweeps of a loop of ``n_scans`` (relative times); the yaw turns once per loop."""
    traj = Trajectory(0.0, velocity=(1.0, 0.2, 0.0), yaw_rate=2 * np.pi / (n_scans * SCAN_PERIOD))
    dirs = scan_directions(stream["elevations"], stream["azimuths"])
    world = BoxWorld()
    scans = []
    for k in range(n_scans):
        xyz, offsets = simulate_scan(
            world, dirs, stream["azimuths"], traj, k * SCAN_PERIOD, LIDAR_HEIGHT, SCAN_PERIOD
        )
        cols: dict[str, np.ndarray] = {a: xyz[:, i].astype(np.float32) for i, a in enumerate("xyz")}
        cols["intensity"] = np.full(len(xyz), 20.0, np.float32)
        if stream["time_field"] == "t":
            cols["t"] = np.round(offsets * 1e9).astype(np.uint32)
        else:
            cols["time"] = offsets.astype(np.float32)
        scans.append(cols)
    return traj, scans


class TfPoses:
    """``--tf-poses``: the base pose on /tf (odom -> base_link) and the lidar mount on
    /tf_static instead of an odometry topic and the lidar.* parameters."""

    def __init__(self, feeder: Feeder, mount: tuple[float, float, float]) -> None:
        from geometry_msgs.msg import TransformStamped
        from tf2_msgs.msg import TFMessage

        self.TFMessage, self.TransformStamped = TFMessage, TransformStamped
        self.tf_pub, self.static_pub = tf_publishers(feeder.node)
        self.static_pub.publish(
            TFMessage(transforms=[self._tf("base_link", "lidar", 0.0, mount, (0, 0, 0, 1))])
        )

    def _tf(self, parent: str, child: str, stamp: float, t: Any, q: Any) -> Any:
        tf = self.TransformStamped()
        tf.header.frame_id, tf.child_frame_id = parent, child
        tf.header.stamp = stamp_msg(stamp)
        tr = tf.transform.translation
        tr.x, tr.y, tr.z = (float(v) for v in t)
        r = tf.transform.rotation
        r.x, r.y, r.z, r.w = (float(v) for v in q)
        return tf

    def publish(self, stamp: float, position: Any, quaternion: Any) -> None:
        tf = self._tf("odom", "base_link", stamp, position, quaternion)
        self.tf_pub.publish(self.TFMessage(transforms=[tf]))


@dataclass
class Stream:
    """What the driver sends: ``clouds`` (packed, sent in turn, the ``k``-th at ``k *
    SCAN_PERIOD``), the base pose ``pose(rel)`` (position, quaternion x y z w) ``rel``
    seconds into the stream, the lidar's height on the base and the core resolution."""

    name: str
    clouds: list[PackedCloud]
    pose: Callable[[float], tuple[np.ndarray, np.ndarray]]
    resolution: float
    mount_z: float
    frame: str = "lidar"
    """The clouds' frame: ``lidar`` (mounted ``mount_z`` above base_link) or base_link."""

    @property
    def points(self) -> int:
        return int(np.mean([c.width * c.height for c in self.clouds]))


def make_stream(name: str, n_scans: int, resolution: float | None = None) -> Stream:
    """The clouds and poses of a stream (``STREAMS``, ``norlab`` or ``ouster``); the map
    resolution the stream's own unless ``resolution``."""
    stream = _make_stream(name, n_scans)
    if resolution:
        stream.resolution = resolution
    return stream


def _make_stream(name: str, n_scans: int) -> Stream:
    from mfp_mapper.sensing.pointcloud import pack_columns, pack_records

    if name == "norlab":
        if not NORLAB.is_dir():
            raise SystemExit(f"--stream norlab: {NORLAB} not found")
        return Stream(name, _norlab_clouds(), NorlabPoses().at, 0.2, 0.0, "base_link")
    if name == "ouster":
        if not OUSTER.is_dir():
            raise SystemExit(f"--stream ouster: {OUSTER} not found")
        clouds = [pack_records(_ouster_records(k)) for k in OUSTER_SEQUENCE]
        return Stream(name, clouds, OusterPoses().at, 0.2, 0.0, "base_link")
    stream = STREAMS[name]
    print(f"[{name}] precomputing {n_scans} sweeps ...", flush=True)
    traj, scans = _precompute(stream, n_scans)
    loop = n_scans * SCAN_PERIOD

    def pose(rel: float) -> tuple[np.ndarray, np.ndarray]:
        rel %= loop
        return traj.position(rel), np.array(yaw_quaternion(float(traj.yaw(rel))))

    clouds = [pack_columns(cols) for cols in scans]
    return Stream(name, clouds, pose, stream["resolution"], LIDAR_HEIGHT)


def _odom(stamp: float, position: np.ndarray, quaternion: np.ndarray) -> Any:
    msg = odom_msg(stamp, position, 0.0)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in quaternion)
    return msg


def run_stream(
    stream: Stream,
    duration: float,
    workdir: Path,
    threads: int | None,
    tf_poses: bool = False,
    node_env: dict[str, str] | None = None,
    queue_size: int = 0,
    extra: dict[str, Any] | None = None,
    tree: Path | None = None,
) -> dict[str, Any]:
    """Stream to a node for ``duration`` s; ``extra``: more node parameters; ``tree``: the
    checkout whose node runs (default: this one)."""
    from mfp_mapper.ros.messages import cloud_msg

    domain = int(os.environ["ROS_DOMAIN_ID"])
    params: dict[str, Any] = {
        "resolution": stream.resolution,
        "sensor_model.max_range": 100.0,
        "publish_rate": 1.0,
        "status_period": 1.0,
        "odom_wait": 1.0,
    }
    if threads is not None:  # else the node's own default
        params["threads"] = threads
    if queue_size:
        params["cloud_queue_size"] = queue_size
    params.update(extra or {})
    if tf_poses:
        params["frame_id"] = "odom"
    elif stream.frame != "base_link":
        params["lidar.translation"] = [0.0, 0.0, stream.mount_z]
    # another commit's node reads its own parameter file (it may lack newer settings)
    own = {} if tree is None else {"params_file": tree / "config" / "mfp_mapper.yaml"}
    node = NodeProcess(
        domain, params, workdir / f"{stream.name}.log", env=node_env, cwd=tree, **own
    )
    feeder = Feeder()
    tf = TfPoses(feeder, (0.0, 0.0, stream.mount_z)) if tf_poses else None
    # built once: the driver's own CPU stays small (it shares the cores with the node)
    msgs = [cloud_msg(c, stream.frame, stamp_msg(0.0)) for c in stream.clouds]

    def pose(stamp: float, rel: float) -> None:
        position, quaternion = stream.pose(rel)
        if tf is not None:
            tf.publish(stamp, position, quaternion)
        else:
            feeder.odom_pub.publish(_odom(stamp, position, quaternion))

    try:
        # a node compiling its kernels into a cold cache (--cold-cache) subscribes after it
        if not feeder.wait_connected(300.0):
            raise RuntimeError(f"node not discovered:\n{node.log()[-2000:]}")
        feeder.wait(lambda: feeder.status is not None, 10.0)
        if os.environ.get("BENCH_DEBUG"):
            (workdir / "node.pid").write_text(str(node.pid))
        # the window: from the first status after WARMUP_S of streaming (the first scans
        # also load the compiled kernels) to the first one ``duration`` s later
        before: dict[str, Any] | None = None
        after: dict[str, Any] | None = None
        cpu0 = wall0 = driver0 = load0 = 0.0
        samples: list[float | None] = []  # latency_last_s of each status in the window
        last_uptime = None
        start = time.time()
        next_odom, next_scan, sent, k = start, start, 0, 0
        while after is None and time.time() - start < WARMUP_S + duration + 30.0:
            now = time.time()
            if now >= next_odom:
                pose(now, now - start)
                next_odom += ODOM_PERIOD
            if now >= next_scan:
                msg = msgs[k % len(msgs)]
                msg.header.stamp = stamp_msg(start + k * SCAN_PERIOD)
                feeder.cloud_pub.publish(msg)
                sent += 1
                k += 1
                next_scan += SCAN_PERIOD
            feeder.spin(max(0.0, min(next_odom, next_scan) - time.time()))
            st = feeder.status or {}
            if before is not None and st.get("uptime_s") != last_uptime:
                last_uptime = st.get("uptime_s")
                samples.append(st.get("latency_last_s"))
            if before is None:
                if now - start >= WARMUP_S and st.get("clouds_integrated", 0) >= 1:
                    before, cpu0, wall0 = dict(st), _cpu_seconds(node.pid), time.time()
                    driver0, load0 = time.process_time(), os.getloadavg()[0]
            elif st.get("uptime_s", 0.0) >= before["uptime_s"] + duration:
                after = dict(st)
        wall = time.time() - wall0
        cpu_node = _cpu_seconds(node.pid) - cpu0
        driver = time.process_time() - driver0
        if before is None or after is None:
            raise RuntimeError(f"no status window: nothing integrated\n{node.log()[-2000:]}")
        if os.environ.get("BENCH_DEBUG"):
            print(json.dumps(after), node.log()[-3000:], sep="\n")
    finally:
        feeder.destroy()
        node.stop()
    after["latency_samples_s"] = [round(v, 3) for v in samples if v is not None]
    after["driver_cpu_share"] = round(driver / wall, 3)  # this process: the lidar driver
    after["load_average"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    return _report(stream, after["uptime_s"] - before["uptime_s"], wall, cpu_node, before, after)


def _mean_since(before: dict[str, Any], after: dict[str, Any], key: str) -> float | None:
    """The mean of ``key`` over the clouds integrated between two status messages."""
    n0, n1 = before["clouds_integrated"], after["clouds_integrated"]
    if n1 <= n0 or after.get(key) is None:
        return None
    total = after[key] * n1 - (before.get(key) or 0.0) * n0
    return round(total / (n1 - n0), 3)


def _report(
    stream: Stream,
    duration: float,
    wall: float,
    cpu_node: float,
    before: dict[str, Any],
    after: dict[str, Any],
) -> dict[str, Any]:
    integrated = after["clouds_integrated"] - before["clouds_integrated"]
    drops = {
        k: v - before["clouds_dropped"].get(k, 0)
        for k, v in after["clouds_dropped"].items()
        if v - before["clouds_dropped"].get(k, 0)
    }
    cpu_int = after["integration_cpu_s"] - before["integration_cpu_s"]
    pub_n = after["publish_count"] - before["publish_count"]
    pub_s = after["publish_total_s"] - before["publish_total_s"]
    pub_locked = after["publish_locked_total_s"] - before["publish_locked_total_s"]
    n = max(integrated, 1)
    stages = {  # (a node without these counters: none)
        k: round(1000 * (v - before["stage_s"].get(k, 0.0)) / n, 1)
        for k, v in after.get("stage_s", {}).items()
    }
    received = _mean_since(before, after, "received_latency_mean_s")
    cpu0, cpu1 = before.get("cpu_s", {}), after.get("cpu_s", {})  # (older nodes: none)
    threads = {k: v - cpu0[k] for k, v in cpu1.items() if k in cpu0}
    if "process" in threads:  # DDS, rclpy and the rest: the process less the named threads
        threads["other"] = threads["process"] - sum(v for k, v in threads.items() if k != "process")
    lost = after["clouds_lost_transport"] - before["clouds_lost_transport"]
    result = {
        "stream": stream.name,
        "resolution_m": stream.resolution,
        "points_per_scan": stream.points,
        "window_s": round(duration, 2),
        "clouds_sent": after["clouds_in"] - before["clouds_in"] + lost,
        "clouds_received": after["clouds_in"] - before["clouds_in"],
        "clouds_lost_in_transport": lost,
        "clouds_integrated": integrated,
        "clouds_dropped": drops,
        "rate_hz": round(integrated / duration, 2),
        "rays_per_s": round((after["rays_used"] - before["rays_used"]) / duration),
        "latency_mean_s": _mean_since(before, after, "latency_mean_s"),
        "latency_max_s": max(after["latency_samples_s"], default=None),
        "latency_samples_s": after["latency_samples_s"],
        "received_latency_mean_s": received,
        "stage_ms_per_scan": stages,
        "integration_cpu_share_of_one_core": round(cpu_int / duration, 3),
        "integration_cpu_per_scan_ms": round(1000 * cpu_int / max(integrated, 1), 1),
        "cpu_ms_per_integrated_cloud": {k: round(1000 * v / n, 1) for k, v in threads.items()},
        "publisher_cpu_ms_per_publication": (
            round(1000 * threads["publisher"] / pub_n, 1)
            if pub_n and "publisher" in threads
            else None
        ),
        "node_cpu_share_of_one_core": round(cpu_node / wall, 3),
        "driver_cpu_share_of_one_core": after["driver_cpu_share"],
        "load_average_start_end": after["load_average"],
        "publications": pub_n,
        "publish_ms_mean": round(1000 * pub_s / pub_n, 1) if pub_n else None,
        "publish_map_locked_ms_mean": round(1000 * pub_locked / pub_n, 1) if pub_n else None,
        "published_voxels": after["published_voxels"],
        # since the node started (the first publication of a loaded map included)
        "publish_map_locked_max_ms": _ms(after.get("publish_locked_max_s")),
        "map_wait_max_ms": _ms(after.get("map_wait_max_s")),
        "last_publication_slices": after.get("publish_slices"),
        "dropped_before_window": before["clouds_dropped"],
        "integrated_before_window": before["clouds_integrated"],
        "voxels": after["voxels"],
        "memory_mb": round(after["memory_bytes"] / 1e6, 1),
    }
    print(json.dumps(result, indent=2), flush=True)
    return result


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(1000 * seconds, 1)


def build_map(path: Path, resolution: float, scans: int, step: float) -> None:
    """A map file of ``scans`` norlab scans, each ``step`` m further along x (a robot
    driving through a growing map), integrated as the node does; ``--map-file``."""
    from mfp_mapper import Mapper
    from mfp_mapper.config.sections import PlacementSection, SensorModelSection
    from mfp_mapper.mapio import save_map
    from mfp_mapper.mapping.loop import ScanLoop
    from mfp_mapper.sensing.poses import Extrinsic, PoseBuffer
    from mfp_mapper.sources.scan_files import packed_cloud_message

    stream = make_stream("norlab", 14, resolution)
    t0 = 1000.0
    poses = PoseBuffer(max_age=1e9)
    for rel in np.arange(0.0, (scans + 1) * SCAN_PERIOD + 1e-9, ODOM_PERIOD):
        pos, q = stream.pose(float(rel))
        poses.add(t0 + rel, pos + [step * rel / SCAN_PERIOD, 0.0, 0.0], q)
    mapper = Mapper(resolution, max_range=100.0, threads=2, frame_id="odom")
    loop = ScanLoop(mapper, PlacementSection(), SensorModelSection(max_range=100.0))
    for k in range(scans):
        c = stream.clouds[k % len(stream.clouds)]
        msg = packed_cloud_message(c, t0 + k * SCAN_PERIOD, "base_link")
        placed = loop.place(loop.prepare(msg), poses, Extrinsic(translation=np.zeros(3)))
        mapper.integrate(placed.points, placed.origins, placed.stamp, placed.no_return)
    save_map(mapper, path)
    print(f"built {path}: {scans} norlab scans {step} m apart, {mapper.num_voxels} voxels")
    mapper.close()


def core_times(
    name: str, n_scans: int, threads: int, count: int, resolution: float | None = None
) -> dict[str, Any]:
    """Without ROS, in this process: the stream's first ``count`` clouds through the
    node's loop (parse, place) into two Mappers, one by ``Mapper.integrate`` (the core
    alone), one by ``stage`` + ``commit`` (what the node does); median ms of the scans
    after the first, per stage."""
    from mfp_mapper import Mapper
    from mfp_mapper.config.sections import MapSection, PlacementSection, SensorModelSection
    from mfp_mapper.mapping.loop import ScanLoop
    from mfp_mapper.sensing.poses import Extrinsic, PoseBuffer
    from mfp_mapper.sources.scan_files import packed_cloud_message

    threads = threads or MapSection().core("threads")  # 0: the node's default, automatic
    stream = make_stream(name, n_scans, resolution)
    t0 = 1_000.0
    poses = PoseBuffer(max_age=1e9)
    for rel in np.arange(0.0, (count + 1) * SCAN_PERIOD + 1e-9, ODOM_PERIOD):
        poses.add(t0 + rel, *stream.pose(float(rel)))
    extrinsic = Extrinsic(translation=np.array([0.0, 0.0, stream.mount_z]))
    direct = Mapper(stream.resolution, threads=threads, max_range=100.0)
    staged = Mapper(stream.resolution, threads=threads, max_range=100.0)
    loop = ScanLoop(direct, PlacementSection(), SensorModelSection())
    times: dict[str, list[float]] = {k: [] for k in ("parse", "place", "core", "walk", "merge")}
    for k in range(count):
        c = stream.clouds[k % len(stream.clouds)]
        msg = packed_cloud_message(c, t0 + k * SCAN_PERIOD, "lidar")
        clock = time.perf_counter()
        prepared = loop.prepare(msg)
        t_parse = time.perf_counter()
        placed = loop.place(prepared, poses, extrinsic)
        t_place = time.perf_counter()
        direct.integrate(placed.points, placed.origins, placed.stamp, placed.no_return)
        t_core = time.perf_counter()
        scan = staged.stage(placed.points, placed.origins, placed.stamp, placed.no_return)
        t_walk = time.perf_counter()
        staged.commit(scan)
        t_merge = time.perf_counter()
        for key, a, b in (("parse", clock, t_parse), ("place", t_parse, t_place),
                          ("core", t_place, t_core), ("walk", t_core, t_walk),
                          ("merge", t_walk, t_merge)):  # fmt: skip
            times[key].append(b - a)
    same = direct.num_voxels == staged.num_voxels
    direct.close()
    staged.close()
    return {
        "scans": count,
        "rays_per_scan": len(placed.points),
        "ms_per_scan": {k: round(1000 * float(np.median(v[1:])), 1) for k, v in times.items()},
        "staged_map_has_the_same_voxels": same,
    }


def _core_child(
    name: str, n_scans: int, threads: int | None, resolution: float | None = None
) -> dict[str, Any]:
    """``core_times`` in a fresh process (its own memory, as the node's)."""
    import subprocess

    out = subprocess.run(
        [
            sys.executable,
            __file__,
            "--core-child",
            name,
            str(n_scans),
            str(threads or 0),
            str(resolution or 0.0),
        ],  # fmt: skip
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    result = json.loads(out.strip().splitlines()[-1])
    print(f"[{name}] core without ROS: {json.dumps(result)}", flush=True)
    return result


def _room_scan(count: int) -> dict[str, np.ndarray]:
    """About ``count`` returns in a 30 x 30 m room (floor 2 m below, ceiling 6 m above)."""
    rows = max(1, count // 2048)
    el = np.radians(np.linspace(-30.0, 30.0, rows))
    az = np.linspace(-np.pi, np.pi, 2048, endpoint=False)
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        up = np.where(d[:, 2] > 0, 6.0 / d[:, 2], 2.0 / np.abs(d[:, 2]))
        t = np.minimum(np.minimum(15.0 / np.abs(d[:, 0]), 15.0 / np.abs(d[:, 1])), up)
    xyz = (d * t[:, None]).astype(np.float32)
    return {k: xyz[:, i] for i, k in enumerate("xyz")}


def run_big_scan(points: int, workdir: Path) -> dict[str, Any]:
    """Service latencies while one scan of ``points`` points integrates (``--big-scan``)."""
    from nav_msgs.srv import GetMap
    from std_srvs.srv import Trigger

    domain = int(os.environ["ROS_DOMAIN_ID"])
    params = {
        "resolution": 0.1, "frame_id": "odom", "publish_rate": 0.0, "status_period": 0.1,
        "odom_wait": 5.0, "sensor_model.max_range": 100.0, "point_cloud_min_z": -100.0,
        "point_cloud_max_z": 100.0, "map_path": str(workdir / "big_scan_map.npz"),
    }  # fmt: skip
    node = NodeProcess(domain, params, workdir / "big_scan.log")
    feeder = Feeder()
    t0 = 1_700_000_000.0
    lat: dict[str, list[float]] = {"query": [], "get_map": [], "save_map": []}
    when: dict[str, list[float]] = {k: [] for k in lat}  # sent, s after the cloud arrived
    try:
        if not feeder.wait_connected(60.0):
            raise RuntimeError(f"node not discovered:\n{node.log()[-2000:]}")
        feeder.wait(lambda: feeder.status is not None, 10.0)
        for t in np.arange(t0 - 1.0, t0 + 3.0, 0.05):
            feeder.odom_pub.publish(odom_msg(float(t), np.zeros(3), 0.0))
        for k, cols in enumerate((_room_scan(32_768), _room_scan(points))):
            while (feeder.status or {}).get("clouds_in", 0) <= k:
                feeder.cloud_pub.publish(cloud_from_columns(cols, "base_link", t0 + k))
                feeder.wait(lambda k=k: (feeder.status or {}).get("clouds_in", 0) > k, 5.0)
            if k == 0:
                feeder.wait(lambda: (feeder.status or {}).get("clouds_integrated", 0) >= 1, 60)
        received = time.monotonic()
        query = cloud_from_columns(_room_scan(2048), "odom", t0 + 1.0)
        pending: dict[str, Any] = {}
        sent: dict[str, float] = {}
        saves: list[Any] = []
        next_round = received
        while (feeder.status or {}).get("clouds_integrated", 0) < 2:
            now = time.monotonic()
            if now - received > 600:
                raise RuntimeError("the large scan was not integrated in 600 s")
            if now >= next_round and not pending:
                n_results = len(feeder.results)
                feeder.query_pub.publish(query)
                save = feeder.save.call_async(Trigger.Request())
                saves.append(save)
                pending = {
                    "query": lambda n=n_results: len(feeder.results) > n,
                    "get_map": feeder.get_map.call_async(GetMap.Request()).done,
                    "save_map": save.done,
                }
                sent = dict.fromkeys(pending, now)
                next_round = now + 0.5
            feeder.spin(0.005)
            for name, done in list(pending.items()):
                if done():
                    lat[name].append(time.monotonic() - sent[name])
                    when[name].append(round(sent[name] - received, 1))
                    del pending[name]
        integration = time.monotonic() - received
        status = dict(feeder.status or {})
        started = [  # "started after X s" of each save's answer: the wait for the map
            float(f.result().message.split("started after ")[1].split(" s")[0])
            for f in saves
            if f.done() and "started after" in f.result().message
        ]
    finally:
        feeder.destroy()
        node.stop()
    result = {
        "points": points,
        "integration_s": round(integration, 2),
        "voxels": status.get("voxels"),
        **{
            f"{name}_s": {
                "count": len(v),
                "max": round(max(v), 3) if v else None,
                "median": round(float(np.median(v)), 3) if v else None,
            }
            for name, v in lat.items()
        },
        "save_map_started_s": {
            "max": round(max(started), 3) if started else None,
            "median": round(float(np.median(started)), 3) if started else None,
        },
        "slowest_sent_at_s": {
            name: when[name][int(np.argmax(v))] if v else None for name, v in lat.items()
        },
    }
    print(json.dumps(result, indent=2), flush=True)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--stream",
        choices=[*STREAMS, "ouster", "norlab", "all"],
        default="all",
        help="all: the simulated streams (vlp16, os1-128); ouster: the real OS1-128 scans; "
        "norlab: the real VLP-32C-like scans",
    )
    parser.add_argument("--resolution", type=float, help="the map resolution (m)")
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="another node parameter (a JSON value or a string), repeatable",
    )
    parser.add_argument(
        "--baseline",
        metavar="REF",
        help="also run the node of this git commit (git archive into a temporary directory), "
        "alternating with this checkout's",
    )
    parser.add_argument(
        "--baseline-param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="node parameters of the baseline only (default: those of --param)",
    )
    parser.add_argument("--repeat", type=int, default=1, help="runs of each node, alternating")
    parser.add_argument(
        "--core",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="also time the same clouds without ROS (default: with --stream ouster)",
    )
    parser.add_argument("--core-child", nargs=4, help=argparse.SUPPRESS)
    parser.add_argument("--duration", type=float, default=15.0, help="seconds per stream")
    parser.add_argument("--scans", type=int, default=20, help="distinct sweeps in the loop")
    parser.add_argument("--logs", type=Path, help="keep the node logs in this directory")
    parser.add_argument(
        "--threads", type=int, help="the node's core threads (default: the node's default)"
    )
    parser.add_argument(
        "--queue-size", type=int, default=0, help="the node's cloud_queue_size (0: its default)"
    )
    parser.add_argument(
        "--tf-poses",
        action="store_true",
        help="poses on /tf and the lidar mount on /tf_static instead of odometry",
    )
    parser.add_argument(
        "--dds",
        choices=["all", "mapper", "none"],
        default="all",
        help="which processes get config/fastdds_large_data.xml: this driver and the node "
        "(all), the node only (mapper), neither (none: Fast DDS defaults)",
    )
    parser.add_argument(
        "--big-scan",
        type=float,
        metavar="POINTS",
        help="instead of the streams: service latency while a scan of POINTS integrates",
    )
    parser.add_argument("--default-dds", action="store_true", help="the same as --dds none")
    parser.add_argument("--json", type=Path, help="also write the results to this file")
    parser.add_argument(
        "--map-file",
        type=Path,
        help="start each node with this map (map_path, copied; not saved back); built when "
        "missing from --map-scans norlab scans --map-step m apart at --resolution",
    )
    parser.add_argument("--map-scans", type=int, default=14, help="scans of a built --map-file")
    parser.add_argument("--map-step", type=float, default=20.0, help="metres between them")
    parser.add_argument(
        "--cold-cache",
        action="store_true",
        help="each node compiles numba's kernels into an empty cache (NUMBA_CACHE_DIR)",
    )
    args = parser.parse_args()
    if args.core_child:
        name, n_scans, threads, res = args.core_child
        times = core_times(name, int(n_scans), int(threads), CORE_SCANS, float(res) or None)
        print(json.dumps(times))
        return 0
    if args.default_dds:
        args.dds = "none"
    import rclpy

    domain = int(os.environ.get("ROS_DOMAIN_ID") or os.getpid() % 90 + 10)  # a set one is kept
    set_ros_env(domain)
    node_env: dict[str, str] = {}
    if args.dds == "all":  # node and feeder alike (the node inherits this environment)
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(DDS_PROFILE)
    else:
        os.environ.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
        if args.dds == "mapper":
            node_env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(DDS_PROFILE)
    dds = {
        "all": f"{DDS_PROFILE} (driver and node)",
        "mapper": f"{DDS_PROFILE} (node only)",
        "none": "Fast DDS defaults",
    }[args.dds]
    source = "/tf + /tf_static" if args.tf_poses else "odometry + lidar.* parameters"
    print(f"node threads: {args.threads or 'the default'}; DDS profile: {dds}; poses: {source}")
    rclpy.init(domain_id=domain)
    results = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            logs = args.logs or Path(tmp)
            logs.mkdir(parents=True, exist_ok=True)
            if args.big_scan:
                run_big_scan(int(args.big_scan), logs)
                return 0
            extra = _params(args.param)
            if args.map_file is not None:
                if not args.map_file.exists():
                    build_map(args.map_file, args.resolution or 0.2, args.map_scans, args.map_step)
                copy = logs / ("start_map" + "".join(args.map_file.suffixes))
                extra["map_path"] = str(copy)
            nodes: list[tuple[str, Path | None, dict[str, Any]]] = [("this", None, extra)]
            if args.baseline:
                base_extra = _params(args.baseline_param) if args.baseline_param else extra
                if "map_path" in extra:
                    base_extra["map_path"] = extra["map_path"]
                nodes.insert(0, (args.baseline, _export(args.baseline, logs), base_extra))
            for name in STREAMS if args.stream == "all" else [args.stream]:
                core = args.core if args.core is not None else name == "ouster"
                before = (
                    _core_child(name, args.scans, args.threads, args.resolution) if core else None
                )
                stream = make_stream(name, args.scans, args.resolution)
                for rep in range(args.repeat):
                    for label, tree, params in nodes:
                        print(f"[{name}] run {rep + 1}/{args.repeat}: node of {label}", flush=True)
                        env = dict(node_env)
                        if args.cold_cache:
                            cache = Path(tempfile.mkdtemp(prefix="numba_cold_", dir=logs))
                            env["NUMBA_CACHE_DIR"] = str(cache)
                        if args.map_file is not None:
                            import shutil

                            shutil.copyfile(args.map_file, extra["map_path"])
                        result = run_stream(
                            stream,
                            args.duration,
                            logs,
                            args.threads,
                            args.tf_poses,
                            env,
                            args.queue_size,
                            params,
                            tree,
                        )
                        result["node"] = label
                        results.append(result)
                if before is not None:  # the core before and after the node: its time drifts
                    after = _core_child(name, args.scans, args.threads, args.resolution)
                    results[-1]["core_ms_per_scan"] = _core_pair(before, after)
    finally:
        rclpy.try_shutdown()
    if args.json:
        args.json.write_text(json.dumps(results))
    print(f"load average at the end: {os.getloadavg()[0]:.2f} (1 min), on {os.cpu_count()} cores")
    print(
        "\nstream      node      res   pts/scan  rate(Hz)  latency mean/max (s)  integ. CPU  "
        "node CPU  drops  map pubs (ms, locked ms, voxels)"
    )
    for r in results:
        if not r["clouds_integrated"]:
            print(f"{r['stream']:<10} nothing integrated: {r['clouds_dropped']}")
            continue
        print(
            f"{r['stream']:<10} {r['node'][:8]:<8} {r['resolution_m']:>4}  "
            f"{r['points_per_scan']:>8}  "
            f"{r['rate_hz']:>8}  {r['latency_mean_s']:.3f} / {r['latency_max_s']:.3f}"
            f"          {100 * r['integration_cpu_share_of_one_core']:>5.0f}%    "
            f"{100 * r['node_cpu_share_of_one_core']:>5.0f}%  "
            f"{sum(r['clouds_dropped'].values()):>5}"
            f"  {r['publications']} ({r['publish_ms_mean']}, {r['publish_map_locked_ms_mean']}, "
            f"{r['published_voxels']})"
        )
        print(
            f"{'':<10} since start: longest map-lock hold by a publication "
            f"{r['publish_map_locked_max_ms']} ms (the last read in {r['last_publication_slices']} "
            "slices), longest wait of a scan for the map "
            f"{r['map_wait_max_ms']} ms; before the window {r['integrated_before_window']} "
            f"integrated, dropped {r['dropped_before_window']}"
        )
    for r in results:
        if r["clouds_integrated"] and r["stage_ms_per_scan"]:
            _print_split(r)
    return 0


def _params(pairs: list[str]) -> dict[str, Any]:
    """``NAME=VALUE`` node parameters: a JSON value, else the string."""
    out: dict[str, Any] = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _export(ref: str, workdir: Path) -> Path:
    """The tree of git commit ``ref`` in a directory of ``workdir`` (``git archive``)."""
    import subprocess

    target = workdir / f"tree-{ref.replace('/', '_')}"
    target.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", ref], check=True, capture_output=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(target)], input=archive, check=True)
    return target


def _core_pair(before: dict[str, Any], after: dict[str, Any]) -> dict[str, Any]:
    """The core's ms per scan measured before and after the node ran: their mean, and both."""
    b, a = before["ms_per_scan"], after["ms_per_scan"]
    return {k: round((b[k] + a[k]) / 2, 1) for k in b} | {"before": b, "after": a}


def _print_split(r: dict[str, Any]) -> None:
    """Where an integrated scan's time went in the node; against the core's, same clouds."""
    st = r["stage_ms_per_scan"]
    walker, worker = st["walk"] + st["merge"], st["parse"] + st["place"]
    print(
        f"\n{r['stream']}: ms per integrated scan in the node: "
        + ", ".join(f"{k} {v:.1f}" for k, v in st.items())
        + f"; walker (walk + merge) {walker:.1f}, worker (parse + place) {worker:.1f}: at most "
        f"{1000 / max(walker, worker, 1e-9):.1f} Hz; cloud received -> integrated "
        f"{r['received_latency_mean_s']} s mean; load average {r['load_average_start_end'][0]}"
        f" -> {r['load_average_start_end'][1]} on {os.cpu_count()} cores, the driver (this "
        f"process) {100 * r['driver_cpu_share_of_one_core']:.0f}% of a core"
    )
    cpu = r.get("cpu_ms_per_integrated_cloud")
    if cpu:
        total = cpu.get("process", 0.0)
        print(
            "  CPU ms per integrated cloud by thread: "
            + ", ".join(f"{k} {v:.1f}" for k, v in cpu.items())
            + f"; publisher {r['publisher_cpu_ms_per_publication']} ms a publication; one idle "
            f"core would take {1000 / max(total, 1e-9):.1f} clouds a second at this CPU"
        )
    core = r.get("core_ms_per_scan")
    if core:
        print(
            f"  the same clouds without ROS (mean of before/after the node): parse "
            f"{core['parse']}, place {core['place']}, Mapper.integrate {core['core']} "
            f"(stage {core['walk']} + commit {core['merge']}) ms a scan; node walker / "
            f"Mapper.integrate = {walker / core['core']:.2f}; the core alone allows "
            f"{1000 / core['core']:.1f} Hz"
        )


if __name__ == "__main__":
    sys.exit(main())
