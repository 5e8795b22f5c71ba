"""The settings sections: every setting of the node, the replay and the CLI, defined once.

Each section is a frozen dataclass; each field is one setting, made by ``setting(default,
description, lo, hi, ...)``, which carries the ROS parameter name, the range, the CLI flag,
whether it changes at run time (``dynamic``), where it applies (``node``: a ROS parameter only;
``replay``: the offline replay and its CLI only; ``both``) and "<= 0 means no limit"
(``unlimited``). Everything else derives from these fields (``mfp_mapper.config.schema``):
``SETTINGS``, the ROS declarations, ``config/mfp_mapper.yaml``, the replay's flags,
``NodeConfig`` (``cfg.map.resolution``) and ``ReplayOptions`` (``opts.map.resolution``).

Adding a setting: one field in one section below, then regenerate the YAML
(``python -m mfp_mapper.config.schema > config/mfp_mapper.yaml``; a test checks it).

A field is named after its setting: the name without the section's ``PREFIX``, '.' -> '_'
(``localization.fit_drop`` is ``LocalizationSection.fit_drop``, ``prior.shape`` is
``MapSection.prior_shape``). Node parameter names follow octomap_server where a counterpart
exists (``resolution``, ``frame_id``, ``sensor_model.max_range``, ``point_cloud_min_z``,
``latch``...). Values are held as the user gives them; ``section.core(field)`` is the value
the core takes ("<= 0 means no limit" applied). Plain data: no ROS, no numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

from mfp_mapper.config.setting import NO_LIMIT_BAND, NO_LIMIT_Z, Section, XyzRpy, setting, xyz_rpy


@dataclass(frozen=True)
class MapSection(Section):
    """The map: what the core's ``Mapper`` is built with (with ``SensorModelSection``)."""

    KEY = "map"
    TITLE = "The map"

    resolution: float = setting(
        0.1,
        "Voxel edge (m). A map loaded from map_path keeps its own.",
        0.01,
        10.0,
        applies="both",
        flag="--resolution",
    )
    frame_id: str = setting(
        "",
        "Map frame, fixed for the run (octomap_server's frame_id; set it to 'map' with "
        "SLAM/localization: map -> odom is then taken from TF and clouds wait for it). Empty:"
        " a loaded map's frame, else decided at the first cloud placed: the odometry's "
        "header.frame_id, without odometry the root of the cloud frame's TF tree; never "
        "changed afterwards.",
    )
    decay_time: float = setting(
        0.0,
        "Time constant T (s) of the dynamic-environment decay (Eq. 28-30): evidence is scaled"
        " by exp(-dt/T). 0: static map (T = inf).",
        0.0,
        1.0e9,
        applies="both",
        flag="--decay-time",
        unlimited="inf",
    )
    threads: int = setting(
        0,
        "Threads the core uses to walk the rays of one scan. 0: automatic, one a core this "
        "process may run on (its CPU affinity), at most 4 (docs/performance.md: two cores "
        "keep up with a VLP-32C at 10 Hz where one thread falls behind at 0.1 m). The map is "
        "the same bit for bit whatever the count. 1 leaves the other cores to the rest of the"
        " robot's software.",
        0,
        64,
        applies="both",
        flag="--threads",
        unlimited="cores",
    )
    max_voxels: int = setting(
        0,
        "Memory bound: at most this many voxels. 0: no limit.",
        0,
        2**31 - 1,
        applies="both",
        flag="--max-voxels",
        unlimited="none",
    )
    keep_radius: float = setting(
        0.0,
        "Keep only the map blocks within this distance (m) of the latest sensor position; "
        "farther ones are evicted after each scan. 0: keep all.",
        0.0,
        1.0e6,
        applies="both",
        flag="--keep-radius",
        unlimited="none",
    )
    prior_shape: float = setting(
        0.0,
        "Shape alpha (returns) of the Gamma prior on each voxel's extinction (docs/model.md)."
        " 0: from the family, prior.scale * resolution. 1 (with prior.rate 1): the paper's "
        "uniform prior on m. Used by every estimate but the most likely DoO (mean, std, "
        "intervals, hit probability, the grids' thresholds); never stored in the statistics."
        " `mfp-mapper fit-prior` fits it to a recording.",
        0.0,
        1.0e6,
        name="prior.shape",
        applies="both",
        flag="--prior-shape",
    )
    prior_rate: float = setting(
        0.0,
        "Rate beta (metres of ray) of the Gamma prior on the extinction: the prior weighs "
        "like beta metres of ray with alpha returns. 0: from the family, prior.scale * "
        "resolution / 2.",
        0.0,
        1.0e6,
        name="prior.rate",
        applies="both",
        flag="--prior-rate",
    )
    prior_scale: float = setting(
        0.0275,
        "Scale a (per metre) of the default prior's family: shape a * resolution, rate a * "
        "resolution / 2 m, for prior.shape and prior.rate left at 0 (docs/scoring.md: "
        "measured on real recordings; `mfp-mapper fit-prior` over several recordings fits "
        "it).",
        1.0e-6,
        1.0e6,
        name="prior.scale",
        applies="both",
        flag="--prior-scale",
    )
    reflectivity_bins: int = setting(
        8,
        "Bins J of the reflectivity histogram each voxel with returns keeps (Appendix B; "
        "docs/model.md): clouds with an intensity field (Ouster 'reflectivity', else "
        "'intensity') are binned on log-spaced edges fixed per field. 0: no histograms. A "
        "loaded map keeps its own bins.",
        0,
        64,
        name="reflectivity.bins",
        applies="both",
        flag="--reflectivity-bins",
    )


