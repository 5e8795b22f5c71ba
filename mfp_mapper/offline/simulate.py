"""The built-in example: a simulated lidar bag with ground truth.

A robot drives a circle in a closed room (solid floor, walls and ceiling) with solid boxes
and volumes of *participating medium* (foliage-like) of known extinction ``lambda`` (returns
per metre). Each ray of a Velodyne-like pattern (``offline.scan_pattern``)
travels until a first return: inside a medium after an exponentially distributed free path
of rate ``lambda`` (MODEL.md, "Physics check"), otherwise at the first solid surface.

Rays that would leave the scene with no return are omitted from the cloud, as a lidar driver
omits points with no return. Omitted rays carry information (the space they crossed) that
the map never sees, so silently dropping them biases ``n/s`` upward; that is why the
built-in scenes are closed (walls and ceiling): every ray returns. The ground truth JSON
counts omitted rays, and ``evaluate`` warns when some crossed a medium.

Output: a bag (ROS 2 sqlite3 or mcap, or ROS 1 ``.bag``) with ``nav_msgs/Odometry``
(odom -> base_link), ``/tf_static`` (base_link -> lidar), optionally ``/tf``, and
``sensor_msgs/PointCloud2`` with fields x y z intensity ring time (the velodyne_pointcloud
layout: float32, float32, float32, float32, uint16, float32 relative seconds), plus
``<bag>.truth.json`` beside it.
"""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.atomic import write_text_atomic
from mfp_mapper.offline.names import BAG_FORMATS, SCENES
from mfp_mapper.offline.scan_pattern import VLP16_ELEVATIONS_DEG, scan_directions
from mfp_mapper.sensing.pointcloud import FieldSpec, pack_records, point_fields
from mfp_mapper.sensing.poses import quaternion_to_matrix, rpy_to_quaternion

FloatArray = NDArray[np.float64]

TRUTH_FORMAT = "mfp_mapper.offline.simulate.truth"
TRUTH_VERSION = 1

CLOUD_TOPIC = "/velodyne_points"
ODOM_TOPIC = "/odom"

# surface codes of each return, for intensities (and tests)
SURFACE_FLOOR, SURFACE_CEILING, SURFACE_WALL, SURFACE_SOLID, SURFACE_MEDIUM = range(5)
_INTENSITY = np.array([30.0, 60.0, 90.0, 140.0, 15.0])
"""Mean intensity of a return from each surface code."""


class SimulationError(ValueError):
    """The scene or the options are inconsistent, or the output cannot be written."""


@dataclass(frozen=True)
class Solid:
    """An opaque axis-aligned box (lo, hi corners, metres)."""

    name: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


@dataclass(frozen=True)
class Medium:
    """A box of participating medium with uniform extinction (returns per metre)."""

    name: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    extinction: float


