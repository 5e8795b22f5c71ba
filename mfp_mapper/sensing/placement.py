"""Where a cloud's pose comes from: odometry, TF, or both — never a silent wrong pose.

``resolve_placement`` gives the pose source (map <- robot over time) and the extrinsic
(robot <- cloud frame) of one cloud, or raises ``ScanDropped`` naming the frames:

- with odometry (``odom_frame -> odom_child``): the odometry poses; when the map frame
  (``frame_id``) is above the odometry frame, ``map -> odom`` from TF composed with them;
  a cloud already in the odometry or map frame is not moved by odometry again;
- without odometry: the cloud frame's pose in the map frame straight from TF (de-skew then
  interpolates TF across the scan); the map frame is ``frame_id``, else the root of the
  cloud frame's TF tree;
- the extrinsic (robot <- cloud frame, with odometry): identity when the cloud frame is the
  odometry child (or ``base_frame_id``); else the ``lidar.*`` parameters when set (an
  override); else TF (``/tf_static``); else the cloud is dropped (``no_extrinsic``).

``StampGuard`` (in ``poses``) keeps one far-off stamp from stopping a stream.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.config.frames import frame_name
from mfp_mapper.sensing.deskew import PoseSource
from mfp_mapper.sensing.pipeline import ScanDropped
from mfp_mapper.sensing.poses import Extrinsic
from mfp_mapper.sensing.tf_tree import (
    TfChain,
    TfTree,
    TransformUnavailable,
    compose,
    frame_list,
)

FloatArray = NDArray[np.float64]


@dataclass
class Placement:
    """How one cloud is placed: ``poses`` (map <- robot), ``extrinsic`` (robot <- cloud)."""

    poses: PoseSource
    extrinsic: Extrinsic
    map_frame: str
    source: str
    """In words, for the log: e.g. "odometry odom -> base_link, map -> odom from TF"."""
    source_moves: bool = True
    """False when ``poses`` is not the robot's (a cloud already in the map/odometry frame)."""


