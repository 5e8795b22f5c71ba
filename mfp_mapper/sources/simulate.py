"""The built-in example: a simulated lidar bag with ground truth.

A robot drives a circle in a closed room (solid floor, walls and ceiling) with solid boxes
and volumes of *participating medium* (foliage-like) of known extinction ``lambda`` (returns
per metre). Each ray of a Velodyne-like pattern (``sources.scan_pattern``)
travels until a first return: inside a medium after an exponentially distributed free path
of rate ``lambda`` (docs/model.md, "A physics check"), otherwise at the first solid surface.

Rays that would leave the scene with no return are omitted from the cloud, as a lidar driver
omits points with no return; with ``organized`` the cloud keeps every firing (height = beams,
width = azimuth steps) and marks those NaN, as velodyne_pointcloud's ``organize_cloud``
does. Omitted rays carry information (the space they crossed) that the map never sees unless
the mapper recovers them (``sensing.no_return``), so silently dropping them biases ``n/s``
upward; that is why the built-in scenes but ``open`` are closed (walls and ceiling): every
ray returns. The ground truth JSON counts omitted rays, and ``evaluate`` warns when some
crossed a medium.

Scenes are in ``sources.sim_scene``, the bag writer in ``sources.sim_bag``. Without a bag,
``open_simulation`` gives the same clouds as a recording placed by the true path.

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
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.config.names import BAG_FORMATS, SCENES
from mfp_mapper.mapio.atomic import write_text_atomic
from mfp_mapper.sensing.poses import Extrinsic, quaternion_to_matrix, rpy_to_quaternion
from mfp_mapper.sources.recording import Poses, RecordedCloud, Recording
from mfp_mapper.sources.scan_files import cloud_message
from mfp_mapper.sources.scan_pattern import VLP16_ELEVATIONS_DEG, scan_directions
from mfp_mapper.sources.sim_bag import VELODYNE_DTYPE, VELODYNE_FIELDS, BagSink, bag_format_for
from mfp_mapper.sources.sim_scene import (
    SURFACE_CEILING,
    SURFACE_FLOOR,
    SURFACE_MEDIUM,
    SURFACE_SOLID,
    SURFACE_WALL,
    Circle,
    Medium,
    Scene,
    SimulationError,
    Solid,
    builtin_scene,
    physics_scene,
    slab,
)

__all__ = [
    "BAG_FORMATS",
    "SURFACE_CEILING",
    "SURFACE_FLOOR",
    "SURFACE_MEDIUM",
    "SURFACE_SOLID",
    "SURFACE_WALL",
    "VELODYNE_DTYPE",
    "VELODYNE_FIELDS",
    "BagSink",
    "Circle",
    "Medium",
    "Scene",
    "SimulationConfig",
    "SimulationError",
    "Solid",
    "generate_scans",
    "load_truth",
    "open_simulation",
    "preset",
    "simulate",
]

FloatArray = NDArray[np.float64]

TRUTH_FORMAT = "mfp_mapper.offline.simulate.truth"
TRUTH_VERSION = 1

CLOUD_TOPIC = "/velodyne_points"
ODOM_TOPIC = "/odom"

_INTENSITY = np.array([30.0, 60.0, 90.0, 140.0, 15.0])
"""Mean intensity of a return from each surface code."""


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
    organized: bool = False
    """Write organized clouds (height = beams, width = azimuth steps) with NaN x y z for
    the firings without a return, as velodyne_pointcloud's ``organize_cloud`` does."""


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
    cells: NDArray[np.intp]
    """Flat index (beam * azimuths + step) of each point in the firing grid."""
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
                t_in, t_out = slab(lost_o, lost_d, np.array(m.lo), np.array(m.hi))
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
            cells=np.flatnonzero(keep),
            omitted=omitted,
            omitted_through_media=through,
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
    records = scan_records(cfg, scan, t_ext, q_ext)
    msg = sink.pointcloud(scan.stamp, cloud_frame, records, VELODYNE_FIELDS)
    sink.write(cfg.cloud_topic, scan.stamp + cfg.scan_period, msg)
    totals["rays"] += scan.rays
    totals["returns"] += scan.rays - scan.omitted
    totals["omitted"] += scan.omitted
    totals["omitted_through_media"] += scan.omitted_through_media


