"""Bags as recordings (``open_bag``): open them (rosbags), pick topics, and the poses and
transforms they hold.

Bags are read with rosbags: no ROS installation is needed. The cloud topic
(``sensor_msgs/PointCloud2``) and the odometry topic (``nav_msgs/Odometry``) are found
automatically when the bag holds exactly one of each. Without an odometry topic (or with
``--tf``, ``use_tf_poses``), poses come from ``/tf``: the chain of transforms from the cloud
frame up to the fixed frame (``odom``, or the root of the tree). Or from a pose file matched by
stamp (``sources.pose_files``), or KISS-ICP (``sources.lidar_odometry``). The lidar extrinsic
comes from ``/tf_static``; it is the identity when the cloud frame is the odometry child frame;
otherwise it must be given (``--extrinsic`` or ``lidar.translation``/``lidar.rpy`` in the
node's YAML). Errors are ``ReplayError`` with the reason, before any cloud is mapped; a bag
damaged part way raises one naming the message reached. With ``second_return_topic`` (ouster-ros
``points2``) each cloud is paired with the second-return cloud of its stamp as the node pairs
them (``paired_clouds``).
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.config.frames import frame_name
from mfp_mapper.config.replay_options import ReplayError as ReplayError  # defined with the options
from mfp_mapper.config.replay_options import ReplayOptions
from mfp_mapper.sensing.pipeline import ReturnPair
from mfp_mapper.sensing.poses import Extrinsic, PoseBuffer, odometry_sample
from mfp_mapper.sensing.return_pairs import ReturnPairer
from mfp_mapper.sensing.tf_tree import TfTree, TransformUnavailable, frame_list
from mfp_mapper.sources import lidar_odometry
from mfp_mapper.sources.pose_files import read_poses
from mfp_mapper.sources.recording import Poses, RecordedCloud, Recording

FloatArray = NDArray[np.float64]

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"


# --- the bag as a recording --------------------------------------------------------------------


def open_bag(
    bag: str | Path,
    opts: ReplayOptions,
    poses: str | Path | None = None,
    log: Callable[[str], None] | None = None,
) -> Recording:
    """The bag ``bag`` as a recording: its clouds, with poses from its odometry or /tf,
    ``opts.replay.odometry``, or the pose file ``poses`` (TUM or odometry CSV matched by stamp, or
    ``identity``). ReplayError says why it cannot be used."""
    path = resolve_bag_path(bag)
    reader = open_reader(path)
    try:
        return _bag_recording(reader, path, opts, poses, log)
    except BaseException:
        reader.close()
        raise


def _bag_recording(
    reader: Any,
    path: Path,
    opts: ReplayOptions,
    poses: str | Path | None,
    log: Callable[[str], None] | None,
) -> Recording:
    second_topic = second_return_topic(reader, opts.placement.second_return_topic)
    if second_topic is not None and opts.replay.cloud_topic == second_topic:
        raise ReplayError(f"{second_topic} cannot be both the cloud and the second-return topic")
    cloud_topic = pick_topic(
        reader, CLOUD_TYPE, opts.replay.cloud_topic, "PointCloud2", "--cloud-topic", second_topic
    )
    if cloud_topic is None:
        listing = ", ".join(sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections}))
        raise ReplayError(
            f"the bag has no sensor_msgs/PointCloud2 topic; topics: {listing or 'none'}"
        )
    odom_topic = None
    if not opts.replay.use_tf_poses and poses is None and opts.replay.odometry is None:
        odom_topic = pick_topic(
            reader, ODOM_TYPE, opts.replay.odom_topic, "Odometry", "--odom-topic"
        )
    cloud_conns = [c for c in reader.connections if c.topic == cloud_topic]
    count = sum(c.msgcount for c in cloud_conns)
    if count == 0:
        raise ReplayError(f"the cloud topic {cloud_topic} has no messages")
    t_poses = time.perf_counter()
    if poses is not None:
        cloud_frame = _first_cloud_frame(reader, path, cloud_conns)
        found, tfs = read_poses(poses, cloud_frame, opts.placement.odom_max_gap), read_transforms()
    elif opts.replay.odometry is not None:
        cloud_frame = _first_cloud_frame(reader, path, cloud_conns)
        found, tfs = _estimated_poses(reader, path, opts, cloud_conns, cloud_frame, log)
    else:
        found, tfs, cloud_frame = _read_poses(reader, path, opts, odom_topic, cloud_conns)
    seconds_poses = time.perf_counter() - t_poses
    extrinsics: dict[str, Extrinsic] = {}
    extrinsics[cloud_frame], extrinsic_source = extrinsic_for(cloud_frame, found.body, tfs, opts)

    pairers: list[ReturnPairer] = []

    def clouds() -> Iterator[RecordedCloud]:
        if second_topic is not None:
            pairers[:] = [ReturnPairer()]
            second_conns = [c for c in reader.connections if c.topic == second_topic]
            yield from paired_clouds(reader, cloud_conns, second_conns, path, pairers[0])
            return
        for index, (conn, _, raw) in enumerate(read_messages(reader, cloud_conns, path)):
            yield RecordedCloud(index, partial(reader.deserialize, raw, conn.msgtype))

    def extrinsic_of(frame: str) -> Extrinsic:
        if frame not in extrinsics:
            extrinsics[frame], _ = extrinsic_for(frame, found.body, tfs, opts)
        return extrinsics[frame]

    return Recording(
        name=str(path),
        cloud_source=cloud_topic if second_topic is None else f"{cloud_topic} + {second_topic}",
        cloud_frame=cloud_frame,
        cloud_count=count,
        poses=found,
        extrinsic_source=extrinsic_source,
        read_clouds=clouds,
        extrinsic_of=extrinsic_of,
        release=reader.close,
        seconds_poses=seconds_poses,
        second_returns=lambda: pairers[0] if pairers else None,
        second_return_topic=second_topic or "",
    )


def second_return_topic(reader: Any, wanted: str) -> str | None:
    """The bag's topic of second-return clouds named by ``second_return_topic`` (as given,
    or with a leading ``/``: the node's name resolved in the root namespace); None when the
    setting is empty. ReplayError when the bag has no such PointCloud2 topic."""
    if not wanted:
        return None
    topics = {c.topic: c.msgtype for c in reader.connections}
    for name in (wanted, wanted if wanted.startswith("/") else "/" + wanted):
        if topics.get(name) == CLOUD_TYPE:
            return name
    listing = ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "none"
    raise ReplayError(
        f"second_return_topic {wanted!r} is not a PointCloud2 topic of the bag; topics: "
        f"{listing} (--second-return-topic '' maps the clouds without their second returns)"
    )


def paired_clouds(
    reader: Any, first_conns: list[Any], second_conns: list[Any], path: Path, pairer: ReturnPairer
) -> Iterator[RecordedCloud]:
    """The bag's first-return clouds, each with its second-return cloud (a ``ReturnPair``)
    or alone, as the live node pairs them (``sensing.return_pairs``), its clock the bag's
    receive times: in the order the pairer gives them out, each at the position of its
    first cloud among the first clouds. Both topics are read (and deserialized) in receive
    order; a damaged first cloud is given out where it lies, its ``load`` raising."""
    first_topics = {c.topic for c in first_conns}
    positions: dict[int, int] = {}
    count = 0

    def given_out(ready: list[Any]) -> Iterator[RecordedCloud]:
        for item in ready:
            first = item.first if isinstance(item, ReturnPair) else item
            yield RecordedCloud(positions.pop(id(first)), partial(_itself, item))

    for conn, receive_ns, raw in read_messages(reader, first_conns + second_conns, path):
        now = receive_ns * 1e-9
        yield from given_out(pairer.expired(now))
        try:
            msg = reader.deserialize(raw, conn.msgtype)
            _stamp_of(msg)
        except Exception as err:  # a damaged message
            if conn.topic in first_topics:
                yield RecordedCloud(count, partial(_raise, err))
                count += 1
            else:
                pairer.unreadable_second()
            continue
        if conn.topic in first_topics:
            positions[id(msg)] = count
            count += 1
            yield from given_out(pairer.first(msg, now))
        else:
            yield from given_out(pairer.second(msg, now))
    yield from given_out(pairer.flush())


def _itself(item: Any) -> Any:
    return item


def _raise(err: Exception) -> Any:
    raise err


def _stamp_of(msg: Any) -> tuple[int, int, int, int]:
    """The fields the pairer reads (AttributeError when the message lacks one)."""
    return msg.header.stamp.sec, msg.header.stamp.nanosec, msg.height, msg.width


def _first_cloud_frame(reader: Any, path: Path, cloud_conns: list[Any]) -> str:
    """The frame of the bag's first cloud; ReplayError when it cannot be read."""
    try:
        conn, _, raw = next(read_messages(reader, cloud_conns, path))
        return frame_name(reader.deserialize(raw, conn.msgtype).header.frame_id)
    except ReplayError:
        raise
    except Exception as err:
        raise ReplayError(f"{path}: cannot read the first cloud: {type(err).__name__}: {err}"
                          ) from None  # fmt: skip


