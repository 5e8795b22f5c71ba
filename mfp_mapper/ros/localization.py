"""The node's localization mode (``localization.enabled``), AMCL's interface on the
forward model: clouds placed in the odometry frame are aligned against the map
(``mapping.live_localization.LiveLocalizer``, through the worker's
``mapping.pose_correction.LocalizerCorrection``); this role publishes what it vouches for
and takes what RViz gives:

- ``map -> odom`` on ``/tf`` (``localization.tf_publish``): a new correction stamped with
  its cloud's stamp (a late one, more than ``transform_tolerance`` behind the clock or
  behind the last published, at that bound: ``tf_stamp``), else the last one stamped now,
  both future-dated by ``localization.transform_tolerance``, at ``localization.tf_rate``;
- ``~/pose`` (AMCL's ``amcl_pose``): the robot in the map frame at each alignment that
  vouched for it, with the alignment's standard deviations;
- ``/initialpose`` (RViz's "2D Pose Estimate"): resets map -> odom.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import rclpy.time
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
from rclpy.clock import Clock
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from tf2_msgs.msg import TFMessage

from mfp_mapper.config.frames import frame_name
from mfp_mapper.config.schema import NodeConfig
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.store import MAX_VOXEL_INDEX
from mfp_mapper.mapping.live import LiveIntegrator
from mfp_mapper.mapping.live_localization import LiveLocalizer
from mfp_mapper.mapping.pose_correction import LocalizerCorrection
from mfp_mapper.ros.guarded_node import GuardedNode, tracked_role
from mfp_mapper.sensing.pointcloud import stamp_seconds


def tf_stamp(correction_stamp: float, now: float, tolerance: float, last: float) -> float:
    """The stamp a new correction is published at (before ``transform_tolerance`` is added):
    its cloud's, unless that lies more than ``tolerance`` behind the clock (a late
    correction: a slow wide search, a queue) or behind the last one published (``last``;
    not after the clock: a clock that jumped back starts over); then the later of those.
    map -> odom does not go back in time, and a late one is valid at once."""
    floor = max(min(last, now), now - tolerance) if now > 0.0 else last
    return max(correction_stamp, floor)


DEFAULT_MAP_FRAME = "map"
"""The map frame when neither ``frame_id`` nor the loaded map names one other than the
odometry frame."""


def localization_frame(frame_id: str, map_file_frame: str, odom_frame: str) -> str:
    """The map frame localized in: ``frame_id`` when set; else the loaded map's frame, unless
    it is the odometry frame (a map made by ``mfp-mapper replay`` is in its recording's
    ``odom``: the file's frame is where its voxels are, the node publishes map -> odom) or
    none; then ``map``."""
    if frame_id:
        return frame_id
    if map_file_frame and map_file_frame != odom_frame:
        return map_file_frame
    return DEFAULT_MAP_FRAME


class Localization:
    """The localization mode's state, publishers, subscription and timer (see the module
    docstring). ``correction`` is what the worker takes to place clouds in the map frame."""

    def __init__(
        self,
        node: GuardedNode,
        config: Callable[[], NodeConfig],
        mapper: Mapper,
        now: Callable[[], float],
    ) -> None:
        """Localize against ``mapper`` (the map loaded at configure), its map frame being
        ``localization_frame`` (``mapper.frame_id`` is set to it); raises ValueError when
        ``frame_id`` names the odometry frame."""
        self.node = node
        self._config = config
        self._now = now
        cfg = config()
        settings = cfg.localization
        odom_frame = frame_name(settings.odom_frame)
        global_frame = localization_frame(cfg.map.frame_id, mapper.frame_id, odom_frame)
        if not cfg.map.frame_id and mapper.frame_id == odom_frame:
            node.get_logger().info(
                f"the map was built in {odom_frame!r} (the odometry frame of its recording, as "
                f"`mfp-mapper replay` writes it): localizing in {global_frame!r}, its voxels "
                f"taken as coordinates of {global_frame!r}; publishing {global_frame} -> "
                f"{odom_frame} (set frame_id to name the map frame)"
            )
        mapper.frame_id = global_frame
        if not mapper.num_voxels:
            node.get_logger().warning(
                "localization.enabled but no map was loaded from map_path "
                f"{cfg.node.map_path!r}: waiting for a map"
                + (
                    " (none will come: localization.freeze_map is true)"
                    if settings.freeze_map
                    else ""
                )
            )
        if odom_frame == global_frame:
            raise ValueError(
                f"frame_id and localization.odom_frame are both {global_frame!r}: the "
                f"correction map -> odom needs two frames; set frame_id to the map frame "
                f"(e.g. -p frame_id:=map), or leave it empty to localize in 'map'"
            )
        self.localizer = LiveLocalizer(settings, global_frame, log=node.get_logger().info)
        self.correction = LocalizerCorrection(self.localizer)
        self._worker: LiveIntegrator | None = None
        self._pose_pub: Any = None
        self._tf_pub: Any = None
        self._pose_version = 0
        self._tf_version = -1
        self._tf_stamp = -math.inf  # the last map -> odom's stamp (before the tolerance)

    def start(self, worker: LiveIntegrator) -> None:
        """Localize ``worker``'s clouds; the field of a loaded map is built at once (in the
        background)."""
        self._worker = worker
        if worker.mapper.num_voxels:
            self.localizer.build_in_background(worker.mapper, worker.whole_map, force=True)

    def create_publishers(self) -> list[Any]:
        """``~/pose`` and, with ``localization.tf_publish``, ``/tf`` (at configure)."""
        self._pose_pub = self.node.create_publisher(PoseWithCovarianceStamped, "~/pose", 10)
        created = [self._pose_pub]
        self._pose_version = 0
        self._tf_version = -1
        self._tf_stamp = -math.inf
        if self._config().localization.tf_publish:
            tf_qos = QoSProfile(
                history=HistoryPolicy.KEEP_LAST,
                depth=100,
                reliability=ReliabilityPolicy.RELIABLE,
            )
            self._tf_pub = self.node.create_publisher(TFMessage, "/tf", tf_qos)
            created.append(self._tf_pub)
        return created

    def create_inputs(self, clock: Clock) -> list[Any]:
        """``/initialpose`` and the map -> odom timer on ``clock`` (at activate)."""
        return [
            self.node.create_subscription(
                PoseWithCovarianceStamped, "initialpose", self._on_initial_pose, 10
            ),
            self.node.create_timer(
                1.0 / self._config().localization.tf_rate, self._on_tf_timer, clock=clock
            ),
        ]

    def reconfigure(self, cfg: NodeConfig) -> None:
        """Parameters changed at run time: the next cloud uses them."""
        self.localizer.settings = cfg.localization

    def map_changed(self) -> None:
        """After a reset or a cleared box: the field is rebuilt."""
        worker = self._started()
        self.localizer.build_in_background(worker.mapper, worker.whole_map, force=True)

    def report(self) -> dict[str, Any]:
        """``~/status``'s ``localization`` part."""
        return self.localizer.report()

    def _started(self) -> LiveIntegrator:
        assert self._worker is not None, "start() comes first"
        return self._worker

    @tracked_role
    def _on_initial_pose(self, msg: PoseWithCovarianceStamped) -> None:
        """``/initialpose`` (RViz's "2D Pose Estimate"): the robot's pose in the map frame;
        map -> odom is reset so that the robot's odometry pose maps to it."""
        worker = self._started()
        mapper = worker.mapper
        frame = frame_name(msg.header.frame_id)
        expected = self.localizer.global_frame
        if frame != expected:
            self.node.warn_throttled(
                "initialpose_frame",
                f"/initialpose in frame {frame!r} ignored: it must be in the map frame "
                f"{expected!r} (RViz: set the Fixed Frame to {expected!r})",
                error=True,
            )
            return
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        values = (p.x, p.y, p.z, q.x, q.y, q.z, q.w)
        if (
            not all(np.isfinite(values))
            or abs(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w - 1) > 0.01
        ):
            self.node.warn_throttled(
                "initialpose_bad",
                f"/initialpose ignored: not finite or not a unit quaternion {values}",
                error=True,
            )
            return
        reach = MAX_VOXEL_INDEX * mapper.resolution
        origin = np.asarray(mapper.origin or (0.0, 0.0, 0.0))
        if float(np.max(np.abs(np.array((p.x, p.y, p.z)) - origin))) >= reach:
            self.node.warn_throttled(
                "initialpose_far",
                f"/initialpose ignored: position ({p.x:.6g}, {p.y:.6g}, {p.z:.6g}) is beyond "
                f"the map's reach ({reach:.6g} m from its origin at {mapper.resolution} m)",
                error=True,
            )
            return
        stamp, clock = stamp_seconds(msg.header.stamp), self._now()
        stamp = stamp if stamp > 0.0 else clock  # RViz may leave it 0
        ahead = stamp - clock if clock > 0.0 else 0.0
        if ahead > 1.0:  # would stamp map -> odom ahead of every lookup until a correction
            stamp = clock
        now = self.localizer.initial_pose(
            stamp,
            (p.x, p.y, p.z),
            (q.x, q.y, q.z, q.w),
            self.correction.robot_in_odom(worker.pose_inputs, stamp),
        )
        when = "map -> odom reset now" if now else "applied at the next cloud (no odometry yet)"
        self.node.get_logger().info(
            f"/initialpose received: robot at x {p.x:.3f} y {p.y:.3f} z {p.z:.3f} in "
            f"{expected!r}; {when}"
            + (
                f"; its stamp was {ahead:.6g} s ahead of the clock: taken as now"
                if ahead > 1.0
                else ""
            )
        )

    @tracked_role
    def _on_tf_timer(self) -> None:
        """Publish ``~/pose`` when an alignment vouched for a new one, and map -> odom: a new
        correction stamped with its cloud's stamp, else the last one stamped now; both
        future-dated by ``transform_tolerance`` (AMCL's rule)."""
        self._publish_pose()
        if not self._config().localization.tf_publish:
            return
        m, stamp, version = self.localizer.transform()
        if not np.isfinite(stamp):
            return  # no correction yet (none accepted, no /initialpose): nothing to claim
        now = self._now()
        if version == self._tf_version:
            if now <= 0.0:
                return  # use_sim_time before /clock
            stamp = max(now, stamp)
        else:
            tolerance = self._config().localization.transform_tolerance
            stamp = tf_stamp(stamp, now, tolerance, self._tf_stamp)
        self._tf_version = version
        self._tf_stamp = stamp
        self._tf_pub.publish(TFMessage(transforms=[self._map_to_odom(m, stamp)]))

    def _publish_pose(self) -> None:
        """``~/pose`` (AMCL's amcl_pose): the robot in the map frame, at each alignment that
        vouched for it, with the alignment's standard deviations on the diagonal."""
        version, estimate = self.localizer.pose_estimate()
        if estimate is None or version == self._pose_version:
            return
        self._pose_version = version
        stamp, m, sigma = estimate
        msg = PoseWithCovarianceStamped()
        msg.header.frame_id = self.localizer.global_frame
        msg.header.stamp = rclpy.time.Time(nanoseconds=int(round(stamp * 1e9))).to_msg()
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        p.x, p.y, p.z = (float(v) for v in m[:3, 3])
        o.x, o.y, o.z, o.w = (float(v) for v in Rotation.from_matrix(m[:3, :3]).as_quat())
        std = np.concatenate([sigma[:3], np.radians(sigma[3:])])
        var = np.where(np.isfinite(std), std * std, 1e6)  # unbounded: a large variance
        msg.pose.covariance = [float(v) for v in np.diag(var).ravel()]
        self._pose_pub.publish(msg)

    def _map_to_odom(self, m: np.ndarray, stamp: float) -> TransformStamped:
        localizer = self.localizer
        out = TransformStamped()
        t = stamp + self._config().localization.transform_tolerance
        out.header.stamp = rclpy.time.Time(nanoseconds=int(round(t * 1e9))).to_msg()
        out.header.frame_id = localizer.global_frame
        out.child_frame_id = localizer.odom_frame
        out.transform.translation.x, out.transform.translation.y, out.transform.translation.z = (
            float(v) for v in m[:3, 3]
        )
        q = Rotation.from_matrix(m[:3, :3]).as_quat()
        r = out.transform.rotation
        r.x, r.y, r.z, r.w = (float(v) for v in q)
        return out