@dataclass(frozen=True)
class Scene:
    """A room ``[room_lo, room_hi]`` (floor at room_lo z) with solids and media inside.

    With ``enclosed`` the walls go up to a ceiling at ``room_hi`` z: every ray returns.
    Without it there is no ceiling and the walls stop at ``wall_height``: rays can escape.
    """

    room_lo: tuple[float, float, float] = (-14.0, -10.0, 0.0)
    room_hi: tuple[float, float, float] = (14.0, 10.0, 5.0)
    solids: tuple[Solid, ...] = ()
    media: tuple[Medium, ...] = ()
    enclosed: bool = True
    wall_height: float = 2.0

    def validate(self) -> None:
        lo, hi = np.array(self.room_lo), np.array(self.room_hi)
        if not np.all(hi > lo):
            raise SimulationError(f"room_hi {self.room_hi} must exceed room_lo {self.room_lo}")
        boxes: list[tuple[str, FloatArray, FloatArray]] = [
            (b.name, np.array(b.lo), np.array(b.hi)) for b in self.solids
        ] + [(m.name, np.array(m.lo), np.array(m.hi)) for m in self.media]
        for name, blo, bhi in boxes:
            if not np.all(bhi > blo):
                raise SimulationError(f"box {name!r}: hi {bhi} must exceed lo {blo}")
        for m in self.media:
            if not (m.extinction > 0 and math.isfinite(m.extinction)):
                raise SimulationError(f"medium {m.name!r}: extinction must be > 0 per metre")
        for a in range(len(self.media)):
            for b in range(a + 1, len(self.media)):
                ma, mb = self.media[a], self.media[b]
                if np.all(np.array(ma.lo) < np.array(mb.hi)) and np.all(
                    np.array(mb.lo) < np.array(ma.hi)
                ):
                    raise SimulationError(f"media {ma.name!r} and {mb.name!r} overlap")

    def cast(
        self, origins: FloatArray, directions: FloatArray, rng: np.random.Generator
    ) -> tuple[FloatArray, NDArray[np.int8]]:
        """First-return range (inf: no return) and surface code of each unit-direction ray."""
        o = np.broadcast_to(np.asarray(origins, dtype=np.float64), directions.shape)
        d = directions
        rng_solid = np.full(d.shape[0], np.inf)
        code = np.full(d.shape[0], -1, dtype=np.int8)
        lo, hi = np.array(self.room_lo), np.array(self.room_hi)

        def take(t: FloatArray, ok: NDArray[np.bool_], what: int) -> None:
            closer = ok & (t > 0) & (t < rng_solid)
            rng_solid[closer] = t[closer]
            code[closer] = what

        with np.errstate(divide="ignore", invalid="ignore"):
            take((lo[2] - o[:, 2]) / d[:, 2], d[:, 2] < 0, SURFACE_FLOOR)
            if self.enclosed:
                take((hi[2] - o[:, 2]) / d[:, 2], d[:, 2] > 0, SURFACE_CEILING)
            top = hi[2] if self.enclosed else lo[2] + self.wall_height
            for axis in (0, 1):
                for wall, sign in ((lo[axis], -1.0), (hi[axis], 1.0)):
                    t = (wall - o[:, axis]) / d[:, axis]
                    z = o[:, 2] + t * d[:, 2]
                    take(t, (sign * d[:, axis] > 0) & (z <= top), SURFACE_WALL)
            for solid in self.solids:
                t_in, t_out = _slab(o, d, np.array(solid.lo), np.array(solid.hi))
                take(t_in, (t_out >= t_in) & (t_in > 0), SURFACE_SOLID)
            ranges = rng_solid.copy()
            if self.media:
                enters, exits = [], []
                for medium in self.media:
                    t_in, t_out = _slab(o, d, np.array(medium.lo), np.array(medium.hi))
                    t_in = np.maximum(t_in, 0.0)
                    t_out = np.minimum(t_out, rng_solid)
                    enters.append(np.where(t_out > t_in, t_in, np.inf))
                    exits.append(t_out)
                enter = np.stack(enters, axis=1)
                leave = np.stack(exits, axis=1)
                lam = np.array([m.extinction for m in self.media])
                # media are disjoint: visit them in the order the ray enters them
                order = np.argsort(enter, axis=1)
                done = np.zeros(d.shape[0], dtype=bool)
                for k in range(len(self.media)):
                    idx = order[:, k]
                    t_in = np.take_along_axis(enter, idx[:, None], 1)[:, 0]
                    t_out = np.take_along_axis(leave, idx[:, None], 1)[:, 0]
                    crosses = ~done & np.isfinite(t_in)
                    free_path = rng.exponential(1.0, d.shape[0]) / lam[idx]
                    hit = crosses & (free_path < t_out - t_in)
                    ranges[hit] = t_in[hit] + free_path[hit]
                    code[hit] = SURFACE_MEDIUM
                    done |= hit
        return ranges, code

    def to_json(self) -> dict[str, Any]:
        return {
            "room_lo": list(self.room_lo),
            "room_hi": list(self.room_hi),
            "enclosed": self.enclosed,
            "wall_height": self.wall_height,
            "solids": [asdict(s) for s in self.solids],
            "media": [{**asdict(m), "mean_free_path": 1.0 / m.extinction} for m in self.media],
        }


