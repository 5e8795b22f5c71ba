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
- rate: clouds integrated / clouds sent, rays per second;
- integration CPU: CPU time of the integration thread (parse, place, integrate) over
  wall time, as a share of one core; node CPU: the whole node process.

Streams: VLP-16 (16 x 1800 = 28.8k points, 0.1 m) and an OS1-128-like lidar
(128 x 1024 = 131k points, 0.2 m, elevations -22.5..22.5 deg).

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


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


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

    def __init__(self, feeder: Feeder) -> None:
        from geometry_msgs.msg import TransformStamped
        from tf2_msgs.msg import TFMessage

        self.TFMessage, self.TransformStamped = TFMessage, TransformStamped
        self.tf_pub, self.static_pub = tf_publishers(feeder.node)
        self.static_pub.publish(
            TFMessage(transforms=[self._tf("base_link", "lidar", 0.0, [0, 0, LIDAR_HEIGHT], 0.0)])
        )

    def _tf(self, parent: str, child: str, stamp: float, t: Any, yaw: float) -> Any:
        tf = self.TransformStamped()
        tf.header.frame_id, tf.child_frame_id = parent, child
        tf.header.stamp = stamp_msg(stamp)
        tr = tf.transform.translation
        tr.x, tr.y, tr.z = (float(v) for v in t)
        r = tf.transform.rotation
        r.x, r.y, r.z, r.w = yaw_quaternion(yaw)
        return tf

    def publish(self, stamp: float, position: Any, yaw: float) -> None:
        tf = self._tf("odom", "base_link", stamp, position, yaw)
        self.tf_pub.publish(self.TFMessage(transforms=[tf]))


def run_stream(
    name: str,
    duration: float,
    n_scans: int,
    workdir: Path,
    threads: int,
    tf_poses: bool = False,
    node_env: dict[str, str] | None = None,
) -> dict[str, Any]:

    stream = STREAMS[name]
    print(f"[{name}] precomputing {n_scans} sweeps ...", flush=True)
    traj, scans = _precompute(stream, n_scans)
    points = int(np.mean([len(s["x"]) for s in scans]))
    domain = int(os.environ["ROS_DOMAIN_ID"])
    params: dict[str, Any] = {
        "resolution": stream["resolution"],
        "sensor_model.max_range": 100.0,
        "publish_rate": 1.0,
        "status_period": 1.0,
        "odom_wait": 1.0,
        "threads": threads,
    }
    if tf_poses:
        params["frame_id"] = "odom"
    else:
        params["lidar.translation"] = [0.0, 0.0, LIDAR_HEIGHT]
    node = NodeProcess(domain, params, workdir / f"{name}.log", env=node_env)
    feeder = Feeder()
    tf = TfPoses(feeder) if tf_poses else None

    def pose(stamp: float, rel: float) -> None:
        if tf is not None:
            tf.publish(stamp, traj.position(rel), float(traj.yaw(rel)))
        else:
            feeder.odom_pub.publish(odom_msg(stamp, traj.position(rel), float(traj.yaw(rel))))

    try:
        if not feeder.wait_connected(30.0):
            raise RuntimeError(f"node not discovered:\n{node.log()[-2000:]}")
        feeder.wait(lambda: feeder.status is not None, 10.0)
        cpu0, before = _cpu_seconds(node.pid), dict(feeder.status or {})
        if os.environ.get("BENCH_DEBUG"):
            (workdir / "node.pid").write_text(str(node.pid))
        start = time.time()
        next_odom, next_scan, sent, k = start, start, 0, 0
        loop = n_scans * SCAN_PERIOD
        while time.time() - start < duration:
            now = time.time()
            if now >= next_odom:
                pose(now, (now - start) % loop)
                next_odom += ODOM_PERIOD
            if now >= next_scan:
                cols = scans[k % n_scans]
                stamp = start + k * SCAN_PERIOD
                feeder.cloud_pub.publish(cloud_from_columns(cols, "lidar", stamp))
                sent += 1
                k += 1
                next_scan += SCAN_PERIOD
            feeder.spin(max(0.0, min(next_odom, next_scan) - time.time()))
        # keep odometry flowing until the node has drained its queue
        drain_end = time.time() + 3.0
        while time.time() < drain_end:
            now = time.time()
            pose(now, (now - start) % loop)
            feeder.spin(ODOM_PERIOD)
            st = feeder.status or {}
            done = st.get("clouds_integrated", 0) + sum(st.get("clouds_dropped", {}).values())
            if st.get("queued", 1) == 0 and done - _done(before) >= sent:
                break
        wall = time.time() - start
        cpu_node = _cpu_seconds(node.pid) - cpu0
        feeder.wait(lambda: (feeder.status or {}).get("uptime_s", 0) > before["uptime_s"] + 1, 3)
        after = dict(feeder.status or {})
        if os.environ.get("BENCH_DEBUG"):
            print(json.dumps(after), node.log()[-3000:], sep="\n")
    finally:
        feeder.destroy()
        node.stop()
    return _report(name, stream, points, sent, duration, wall, cpu_node, before, after)


