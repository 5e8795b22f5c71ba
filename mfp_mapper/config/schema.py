"""The settings schema: every setting of the node, the replay and the CLI, defined once.

Each ``Setting`` gives its name, type, default, range, description, whether it can change at
run time, where it applies (``node``: a ROS parameter only; ``replay``: the offline replay and
its CLI only; ``both``) and its CLI flag. Everything else derives from ``SETTINGS``:

- the ROS parameter declarations (``mfp_mapper.ros.params``) and ``NodeConfig``;
- ``config/mfp_mapper.yaml`` (``python -m mfp_mapper.config.schema > config/mfp_mapper.yaml``;
  a test checks it both ways);
- ``ReplayOptions`` field defaults and the ``replay`` CLI flags
  (``mfp_mapper.config.replay_options``);
- the checks of a parameter file (``check_parameters``): the node and ``--config`` use them.

Reading a setting: the node reads ``NodeConfig`` attributes (``cfg.resolution``,
``cfg.sensor_model_max_range``; ``cfg.core(name)`` or ``cfg.max_range``/``cfg.decay`` for the
core's value, "<= 0 means no limit" applied; ``cfg.map_settings()`` for ``Mapper``); the
replay reads ``ReplayOptions`` fields (``opts.max_range``, already in core units);
``BY_NAME[name]`` is the entry itself.

Adding a setting: one entry in ``SETTINGS`` (``_node``, ``_both`` or ``_replay``); a node
parameter also needs its ``NodeConfig`` attribute (name with '.' -> '_'), a replay one its
``ReplayOptions`` field (``field``), then regenerate the YAML. Tests fail until all agree.

Node parameter names follow octomap_server where a counterpart exists (``resolution``,
``frame_id``, ``sensor_model.max_range``, ``point_cloud_min_z``, ``latch``...). This module is
plain data and imports neither ROS nor numpy.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Any, Literal

XyzRpy = tuple[tuple[float, float, float], tuple[float, float, float]]
"""A rigid mounting as configured: ([x, y, z] metres, fixed-axis [roll, pitch, yaw] radians)."""


def xyz_rpy(translation: Any, rpy: Any) -> XyzRpy:
    """An ``XyzRpy`` from two triples of finite numbers; ValueError otherwise."""
    t = tuple(float(v) for v in translation)
    r = tuple(float(v) for v in rpy)
    if len(t) != 3 or len(r) != 3 or not all(math.isfinite(v) for v in t + r):
        raise ValueError(f"an extrinsic needs 3 + 3 finite numbers, got {t} and {r}")
    return (t[0], t[1], t[2]), (r[0], r[1], r[2])


NO_LIMIT_Z = 1.0e6
"""The "no limit" value of the z band parameters (metres)."""

Applies = Literal["node", "replay", "both"]
Unlimited = Literal["inf", "none"]


@dataclass(frozen=True)
class Setting:
    """One setting. ``type`` is bool, int, float, str or list (of floats, ``length`` long).

    ``unlimited``: a value <= 0 means "no limit" to the core: ``inf`` or ``None``
    (``core_value`` applies it). ``field``: the ``ReplayOptions`` field (default: the name
    with '.' -> '_'). ``flag``: the ``replay`` CLI flag; for a bool it switches the default
    off (``--no-deskew``) or on (``--tf``).
    """

    name: str
    type: type
    default: Any
    description: str
    lo: float | None = None
    hi: float | None = None
    dynamic: bool = False
    """Can be changed at run time with ``ros2 param set``; all others are read-only."""
    applies: Applies = "node"
    flag: str | None = None
    field: str | None = None
    unlimited: Unlimited | None = None
    length: int | None = None
    metavar: tuple[str, ...] | None = None

    @property
    def is_parameter(self) -> bool:
        """A ROS parameter of the node (declared, in the YAML, accepted by --config)."""
        return self.applies in ("node", "both")

    @property
    def in_replay(self) -> bool:
        """A field of ``ReplayOptions``."""
        return self.applies in ("replay", "both")

    @property
    def option(self) -> str:
        """The ``ReplayOptions`` field."""
        return self.field or attr_name(self.name)

    @property
    def ros_type(self) -> str:
        """The rclpy ``Parameter.Type`` name this setting is declared with."""
        return {bool: "BOOL", int: "INTEGER", float: "DOUBLE", str: "STRING"}.get(
            self.type, "DOUBLE_ARRAY"
        )

    def core_value(self, value: Any) -> Any:
        """The value the core (Mapper, replay) takes: "<= 0 means no limit" applied."""
        if self.unlimited is not None and value is not None and value <= 0:
            return math.inf if self.unlimited == "inf" else None
        return value

    @property
    def core_default(self) -> Any:
        return self.core_value(self.default)

    def check_range(self, value: Any) -> str | None:
        """Why ``value`` is outside the range, in rclpy's words; None when inside."""
        if self.lo is None or self.hi is None or self.type not in (int, float):
            return None
        if self.type is float:
            rel = 1e-6  # rclpy Node.PARAM_REL_TOL: values at the edges are accepted
            if math.isclose(value, self.lo, rel_tol=rel) or math.isclose(
                value, self.hi, rel_tol=rel
            ):
                return None
            sep = " "
        else:
            if value in (self.lo, self.hi):
                return None
            sep = ". "
        if self.lo < value < self.hi:
            return None
        lo, hi = (float(self.lo), float(self.hi)) if self.type is float else (self.lo, self.hi)
        return f"Parameter {self.name} out of range{sep}Min: {lo}, Max: {hi}, value: {value}"