def _slab(o: FloatArray, d: FloatArray, lo: FloatArray, hi: FloatArray) -> tuple[FloatArray, ...]:
    """Entry and exit distances of each ray through the box (t_out < t_in: missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    # a zero direction component: inside the slab -> (-inf, inf), outside -> empty
    inside = (o >= lo) & (o <= hi)
    t_lo = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    t_hi = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    return t_lo.max(axis=1), t_hi.min(axis=1)


@dataclass(frozen=True)
class Circle:
    """The robot (base_link, on the floor) drives a circle counter-clockwise at ``speed``."""

    center: tuple[float, float] = (0.0, 0.0)
    radius: float = 8.0
    speed: float = 3.0
    start_angle: float = -0.5 * math.pi

    def pose(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Positions (N, 3) and yaw (N,) at ``t`` seconds since the start."""
        theta = self.start_angle + self.speed / self.radius * np.asarray(t, dtype=np.float64)
        pos = np.stack(
            [
                self.center[0] + self.radius * np.cos(theta),
                self.center[1] + self.radius * np.sin(theta),
                np.zeros_like(theta),
            ],
            axis=-1,
        )
        return pos, theta + 0.5 * math.pi


@dataclass(frozen=True)
class SimulationConfig:
    """Everything that defines a simulated bag; ``seed`` makes it reproducible."""

    scene: Scene = field(default_factory=lambda: builtin_scene())
    path: Circle = field(default_factory=Circle)
    scans: int = 60
    azimuths: int = 900
    elevations_deg: tuple[float, ...] = tuple(float(e) for e in VLP16_ELEVATIONS_DEG)
    scan_period: float = 0.1
    odom_rate: float = 50.0
    lidar_translation: tuple[float, float, float] = (0.3, 0.0, 1.2)
    lidar_rpy: tuple[float, float, float] = (0.0, 0.0, 0.35)
    seed: int = 0
    start_time: float = 1_700_000_000.0
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    lidar_frame: str = "velodyne"
    cloud_topic: str = CLOUD_TOPIC
    odom_topic: str | None = ODOM_TOPIC
    """None: no Odometry topic (poses only on /tf, if ``write_tf``)."""
    write_tf: bool = False
    write_tf_static: bool = True
    cloud_in_base_frame: bool = False
    """Publish the points in base_link (frame_id = odometry child frame, no extrinsic), as
    a driver configured with a target frame does; a mapper then takes the base_link origin
    as the ray origin."""


def builtin_scene() -> Scene:
    """The demo scene: a hall with pillars, a car, a dense bush and a lighter hedge."""
    return Scene(
        room_lo=(-14.0, -11.0, 0.0),
        room_hi=(14.0, 11.0, 5.0),
        solids=(
            Solid("pillar_ne", (9.5, 5.5, 0.0), (10.5, 6.5, 5.0)),
            Solid("pillar_sw", (-10.5, -6.5, 0.0), (-9.5, -5.5, 5.0)),
            Solid("car", (-12.0, 2.0, 0.0), (-10.5, 6.5, 1.5)),
            Solid("crate", (3.0, -3.5, 0.0), (4.0, -2.5, 1.0)),
        ),
        media=(
            Medium("bush", (-2.0, -1.5, 0.2), (2.0, 1.5, 2.6), extinction=1.0),
            Medium("hedge", (11.0, -5.0, 0.0), (12.0, 3.0, 2.0), extinction=0.4),
        ),
    )


def physics_scene() -> Scene:
    """A small closed room around one cube of medium (lambda = 1 /m): the physics test."""
    return Scene(
        room_lo=(-7.0, -7.0, 0.0),
        room_hi=(7.0, 7.0, 4.0),
        media=(Medium("cube", (-0.8, -0.8, 0.4), (0.8, 0.8, 2.0), extinction=1.0),),
    )


