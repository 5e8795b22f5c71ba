"""Replay a recorded bag (ROS 1 ``.bag``, ROS 2 sqlite3 or mcap) into a Mapper, offline.

Reading is done with rosbags' ``AnyReader``, so no ROS installation is needed. The cloud
topic (``sensor_msgs/PointCloud2``) and the odometry topic (``nav_msgs/Odometry``) are found
automatically when the bag holds exactly one of each. Without an odometry topic, poses come
from ``/tf``: the chain of transforms from the cloud frame up to the odometry frame
(``odom``, or the root of the tree). The lidar extrinsic comes from ``/tf_static``; it is
the identity when the cloud frame is the odometry child frame; otherwise it must be given
(``--extrinsic`` or ``lidar.translation``/``lidar.rpy`` in the node's YAML).

The per-point work is the node's: ``mfp_mapper.sensing.pointcloud.parse_pointcloud2`` and
``mfp_mapper.sensing.poses.cloud_to_map`` (interpolation and de-skew), then ``Mapper.integrate``.
Nothing is written here: the caller saves the map (atomically) only when the replay
succeeded, so a failed replay never leaves a map that looks complete.
"""

from __future__ import annotations

import math
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.offline.options import ConfigError as ConfigError  # re-exported
from mfp_mapper.offline.options import ReplayError as ReplayError
from mfp_mapper.offline.options import ReplayOptions as ReplayOptions
from mfp_mapper.offline.options import options_from_yaml as options_from_yaml
from mfp_mapper.sensing.pointcloud import parse_pointcloud2, stamp_seconds
from mfp_mapper.sensing.poses import (
    Extrinsic,
    PoseBuffer,
    PoseUnavailable,
    cloud_to_map,
    quaternion_to_matrix,
    z_band,
)

FloatArray = NDArray[np.float64]

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"


# --- summary and progress ---------------------------------------------------------------------


@dataclass
class ReplaySummary:
    """What a replay did; ``format()`` gives the lines printed at the end."""

    bag: str
    cloud_topic: str = ""
    pose_source: str = ""
    map_frame: str = ""
    cloud_frame: str = ""
    extrinsic_source: str = ""
    deskew: bool = False
    scans_total: int = 0
    scans_used: int = 0
    scans_skipped: dict[str, int] = field(default_factory=dict)
    points_in: int = 0
    rays_used: int = 0
    rays_truncated: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    voxels: int = 0
    memory_bytes: int = 0
    seconds: float = 0.0
    seconds_core: float = 0.0
    seconds_poses: float = 0.0
    first_stamp: float | None = None
    last_stamp: float | None = None

    @property
    def rays_per_second(self) -> float:
        return self.rays_used / self.seconds if self.seconds > 0 else 0.0

    @property
    def share_outside_core(self) -> float:
        """Share of the replay time spent outside Mapper.integrate (reading, parsing, poses)."""
        return 1.0 - self.seconds_core / self.seconds if self.seconds > 0 else 0.0

    def format(self) -> str:
        skipped = sum(self.scans_skipped.values())
        dropped = {k: v for k, v in self.dropped.items() if v}
        lines = [
            f"bag          {self.bag}",
            f"clouds       {self.cloud_topic} (frame {self.cloud_frame or '?'})",
            f"poses        {self.pose_source}; map frame {self.map_frame or '?'}",
            f"extrinsic    {self.extrinsic_source}",
            f"de-skew      {'yes (per-point time)' if self.deskew else 'no'}",
            f"scans        {self.scans_used} used of {self.scans_total}"
            + (f"; skipped {skipped}: {_counts(self.scans_skipped)}" if skipped else ""),
            f"rays         {self.rays_used:,} used of {self.points_in:,} points"
            + (f"; {self.rays_truncated:,} cut at max range" if self.rays_truncated else ""),
            f"dropped      {_counts(dropped) if dropped else 'none'}",
            f"voxels       {self.voxels:,} ({self.memory_bytes / 2**20:.1f} MiB)",
            f"time         {self.seconds:.2f} s, {self.rays_per_second:,.0f} rays/s; "
            f"{100 * self.share_outside_core:.0f}% outside the core "
            f"(+{self.seconds_poses:.2f} s reading poses)",
        ]
        return "\n".join(lines)