def _node(name: str, default: Any, description: str, *args: Any, **kw: Any) -> Setting:
    return Setting(name, type(default), default, description, *args, **kw)


def _both(name: str, default: Any, description: str, *args: Any, **kw: Any) -> Setting:
    return replace(_node(name, default, description, *args, **kw), applies="both")


def _replay(name: str, typ: type, description: str, **kw: Any) -> Setting:
    return Setting(name, typ, kw.pop("default", None), description, applies="replay", **kw)


SETTINGS: tuple[Setting, ...] = (
    # --- the map ---------------------------------------------------------------------------
    _both("resolution", 0.1, "Voxel edge (m). A map loaded from map_path keeps its own.",
          0.01, 10.0, flag="--resolution"),
    _node("frame_id", "", "Map frame, fixed for the run (octomap_server's frame_id; set it "
          "to 'map' with SLAM/localization: map -> odom is then taken from TF and clouds wait "
          "for it). Empty: a loaded map's frame, else decided at the first cloud placed: the "
          "odometry's header.frame_id, without odometry the root of the cloud frame's TF "
          "tree; never changed afterwards."),
    _node("cloud_frame_id", "", "Frame of clouds whose header.frame_id is empty (e.g. the "
          "lidar frame). Empty: such clouds are dropped (no_frame)."),
    _node("base_frame_id", "", "Robot body frame the lidar extrinsic (from /tf_static) is "
          "relative to. Empty: the odometry's child_frame_id."),
    _both("decay_time", 0.0, "Time constant T (s) of the dynamic-environment decay (Eq. "
          "28-30): evidence is scaled by exp(-dt/T). 0: static map (T = inf).", 0.0, 1.0e9,
          flag="--decay-time", unlimited="inf"),
    _both("threads", 1, "Threads the core uses to walk the rays of one scan.", 1, 64,
          flag="--threads"),
    _both("max_voxels", 0, "Memory bound: at most this many voxels. 0: no limit.",
          0, 2**31 - 1, flag="--max-voxels", unlimited="none"),
    _both("keep_radius", 0.0, "Keep only the map blocks within this distance (m) of the "
          "latest sensor position; farther ones are evicted after each scan. 0: keep all.",
          0.0, 1.0e6, flag="--keep-radius", unlimited="none"),
    _both("prior.shape", 1.0, "Shape alpha (returns) of the Gamma prior on each voxel's "
          "extinction (docs/PRIOR.md); with prior.rate = 1, the paper's uniform prior on m. "
          "Used by every estimate but the most likely DoO (mean, std, intervals, hit "
          "probability, the grids' thresholds); never stored in the statistics. "
          "`mfp-mapper fit-prior` fits it to a recording.", 1.0e-6, 1.0e6,
          flag="--prior-shape", field="prior_shape"),
    _both("prior.rate", 1.0, "Rate beta (metres of ray) of the Gamma prior on the "
          "extinction: the prior weighs like beta metres of ray with alpha returns.",
          1.0e-6, 1.0e6, flag="--prior-rate", field="prior_rate"),
    # --- the sensor ------------------------------------------------------------------------
    _both("sensor_model.max_range", 100.0, "Rays are cut at this range (m); a return beyond "
          "it clears space up to it but counts no return. <= 0: no limit (octomap_server's "
          "-1).", -1.0, 1.0e5, dynamic=True, flag="--max-range", field="max_range",
          unlimited="inf"),
    _both("sensor_model.min_range", 0.0, "Returns closer than this (m) are dropped with "
          "their rays (robot body, dust).", 0.0, 1.0e3, flag="--min-range", field="min_range"),
    _both("sensor_model.no_return_range", 0.0, "Firings that returned nothing (NaN/zero "
          "cells of organized clouds, gaps of ring/channel clouds) become rays that clear "
          "space up to this range (m) and count no return. 0: off, the default: a missing "
          "return may also be a dark or glossy obstacle, or one closer than the minimum "
          "range (README, 'Rays with no return').", 0.0, 1.0e5, flag="--no-return-range",
          field="no_return_range"),
    _both("point_cloud_min_x", -NO_LIMIT_Z, "Returns whose map-frame x (m) is below this are "
          "dropped with their rays.", -NO_LIMIT_Z, NO_LIMIT_Z, dynamic=True, flag="--min-x"),
    _both("point_cloud_max_x", NO_LIMIT_Z, "Returns whose map-frame x (m) is above this are "
          "dropped with their rays.", -NO_LIMIT_Z, NO_LIMIT_Z, dynamic=True, flag="--max-x"),
    _both("point_cloud_min_y", -NO_LIMIT_Z, "Returns whose map-frame y (m) is below this are "
          "dropped with their rays.", -NO_LIMIT_Z, NO_LIMIT_Z, dynamic=True, flag="--min-y"),
    _both("point_cloud_max_y", NO_LIMIT_Z, "Returns whose map-frame y (m) is above this are "
          "dropped with their rays.", -NO_LIMIT_Z, NO_LIMIT_Z, dynamic=True, flag="--max-y"),
    _both("point_cloud_min_z", -NO_LIMIT_Z, "Returns whose map-frame z (m) is below this are "
          "dropped with their rays.", -NO_LIMIT_Z, NO_LIMIT_Z, dynamic=True, flag="--min-z"),
    _both("point_cloud_max_z", NO_LIMIT_Z, "Returns whose map-frame z (m) is above this are "
          "dropped with their rays.", -NO_LIMIT_Z, NO_LIMIT_Z, dynamic=True, flag="--max-z"),
    _both("lidar.translation", [0.0, 0.0, 0.0], "Lidar position [x, y, z] (m) in the "
          "odometry child frame; when set (not all zero with lidar.rpy) it overrides "
          "/tf_static. Ignored when the cloud's frame_id is the odometry child_frame_id "
          "(identity).", length=3),
    _both("lidar.rpy", [0.0, 0.0, 0.0], "Lidar orientation [roll, pitch, yaw] (rad, fixed "
          "axes X-Y-Z) in the odometry child frame. Ignored like lidar.translation.", length=3),
    _node("use_tf", False, "No effect (kept for old parameter files): /tf and /tf_static "
          "are always read; the extrinsic comes from /tf_static unless lidar.* are set."),
    _both("deskew", True, "Give every point its own pose when the cloud has per-point time "
          "(Velodyne 'time', Ouster 't', Hesai/Nebula 'timestamp'/'time_stamp').",
          flag="--no-deskew"),
    # --- timing ----------------------------------------------------------------------------
    _node("cloud_queue_size", 5, "Clouds waiting for integration; when full the oldest is "
          "dropped (counted).", 1, 1000),
    _node("odom_wait", 1.0, "How long (s, wall clock) a cloud newer than the latest "
          "odometry waits for odometry to cover it before it is dropped.", 0.0, 60.0),
    _node("odom_buffer", 10.0, "Odometry history kept (s of stamps); older clouds are "
          "dropped.", 0.1, 3600.0),
    _both("odom_max_gap", 0.5, "Largest time (s) between two odometry messages that a cloud "
          "may be interpolated across; clouds in a longer gap are dropped.", 0.001, 60.0,
          flag="--max-gap", field="max_gap"),
    # --- outputs ---------------------------------------------------------------------------
    _node("latch", True, "Publish the map clouds transient-local (late joiners such as RViz "
          "get the last one)."),
    _node("publish_rate", 1.0, "Rate (Hz) of ~/degree_of_occupancy and ~/std; published "
          "only when the map changed and someone subscribes. 0: never.", 0.0, 100.0),
    _node("min_degree_of_occupancy", 0.1, "Published voxels have at least this most likely "
          "degree of occupancy.", 0.0, 1.0, dynamic=True),
    _node("min_evidence", 0.0, "Published voxels have at least this evidence s (m travelled "
          "by rays in them).", 0.0, 1.0e9, dynamic=True),
    _node("publish_radius", 0.0, "Publish only voxels within this distance (m) of the robot. "
          "0: the whole map.", 0.0, 1.0e6, dynamic=True),
    _node("occupancy_min_z", 0.1, "Bottom (m, map frame) of the height band of "
          "~/hit_probability_map.", -NO_LIMIT_Z, NO_LIMIT_Z, dynamic=True),
    _node("occupancy_max_z", 2.0, "Top (m, map frame) of the height band of "
          "~/hit_probability_map.", -NO_LIMIT_Z, NO_LIMIT_Z, dynamic=True),
    _node("hit_probability_map.radius", 0.0, "~/hit_probability_map covers the square of "
          "this half side (m) around the robot. 0: the whole map.", 0.0, 1.0e6, dynamic=True),
    _node("hit_probability_map.max_cells", 25_000_000, "Most cells ~/hit_probability_map and "
          "~/projected_map may hold; a larger map is served as the largest square around the "
          "robot that fits (logged).", 1, 2**31 - 1, dynamic=True),
    _node("projected_map.trinary", True, "~/projected_map cells 100 (occupied) / 0 (free) / "
          "-1 (unknown), as Nav2's static layer expects. False: round(100 hit probability), "
          "like ~/hit_probability_map.", dynamic=True),
    _node("projected_map.occupied_threshold", 0.25, "Hit probability at or above which a "
          "~/projected_map cell is occupied (100).", 0.0, 1.0, dynamic=True),
    _node("projected_map.free_threshold", -1.0, "Hit probability below which an observed "
          "~/projected_map cell is free (0). Negative: that of a never-observed voxel, "
          "resolution / (1 + resolution).", -1.0, 1.0, dynamic=True),
    _node("octomap_topics", False, "Publish under octomap_server's topic names, relative "
          "to the node's namespace: projected_map (the grid) and octomap_point_cloud_centers "
          "(the degree-of-occupancy cloud) instead of ~/projected_map and "
          "~/degree_of_occupancy, so Nav2/RViz configs made for octomap_server work "
          "unchanged."),
    _node("tf_buffer", 10.0, "TF cache time (s; tf2's default 10): /tf samples kept per "
          "transform; a transform not received for this long (stream time) is forgotten.",
          0.1, 3600.0),
    # --- localization against the loaded map (README "Localization mode") ---------------------
    _node("localization.enabled", False, "Localize each cloud against the map loaded from "
          "map_path (scan-to-map alignment by the forward model's likelihood) and publish the "
          "map -> odom correction on /tf, as AMCL does; clouds are placed in "
          "localization.odom_frame, the map frame is frame_id (or the loaded map's)."),
    _node("localization.freeze_map", True, "true: the loaded map is not changed (localization "
          "only); false: clouds are also integrated at their corrected poses."),
    _node("localization.odom_frame", "odom", "The odometry frame (AMCL's odom_frame_id): "
          "clouds are placed in it by odometry or TF, and the node publishes map -> "
          "odom_frame."),
    _node("localization.tf_publish", True, "Publish map -> odom on /tf (AMCL's tf_broadcast); "
          "false: only ~/status reports the correction."),
    _node("localization.transform_tolerance", 0.5, "Seconds the published map -> odom is "
          "future-dated by (AMCL's transform_tolerance).", 0.0, 60.0, dynamic=True),
    _node("localization.tf_rate", 20.0, "Rate (Hz) at which the last map -> odom is "
          "republished, stamped now + transform_tolerance, so that it never expires.", 0.1,
          1000.0),
    _node("localization.min_period", 0.0, "Align at most one cloud per this many seconds "
          "(stamp time); the others are placed with the last correction. 0: every cloud.",
          0.0, 3600.0, dynamic=True),
    _node("localization.max_rays", 3000, "Rays per cloud used by the wide search's alignment "
          "(an evenly spread subset; while localized: localization.tracking_rays).", 10,
          10_000_000, dynamic=True),
    _node("localization.max_sigma", 0.05, "Refuse a correction whose standard deviation "
          "along its weakest direction exceeds this (m): degenerate geometry.", 0.0, 100.0,
          dynamic=True),
    _node("localization.min_gain_per_ray", 0.02, "Refuse a correction that raises the "
          "scan's log-likelihood by less than this per ray (nats).", 0.0, 100.0,
          dynamic=True),
    _node("localization.min_constraints", 5, "Refuse when fewer planar patches of the scan "
          "than this constrain some direction (a corridor's axis).", 0, 1_000_000,
          dynamic=True),
    _node("localization.max_shift", 0.5, "While localized: refuse a correction that moves the "
          "robot further than this (m).", 0.0, 100.0, dynamic=True),
    _node("localization.max_angle", 5.0, "While localized: refuse a correction that turns the "
          "robot by more than this (degrees).", 0.0, 180.0, dynamic=True),
    _node("localization.initial_max_shift", 1.0, "Before the first accepted correction (at "
          "start, after /initialpose, when lost): the wider search range (m).", 0.0, 100.0,
          dynamic=True),
    _node("localization.initial_max_angle", 10.0, "Before the first accepted correction: the "
          "wider search range (degrees).", 0.0, 180.0, dynamic=True),
    _node("localization.lost_after", 10, "Consecutive refused corrections after which the "
          "state is 'lost' (the wider search is used again).", 1, 1_000_000, dynamic=True),
    _node("localization.tracking_levels", 1, "While localized: pyramid levels the alignment "
          "uses, finest first (before the first acceptance and when lost: all 3).", 1, 3,
          dynamic=True),
    _node("localization.tracking_rays", 1000, "While localized: rays per cloud used by the "
          "alignment (localization.max_rays: the wide search).", 10, 10_000_000, dynamic=True),
    _node("localization.tracking_iterations", 10, "While localized: Levenberg-Marquardt steps "
          "per alignment (the wide search: 30).", 1, 1000, dynamic=True),
    _node("localization.exact_check", True, "Refuse a correction of the wide search (start, "
          "/initialpose, lost) unless the exact likelihood of the scan under the map rises "
          "significantly (refusal 'exact_check').", dynamic=True),
    _node("localization.exact_check_tracking", False, "Also check the corrections found "
          "while localized (sub-voxel corrections of drifting odometry are mostly refused).",
          dynamic=True),
    _node("localization.fit_drop", 0.3, "Refuse a scan, and stop vouching for the pose, when "
          "it fits the map this much worse (smoothed log-likelihood per ray, nats) than the "
          "scans accepted before it (refusal 'poor_fit': odometry that jumped, a kidnapped "
          "robot); lost after lost_after such scans; 0: no check.", 0.0, 100.0, dynamic=True),
    _node("localization.normals_refresh", 0.5, "While localized: recompute the scan's surface "
          "normals (geometric conditioning) once the robot moved this far (m, odometry) since "
          "they were; 0: every cloud.", 0.0, 1000.0, dynamic=True),
    _node("localization.update_min_d", 0.25, "While localized: align a cloud only after the "
          "robot moved this far (m, odometry) since the last alignment, or turned "
          "update_min_a (AMCL's update_min_d). 0 and 0: every cloud.", 0.0, 1000.0,
          dynamic=True),
    _node("localization.update_min_a", 11.5, "While localized: align a cloud only after the "
          "robot turned this much (degrees, odometry) since the last alignment, or moved "
          "update_min_d (AMCL's update_min_a, 0.2 rad).", 0.0, 360.0, dynamic=True),
    _node("localization.rebuild_period", 5.0, "With freeze_map false: the alignment's field "
          "is rebuilt from the growing map at most this often (s, in the background).", 0.1,
          86400.0, dynamic=True),
    # --- map file, health ------------------------------------------------------------------
    _node("map_path", "", "Map file (.npz), or tiled map (a directory), for ~/save_map, "
          "loaded at start when it exists. Empty: none."),
    _node("save_on_shutdown", False, "Save the map to map_path when the node stops."),
    _node("autosave_period", 0.0, "Save the map to map_path in the background at most this "
          "often (s), when it changed; mapping goes on meanwhile. 0: off.", 0.0, 86400.0),
    _node("autostart", True, "Configure and activate the node when it starts (a plain "
          "node). false: it waits unconfigured for a lifecycle manager (Nav2's "
          "lifecycle_manager, ros2 lifecycle set) to configure and activate it."),
    _node("status_period", 10.0, "Period (s) of the status log line and of ~/status. 0: "
          "off.", 0.0, 3600.0),
    # --- the offline replay only -------------------------------------------------------------
    _replay("cloud_topic", str, "sensor_msgs/PointCloud2 topic (default: detected).",
            flag="--cloud-topic"),
    _replay("odom_topic", str, "nav_msgs/Odometry topic (default: detected).",
            flag="--odom-topic"),
    _replay("use_tf_poses", bool, "Poses from the /tf chain even when the bag has an "
            "Odometry topic.", default=False, flag="--tf", field="use_tf"),
    _replay("fixed_frame", str, "With /tf poses: the map frame (default: odom if on the "
            "chain, else the root).", flag="--fixed-frame"),
    _replay("extrinsic", list, "Lidar pose [x, y, z, roll, pitch, yaw] (m, rad) in the "
            "odometry child frame; overrides /tf_static and the lidar.* parameters.",
            flag="--extrinsic", length=6, metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW")),
    _replay("max_scans", int, "Stop after this many clouds.", lo=0, hi=2**63 - 1,
            flag="--max-scans"),
    # which clouds: --start/--end (cli.input_args) set one of the three kinds of bound
    _replay("start", float, "Map only clouds stamped at or after this absolute time (s); "
            "the window is half-open, [start, end)."),
    _replay("end", float, "Map only clouds stamped before this absolute time (s)."),
    _replay("start_offset", float, "Like start, in seconds after the first cloud."),
    _replay("end_offset", float, "Like end, in seconds after the first cloud."),
    _replay("start_index", int, "First cloud mapped, by its position in the recording "
            "(0: the first).", default=0, lo=0, hi=2**63 - 1),
    _replay("end_index", int, "Clouds from this position on are not mapped: "
            "[start_index, end_index).", lo=0, hi=2**63 - 1),
    _replay("every", int, "Map one cloud in N of those selected (the first, then every "
            "N-th).", default=1, lo=1, hi=2**63 - 1, flag="--every"),
    _replay("odometry", str, "Poses estimated from the clouds: kiss-icp (needs the kiss-icp "
            "package). Default: poses from the recording."),
)  # fmt: skip

BY_NAME: dict[str, Setting] = {s.name: s for s in SETTINGS}
PARAMS: tuple[Setting, ...] = tuple(s for s in SETTINGS if s.is_parameter)
"""The node's ROS parameters, in declaration order."""
SPECS: dict[str, Setting] = {p.name: p for p in PARAMS}
"""ROS parameter name -> Setting."""
ParamSpec = Setting
"""Former name of ``Setting``."""

ROS_OWN_PARAMETERS = ("use_sim_time", "start_type_description_service")
"""Parameters rclpy declares on every node: accepted in a parameter file, not ours."""

OCTOMAP_ONLY = (
    "color.a", "color.b", "color.g", "color.r", "color_factor",
    "color_free.a", "color_free.b", "color_free.g", "color_free.r", "colored_map",
    "compress_map", "filter_ground_plane", "filter_speckles", "ground_filter.angle",
    "ground_filter.distance", "ground_filter.plane_distance",
    "incremental_2D_projection", "max_depth", "min_x_size", "min_y_size", "octomap_path",
    "publish_free_space", "sensor_model.hit", "sensor_model.max", "sensor_model.min",
    "sensor_model.miss", "use_height_map",
)  # fmt: skip
"""octomap_server (ROS 2) parameters with no meaning here (occupancy log-odds, colours,
ground filtering, octree depth, its .bt/.ot file): a parameter file naming them starts the
node with one warning listing them (``octomap_only_parameters``)."""


# --- checking parameter values with the node's rules ------------------------------------------


def python_type_name(value: Any) -> str:
    """The rclpy ``Parameter.Type`` name of a Python value (rclpy's own inference)."""
    if isinstance(value, bool):
        return "BOOL"
    if isinstance(value, int):
        return "INTEGER"
    if isinstance(value, float):
        return "DOUBLE"
    if isinstance(value, str):
        return "STRING"
    if isinstance(value, (list, tuple)):
        kinds = (
            (bytes, "BYTE"),
            (bool, "BOOL"),
            (int, "INTEGER"),
            (float, "DOUBLE"),
            (str, "STRING"),
        )
        for kind, name in kinds:  # rclpy's order: an empty list is a BYTE_ARRAY
            if all(isinstance(v, kind) for v in value):
                return f"{name}_ARRAY"
    raise ValueError(f"not a parameter value: {value!r}")


def unknown_parameters(names: list[str]) -> list[str]:
    """The names that are neither our parameters, rclpy's own nor octomap_server's, sorted."""
    return sorted(
        n
        for n in names
        if n not in SPECS
        and n not in ROS_OWN_PARAMETERS
        and n not in OCTOMAP_ONLY
        and not n.startswith("qos_overrides.")
    )


def octomap_only_parameters(names: list[str]) -> list[str]:
    """The octomap_server parameters among ``names`` that mean nothing here, sorted."""
    return sorted(n for n in names if n in OCTOMAP_ONLY)


def octomap_only_warning(names: list[str]) -> str:
    """The one warning for octomap_server-only names in a parameter file."""
    return (
        f"ignoring octomap_server parameter(s) with no meaning in mfp_mapper: {', '.join(names)} "
        "(README 'Migrating from octomap_server')"
    )


def unknown_parameters_error(names: list[str]) -> str:
    """The one message for typos in a parameter file (node and --config)."""
    return f"unknown parameter(s) {', '.join(names)} (see config/mfp_mapper.yaml for the names)"


def check_value(setting: Setting, value: Any) -> None:
    """Reject a value the node rejects when declaring it, with the text of rclpy's exception
    (``InvalidParameterTypeException``, ``InvalidParameterValueException``): ValueError."""
    if value is None:
        return  # rclpy: "not set" (an empty list in a file) passes; NodeConfig rejects it
    got = python_type_name(value)
    if got != setting.ros_type:
        raise ValueError(
            f"Trying to set parameter '{setting.name}' to '{value}' of type '{got}', "
            f"expecting type '{setting.ros_type}': {setting.name}"
        )
    reason = setting.check_range(value)
    if reason is not None:
        raise ValueError(
            f"Invalid parameter value ({value}) for parameter. Reason: {reason}: {setting.name}"
        )


def check_parameters(values: dict[str, Any]) -> NodeConfig:
    """Parameter overrides -> NodeConfig with the node's rules: unknown names, then each value
    in declaration order (type, range), then the relations. Raises ValueError."""
    unknown = unknown_parameters(list(values))
    if unknown:
        raise ValueError(unknown_parameters_error(unknown))
    ours = {name: value for name, value in values.items() if name in SPECS}
    for spec in PARAMS:
        if spec.name in ours:
            check_value(spec, ours[spec.name])
    return NodeConfig.from_values(ours)


# --- sections ----------------------------------------------------------------------------------

MAP_SECTION: dict[str, str] = {
    "resolution": "resolution",
    "max_range": "sensor_model.max_range",
    "min_range": "sensor_model.min_range",
    "decay_time": "decay_time",
    "threads": "threads",
    "max_voxels": "max_voxels",
    "keep_radius": "keep_radius",
    "prior_shape": "prior.shape",
    "prior_rate": "prior.rate",
}
"""``MapSettings`` field -> the setting it holds."""


@dataclass(frozen=True)
class MapSettings:
    """The map section: what the core's ``Mapper`` takes, in the core's units ("<= 0 means
    no limit" applied). The node (``NodeConfig.map_settings``) and the replay
    (``ReplayOptions.map_settings``) both build it from the schema's settings."""

    resolution: float = BY_NAME["resolution"].core_default
    max_range: float = BY_NAME["sensor_model.max_range"].core_default
    min_range: float = BY_NAME["sensor_model.min_range"].core_default
    decay_time: float = BY_NAME["decay_time"].core_default
    threads: int = BY_NAME["threads"].core_default
    max_voxels: int | None = BY_NAME["max_voxels"].core_default
    keep_radius: float | None = BY_NAME["keep_radius"].core_default
    prior_shape: float = BY_NAME["prior.shape"].core_default
    prior_rate: float = BY_NAME["prior.rate"].core_default

    @classmethod
    def of(cls, core_value: Callable[[str], Any]) -> MapSettings:
        """From ``core_value(setting name)``, the core's value of each setting."""
        return cls(**{field: core_value(name) for field, name in MAP_SECTION.items()})

    def mapper_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``Mapper`` besides the resolution (also the overrides a
        loaded map takes: its own resolution stays)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "resolution"}