@dataclass(frozen=True)
class SensorModelSection(Section):
    """The sensor model: which returns and rays are used (``sensor_model.*``)."""

    PREFIX = "sensor_model."
    KEY = "sensor_model"
    TITLE = "The sensor model"

    max_range: float = setting(
        100.0,
        "Rays are cut at this range (m); a return beyond it clears space up to it but counts "
        "no return. <= 0: no limit (octomap_server's -1).",
        -1.0,
        1.0e5,
        dynamic=True,
        applies="both",
        flag="--max-range",
        unlimited="inf",
    )
    min_range: float = setting(
        0.0,
        "Returns closer than this (m) are dropped with their rays (robot body, dust).",
        0.0,
        1000.0,
        applies="both",
        flag="--min-range",
    )
    no_return_range: float = setting(
        0.0,
        "Firings that returned nothing (NaN/zero cells of organized clouds, gaps of "
        "ring/channel clouds) become rays that clear space up to this range (m) and count no "
        "return. 0: off, the default: a missing return may also be a dark or glossy obstacle,"
        " or one closer than the minimum range (docs/model.md, 'Rays with no return').",
        0.0,
        1.0e5,
        applies="both",
        flag="--no-return-range",
    )
    first_echo_only: bool = setting(
        False,
        "Use only the first echo of each laser shot. False (the default): every echo the "
        "cloud marks (Nebula return_type, ouster-ros points2, Livox tag, target_index) joins "
        "its shot's ray, one Poisson process along the beam (docs/model.md, 'Every echo of a "
        "shot').",
        applies="both",
        flag="--first-echo-only",
    )
    echo_blind_stretch: float = setting(
        0.75,
        "Metres of beam after each echo left out of the free space a shot clears: right "
        "behind an echo a lidar sees later echoes at a fraction of their rate (measured on a "
        "RIEGL scan of conifers; docs/model.md, 'Every echo of a shot').",
        0.0,
        100.0,
        applies="both",
        flag="--echo-blind-stretch",
    )


