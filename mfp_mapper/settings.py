"""Parameters of the ``mfp_mapper`` ROS 2 node: one table, declared and validated here.

Names follow octomap_server where a counterpart exists (``resolution``, ``frame_id``,
``base_frame_id``, ``sensor_model.max_range``, ``sensor_model.min_range``,
``point_cloud_min_z``/``point_cloud_max_z``, ``occupancy_min_z``/``occupancy_max_z``,
``latch``). The table is plain data so that tests and ``config/mfp_mapper.yaml`` can be
checked against it without ROS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

from mfp_mapper.sensing.poses import Extrinsic

NO_LIMIT_Z = 1.0e6
"""The "no limit" value of the z band parameters (metres)."""


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter: name, default, description and the allowed range."""

    name: str
    default: Any
    description: str
    lo: float | None = None
    hi: float | None = None
    dynamic: bool = False
    """Can be changed at run time with ``ros2 param set``; all others are read-only."""


PARAMS: tuple[ParamSpec, ...] = (
    # --- the map ---------------------------------------------------------------------------
    ParamSpec(
        "resolution", 0.1, "Voxel edge (m). A map loaded from map_path keeps its own.", 0.01, 10.0
    ),
    ParamSpec(
        "frame_id",
        "",
        "Map frame. Empty: the odometry's header.frame_id. When set, odometry in any other "
        "frame is rejected (no TF between them here).",
    ),
    ParamSpec(
        "base_frame_id",
        "",
        "Robot body frame the lidar extrinsic is relative to. Empty: the odometry's "
        "child_frame_id. Only used for the TF lookup (use_tf).",
    ),
    ParamSpec(
        "decay_time",
        0.0,
        "Time constant T (s) of the dynamic-environment decay (Eq. 28-30): evidence is "
        "scaled by exp(-dt/T). 0: static map (T = inf).",
        0.0,
        1.0e9,
    ),
    ParamSpec("threads", 1, "Threads the core uses to walk the rays of one scan.", 1, 64),
    ParamSpec(
        "max_voxels", 0, "Memory bound: at most this many voxels. 0: no limit.", 0, 2**31 - 1
    ),
    # --- the sensor ------------------------------------------------------------------------
    ParamSpec(
        "sensor_model.max_range",
        100.0,
        "Rays are cut at this range (m); a return beyond it clears space up to it but "
        "counts no return. <= 0: no limit (octomap_server's -1).",
        -1.0,
        1.0e5,
    ),
    ParamSpec(
        "sensor_model.min_range",
        0.0,
        "Returns closer than this (m) are dropped with their rays (robot body, dust).",
        0.0,
        1.0e3,
    ),
    ParamSpec(
        "point_cloud_min_z",
        -NO_LIMIT_Z,
        "Returns whose map-frame z (m) is below this are dropped with their rays.",
        -NO_LIMIT_Z,
        NO_LIMIT_Z,
    ),
    ParamSpec(
        "point_cloud_max_z",
        NO_LIMIT_Z,
        "Returns whose map-frame z (m) is above this are dropped with their rays.",
        -NO_LIMIT_Z,
        NO_LIMIT_Z,
    ),
    ParamSpec(
        "lidar.translation",
        [0.0, 0.0, 0.0],
        "Lidar position [x, y, z] (m) in the odometry child frame. Ignored when the "
        "cloud's frame_id is the odometry child_frame_id (identity).",
    ),
    ParamSpec(
        "lidar.rpy",
        [0.0, 0.0, 0.0],
        "Lidar orientation [roll, pitch, yaw] (rad, fixed axes X-Y-Z) in the odometry "
        "child frame. Ignored like lidar.translation.",
    ),
    ParamSpec(
        "use_tf",
        False,
        "Look the lidar pose up in TF (base_frame_id <- cloud frame) instead of the "
        "lidar.* parameters. Needs tf2_ros; falls back to the parameters without it.",
    ),
    ParamSpec(
        "deskew",
        True,
        "Give every point its own pose when the cloud has per-point time (Velodyne "
        "'time', Ouster 't', Hesai/Nebula 'timestamp'/'time_stamp').",
    ),
    # --- timing ----------------------------------------------------------------------------
    ParamSpec(
        "cloud_queue_size",
        5,
        "Clouds waiting for integration; when full the oldest is dropped (counted).",
        1,
        1000,
    ),
    ParamSpec(
        "odom_wait",
        1.0,
        "How long (s, wall clock) a cloud newer than the latest odometry waits for "
        "odometry to cover it before it is dropped.",
        0.0,
        60.0,
    ),
    ParamSpec(
        "odom_buffer",
        10.0,
        "Odometry history kept (s of stamps); older clouds are dropped.",
        0.1,
        3600.0,
    ),
    ParamSpec(
        "odom_max_gap",
        0.5,
        "Largest time (s) between two odometry messages that a cloud may be "
        "interpolated across; clouds in a longer gap are dropped.",
        0.001,
        60.0,
    ),
    # --- outputs ---------------------------------------------------------------------------
    ParamSpec(
        "latch",
        True,
        "Publish the map clouds transient-local (late joiners such as RViz get the last one).",
    ),
    ParamSpec(
        "publish_rate",
        1.0,
        "Rate (Hz) of ~/degree_of_occupancy and ~/std; published only when the map "
        "changed and someone subscribes. 0: never.",
        0.0,
        100.0,
    ),
    ParamSpec(
        "min_degree_of_occupancy",
        0.1,
        "Published voxels have at least this most likely degree of occupancy.",
        0.0,
        1.0,
        dynamic=True,
    ),
    ParamSpec(
        "min_evidence",
        0.0,
        "Published voxels have at least this evidence s (m travelled by rays in them).",
        0.0,
        1.0e9,
        dynamic=True,
    ),
    ParamSpec(
        "publish_radius",
        0.0,
        "Publish only voxels within this distance (m) of the robot. 0: the whole map.",
        0.0,
        1.0e6,
        dynamic=True,
    ),
    ParamSpec(
        "occupancy_min_z",
        0.1,
        "Bottom (m, map frame) of the height band of ~/hit_probability_map.",
        -NO_LIMIT_Z,
        NO_LIMIT_Z,
        dynamic=True,
    ),
    ParamSpec(
        "occupancy_max_z",
        2.0,
        "Top (m, map frame) of the height band of ~/hit_probability_map.",
        -NO_LIMIT_Z,
        NO_LIMIT_Z,
        dynamic=True,
    ),
    ParamSpec(
        "hit_probability_map.radius",
        0.0,
        "~/hit_probability_map covers the square of this half side (m) around the "
        "robot. 0: the whole map.",
        0.0,
        1.0e6,
        dynamic=True,
    ),
    # --- map file, health ------------------------------------------------------------------
    ParamSpec(
        "map_path",
        "",
        "Map file (.npz) for ~/save_map, loaded at start when it exists. Empty: none.",
    ),
    ParamSpec("save_on_shutdown", False, "Save the map to map_path when the node stops."),
    ParamSpec(
        "status_period",
        10.0,
        "Period (s) of the status log line and of ~/status. 0: off.",
        0.0,
        3600.0,
    ),
)