def preset(name: str) -> SimulationConfig:
    """Named configurations: ``demo`` (the built-in example) and ``small`` (tests)."""
    if name == "demo":
        return SimulationConfig(scans=120)
    if name in ("small", "open"):
        scene = physics_scene()
        if name == "open":
            scene = replace(scene, enclosed=False, wall_height=1.0)
        return SimulationConfig(
            scene=scene,
            path=Circle(radius=4.0, speed=2.5),
            scans=40,
            azimuths=720,
            lidar_translation=(0.2, 0.0, 1.0),
        )
    raise SimulationError(f"unknown scene preset {name!r}: expected demo, small or open")


PRESETS = SCENES


@dataclass
class Scan:
    """One simulated rotation: points in the lidar frame and their per-point data."""

    stamp: float
    xyz: NDArray[np.float32]
    intensity: NDArray[np.float32]
    ring: NDArray[np.uint16]
    time: NDArray[np.float32]
    rays: int
    """Rays emitted (returned + omitted)."""
    omitted: int
    omitted_through_media: int


def _lidar_mount(cfg: SimulationConfig) -> tuple[FloatArray, FloatArray]:
    q = rpy_to_quaternion(*cfg.lidar_rpy)
    return np.array(cfg.lidar_translation, dtype=np.float64), q


def generate_scans(cfg: SimulationConfig) -> Iterator[Scan]:
    """Simulate ``cfg.scans`` rotations; each point is seen from the pose at its own time."""
    cfg.scene.validate()
    rng = np.random.default_rng(cfg.seed)
    elev = np.asarray(cfg.elevations_deg, dtype=np.float64)
    beams, az = elev.size, cfg.azimuths
    dirs_lidar = scan_directions(elev, az).reshape(beams, az, 3)
    t_ext, q_ext = _lidar_mount(cfg)
    r_ext = quaternion_to_matrix(q_ext)
    dirs_base = dirs_lidar @ r_ext.T
    ring = np.repeat(np.arange(beams, dtype=np.uint16), az).reshape(beams, az)
    frac = np.arange(az, dtype=np.float64) / az * cfg.scan_period
    lam = {m.name: m.extinction for m in cfg.scene.media}
    for k in range(cfg.scans):
        t_rel = k * cfg.scan_period + frac
        pos, yaw = cfg.path.pose(t_rel)
        c, s = np.cos(yaw), np.sin(yaw)
        # per azimuth column: sensor origin and base->world rotation (yaw only)
        origin = pos + np.stack(
            [c * t_ext[0] - s * t_ext[1], s * t_ext[0] + c * t_ext[1], np.full_like(c, t_ext[2])],
            axis=-1,
        )
        dx, dy, dz = dirs_base[..., 0], dirs_base[..., 1], dirs_base[..., 2]
        world = np.stack([c * dx - s * dy, s * dx + c * dy, dz], axis=-1).reshape(-1, 3)
        origins = np.broadcast_to(origin[None], (beams, az, 3)).reshape(-1, 3)
        ranges, code = cfg.scene.cast(origins, world, rng)
        keep = np.isfinite(ranges)
        omitted = int(np.count_nonzero(~keep))
        through = 0
        if omitted and lam:
            lost_o, lost_d = origins[~keep], world[~keep]
            crossed = np.zeros(lost_o.shape[0], dtype=bool)
            for m in cfg.scene.media:
                t_in, t_out = _slab(lost_o, lost_d, np.array(m.lo), np.array(m.hi))
                crossed |= t_out > np.maximum(t_in, 0.0)
            through = int(np.count_nonzero(crossed))
        flat_dirs = dirs_lidar.reshape(-1, 3)
        xyz = (flat_dirs[keep] * ranges[keep, None]).astype(np.float32)
        base = _INTENSITY[code[keep]]
        intensity = (base * rng.uniform(0.8, 1.2, base.size)).astype(np.float32)
        yield Scan(
            stamp=cfg.start_time + k * cfg.scan_period,
            xyz=xyz,
            intensity=intensity,
            ring=ring.reshape(-1)[keep],
            time=np.broadcast_to(frac[None], (beams, az)).reshape(-1)[keep].astype(np.float32),
            rays=int(ranges.size),
            omitted=omitted,
            omitted_through_media=through,
        )