@dataclass(frozen=True)
class PlacementSection(Section):
    """How clouds are received and placed in the map frame: frames, the lidar extrinsic,
    de-skewing, the point-cloud box, the cloud queue and the odometry/TF timing."""

    KEY = "placement"
    TITLE = "Placing the clouds"

    cloud_frame_id: str = setting(
        "",
        "Frame of clouds whose header.frame_id is empty (e.g. the lidar frame). Empty: such "
        "clouds are dropped (no_frame).",
    )
    base_frame_id: str = setting(
        "",
        "Robot body frame the lidar extrinsic (from /tf_static) is relative to. Empty: the "
        "odometry's child_frame_id.",
    )
    lidar_translation: tuple[float, float, float] = setting(
        (0.0, 0.0, 0.0),
        "Lidar position [x, y, z] (m) in the odometry child frame; when set (not all zero "
        "with lidar.rpy) it overrides /tf_static. Ignored when the cloud's frame_id is the "
        "odometry child_frame_id (identity).",
        name="lidar.translation",
        applies="both",
        length=3,
    )
    lidar_rpy: tuple[float, float, float] = setting(
        (0.0, 0.0, 0.0),
        "Lidar orientation [roll, pitch, yaw] (rad, fixed axes X-Y-Z) in the odometry child "
        "frame. Ignored like lidar.translation.",
        name="lidar.rpy",
        applies="both",
        length=3,
    )
    deskew: bool = setting(
        True,
        "Give every point its own pose when the cloud has per-point time (Velodyne 'time', "
        "Ouster 't', Hesai/Nebula 'timestamp'/'time_stamp').",
        applies="both",
        flag="--no-deskew",
    )
    point_cloud_min_x: float = setting(
        -NO_LIMIT_BAND,
        "Returns whose map-frame x (m) is below this are dropped with their rays.",
        -NO_LIMIT_BAND,
        NO_LIMIT_BAND,
        dynamic=True,
        applies="both",
        flag="--min-x",
    )
    point_cloud_max_x: float = setting(
        NO_LIMIT_BAND,
        "Returns whose map-frame x (m) is above this are dropped with their rays.",
        -NO_LIMIT_BAND,
        NO_LIMIT_BAND,
        dynamic=True,
        applies="both",
        flag="--max-x",
    )
    point_cloud_min_y: float = setting(
        -NO_LIMIT_BAND,
        "Returns whose map-frame y (m) is below this are dropped with their rays.",
        -NO_LIMIT_BAND,
        NO_LIMIT_BAND,
        dynamic=True,
        applies="both",
        flag="--min-y",
    )
    point_cloud_max_y: float = setting(
        NO_LIMIT_BAND,
        "Returns whose map-frame y (m) is above this are dropped with their rays.",
        -NO_LIMIT_BAND,
        NO_LIMIT_BAND,
        dynamic=True,
        applies="both",
        flag="--max-y",
    )
    point_cloud_min_z: float = setting(
        -NO_LIMIT_BAND,
        "Returns whose map-frame z (m) is below this are dropped with their rays.",
        -NO_LIMIT_BAND,
        NO_LIMIT_BAND,
        dynamic=True,
        applies="both",
        flag="--min-z",
    )
    point_cloud_max_z: float = setting(
        NO_LIMIT_BAND,
        "Returns whose map-frame z (m) is above this are dropped with their rays.",
        -NO_LIMIT_BAND,
        NO_LIMIT_BAND,
        dynamic=True,
        applies="both",
        flag="--max-z",
    )
    second_return_topic: str = setting(
        "",
        "Topic of a second cloud holding the second returns of the clouds on cloud_in, in the "
        "same pixel layout and with the same stamps (ouster-ros 'points2'); each pair is "
        "integrated as one cloud, the two returns of a pixel as one shot. Empty: off. Offline "
        "(replay, score, localize, fleet): the bag's topic of that name, paired with the cloud "
        "topic as the node pairs them.",
        applies="both",
        flag="--second-return-topic",
    )
    cloud_queue_size: int = setting(
        5,
        "Clouds waiting for integration; when full the oldest is dropped (counted).",
        1,
        1000,
    )
    odom_wait: float = setting(
        1.0,
        "How long (s, wall clock) a cloud newer than the latest odometry waits for odometry "
        "to cover it before it is dropped.",
        0.0,
        60.0,
    )
    odom_buffer: float = setting(
        10.0,
        "Odometry history kept (s of stamps); older clouds are dropped.",
        0.1,
        3600.0,
    )
    odom_max_gap: float = setting(
        0.5,
        "Largest time (s) between two odometry messages that a cloud may be interpolated "
        "across; clouds in a longer gap are dropped.",
        0.001,
        60.0,
        applies="both",
        flag="--max-gap",
    )
    tf_buffer: float = setting(
        10.0,
        "TF cache time (s; tf2's default 10): /tf samples kept per transform; a transform not"
        " received for this long (stream time) is forgotten.",
        0.1,
        3600.0,
    )

    def lidar_xyz_rpy(self) -> XyzRpy:
        """The lidar pose in the odometry child frame (``lidar.translation``, ``lidar.rpy``)."""
        return xyz_rpy(self.lidar_translation, self.lidar_rpy)

    def lidar_override(self) -> XyzRpy | None:
        """The ``lidar.*`` extrinsic when set (not all zero): it overrides /tf_static."""
        if any(self.lidar_translation) or any(self.lidar_rpy):
            return self.lidar_xyz_rpy()
        return None