class ComposedPoses:
    """``outer`` (map <- odom, from TF) composed with ``inner`` (odom <- robot, odometry)."""

    def __init__(self, outer: PoseSource, inner: PoseSource) -> None:
        self.outer, self.inner = outer, inner

    @property
    def latest_stamp(self) -> float | None:
        a, b = self.outer.latest_stamp, self.inner.latest_stamp
        return None if a is None or b is None else min(a, b)

    def interpolate(self, stamps: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t_outer, r_outer = self.outer.interpolate(stamps)
        t_inner, r_inner = self.inner.interpolate(stamps)
        return np.einsum("nij,nj->ni", r_outer, t_inner) + t_outer, r_outer @ r_inner


class FixedPose:
    """The identity at every stamp (a cloud already in the map frame)."""

    latest_stamp = math.inf

    def interpolate(self, stamps: ArrayLike) -> tuple[FloatArray, FloatArray]:
        n = np.asarray(stamps).reshape(-1).size
        return np.zeros((n, 3)), np.broadcast_to(np.eye(3), (n, 3, 3)).copy()


@dataclass
class Odometry:
    """The odometry stream as the placement sees it."""

    frame: str
    child: str
    poses: PoseSource


def resolve_placement(
    cloud_frame: str,
    tree: TfTree,
    odometry: Odometry | None,
    frame_id: str = "",
    base_frame_id: str = "",
    param_extrinsic: Extrinsic | None = None,
) -> Placement:
    """Pose source and extrinsic of a cloud in ``cloud_frame`` (module docstring); raises
    ScanDropped ``no_poses`` (TF cannot connect the frames) or ``no_extrinsic``."""
    cloud_frame = frame_name(cloud_frame)
    if odometry is None:
        return _tf_only(cloud_frame, tree, frame_id)
    map_frame = frame_id or odometry.frame
    outer: PoseSource | None = None
    if map_frame != odometry.frame:
        outer = TfChain(tree, map_frame, odometry.frame)
        _require_chain(tree, map_frame, odometry.frame, "the map frame", "the odometry frame")
    if cloud_frame in (map_frame, odometry.frame):  # already placed: not moved twice
        poses: PoseSource = FixedPose() if cloud_frame == map_frame else (outer or FixedPose())
        return Placement(poses, Extrinsic(), map_frame, f"cloud already in {cloud_frame}", False)
    poses = odometry.poses if outer is None else ComposedPoses(outer, odometry.poses)
    via = f"odometry {odometry.frame} -> {odometry.child}"
    if outer is not None:
        via += f", {map_frame} -> {odometry.frame} from TF"
    extrinsic, how = _extrinsic(cloud_frame, tree, odometry.child, base_frame_id, param_extrinsic)
    return Placement(poses, extrinsic, map_frame, f"{via}; extrinsic {how}")


def _tf_only(cloud_frame: str, tree: TfTree, frame_id: str) -> Placement:
    if not cloud_frame:
        raise ScanDropped(
            "no_extrinsic", "the cloud has no frame_id and there is no odometry to place it"
        )
    if tree.parent(cloud_frame) is None and cloud_frame != frame_id:
        raise ScanDropped(
            "no_poses",
            f"no odometry, and TF has no transform for the cloud frame {cloud_frame!r} "
            f"(frames known: {frame_list(tree.frames())})",
        )
    try:
        root = tree.ancestors(cloud_frame)[-1]
    except TransformUnavailable as err:
        raise ScanDropped("no_poses", str(err)) from None
    map_frame = frame_id or root
    if map_frame == cloud_frame:
        return Placement(
            FixedPose(), Extrinsic(), map_frame, f"cloud already in {cloud_frame}", False
        )
    _require_chain(tree, map_frame, cloud_frame, "the map frame", "the cloud frame")
    return Placement(
        TfChain(tree, map_frame, cloud_frame),
        Extrinsic(),
        map_frame,
        f"TF {map_frame} <- {cloud_frame} at the cloud stamp (no odometry)",
    )


def _require_chain(tree: TfTree, top: str, bottom: str, top_role: str, bottom_role: str) -> None:
    try:
        tree.latest_common_stamp(top, bottom)
    except TransformUnavailable as err:
        raise ScanDropped(
            "no_poses",
            f"TF has no chain from {bottom_role} {bottom!r} to {top_role} {top!r} ({err}); "
            f"publish {top} -> ... -> {bottom} or set frame_id to {bottom!r}",
        ) from None


def _extrinsic(
    cloud_frame: str,
    tree: TfTree,
    odom_child: str,
    base_frame_id: str,
    param_extrinsic: Extrinsic | None,
) -> tuple[Extrinsic, str]:
    body = base_frame_id or odom_child
    if cloud_frame == odom_child or (not cloud_frame and param_extrinsic is None):
        return Extrinsic(), f"identity (the cloud frame is the odometry child {odom_child})"
    if param_extrinsic is not None:
        return param_extrinsic, "lidar.translation / lidar.rpy parameters"
    chain = tree.static_chain(body, cloud_frame)
    if chain is None:
        raise ScanDropped(
            "no_extrinsic",
            f"the cloud frame {cloud_frame!r} is not the odometry child frame {body!r} and "
            f"/tf_static has no chain {body} -> {cloud_frame}; publish it or set "
            "lidar.translation / lidar.rpy",
        )
    extrinsic = Extrinsic(*chain)
    if body != odom_child:  # base_frame_id below the odometry child: through TF too
        upper = tree.static_chain(odom_child, body)
        if upper is None:
            raise ScanDropped(
                "no_extrinsic",
                f"/tf_static has no chain {odom_child} -> {body} (base_frame_id)",
            )
        extrinsic = Extrinsic(*compose(upper, chain))
    return extrinsic, f"/tf_static {body} -> {cloud_frame}"