def _estimated_poses(
    reader: Any,
    path: Path,
    opts: ReplayOptions,
    cloud_conns: list[Any],
    cloud_frame: str,
    log: Callable[[str], None] | None,
) -> tuple[Poses, TfTree]:
    """Poses from the clouds (KISS-ICP): the map frame is the first scan's lidar frame."""
    clouds = (
        (None, partial(reader.deserialize, raw, conn.msgtype))
        for conn, _, raw in read_messages(reader, cloud_conns, path)
    )
    total = sum(c.msgcount for c in cloud_conns)
    return lidar_odometry.odometry_poses(clouds, opts, cloud_frame, total, log), read_transforms()


def _read_poses(
    reader: Any, path: Path, opts: ReplayOptions, odom_topic: str | None, cloud_conns: list[Any]
) -> tuple[Poses, TfTree, str]:
    """Poses, transforms and the cloud frame: small, read first, so a bag without them
    fails fast."""
    tfs = read_transforms()
    tf_conns = [
        c for c in reader.connections if c.msgtype == TF_TYPE and c.topic in ("/tf", "/tf_static")
    ]
    read_conns = [c for c in tf_conns if c.topic == "/tf_static" or odom_topic is None]
    try:
        if read_conns:
            for conn, _, raw in reader.messages(connections=read_conns):
                tfs.add_message(
                    reader.deserialize(raw, conn.msgtype), static=conn.topic == "/tf_static"
                )
        first_cloud = next(reader.messages(connections=cloud_conns))
        cloud_frame = frame_name(
            reader.deserialize(first_cloud[2], first_cloud[0].msgtype).header.frame_id
        )
        if odom_topic is not None:
            poses = odometry_poses(reader, odom_topic, opts)
        else:
            poses = tf_poses(cloud_frame, tfs, opts)
    except ReplayError:
        raise
    except Exception as err:
        raise ReplayError(f"{path}: cannot read poses: {type(err).__name__}: {err}") from None
    if len(poses.buffer) == 0:
        raise ReplayError(f"no usable pose in {poses.source}")
    return poses, tfs, cloud_frame