# --- bag writing ----------------------------------------------------------------------------


VELODYNE_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "ring", "time"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
        "offsets": [0, 4, 8, 12, 16, 18],
        "itemsize": 22,
    }
)
VELODYNE_FIELDS = tuple(point_fields(VELODYNE_DTYPE)[0])


def bag_format_for(path: Path, fmt: str | None) -> str:
    """The storage to write: ``fmt`` if given, ``ros1`` for ``*.bag``, else ``mcap``."""
    if fmt is None:
        return "ros1" if path.suffix == ".bag" else "mcap"
    if fmt not in BAG_FORMATS:
        raise SimulationError(f"unknown bag format {fmt!r}: expected one of {BAG_FORMATS}")
    if (fmt == "ros1") != (path.suffix == ".bag"):
        raise SimulationError(
            f"{path}: ROS 1 bags are files named *.bag, ROS 2 bags are directories without "
            f"that suffix (format {fmt})"
        )
    return fmt


class BagSink:
    """A thin layer over the rosbags writers: builds and serialises messages for one format."""

    def __init__(self, path: Path, fmt: str) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.ros1 = fmt == "ros1"
        if self.ros1:
            from rosbags.rosbag1 import Writer as Writer1

            self.typestore = get_typestore(Stores.ROS1_NOETIC)
            self.typestore.register(
                get_types_from_msg(
                    "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
                )
            )
            self.writer: Any = Writer1(path)
        else:
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as Writer2

            self.typestore = get_typestore(Stores.ROS2_JAZZY)
            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        self.types = self.typestore.types
        self.connections: dict[str, Any] = {}
        self.seq = 0

    def __enter__(self) -> BagSink:
        self.writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.writer.close()

    def add(self, topic: str, msgtype: str, latched: bool = False) -> None:
        if self.ros1:
            conn = self.writer.add_connection(
                topic, msgtype, typestore=self.typestore, latching=1 if latched else None
            )
        else:
            qos = [_latched_qos()] if latched else ()
            conn = self.writer.add_connection(
                topic, msgtype, typestore=self.typestore, offered_qos_profiles=qos
            )
        self.connections[topic] = conn

    def write(self, topic: str, stamp: float, msg: Any) -> None:
        conn = self.connections[topic]
        if self.ros1:
            data = self.typestore.serialize_ros1(msg, conn.msgtype)
        else:
            data = self.typestore.serialize_cdr(msg, conn.msgtype)
        self.writer.write(conn, int(round(stamp * 1e9)), data)

    # --- message builders (field sets differ between ROS 1 and ROS 2) ---
    def time(self, stamp: float) -> Any:
        ns = int(round(stamp * 1e9))
        return self.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)

    def header(self, stamp: float, frame: str) -> Any:
        if self.ros1:
            self.seq += 1
            return self.types["std_msgs/msg/Header"](
                seq=self.seq, stamp=self.time(stamp), frame_id=frame
            )
        return self.types["std_msgs/msg/Header"](stamp=self.time(stamp), frame_id=frame)

    def transform_stamped(
        self, stamp: float, parent: str, child: str, xyz: FloatArray, q: FloatArray
    ) -> Any:
        t = self.types
        return t["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp, parent),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](*map(float, xyz)),
                rotation=t["geometry_msgs/msg/Quaternion"](*map(float, q)),
            ),
        )

    def tf_message(self, transforms: list[Any]) -> Any:
        return self.types["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def odometry(
        self,
        stamp: float,
        parent: str,
        child: str,
        xyz: FloatArray,
        q: FloatArray,
        linear: float,
        angular: float,
    ) -> Any:
        t = self.types
        vec = t["geometry_msgs/msg/Vector3"]
        cov = np.zeros(36, dtype=np.float64)
        return t["nav_msgs/msg/Odometry"](
            header=self.header(stamp, parent),
            child_frame_id=child,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](*map(float, xyz)),
                    orientation=t["geometry_msgs/msg/Quaternion"](*map(float, q)),
                ),
                covariance=cov,
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](
                    linear=vec(float(linear), 0.0, 0.0), angular=vec(0.0, 0.0, float(angular))
                ),
                covariance=cov.copy(),
            ),
        )

    def pointcloud(
        self,
        stamp: float,
        frame: str,
        records: NDArray[np.void],
        fields: tuple[FieldSpec, ...] | None = None,
    ) -> Any:
        """A sensor_msgs/PointCloud2 holding ``records`` (``pack_records``); ``fields``
        replaces the field list derived from their dtype."""
        t = self.types
        packed = pack_records(records)
        return t["sensor_msgs/msg/PointCloud2"](
            header=self.header(stamp, frame),
            fields=[
                t["sensor_msgs/msg/PointField"](
                    name=f.name, offset=f.offset, datatype=f.datatype, count=f.count
                )
                for f in (packed.fields if fields is None else fields)
            ],
            data=np.frombuffer(packed.data, dtype=np.uint8),
            is_dense=True,
            **packed.layout(),
        )