@dataclass(frozen=True)
class OutputsSection(Section):
    """What the node publishes: the map clouds, the 2D grids and their thresholds."""

    KEY = "outputs"
    TITLE = "What the node publishes"

    latch: bool = setting(
        True,
        "Publish the map clouds transient-local (late joiners such as RViz get the last one).",
    )
    publish_rate: float = setting(
        1.0,
        "Rate (Hz) of ~/degree_of_occupancy, ~/std and ~/projected_map; published only when "
        "the map changed and someone subscribes, and spaced out so that building them holds "
        "the map at most a tenth of the time (a large map with publish_radius 0). 0: never.",
        0.0,
        100.0,
    )
    min_degree_of_occupancy: float = setting(
        0.1,
        "Published voxels have at least this most likely degree of occupancy.",
        0.0,
        1.0,
        dynamic=True,
    )
    min_evidence: float = setting(
        0.0,
        "Published voxels have at least this evidence s (m travelled by rays in them).",
        0.0,
        1.0e9,
        dynamic=True,
    )
    publish_radius: float = setting(
        0.0,
        "Publish only voxels within this distance (m) of the robot. 0: the whole map (its "
        "cost grows with the map's size; docs/node.md 'Map outputs').",
        0.0,
        1.0e6,
        dynamic=True,
    )
    publish_changed_blocks: bool = setting(
        True,
        "Rebuild the map clouds and ~/projected_map from the blocks scans changed since the "
        "last publication, the rest from the previous ones: the same whole outputs, holding "
        "the map for a fraction of the time when the robot drives (docs/node.md 'Map "
        "outputs'). False: read the whole map each time (as with min_degree_of_occupancy 0 "
        "for the clouds).",
        dynamic=True,
    )
    occupancy_min_z: float = setting(
        0.1,
        "Bottom (m, map frame) of the height band of ~/hit_probability_map.",
        -NO_LIMIT_Z,
        NO_LIMIT_Z,
        dynamic=True,
    )
    occupancy_max_z: float = setting(
        2.0,
        "Top (m, map frame) of the height band of ~/hit_probability_map.",
        -NO_LIMIT_Z,
        NO_LIMIT_Z,
        dynamic=True,
    )
    hit_probability_map_radius: float = setting(
        0.0,
        "~/hit_probability_map covers the square of this half side (m) around the robot. 0: "
        "the whole map.",
        0.0,
        1.0e6,
        name="hit_probability_map.radius",
        dynamic=True,
    )
    hit_probability_map_max_cells: int = setting(
        25_000_000,
        "Most cells ~/hit_probability_map and ~/projected_map may hold; a larger map is "
        "served as the largest square around the robot that fits (logged).",
        1,
        2**31 - 1,
        name="hit_probability_map.max_cells",
        dynamic=True,
    )
    projected_map_trinary: bool = setting(
        True,
        "~/projected_map cells 100 (occupied) / 0 (free) / -1 (unknown), as Nav2's static "
        "layer expects. False: round(100 hit probability), like ~/hit_probability_map.",
        name="projected_map.trinary",
        dynamic=True,
    )
    projected_map_occupied_threshold: float = setting(
        0.25,
        "Hit probability at or above which a ~/projected_map cell is occupied (100).",
        0.0,
        1.0,
        name="projected_map.occupied_threshold",
        dynamic=True,
    )
    projected_map_free_threshold: float = setting(
        -1.0,
        "Hit probability below which an observed ~/projected_map cell is free (0). Negative: "
        "that of a never-observed voxel under the map's prior, 1 - (rate / (rate + "
        "resolution))^shape (0.012 at 0.1 m with the default prior).",
        -1.0,
        1.0,
        name="projected_map.free_threshold",
        dynamic=True,
    )
    octomap_topics: bool = setting(
        False,
        "Publish under octomap_server's topic names, relative to the node's namespace: "
        "projected_map (the grid) and octomap_point_cloud_centers (the degree-of-occupancy "
        "cloud) instead of ~/projected_map and ~/degree_of_occupancy, so Nav2/RViz configs "
        "made for octomap_server work unchanged.",
    )