# --- the node's values -----------------------------------------------------------------------


@dataclass
class NodeConfig:
    """Validated parameter values (attribute = parameter name with '.' -> '_'); the
    defaults are those of ``PARAMS`` (see ``from_values``)."""

    resolution: float
    frame_id: str
    cloud_frame_id: str
    base_frame_id: str
    decay_time: float
    threads: int
    max_voxels: int
    keep_radius: float
    prior_shape: float
    prior_rate: float
    sensor_model_max_range: float
    sensor_model_min_range: float
    sensor_model_no_return_range: float
    point_cloud_min_x: float
    point_cloud_max_x: float
    point_cloud_min_y: float
    point_cloud_max_y: float
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
    hit_probability_map_max_cells: int
    projected_map_trinary: bool
    projected_map_occupied_threshold: float
    projected_map_free_threshold: float
    octomap_topics: bool
    tf_buffer: float
    localization_enabled: bool
    localization_freeze_map: bool
    localization_odom_frame: str
    localization_tf_publish: bool
    localization_transform_tolerance: float
    localization_tf_rate: float
    localization_min_period: float
    localization_max_rays: int
    localization_max_sigma: float
    localization_min_gain_per_ray: float
    localization_min_constraints: int
    localization_max_shift: float
    localization_max_angle: float
    localization_initial_max_shift: float
    localization_initial_max_angle: float
    localization_lost_after: int
    localization_tracking_levels: int
    localization_tracking_rays: int
    localization_tracking_iterations: int
    localization_exact_check: bool
    localization_exact_check_tracking: bool
    localization_fit_drop: float
    localization_normals_refresh: float
    localization_update_min_d: float
    localization_update_min_a: float
    localization_rebuild_period: float
    map_path: str
    save_on_shutdown: bool
    autosave_period: float
    autostart: bool
    status_period: float

    @property
    def max_range(self) -> float:
        """``sensor_model.max_range`` for the core: inf when <= 0."""
        return float(SPECS["sensor_model.max_range"].core_value(self.sensor_model_max_range))

    @property
    def decay(self) -> float:
        """``decay_time`` for the core: inf for a static map."""
        return float(SPECS["decay_time"].core_value(self.decay_time))

    def core(self, name: str) -> Any:
        """A parameter's value as the core takes it (``Setting.core_value``)."""
        return SPECS[name].core_value(getattr(self, attr_name(name)))

    def map_settings(self) -> MapSettings:
        """The map section of these values (what ``Mapper`` takes)."""
        return MapSettings.of(self.core)

    def lidar_xyz_rpy(self) -> XyzRpy:
        """The lidar pose in the odometry child frame (``lidar.translation``, ``lidar.rpy``)."""
        return xyz_rpy(self.lidar_translation, self.lidar_rpy)

    def lidar_override(self) -> XyzRpy | None:
        """The ``lidar.*`` extrinsic when set (not all zero): it overrides /tf_static."""
        if any(self.lidar_translation) or any(self.lidar_rpy):
            return self.lidar_xyz_rpy()
        return None

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> NodeConfig:
        """Build from parameter values keyed by parameter name (the others take their
        defaults); raise ValueError if invalid."""
        unknown = [name for name in values if name not in SPECS]
        if unknown:
            raise ValueError(unknown_parameters_error(sorted(unknown)))
        unset = [name for name, value in values.items() if value is None]
        if unset:
            raise ValueError(f"parameter(s) {', '.join(unset)} not set (an empty list?)")
        kwargs = {attr_name(name): value for name, value in {**defaults(), **values}.items()}
        cfg = cls(**kwargs)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Check the relations between parameters; raise ValueError naming the culprit."""
        for spec in PARAMS:
            if spec.type is not list:
                continue
            vec = getattr(self, attr_name(spec.name))
            if len(vec) != spec.length or not all(math.isfinite(float(v)) for v in vec):
                raise ValueError(
                    f"{spec.name} must be {spec.length} finite numbers, got {list(vec)}"
                )
            setattr(self, attr_name(spec.name), tuple(float(v) for v in vec))
        for spec in PARAMS:
            value = getattr(self, attr_name(spec.name))
            if spec.lo is not None and not (spec.lo <= value <= spec.hi):
                raise ValueError(f"{spec.name}={value} outside [{spec.lo}, {spec.hi}]")
        if self.sensor_model_min_range >= self.max_range:
            raise ValueError("sensor_model.min_range must be below sensor_model.max_range")
        for axis in "xyz":
            lo, hi = (getattr(self, f"point_cloud_{end}_{axis}") for end in ("min", "max"))
            if lo >= hi:
                raise ValueError(f"point_cloud_min_{axis} must be below point_cloud_max_{axis}")
        if self.occupancy_min_z >= self.occupancy_max_z:
            raise ValueError("occupancy_min_z must be below occupancy_max_z")
        if self.localization_enabled and not self.localization_odom_frame.strip("/ "):
            raise ValueError(
                "localization.odom_frame must name a frame: the node publishes map -> it"
            )

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


# --- the defaults YAML -----------------------------------------------------------------------

YAML_HEADER = """\
# Default parameters of the mfp_mapper node (ROS 2 parameter file), generated from
# mfp_mapper/config/schema.py by `python -m mfp_mapper.config.schema > config/mfp_mapper.yaml`.
#   ros2 run mfp_mapper mfp_mapper --ros-args --params-file config/mfp_mapper.yaml
# Names follow octomap_server where a counterpart exists. Ranges and the full
# descriptions: `ros2 param describe /mfp_mapper <name>` or mfp_mapper/config/schema.py.
/**:
  ros__parameters:
"""


def _yaml_scalar(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return value or '""'
    if isinstance(value, float):
        return "-1.0e+6" if value == -1.0e6 else "1.0e+6" if value == 1.0e6 else repr(value)
    if isinstance(value, list):
        return "[" + ", ".join(_yaml_scalar(v) for v in value) + "]"
    return str(value)


def _wrap(text: str, indent: str, width: int = 96) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width, initial_indent=indent + "# ", subsequent_indent=indent + "# ")


def defaults_yaml() -> str:
    """The text of ``config/mfp_mapper.yaml``: every parameter with its default."""
    lines = [YAML_HEADER.rstrip("\n")]
    for spec in PARAMS:
        lines += _wrap(spec.description, "    ")
        lines.append(f"    {spec.name}: {_yaml_scalar(spec.default)}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    import sys

    sys.stdout.write(defaults_yaml())