def _latched_qos() -> Any:
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return Qos(
        QosHistory.KEEP_LAST,
        1,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL,
        zero,
        zero,
        QosLiveliness.AUTOMATIC,
        zero,
        False,
    )


@dataclass
class SimulationResult:
    bag: Path
    truth_path: Path
    truth: dict[str, Any]


def truth_path_for(bag: Path) -> Path:
    """Where the ground truth of ``bag`` is written: ``<bag>.truth.json`` beside it."""
    return bag.with_name(bag.name + ".truth.json")


def simulate(
    out: str | Path,
    cfg: SimulationConfig | None = None,
    fmt: str | None = None,
    overwrite: bool = False,
) -> SimulationResult:
    """Write the simulated bag ``out`` and its ground truth JSON; return both paths."""
    cfg = cfg or SimulationConfig()
    cfg.scene.validate()
    bag = Path(out)
    storage = bag_format_for(bag, fmt)
    if bag.exists() or bag.is_symlink():
        if not overwrite:
            raise SimulationError(f"{bag} exists already (use --overwrite to replace it)")
        if bag.is_dir():
            shutil.rmtree(bag)
        else:
            bag.unlink()
    bag.parent.mkdir(parents=True, exist_ok=True)
    t_ext, q_ext = _lidar_mount(cfg)
    cloud_frame = cfg.base_frame if cfg.cloud_in_base_frame else cfg.lidar_frame
    t0 = cfg.start_time
    end = t0 + cfg.scans * cfg.scan_period
    # odometry from a little before the first scan to a little after the last point
    odom_t = np.arange(t0 - 0.2, end + 0.2 + 1e-9, 1.0 / cfg.odom_rate)
    pos, yaw = cfg.path.pose(odom_t - t0)
    totals = {"rays": 0, "returns": 0, "omitted": 0, "omitted_through_media": 0}
    try:
        with BagSink(bag, storage) as sink:
            if cfg.write_tf_static:
                sink.add("/tf_static", "tf2_msgs/msg/TFMessage", latched=True)
            if cfg.write_tf:
                sink.add("/tf", "tf2_msgs/msg/TFMessage")
            if cfg.odom_topic:
                sink.add(cfg.odom_topic, "nav_msgs/msg/Odometry")
            sink.add(cfg.cloud_topic, "sensor_msgs/msg/PointCloud2")
            if cfg.write_tf_static:
                static = sink.transform_stamped(
                    odom_t[0], cfg.base_frame, cfg.lidar_frame, t_ext, q_ext
                )
                sink.write("/tf_static", odom_t[0], sink.tf_message([static]))
            scans = generate_scans(cfg)
            next_scan = next(scans, None)
            omega = cfg.path.speed / cfg.path.radius
            for i, t in enumerate(odom_t):
                # a cloud is recorded when its rotation is complete
                while next_scan is not None and next_scan.stamp + cfg.scan_period <= t:
                    _write_scan(sink, cfg, next_scan, cloud_frame, t_ext, q_ext, totals)
                    next_scan = next(scans, None)
                q = rpy_to_quaternion(0.0, 0.0, float(yaw[i]))
                if cfg.odom_topic:
                    odom = sink.odometry(
                        t, cfg.odom_frame, cfg.base_frame, pos[i], q, cfg.path.speed, omega
                    )
                    sink.write(cfg.odom_topic, t, odom)
                if cfg.write_tf:
                    tf = sink.transform_stamped(t, cfg.odom_frame, cfg.base_frame, pos[i], q)
                    sink.write("/tf", t, sink.tf_message([tf]))
            while next_scan is not None:
                _write_scan(sink, cfg, next_scan, cloud_frame, t_ext, q_ext, totals)
                next_scan = next(scans, None)
    except BaseException:
        # never leave a half-written bag behind
        if bag.is_dir():
            shutil.rmtree(bag, ignore_errors=True)
        elif bag.exists():
            bag.unlink()
        raise
    truth = _truth(cfg, storage, cloud_frame, totals)
    truth_file = truth_path_for(bag)
    write_text_atomic(truth_file, json.dumps(truth, indent=2) + "\n")
    return SimulationResult(bag, truth_file, truth)