@dataclass(frozen=True)
class LocalizationSection(Section):
    """Localization against the loaded map (``localization.*``; docs/localization.md)."""

    PREFIX = "localization."
    KEY = "localization"
    TITLE = "Localization mode (`localization.enabled`)"

    enabled: bool = setting(
        False,
        "Localize each cloud against the map loaded from map_path (scan-to-map alignment by "
        "the forward model's likelihood) and publish the map -> odom correction on /tf, as "
        "AMCL does; clouds are placed in localization.odom_frame, the map frame is frame_id "
        "(or the loaded map's).",
    )
    freeze_map: bool = setting(
        True,
        "true: the loaded map is not changed (localization only); false: clouds are also "
        "integrated at their corrected poses.",
    )
    odom_frame: str = setting(
        "odom",
        "The odometry frame (AMCL's odom_frame_id): clouds are placed in it by odometry or "
        "TF, and the node publishes map -> odom_frame.",
    )
    tf_publish: bool = setting(
        True,
        "Publish map -> odom on /tf (AMCL's tf_broadcast); false: only ~/status reports the "
        "correction.",
    )
    transform_tolerance: float = setting(
        0.5,
        "Seconds the published map -> odom is future-dated by (AMCL's transform_tolerance).",
        0.0,
        60.0,
        dynamic=True,
    )
    tf_rate: float = setting(
        20.0,
        "Rate (Hz) at which the last map -> odom is republished, stamped now + "
        "transform_tolerance, so that it never expires.",
        0.1,
        1000.0,
    )
    min_period: float = setting(
        0.0,
        "Align at most one cloud per this many seconds (stamp time); the others are placed "
        "with the last correction. 0: every cloud.",
        0.0,
        3600.0,
        dynamic=True,
    )
    max_rays: int = setting(
        3000,
        "Rays per cloud used by the wide search's alignment (an evenly spread subset; while "
        "localized: localization.tracking_rays).",
        10,
        10_000_000,
        dynamic=True,
    )
    max_sigma: float = setting(
        0.05,
        "Refuse a correction whose standard deviation along its weakest direction exceeds "
        "this (m): degenerate geometry.",
        0.0,
        100.0,
        dynamic=True,
    )
    min_gain_per_ray: float = setting(
        0.02,
        "Refuse a correction that raises the scan's log-likelihood by less than this per ray "
        "(nats).",
        0.0,
        100.0,
        dynamic=True,
    )
    min_constraints: int = setting(
        5,
        "Refuse when fewer planar patches of the scan than this constrain some direction (a "
        "corridor's axis).",
        0,
        1_000_000,
        dynamic=True,
    )
    max_shift: float = setting(
        0.5,
        "While localized: refuse a correction that moves the robot further than this (m).",
        0.0,
        100.0,
        dynamic=True,
    )
    max_angle: float = setting(
        5.0,
        "While localized: refuse a correction that turns the robot by more than this (degrees).",
        0.0,
        180.0,
        dynamic=True,
    )
    initial_max_shift: float = setting(
        1.0,
        "Before the first accepted correction (at start, after /initialpose, when lost): the "
        "wider search range (m).",
        0.0,
        100.0,
        dynamic=True,
    )
    initial_max_angle: float = setting(
        10.0,
        "Before the first accepted correction: the wider search range (degrees).",
        0.0,
        180.0,
        dynamic=True,
    )
    lost_after: int = setting(
        10,
        "Consecutive refused corrections after which the state is 'lost' (the wider search is"
        " used again).",
        1,
        1_000_000,
        dynamic=True,
    )
    tracking_levels: int = setting(
        1,
        "While localized: pyramid levels the alignment uses, finest first (before the first "
        "acceptance and when lost: all 3).",
        1,
        3,
        dynamic=True,
    )
    tracking_rays: int = setting(
        1000,
        "While localized: rays per cloud used by the alignment (localization.max_rays: the "
        "wide search).",
        10,
        10_000_000,
        dynamic=True,
    )
    tracking_iterations: int = setting(
        10,
        "While localized: Levenberg-Marquardt steps per alignment (the wide search: 30).",
        1,
        1000,
        dynamic=True,
    )
    exact_check: bool = setting(
        True,
        "Refuse a correction of the wide search (start, /initialpose, lost) unless the exact "
        "likelihood of the scan under the map rises significantly (refusal 'exact_check').",
        dynamic=True,
    )
    exact_check_tracking: bool = setting(
        False,
        "Also check the corrections found while localized (sub-voxel corrections of drifting "
        "odometry are mostly refused).",
        dynamic=True,
    )
    fit_drop: float = setting(
        0.3,
        "Refuse a scan, and stop vouching for the pose, when it fits the map this much worse "
        "(smoothed log-likelihood per ray, nats) than the scans accepted before it (refusal "
        "'poor_fit': odometry that jumped, a kidnapped robot); lost after lost_after such "
        "scans; 0: no check.",
        0.0,
        100.0,
        dynamic=True,
    )
    normals_refresh: float = setting(
        0.5,
        "While localized: recompute the scan's surface normals (geometric conditioning) once "
        "the robot moved this far (m, odometry) since they were; 0: every cloud.",
        0.0,
        1000.0,
        dynamic=True,
    )
    update_min_d: float = setting(
        0.25,
        "While localized: align a cloud only after the robot moved this far (m, odometry) "
        "since the last alignment, or turned update_min_a (AMCL's update_min_d). 0 and 0: "
        "every cloud.",
        0.0,
        1000.0,
        dynamic=True,
    )
    update_min_a: float = setting(
        11.5,
        "While localized: align a cloud only after the robot turned this much (degrees, "
        "odometry) since the last alignment, or moved update_min_d (AMCL's update_min_a, 0.2 "
        "rad).",
        0.0,
        360.0,
        dynamic=True,
    )
    rebuild_period: float = setting(
        5.0,
        "With freeze_map false: the alignment's field is rebuilt from the growing map at most"
        " this often (s, in the background).",
        0.1,
        86400.0,
        dynamic=True,
    )


