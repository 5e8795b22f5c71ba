"""Reading bags: open them (rosbags), pick topics, and the poses and transforms they hold.

Poses come from a nav_msgs/Odometry topic, or from the ``/tf`` chain above the cloud frame;
the lidar extrinsic from ``/tf_static`` (or the options). Errors are ``ReplayError`` with
the reason, before any cloud is read.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.offline.options import ReplayError as ReplayError  # defined with the options
from mfp_mapper.sensing.poses import (
    Extrinsic,
    PoseBuffer,
    odometry_sample,
    quaternion_to_matrix,
    transform_sample,
)

if TYPE_CHECKING:
    from mfp_mapper.offline.options import ReplayOptions

FloatArray = NDArray[np.float64]

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"


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


def pick_topic(reader: Any, msgtype: str, wanted: str | None, what: str, flag: str) -> str | None:
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
class Transforms:
    """/tf_static edges (child -> parent, pose) and /tf samples per (parent, child)."""

    static: dict[str, tuple[str, FloatArray, FloatArray]] = field(default_factory=dict)
    dynamic: dict[tuple[str, str], list[tuple[float, FloatArray, FloatArray]]] = field(
        default_factory=dict
    )

    def add(self, msg: Any, static: bool) -> None:
        for tf in msg.transforms:
            sample = transform_sample(tf)
            t, q = sample.translation, sample.quaternion
            if static:
                self.static[sample.child] = (sample.parent, t, q)
            else:
                key = (sample.parent, sample.child)
                self.dynamic.setdefault(key, []).append((sample.stamp, t, q))

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


def extrinsic_for(
    cloud_frame: str, body: str, tfs: Transforms, opts: ReplayOptions
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
class Poses:
    buffer: PoseBuffer
    body: str
    map_frame: str
    source: str


def odometry_poses(reader: Any, topic: str, opts: ReplayOptions) -> Poses:
    conns = [c for c in reader.connections if c.topic == topic]
    samples: list[tuple[float, FloatArray, FloatArray]] = []
    frames: Counter[tuple[str, str]] = Counter()
    for conn, _, raw in reader.messages(connections=conns):
        sample = odometry_sample(reader.deserialize(raw, conn.msgtype))
        samples.append((sample.stamp, sample.position, sample.quaternion))
        frames[(sample.frame_id, sample.child_frame_id)] += 1
    if not samples:
        raise ReplayError(f"the odometry topic {topic} has no messages")
    (map_frame, body), _ = frames.most_common(1)[0]
    if len(frames) > 1:
        raise ReplayError(
            f"odometry on {topic} changes frames ({', '.join(f'{a}->{b}' for a, b in frames)}): "
            "cannot chain them"
        )
    buffer = _buffer(samples, opts.max_gap)
    return Poses(buffer, body, map_frame, f"{topic} (nav_msgs/Odometry {map_frame} -> {body})")


def _buffer(samples: list[tuple[float, FloatArray, FloatArray]], max_gap: float) -> PoseBuffer:
    buffer = PoseBuffer(max_age=math.inf, max_gap=max_gap)
    for stamp, t, q in sorted(samples, key=lambda s: s[0]):
        buffer.add(stamp, t, q)
    return buffer


def tf_poses(cloud_frame: str, tfs: Transforms, opts: ReplayOptions) -> Poses:
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
            buf = _buffer(tfs.dynamic[(parent, child)], math.inf)
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
    return Poses(_buffer(samples, opts.max_gap), body, root, f"/tf chain {chain}")