def bag_extent(bag: str | Path) -> tuple[float, float, int]:
    """First and last message time (s) of a bag and the number of its clouds, from its
    metadata."""
    reader = open_reader(resolve_bag_path(bag))
    try:
        clouds = sum(c.msgcount for c in reader.connections if c.msgtype == CLOUD_TYPE)
        return reader.start_time * 1e-9, reader.end_time * 1e-9, clouds
    finally:
        reader.close()


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
        text = " ".join(str(err).split())  # YAML errors span lines: one line
        raise ReplayError(f"{path}: cannot read the bag: {text}") from None
    return reader


def read_messages(reader: Any, connections: list[Any], path: Path | str) -> Iterator[Any]:
    """``reader.messages(connections=...)``; a file damaged part way (sqlite corruption, a
    truncated chunk) raises ReplayError naming the bag and the message reached."""
    count = 0
    messages = reader.messages(connections=connections)
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except Exception as err:  # apsw.CorruptError, rosbags' reader errors...
            text = " ".join(str(err).split())
            raise ReplayError(
                f"{path}: cannot read the bag after {count} messages: {type(err).__name__}: {text}"
            ) from None
        count += 1
        yield item


def pick_topic(
    reader: Any, msgtype: str, wanted: str | None, what: str, flag: str, other: str | None = None
) -> str | None:
    """The topic ``wanted``, or the bag's one topic of ``msgtype`` (``other``, a topic
    taken for something else, left out); ReplayError when it is not there or not one."""
    topics = {c.topic: c.msgtype for c in reader.connections if c.topic != other}
    listing = ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "none"
    if wanted is not None:
        if wanted not in topics:
            raise ReplayError(f"topic {wanted} is not in the bag; topics: {listing}")
        if topics[wanted] != msgtype:
            raise ReplayError(f"topic {wanted} has type {topics[wanted]}, expected {msgtype}")
        return wanted
    candidates = sorted(t for t, m in topics.items() if m == msgtype)
    if len(candidates) > 1:
        dual = [t for t in candidates if t.endswith("points2")]
        hint = f" (ouster-ros dual returns: --second-return-topic {dual[0]})" if dual else ""
        raise ReplayError(
            f"the bag has several {what} topics ({', '.join(candidates)}): choose one with "
            f"{flag}{hint}"
        )
    return candidates[0] if candidates else None