def _done(status: dict[str, Any]) -> int:
    return status.get("clouds_integrated", 0) + sum(status.get("clouds_dropped", {}).values())


def _report(
    name: str,
    stream: dict[str, Any],
    points: int,
    sent: int,
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
    result = {
        "stream": name,
        "resolution_m": stream["resolution"],
        "points_per_scan": points,
        "clouds_sent": sent,
        "clouds_received": after["clouds_in"] - before["clouds_in"],
        "clouds_lost_in_transport": after["clouds_lost_transport"]
        - before["clouds_lost_transport"],
        "clouds_integrated": integrated,
        "clouds_dropped": drops,
        "rate_hz": round(integrated / duration, 2),
        "rays_per_s": round((after["rays_used"] - before["rays_used"]) / duration),
        "latency_mean_s": after["latency_mean_s"],
        "latency_max_s": after["latency_max_s"],
        "integration_cpu_share_of_one_core": round(cpu_int / duration, 3),
        "integration_cpu_per_scan_ms": round(1000 * cpu_int / max(integrated, 1), 1),
        "node_cpu_share_of_one_core": round(cpu_node / wall, 3),
        "publications": pub_n,
        "publish_ms_mean": round(1000 * pub_s / pub_n, 1) if pub_n else None,
        "publish_map_locked_ms_mean": round(1000 * pub_locked / pub_n, 1) if pub_n else None,
        "published_voxels": after["published_voxels"],
        "voxels": after["voxels"],
        "memory_mb": round(after["memory_bytes"] / 1e6, 1),
    }
    print(json.dumps(result, indent=2), flush=True)
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
    parser.add_argument("--stream", choices=[*STREAMS, "all"], default="all")
    parser.add_argument("--duration", type=float, default=15.0, help="seconds per stream")
    parser.add_argument("--scans", type=int, default=20, help="distinct sweeps in the loop")
    parser.add_argument("--logs", type=Path, help="keep the node logs in this directory")
    parser.add_argument("--threads", type=int, default=1, help="the node's core threads")
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
    args = parser.parse_args()
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
    print(f"node threads: {args.threads}; DDS profile: {dds}; poses: {source}")
    rclpy.init(domain_id=domain)
    results = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            logs = args.logs or Path(tmp)
            logs.mkdir(parents=True, exist_ok=True)
            if args.big_scan:
                run_big_scan(int(args.big_scan), logs)
                return 0
            for name in STREAMS if args.stream == "all" else [args.stream]:
                results.append(
                    run_stream(
                        name, args.duration, args.scans, logs, args.threads, args.tf_poses, node_env
                    )
                )
    finally:
        rclpy.try_shutdown()
    if args.json:
        args.json.write_text(json.dumps(results))
    print("\nstream      res   pts/scan  rate(Hz)  latency mean/max (s)  integ. CPU  node CPU")
    for r in results:
        print(
            f"{r['stream']:<10} {r['resolution_m']:>4}  {r['points_per_scan']:>8}  "
            f"{r['rate_hz']:>8}  {r['latency_mean_s']:.3f} / {r['latency_max_s']:.3f}"
            f"          {100 * r['integration_cpu_share_of_one_core']:>5.0f}%    "
            f"{100 * r['node_cpu_share_of_one_core']:>5.0f}%"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