@dataclass(frozen=True)
class NodeSection(Section):
    """The node's map file, start and health."""

    KEY = "node"
    TITLE = "Map file, start and health"

    map_path: str = setting(
        "",
        "Map file (.npz), or tiled map (a directory), for ~/save_map, loaded at start when it"
        " exists. Empty: none.",
    )
    save_on_shutdown: bool = setting(
        False,
        "Save the map to map_path when the node stops.",
    )
    autosave_period: float = setting(
        0.0,
        "Save the map to map_path in the background at most this often (s), when it changed; "
        "mapping goes on meanwhile. 0: off.",
        0.0,
        86400.0,
    )
    autostart: bool = setting(
        True,
        "Configure and activate the node when it starts (a plain node). false: it waits "
        "unconfigured for a lifecycle manager (Nav2's lifecycle_manager, ros2 lifecycle set) "
        "to configure and activate it.",
    )
    status_period: float = setting(
        10.0,
        "Period (s) of the status log line and of ~/status. 0: off.",
        0.0,
        3600.0,
    )


@dataclass(frozen=True)
class QuerySection(Section):
    """The largest request ``~/query`` answers (larger ones are refused with a message)."""

    KEY = "query"
    PREFIX = "query."
    TITLE = "Map queries (`~/query`)"

    max_points: int = setting(
        100_000,
        "Most points one ~/query request may ask about.",
        0,
        10_000_000,
        dynamic=True,
    )
    max_segments: int = setting(
        10_000,
        "Most segments one ~/query request may ask about.",
        0,
        1_000_000,
        dynamic=True,
    )
    max_segment_length: float = setting(
        500.0,
        "Longest segment (m) ~/query walks (its time grows with the voxels it crosses).",
        0.0,
        1.0e5,
        dynamic=True,
    )