def read_transforms() -> TfTree:
    """A TF tree for a whole bag: every /tf sample kept (no buffer length, no stream
    checks: the bag is read in one go), interpolated without a gap limit."""
    return TfTree(buffer_length=math.inf, max_jump=math.inf, max_future=math.inf)


def extrinsic_for(
    cloud_frame: str, body: str, tfs: TfTree, opts: ReplayOptions
) -> tuple[Extrinsic, str]:
    if opts.replay.extrinsic is not None:
        return Extrinsic.from_xyz_rpy(*opts.replay.extrinsic), "given on the command line"
    if cloud_frame == body:
        return Extrinsic(), f"identity (the cloud frame is the odometry child frame {body})"
    chain = tfs.static_chain(body, cloud_frame)
    if chain is not None:
        t, q = chain
        return Extrinsic(t, q), f"/tf_static {body} <- {cloud_frame}: " + _describe(t, q)
    if opts.config_extrinsic is not None:
        return Extrinsic.from_xyz_rpy(
            *opts.config_extrinsic
        ), "lidar.translation / lidar.rpy of the configuration"
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
    buffer = _buffer(samples, opts.placement.odom_max_gap)
    return Poses(buffer, body, map_frame, f"{topic} (nav_msgs/Odometry {map_frame} -> {body})")


def _buffer(samples: list[tuple[float, FloatArray, FloatArray]], max_gap: float) -> PoseBuffer:
    buffer = PoseBuffer(max_age=math.inf, max_gap=max_gap)
    for stamp, t, q in sorted(samples, key=lambda s: s[0]):
        buffer.add(stamp, t, q)
    return buffer


def tf_poses(cloud_frame: str, tfs: TfTree, opts: ReplayOptions) -> Poses:
    """Poses of the lowest moving frame above the cloud frame, from the /tf chain."""
    moving = sorted(c for c in tfs.frames() if tfs.is_dynamic(c))
    if not moving:
        raise ReplayError(
            "the bag has no nav_msgs/Odometry topic and no /tf transforms: no poses "
            "(give --odom-topic if the odometry topic has another type name)"
        )
    try:
        above = tfs.ancestors(cloud_frame)
    except TransformUnavailable as err:
        raise ReplayError(f"/tf: {err}") from None
    # the first frame that moves, then up to the fixed frame: odom by default, else the root
    body = next((f for f in above if tfs.is_dynamic(f)), None)
    if body is None:
        raise ReplayError(
            f"/tf does not connect the cloud frame {cloud_frame!r} to a moving frame "
            f"(frames moved by /tf: {frame_list(moving)}); give --odom-topic"
        )
    chain = above[above.index(body) :]
    fixed = opts.replay.fixed_frame
    if fixed is not None and fixed not in chain:
        raise ReplayError(f"the fixed frame {fixed!r} is not above {body!r} in /tf")
    if fixed is None:
        fixed = "odom" if "odom" in chain else chain[-1]
    chain = chain[: chain.index(fixed) + 1]
    if len(chain) < 2:
        raise ReplayError(f"the fixed frame {fixed!r} is the moving frame {body!r} itself")
    stamps = tfs.edge_stamps(body)
    keep = np.ones(stamps.size, dtype=bool)
    for child in chain[1:-1]:  # every other moving edge must cover the stamp
        covered = tfs.edge_stamps(child)
        if covered.size:
            keep &= (stamps >= covered[0]) & (stamps <= covered[-1])
    stamps = stamps[keep]
    samples: list[tuple[float, FloatArray, FloatArray]] = []
    if stamps.size:
        t, q = tfs.lookup(fixed, body, stamps)
        samples = [(float(s), t[i], q[i]) for i, s in enumerate(stamps)]
    text = " -> ".join(reversed(chain))
    return Poses(_buffer(samples, opts.placement.odom_max_gap), body, fixed, f"/tf chain {text}")