def scan_records(
    cfg: SimulationConfig, scan: Scan, t_ext: FloatArray, q_ext: FloatArray
) -> NDArray[np.void]:
    """The points of ``scan`` as the cloud holds them (``VELODYNE_DTYPE``): in the lidar
    frame, or base_link with ``cloud_in_base_frame``; (beams, azimuths) with NaN for the
    firings without a return when ``organized``."""
    xyz = scan.xyz
    if cfg.cloud_in_base_frame:
        xyz = (xyz.astype(np.float64) @ quaternion_to_matrix(q_ext).T + t_ext).astype(np.float32)
    records: NDArray[np.void]
    if cfg.organized:
        beams = len(cfg.elevations_deg)
        records = np.zeros((beams, cfg.azimuths), dtype=VELODYNE_DTYPE)
        flat = records.reshape(-1)
        flat["x"] = flat["y"] = flat["z"] = np.nan
        records["ring"] = np.arange(beams, dtype=np.uint16)[:, None]
        records["time"] = np.arange(cfg.azimuths) / cfg.azimuths * cfg.scan_period
        rows: NDArray[np.void] = flat[scan.cells]
    else:
        records = rows = np.zeros(scan.xyz.shape[0], dtype=VELODYNE_DTYPE)
    rows["x"], rows["y"], rows["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rows["intensity"] = scan.intensity
    rows["ring"] = scan.ring
    rows["time"] = scan.time
    if cfg.organized:
        flat[scan.cells] = rows
    return records


# --- the simulator as a recording -------------------------------------------------------------


@dataclass(frozen=True)
class TruthPoses:
    """The robot's true poses (base_link in odom) along the simulated path, at any time."""

    cfg: SimulationConfig
    earliest_stamp: float = -math.inf
    latest_stamp: float = math.inf
    max_gap: float = math.inf

    def interpolate(self, stamps: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(stamps, dtype=np.float64).reshape(-1) - self.cfg.start_time
        positions, yaw = self.cfg.path.pose(t)
        c, s = np.cos(yaw), np.sin(yaw)
        rotations = np.zeros((t.size, 3, 3))
        rotations[:, 0, 0], rotations[:, 0, 1], rotations[:, 1, 0] = c, -s, s
        rotations[:, 1, 1], rotations[:, 2, 2] = c, 1.0
        return positions, rotations


def _message(msg: Any) -> Any:
    return msg


def open_simulation(cfg: SimulationConfig, opts: Any = None) -> Recording:
    """The simulated recording of ``cfg`` as a recording, without a bag: the clouds a bag of
    ``simulate`` would hold (made again on each pass, the same from the seed), placed by
    the true path (``TruthPoses``); the lidar mount is the extrinsic unless
    ``opts.replay.extrinsic`` gives one."""
    cfg.scene.validate()
    t_ext, q_ext = _lidar_mount(cfg)
    cloud_frame = cfg.base_frame if cfg.cloud_in_base_frame else cfg.lidar_frame
    given = getattr(opts, "extrinsic", None)
    if given is not None:
        extrinsic, extrinsic_source = Extrinsic.from_xyz_rpy(*given), "given on the command line"
    elif cfg.cloud_in_base_frame:
        extrinsic = Extrinsic()
        extrinsic_source = f"identity (the cloud frame is the odometry child frame {cloud_frame})"
    else:
        extrinsic = Extrinsic(t_ext, q_ext)
        extrinsic_source = f"the simulator's lidar mount {cfg.base_frame} <- {cfg.lidar_frame}"

    def clouds() -> Iterator[RecordedCloud]:
        for index, scan in enumerate(generate_scans(cfg)):
            msg = cloud_message(scan_records(cfg, scan, t_ext, q_ext), scan.stamp, cloud_frame)
            yield RecordedCloud(index, partial(_message, msg))

    poses = Poses(
        TruthPoses(cfg),
        cfg.base_frame,
        cfg.odom_frame,
        f"the simulator's true path ({cfg.odom_frame} -> {cfg.base_frame})",
    )
    return Recording(
        name="simulation",
        cloud_source=f"{cfg.scans} simulated clouds",
        cloud_frame=cloud_frame,
        cloud_count=cfg.scans,
        poses=poses,
        extrinsic_source=extrinsic_source,
        read_clouds=clouds,
        extrinsic_of=lambda _: extrinsic,
    )


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
        "organized": cfg.organized,
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