def _write_scan(
    sink: BagSink,
    cfg: SimulationConfig,
    scan: Scan,
    cloud_frame: str,
    t_ext: FloatArray,
    q_ext: FloatArray,
    totals: dict[str, int],
) -> None:
    records = np.zeros(scan.xyz.shape[0], dtype=VELODYNE_DTYPE)
    xyz = scan.xyz
    if cfg.cloud_in_base_frame:
        xyz = (xyz.astype(np.float64) @ quaternion_to_matrix(q_ext).T + t_ext).astype(np.float32)
    records["x"], records["y"], records["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    records["intensity"] = scan.intensity
    records["ring"] = scan.ring
    records["time"] = scan.time
    msg = sink.pointcloud(scan.stamp, cloud_frame, records, VELODYNE_FIELDS)
    sink.write(cfg.cloud_topic, scan.stamp + cfg.scan_period, msg)
    totals["rays"] += scan.rays
    totals["returns"] += scan.rays - scan.omitted
    totals["omitted"] += scan.omitted
    totals["omitted_through_media"] += scan.omitted_through_media


def _truth(
    cfg: SimulationConfig, storage: str, cloud_frame: str, totals: dict[str, int]
) -> dict[str, Any]:
    return {
        "format": TRUTH_FORMAT,
        "version": TRUTH_VERSION,
        "scene": cfg.scene.to_json(),
        "frames": {
            "odom": cfg.odom_frame,
            "base": cfg.base_frame,
            "lidar": cfg.lidar_frame,
            "cloud": cloud_frame,
        },
        "lidar_extrinsic": {"translation": list(cfg.lidar_translation), "rpy": list(cfg.lidar_rpy)},
        "topics": {
            "cloud": cfg.cloud_topic,
            "odom": cfg.odom_topic,
            "tf": "/tf" if cfg.write_tf else None,
            "tf_static": "/tf_static" if cfg.write_tf_static else None,
        },
        "path": asdict(cfg.path),
        "scans": cfg.scans,
        "azimuths": cfg.azimuths,
        "beams": len(cfg.elevations_deg),
        "scan_period": cfg.scan_period,
        "start_time": cfg.start_time,
        "seed": cfg.seed,
        "storage": storage,
        "rays": totals,
    }


def load_truth(path: str | Path) -> dict[str, Any]:
    """Read a ground truth JSON written by ``simulate``; SimulationError if it is not one."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError) as err:
        raise SimulationError(f"{p}: cannot read ground truth JSON: {err}") from None
    if not isinstance(data, dict) or data.get("format") != TRUTH_FORMAT:
        raise SimulationError(f"{p}: not a ground truth file of `mfp-mapper simulate`")
    return data