SPECS: dict[str, ParamSpec] = {p.name: p for p in PARAMS}


@dataclass
class NodeConfig:
    """Validated parameter values (attribute = parameter name with '.' -> '_'); the
    defaults are those of ``PARAMS`` (see ``from_values``)."""

    resolution: float
    frame_id: str
    base_frame_id: str
    decay_time: float
    threads: int
    max_voxels: int
    sensor_model_max_range: float
    sensor_model_min_range: float
    point_cloud_min_z: float
    point_cloud_max_z: float
    lidar_translation: tuple[float, float, float]
    lidar_rpy: tuple[float, float, float]
    use_tf: bool
    deskew: bool
    cloud_queue_size: int
    odom_wait: float
    odom_buffer: float
    odom_max_gap: float
    latch: bool
    publish_rate: float
    min_degree_of_occupancy: float
    min_evidence: float
    publish_radius: float
    occupancy_min_z: float
    occupancy_max_z: float
    hit_probability_map_radius: float
    map_path: str
    save_on_shutdown: bool
    status_period: float

    @property
    def max_range(self) -> float:
        """``sensor_model.max_range`` for the core: inf when <= 0."""
        r = self.sensor_model_max_range
        return math.inf if r <= 0.0 else r

    @property
    def decay(self) -> float:
        """``decay_time`` for the core: inf for a static map."""
        return math.inf if self.decay_time <= 0.0 else self.decay_time

    def mapper_settings(self) -> dict[str, Any]:
        """Keyword arguments of ``Mapper`` (besides resolution and frame) these values give."""
        return {
            "max_range": self.max_range,
            "min_range": self.sensor_model_min_range,
            "decay_time": self.decay,
            "threads": self.threads,
            "max_voxels": self.max_voxels or None,
        }

    def extrinsic(self) -> Extrinsic:
        """The lidar pose in the odometry child frame (``lidar.translation``, ``lidar.rpy``)."""
        return Extrinsic.from_xyz_rpy(self.lidar_translation, self.lidar_rpy)

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> NodeConfig:
        """Build from parameter values keyed by parameter name (the others take their
        defaults); raise ValueError if invalid."""
        kwargs: dict[str, Any] = {}
        for name, value in {**defaults(), **values}.items():
            if name not in SPECS:
                raise ValueError(f"unknown parameter {name!r}")
            kwargs[attr_name(name)] = value
        cfg = cls(**kwargs)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Check the relations between parameters; raise ValueError naming the culprit."""
        for name in ("lidar.translation", "lidar.rpy"):
            vec = getattr(self, attr_name(name))
            if len(vec) != 3 or not all(math.isfinite(float(v)) for v in vec):
                raise ValueError(f"{name} must be 3 finite numbers, got {list(vec)}")
            setattr(self, attr_name(name), tuple(float(v) for v in vec))
        for spec in PARAMS:
            value = getattr(self, attr_name(spec.name))
            if spec.lo is not None and not (spec.lo <= value <= spec.hi):
                raise ValueError(f"{spec.name}={value} outside [{spec.lo}, {spec.hi}]")
        if self.sensor_model_min_range >= self.max_range:
            raise ValueError("sensor_model.min_range must be below sensor_model.max_range")
        if self.point_cloud_min_z >= self.point_cloud_max_z:
            raise ValueError("point_cloud_min_z must be below point_cloud_max_z")
        if self.occupancy_min_z >= self.occupancy_max_z:
            raise ValueError("occupancy_min_z must be below occupancy_max_z")

    def values(self) -> dict[str, Any]:
        """Parameter name -> value."""
        names = {attr_name(p.name): p.name for p in PARAMS}
        return {names[f.name]: getattr(self, f.name) for f in fields(self)}


def attr_name(param_name: str) -> str:
    """Attribute of NodeConfig holding a parameter."""
    return param_name.replace(".", "_")


def defaults() -> dict[str, Any]:
    """Parameter name -> default value."""
    return {p.name: p.default for p in PARAMS}


def descriptor(spec: ParamSpec) -> Any:
    """The rcl_interfaces ParameterDescriptor of a parameter (ROS imported lazily)."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    desc = ParameterDescriptor(
        name=spec.name, description=spec.description, read_only=not spec.dynamic
    )
    if spec.lo is not None and spec.hi is not None:
        if isinstance(spec.default, bool):
            pass
        elif isinstance(spec.default, int):
            desc.integer_range = [
                IntegerRange(from_value=int(spec.lo), to_value=int(spec.hi), step=1)
            ]
        else:
            desc.floating_point_range = [
                FloatingPointRange(from_value=float(spec.lo), to_value=float(spec.hi), step=0.0)
            ]
    return desc


def declare_parameters(node: Any) -> NodeConfig:
    """Declare every parameter on an rclpy node and return the validated values."""
    values: dict[str, Any] = {}
    for spec in PARAMS:
        param = node.declare_parameter(spec.name, spec.default, descriptor(spec))
        values[spec.name] = param.value
    return NodeConfig.from_values(values)