@dataclass(frozen=True)
class ReplaySection(Section):
    """The offline replay only: topics, poses, the extrinsic flag, which clouds."""

    KEY = "replay"
    TITLE = "The replay only"

    cloud_topic: str | None = setting(
        None,
        "sensor_msgs/PointCloud2 topic (default: detected).",
        type=str,
        applies="replay",
        flag="--cloud-topic",
    )
    odom_topic: str | None = setting(
        None,
        "nav_msgs/Odometry topic (default: detected).",
        type=str,
        applies="replay",
        flag="--odom-topic",
    )
    use_tf_poses: bool = setting(
        False,
        "Poses from the /tf chain even when the bag has an Odometry topic.",
        applies="replay",
        flag="--tf",
    )
    fixed_frame: str | None = setting(
        None,
        "With /tf poses: the map frame (default: odom if on the chain, else the root).",
        type=str,
        applies="replay",
        flag="--fixed-frame",
    )
    extrinsic: XyzRpy | None = setting(
        None,
        "Lidar pose [x, y, z, roll, pitch, yaw] (m, rad) in the odometry child frame; "
        "overrides /tf_static and the lidar.* parameters.",
        type=list,
        applies="replay",
        flag="--extrinsic",
        length=6,
        metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"),
    )
    max_scans: int | None = setting(
        None,
        "Stop after this many clouds.",
        0,
        2**63 - 1,
        type=int,
        applies="replay",
        flag="--max-scans",
    )
    start: float | None = setting(
        None,
        "Map only clouds stamped at or after this absolute time (s); the window is half-open,"
        " [start, end).",
        type=float,
        applies="replay",
    )
    end: float | None = setting(
        None,
        "Map only clouds stamped before this absolute time (s).",
        type=float,
        applies="replay",
    )
    start_offset: float | None = setting(
        None,
        "Like start, in seconds after the first cloud.",
        type=float,
        applies="replay",
    )
    end_offset: float | None = setting(
        None,
        "Like end, in seconds after the first cloud.",
        type=float,
        applies="replay",
    )
    start_index: int = setting(
        0,
        "First cloud mapped, by its position in the recording (0: the first).",
        0,
        2**63 - 1,
        applies="replay",
    )
    end_index: int | None = setting(
        None,
        "Clouds from this position on are not mapped: [start_index, end_index).",
        0,
        2**63 - 1,
        type=int,
        applies="replay",
    )
    every: int = setting(
        1,
        "Map one cloud in N of those selected (the first, then every N-th).",
        1,
        2**63 - 1,
        applies="replay",
        flag="--every",
    )
    odometry: str | None = setting(
        None,
        "Poses estimated from the clouds: kiss-icp (needs the kiss-icp package). Default: "
        "poses from the recording.",
        type=str,
        applies="replay",
    )


SECTIONS: tuple[type[Section], ...] = (
    MapSection,
    SensorModelSection,
    PlacementSection,
    OutputsSection,
    LocalizationSection,
    NodeSection,
    QuerySection,
    ReplaySection,
)
"""Every section, in the order of ``SETTINGS`` (and of the YAML)."""