def _counts(d: dict[str, int]) -> str:
    return ", ".join(f"{k} {v:,}" for k, v in sorted(d.items()))


class Progress:
    """A one-line progress bar on stderr: scans, rays/s and time left.

    On a terminal it redraws in place; otherwise it prints a line every ``interval`` s.
    """

    def __init__(
        self,
        total: int,
        stream: TextIO | None = None,
        enabled: bool = True,
        interval: float | None = None,
    ) -> None:
        self.total = max(total, 0)
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval = interval if interval is not None else (0.2 if self.tty else 5.0)
        self.t0 = time.perf_counter()
        self.last = -math.inf
        self.drawn = False

    def update(self, done: int, rays: int, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if not force and now - self.last < self.interval:
            return
        self.last = now
        elapsed = now - self.t0
        rate = rays / elapsed if elapsed > 0 else 0.0
        left = elapsed / done * (self.total - done) if done else math.nan
        width = 24
        filled = int(width * done / self.total) if self.total else width
        bar = "#" * filled + "." * (width - filled)
        text = (
            f"replay [{bar}] {done}/{self.total} scans  {rays / 1e6:.2f} M rays  "
            f"{rate / 1e3:,.0f} k rays/s  elapsed {_clock(elapsed)}  left {_clock(left)}"
        )
        if self.tty:
            self.stream.write("\r" + text)
        else:
            self.stream.write(text + "\n")
        self.stream.flush()
        self.drawn = True

    def close(self) -> None:
        if self.enabled and self.tty and self.drawn:
            self.stream.write("\n")
            self.stream.flush()


def _clock(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "--:--"
    s = int(round(seconds))
    return (
        f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"
    )


# --- reading the bag --------------------------------------------------------------------------


def resolve_bag_path(path: str | Path) -> Path:
    """The path AnyReader wants: a ROS 1 ``.bag`` file or a ROS 2 bag directory.

    A ``.db3``/``.mcap`` file inside a ROS 2 bag directory means that directory.
    """
    p = Path(path)
    if not p.exists():
        raise ReplayError(f"{p}: no such file or directory")
    if p.is_file() and p.suffix in (".db3", ".mcap"):
        if (p.parent / "metadata.yaml").exists():
            return p.parent
        raise ReplayError(
            f"{p}: a ROS 2 bag is a directory with metadata.yaml; this file has none beside it"
        )
    if p.is_dir() and not (p / "metadata.yaml").exists():
        raise ReplayError(f"{p}: not a ROS 2 bag (no metadata.yaml in this directory)")
    if p.is_file() and p.suffix != ".bag":
        raise ReplayError(f"{p}: not a bag (ROS 1 bags end in .bag, ROS 2 bags are directories)")
    return p


def open_reader(path: Path) -> Any:
    """An opened AnyReader; ReplayError when the bag cannot be read."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY))
        reader.open()
    except Exception as err:  # rosbags raises several error types for broken files
        raise ReplayError(f"{path}: cannot read the bag: {err}") from None
    return reader


def _pick_topic(reader: Any, msgtype: str, wanted: str | None, what: str, flag: str) -> str | None:
    topics = {c.topic: c.msgtype for c in reader.connections}
    listing = ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "none"
    if wanted is not None:
        if wanted not in topics:
            raise ReplayError(f"topic {wanted} is not in the bag; topics: {listing}")
        if topics[wanted] != msgtype:
            raise ReplayError(f"topic {wanted} has type {topics[wanted]}, expected {msgtype}")
        return wanted
    candidates = sorted(t for t, m in topics.items() if m == msgtype)
    if len(candidates) > 1:
        raise ReplayError(
            f"the bag has several {what} topics ({', '.join(candidates)}): choose one with {flag}"
        )
    return candidates[0] if candidates else None


def _frame(name: str) -> str:
    return name[1:] if name.startswith("/") else name


def _qmul(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product of xyzw quaternions (broadcast)."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def _compose(
    outer: tuple[FloatArray, FloatArray], inner: tuple[FloatArray, FloatArray]
) -> tuple[FloatArray, FloatArray]:
    """T_a_c = T_a_b * T_b_c with (translation, quaternion) pairs (broadcast)."""
    t1, q1 = outer
    t2, q2 = inner
    rotated = np.einsum("...ij,...j->...i", quaternion_to_matrix(q1), t2)
    return t1 + rotated, _qmul(q1, q2)


@dataclass
class _Transforms:
    """/tf_static edges (child -> parent, pose) and /tf samples per (parent, child)."""

    static: dict[str, tuple[str, FloatArray, FloatArray]] = field(default_factory=dict)
    dynamic: dict[tuple[str, str], list[tuple[float, FloatArray, FloatArray]]] = field(
        default_factory=dict
    )

    def add(self, msg: Any, static: bool) -> None:
        for tf in msg.transforms:
            parent, child = _frame(tf.header.frame_id), _frame(tf.child_frame_id)
            tr, rot = tf.transform.translation, tf.transform.rotation
            t = np.array([tr.x, tr.y, tr.z], dtype=np.float64)
            q = np.array([rot.x, rot.y, rot.z, rot.w], dtype=np.float64)
            if static:
                self.static[child] = (parent, t, q)
            else:
                stamp = stamp_seconds(tf.header.stamp)
                self.dynamic.setdefault((parent, child), []).append((stamp, t, q))

    def dynamic_parent(self, child: str) -> str | None:
        for parent, c in self.dynamic:
            if c == child:
                return parent
        return None

    def static_chain(self, top: str, bottom: str) -> tuple[FloatArray, FloatArray] | None:
        """T_top_bottom through /tf_static edges only; None when they do not connect."""
        t, q = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
        frame, seen = bottom, set()
        while frame != top:
            if frame not in self.static or frame in seen:
                return None
            seen.add(frame)
            parent, te, qe = self.static[frame]
            t, q = _compose((te, qe), (t, q))
            frame = parent
        return t, q


def _extrinsic_for(
    cloud_frame: str, body: str, tfs: _Transforms, opts: ReplayOptions
) -> tuple[Extrinsic, str]:
    if opts.extrinsic is not None:
        return opts.extrinsic, "given on the command line"
    if cloud_frame == body:
        return Extrinsic(), f"identity (the cloud frame is the odometry child frame {body})"
    chain = tfs.static_chain(body, cloud_frame)
    if chain is not None:
        t, q = chain
        return Extrinsic(t, q), f"/tf_static {body} <- {cloud_frame}: " + _describe(t, q)
    if opts.config_extrinsic is not None:
        return opts.config_extrinsic, "lidar.translation / lidar.rpy of the configuration"
    raise ReplayError(
        f"no lidar extrinsic: the cloud frame {cloud_frame!r} is not the odometry child frame "
        f"{body!r} and /tf_static has no chain {body} <- {cloud_frame}; give it with "
        "--extrinsic X Y Z ROLL PITCH YAW (or lidar.translation / lidar.rpy in --config)"
    )


def _describe(t: FloatArray, q: FloatArray) -> str:
    x, y, z, w = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return (
        f"xyz ({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) m, rpy ({roll:.3f}, {pitch:.3f}, {yaw:.3f}) rad"
    )


@dataclass
class _Poses:
    buffer: PoseBuffer
    body: str
    map_frame: str
    source: str


def _odometry_poses(reader: Any, topic: str, opts: ReplayOptions) -> _Poses:
    conns = [c for c in reader.connections if c.topic == topic]
    samples: list[tuple[float, FloatArray, FloatArray]] = []
    frames: Counter[tuple[str, str]] = Counter()
    for conn, _, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        samples.append(
            (
                stamp_seconds(msg.header.stamp),
                np.array([p.x, p.y, p.z]),
                np.array([o.x, o.y, o.z, o.w]),
            )
        )
        frames[(_frame(msg.header.frame_id), _frame(msg.child_frame_id))] += 1
    if not samples:
        raise ReplayError(f"the odometry topic {topic} has no messages")
    (map_frame, body), _ = frames.most_common(1)[0]
    if len(frames) > 1:
        raise ReplayError(
            f"odometry on {topic} changes frames ({', '.join(f'{a}->{b}' for a, b in frames)}): "
            "cannot chain them"
        )
    buffer = _buffer(samples, opts)
    return _Poses(buffer, body, map_frame, f"{topic} (nav_msgs/Odometry {map_frame} -> {body})")


def _buffer(samples: list[tuple[float, FloatArray, FloatArray]], opts: ReplayOptions) -> PoseBuffer:
    buffer = PoseBuffer(max_age=math.inf, max_gap=opts.max_gap)
    for stamp, t, q in sorted(samples, key=lambda s: s[0]):
        buffer.add(stamp, t, q)
    return buffer


def _tf_poses(cloud_frame: str, tfs: _Transforms, opts: ReplayOptions) -> _Poses:
    """Poses of the lowest moving frame above the cloud frame, from the /tf chain."""
    if not tfs.dynamic:
        raise ReplayError(
            "the bag has no nav_msgs/Odometry topic and no /tf transforms: no poses "
            "(give --odom-topic if the odometry topic has another type name)"
        )
    # walk up through static edges to the first frame that moves
    body = cloud_frame
    seen = set()
    while tfs.dynamic_parent(body) is None:
        if body not in tfs.static or body in seen:
            moving = sorted({c for _, c in tfs.dynamic})
            raise ReplayError(
                f"/tf does not connect the cloud frame {cloud_frame!r} to a moving frame "
                f"(frames moved by /tf: {', '.join(moving)}); give --odom-topic"
            )
        seen.add(body)
        body = tfs.static[body][0]
    # then up to the fixed frame: odom by default, else the root of the tree
    edges: list[tuple[str, str]] = []
    frame = body
    while True:
        parent = tfs.dynamic_parent(frame)
        static_parent = tfs.static.get(frame, (None,))[0]
        up = parent if parent is not None else static_parent
        if (
            up is None
            or frame == opts.fixed_frame
            or (opts.fixed_frame is None and frame == "odom")
        ):
            break
        if any(c == frame for _, c in edges) or len(edges) > 32:
            raise ReplayError(f"/tf has a loop through {frame!r}")
        edges.append((up, frame))
        frame = up
    if opts.fixed_frame is not None and frame != opts.fixed_frame:
        raise ReplayError(f"the fixed frame {opts.fixed_frame!r} is not above {body!r} in /tf")
    root = frame
    lowest = sorted(tfs.dynamic[edges[0]], key=lambda s: s[0])
    stamps = np.array([s[0] for s in lowest])
    t = np.array([s[1] for s in lowest])
    q = np.array([s[2] for s in lowest])
    keep = np.ones(stamps.size, dtype=bool)
    for parent, child in edges[1:]:
        if (parent, child) in tfs.dynamic:
            buf = _buffer(tfs.dynamic[(parent, child)], ReplayOptions(max_gap=math.inf))
            inside = (stamps >= (buf.earliest_stamp or 0)) & (stamps <= (buf.latest_stamp or 0))
            keep &= inside
            te = np.zeros_like(t)
            qe = np.tile([0.0, 0.0, 0.0, 1.0], (stamps.size, 1))
            if np.any(inside):
                te[inside], qe[inside] = buf.interpolate_quaternions(stamps[inside])
        else:
            _, te0, qe0 = tfs.static[child]
            te, qe = np.broadcast_to(te0, t.shape), np.broadcast_to(qe0, q.shape)
        t, q = _compose((te, qe), (t, q))
    samples = [(float(s), t[i], q[i]) for i, s in enumerate(stamps) if keep[i]]
    chain = " -> ".join([root, *[c for _, c in reversed(edges)]])
    return _Poses(_buffer(samples, opts), body, root, f"/tf chain {chain}")


# --- the replay -------------------------------------------------------------------------------


ScanCallback = Callable[[float, FloatArray, FloatArray], None]
"""Called with (stamp, points (N, 3), origins (3,) or (N, 3)) for every placed cloud."""


@dataclass
class ReplayResult:
    mapper: Mapper
    summary: ReplaySummary


def replay(
    bag: str | Path,
    opts: ReplayOptions | None = None,
    progress: bool | Progress = True,
    log: Callable[[str], None] | None = None,
    on_scan: ScanCallback | None = None,
) -> ReplayResult:
    """Map every cloud of ``bag``; ReplayError (with the reason) when it cannot be done.

    ``on_scan(stamp, points, origins)`` sees every placed cloud (map frame) just before it
    is integrated, e.g. to feed the same rays to another mapper.
    """
    opts = opts or ReplayOptions()
    path = resolve_bag_path(bag)
    reader = open_reader(path)
    try:
        return _replay(reader, path, opts, progress, log, on_scan)
    finally:
        reader.close()


def _replay(
    reader: Any,
    path: Path,
    opts: ReplayOptions,
    progress: bool | Progress,
    log: Callable[[str], None] | None,
    on_scan: ScanCallback | None,
) -> ReplayResult:
    summary = ReplaySummary(bag=str(path))
    cloud_topic = _pick_topic(reader, CLOUD_TYPE, opts.cloud_topic, "PointCloud2", "--cloud-topic")
    if cloud_topic is None:
        listing = ", ".join(sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections}))
        raise ReplayError(
            f"the bag has no sensor_msgs/PointCloud2 topic; topics: {listing or 'none'}"
        )
    odom_topic = None
    if not opts.use_tf:
        odom_topic = _pick_topic(reader, ODOM_TYPE, opts.odom_topic, "Odometry", "--odom-topic")
    summary.cloud_topic = cloud_topic
    cloud_conns = [c for c in reader.connections if c.topic == cloud_topic]
    summary.scans_total = sum(c.msgcount for c in cloud_conns)
    if opts.max_scans is not None:
        summary.scans_total = min(summary.scans_total, opts.max_scans)
    if summary.scans_total == 0:
        raise ReplayError(f"the cloud topic {cloud_topic} has no messages")

    # poses and transforms first: they are small, and a bag without them fails fast
    t_poses = time.perf_counter()
    tfs = _Transforms()
    tf_conns = [
        c for c in reader.connections if c.msgtype == TF_TYPE and c.topic in ("/tf", "/tf_static")
    ]
    want_dynamic = odom_topic is None
    read_conns = [c for c in tf_conns if c.topic == "/tf_static" or want_dynamic]
    try:
        if read_conns:
            for conn, _, raw in reader.messages(connections=read_conns):
                tfs.add(reader.deserialize(raw, conn.msgtype), static=conn.topic == "/tf_static")
        first_cloud = next(reader.messages(connections=cloud_conns))
        cloud_frame = _frame(
            reader.deserialize(first_cloud[2], first_cloud[0].msgtype).header.frame_id
        )
        if odom_topic is not None:
            poses = _odometry_poses(reader, odom_topic, opts)
        else:
            poses = _tf_poses(cloud_frame, tfs, opts)
    except ReplayError:
        raise
    except Exception as err:
        raise ReplayError(f"{path}: cannot read poses: {type(err).__name__}: {err}") from None
    if len(poses.buffer) == 0:
        raise ReplayError(f"no usable pose in {poses.source}")
    summary.seconds_poses = time.perf_counter() - t_poses
    summary.pose_source = poses.source
    summary.map_frame = poses.map_frame
    summary.cloud_frame = cloud_frame
    extrinsics: dict[str, Extrinsic] = {}
    ext, summary.extrinsic_source = _extrinsic_for(cloud_frame, poses.body, tfs, opts)
    extrinsics[cloud_frame] = ext

    mapper = Mapper(
        opts.resolution,
        max_range=opts.max_range,
        min_range=opts.min_range,
        decay_time=opts.decay_time,
        frame_id=poses.map_frame,
        threads=opts.threads,
        max_voxels=opts.max_voxels,
        keep_radius=opts.keep_radius,
    )
    bar = (
        progress
        if isinstance(progress, Progress)
        else Progress(summary.scans_total, enabled=bool(progress))
    )
    skipped: Counter[str] = Counter()
    dropped: Counter[str] = Counter()
    bad_example = ""
    cloud_span = [math.inf, -math.inf]
    t_loop = time.perf_counter()
    try:
        for done, (conn, _, raw) in enumerate(reader.messages(connections=cloud_conns), 1):
            if opts.max_scans is not None and done > opts.max_scans:
                break
            try:
                msg = reader.deserialize(raw, conn.msgtype)
                cloud = parse_pointcloud2(msg)
            except Exception as err:  # a damaged message (CloudFormatError or worse): skip, count
                skipped["bad_cloud"] += 1
                bad_example = bad_example or f"{type(err).__name__}: {err}"
                continue
            stamp = stamp_seconds(msg.header.stamp)
            cloud_span[0], cloud_span[1] = min(cloud_span[0], stamp), max(cloud_span[1], stamp)
            frame = _frame(msg.header.frame_id)
            if frame not in extrinsics:
                extrinsics[frame], _ = _extrinsic_for(frame, poses.body, tfs, opts)
            summary.points_in += cloud.points_in
            dropped.update(cloud.dropped)
            summary.deskew |= opts.deskew and cloud.time_offset is not None
            try:
                points, origins = cloud_to_map(
                    cloud, stamp, poses.buffer, extrinsics[frame], deskew=opts.deskew
                )
            except PoseUnavailable as err:
                skipped[f"no_pose_{err.reason}"] += 1
                continue
            points, origins, outside = z_band(
                points, origins, opts.point_cloud_min_z, opts.point_cloud_max_z
            )
            dropped["z_band"] += outside
            if on_scan is not None:
                on_scan(stamp, points, origins)
            t_core = time.perf_counter()
            result = mapper.integrate(points, origins, stamp)
            summary.seconds_core += time.perf_counter() - t_core
            summary.scans_used += 1
            summary.rays_used += result.rays_used
            summary.rays_truncated += result.rays_truncated
            dropped.update(result.dropped)
            if summary.first_stamp is None or summary.last_stamp is None:
                summary.first_stamp = summary.last_stamp = stamp
            summary.first_stamp = min(summary.first_stamp, stamp)
            summary.last_stamp = max(summary.last_stamp, stamp)
            bar.update(done, summary.rays_used)
        bar.update(summary.scans_used + sum(skipped.values()), summary.rays_used, force=True)
    finally:
        bar.close()
    summary.scans_skipped = dict(skipped)
    summary.dropped = {k: v for k, v in dropped.items() if v}
    summary.voxels = mapper.num_voxels
    summary.memory_bytes = mapper.memory_bytes
    summary.seconds = time.perf_counter() - t_loop
    if summary.scans_used == 0:
        raise ReplayError(_nothing_mapped(summary, poses, bad_example, cloud_span))
    if skipped and log is not None:
        log(
            f"warning: {sum(skipped.values())} of {summary.scans_total} scans skipped "
            f"({_counts(dict(skipped))})"
            + (f"; first bad cloud: {bad_example}" if bad_example else "")
        )
    return ReplayResult(mapper, summary)


def _nothing_mapped(
    summary: ReplaySummary, poses: _Poses, bad_example: str, cloud_span: list[float]
) -> str:
    reasons = _counts(summary.scans_skipped) or "none"
    text = f"no cloud could be mapped ({summary.scans_total} clouds; skipped: {reasons})"
    if bad_example:
        text += f"; first bad cloud: {bad_example}"
    if any(k.startswith("no_pose") for k in summary.scans_skipped):
        text += (
            f". No pose covers the clouds: poses from {poses.source} span "
            f"[{poses.buffer.earliest_stamp:.3f}, {poses.buffer.latest_stamp:.3f}] s, "
            f"the clouds (header stamps) [{cloud_span[0]:.3f}, {cloud_span[1]:.3f}] s"
            f" (max gap between poses {poses.buffer.max_gap} s)"
        )
    return text
