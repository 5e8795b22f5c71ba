"""The live worker's pose inputs: odometry, TF, the node clock and the run's map frame.

Odometry and transforms arrive on the node's executor: they are stored under ``lock``
(never the map lock: the executor must never wait for a scan), stamps far off their stream
are held back until confirmed, and a clock that jumps back clears the buffers.

**The map frame is decided once per run and never changes under the map**:

- ``frame_id`` set: that frame (octomap_server's rule); clouds wait for TF to reach it;
- else a loaded map's frame;
- else, at the first cloud that can be placed: the odometry frame when odometry is
  received, else the root of the cloud frame's TF tree.

A pose source that appears later is linked into that frame through TF (``map -> odom``
composed with odometry; TF straight to the map frame) or reported (the cloud is dropped
naming the frames, or placed by TF alone while the odometry is reported as unused) —
never a second copy of the world. The frame, when decided, and each pose source, the
first time it places a cloud, are logged at INFO level (``info``), not throttled.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mfp_mapper.config.frames import frame_name
from mfp_mapper.sensing.pipeline import ScanDropped
from mfp_mapper.sensing.placement import Odometry, Placement, resolve_placement
from mfp_mapper.sensing.poses import Extrinsic, OdometrySample, PoseBuffer, StampGuard
from mfp_mapper.sensing.tf_tree import TfTree, TransformRecord, TransformUnavailable, frame_list

CLOCK_JUMP_BACK = 1.0
"""Seconds the clock must go back to count as a jump (bag loop, simulation restart)."""

Log = Callable[[str, str, bool], None]
"""``log(key, text, error)``: a throttled warning (or error) keyed by ``key``."""

_SOURCES_LOGGED = 8
"""Pose sources logged at INFO the first time they place a cloud (then only counted)."""


@dataclass
class PoseCounters:
    """What the pose inputs count (the worker's counters extend these)."""

    odom_in: int = 0
    odom_rejected: Counter[str] = field(default_factory=Counter)
    tf_in: int = 0
    tf_rejected: Counter[str] = field(default_factory=Counter)


class PoseInputs:
    """Odometry, TF and the clock as the live worker sees them (module docstring)."""

    def __init__(
        self,
        poses: PoseBuffer,
        tree: TfTree,
        counters: PoseCounters,
        *,
        frame_id: str,
        log: Log,
        info: Callable[[str], None],
        now: Callable[[], float],
        frame_role: str = "map frame",
    ) -> None:
        """``frame_role``: what ``frame_id`` (the frame clouds are placed in) is to the run,
        as the log names it (in localization: the odometry frame, not the map frame)."""
        self.frame_role = frame_role
        self.poses = poses
        self.tree = tree
        self.counters = counters
        self.lock = threading.Lock()
        self.map_frame: str | None = frame_name(frame_id) or None
        """The run's map frame; None until decided (then never changed)."""
        self.odom_frame: str | None = None
        self.odom_child: str | None = None
        self.robot_position: np.ndarray | None = None
        """The robot (``base_frame_id``, the odometry child or the sensor) in the map
        frame: what ``publish_radius`` and the GetMap window centre on."""
        self.pose_source = "none yet"
        self.generation = 0
        """Bumped whenever a pose or a transform is stored (waiting clouds try again)."""
        self._odom_guard = StampGuard(tree.max_jump, tree.max_future)
        self._last_clock: float | None = None
        self._sources: list[str] = []
        self._log = log
        self._info = info
        self._now = now

    def _clock(self) -> float | None:
        """The node clock, None while it reads 0 (``use_sim_time`` before ``/clock``):
        stamps are then not checked against it."""
        now = self._now()
        return now if now > 0.0 else None

    # --- inputs (the executor) --------------------------------------------------------------

    def add_odometry(self, sample: OdometrySample) -> bool:
        """Store one odometry pose; False (counted, logged) when it is rejected."""
        frame = sample.frame_id
        if self.odom_frame is not None and frame != self.odom_frame:
            self.counters.odom_rejected["frame"] += 1
            self._log(
                "odom_frame_change",
                f"odometry frame changed from {self.odom_frame!r} to {frame!r}: ignored "
                "(restart the node, or set frame_id to the frame the map should be in)",
                True,
            )
            return False
        now = self._clock()
        refused = self._odom_guard.check(sample.stamp, now)
        self.counters.odom_in += 1
        if refused is not None:
            self.counters.odom_rejected[refused] += 1
            self._log(
                f"odom_{refused}",
                f"odometry stamped {sample.stamp:.3f} ignored ({refused}: latest "
                f"{self._odom_guard.latest}, clock {now}); a second message confirms a real "
                "jump",
                True,
            )
            return False
        with self.lock:
            if self._odom_guard.jumped:
                self.poses.clear()
            ok = self.poses.add(sample.stamp, sample.position, sample.quaternion)
            if ok:
                self.generation += 1
        if self._odom_guard.jumped:
            self._log(
                "odom_jump",
                f"odometry stamps jumped to {sample.stamp:.3f}: pose buffer cleared",
                False,
            )
        if not ok:
            self.counters.odom_rejected["out_of_order_or_invalid"] += 1
            self._log(
                "odom_order", "odometry message not newer than the previous one, or invalid", False
            )
            return False
        if self.odom_frame is None:
            self.odom_frame, self.odom_child = frame, sample.child_frame_id
            linked = (
                f"the {self.frame_role}"
                if self.map_frame in (None, frame)
                else f"linked to the {self.frame_role} {self.map_frame!r} through TF"
            )
            self._info(
                f"odometry received in frame {frame!r} (child {sample.child_frame_id!r}): {linked}"
            )
        if self.map_frame == frame:
            self.robot_position = np.asarray(sample.position, dtype=np.float64)
        return True

    def add_transforms(self, records: Sequence[TransformRecord], static: bool) -> int:
        """Store the transforms of one ``/tf`` or ``/tf_static`` message (``TransformRecord``
        values: ``tf_tree.transform_records`` of a message); how many were kept."""
        with self.lock:
            before = sum(self.tree.rejected.values())
            kept = self.tree.add_records(records, static, now=self._clock())
            refused = sum(self.tree.rejected.values()) - before
            events = self.tree.take_events()
            self.counters.tf_in += len(records)
            self.counters.tf_rejected = Counter(self.tree.rejected)
            if kept:
                self.generation += 1
        for kind, text in events:
            self._log(kind, text, kind in ("tf_loop", "tf_conflict"))
        if refused:
            self._log(
                "tf_rejected",
                f"{refused} transform(s) ignored (far off the stream or the clock, closing a "
                f"loop, or invalid; so far: {dict(self.tree.rejected)})",
                False,
            )
        return kept

    def observe_clock(self, now: float) -> float | None:
        """Note the node clock; on a jump back (bag loop) clear poses and TF and return how
        far it jumped (the worker then drops its queue); else None."""
        last, self._last_clock = self._last_clock, now
        if last is None or now >= last - CLOCK_JUMP_BACK:
            return None
        with self.lock:
            self.poses.clear()
            self.tree.clear()
            self._odom_guard.reset()
        return last - now

    # --- placement (the worker) -------------------------------------------------------------

    def placement(
        self, cloud_frame: str, base_frame_id: str, extrinsic: Extrinsic | None
    ) -> Placement:
        """Pose source and extrinsic of a cloud, from copies taken under the lock (the
        executor keeps adding odometry and TF meanwhile); decides the map frame at the
        first cloud placed. Raises ScanDropped."""
        with self.lock:  # the chains of these frames only (a TF flood: thousands of frames)
            tree = self.tree.snapshot(
                (cloud_frame, base_frame_id, self.map_frame or "", self.odom_frame or "")
                + ((self.odom_child,) if self.odom_child else ())
            )
            odometry = None
            if self.odom_frame is not None and len(self.poses):
                odometry = Odometry(self.odom_frame, self.odom_child or "", self.poses.snapshot())
        frame = self.map_frame or ""
        try:
            placement = resolve_placement(
                cloud_frame, tree, odometry, frame, base_frame_id, extrinsic
            )
        except ScanDropped as drop:
            if odometry is None or drop.reason != "no_poses" or not frame:
                raise
            try:  # the odometry is not linked to the map frame: TF alone may place it
                placement = resolve_placement(cloud_frame, tree, None, frame)
            except ScanDropped:
                raise drop from None
            self._log(
                "odom_unlinked",
                f"odometry frame {odometry.frame!r} is not linked to the map frame "
                f"{frame!r} through TF: odometry unused, clouds placed by TF ({drop.detail})",
                False,
            )
        if self.map_frame is None:
            self.map_frame = placement.map_frame
            why = "the odometry frame" if odometry is not None else "the root of the TF tree"
            self._info(
                f"map frame {self.map_frame!r} ({why} at the first cloud placed), fixed for "
                "this run"
            )
        if placement.source not in self._sources:
            if len(self._sources) < _SOURCES_LOGGED:
                self._info(f"clouds in {cloud_frame!r} placed by {placement.source}")
            self._sources.append(placement.source)
            del self._sources[:-_SOURCES_LOGGED]
        self.pose_source = placement.source
        return placement

    def note_robot(self, placement: Placement, stamp: float, base_frame_id: str) -> None:
        """After a cloud is placed: the robot position in the map frame at its stamp
        (``base_frame_id`` through TF when it connects, else the placed robot/sensor)."""
        if self.map_frame == self.odom_frame and self.robot_position is not None:
            return  # odometry gives it with every message
        position = None
        if base_frame_id and self.map_frame:
            with self.lock:
                tree = self.tree.snapshot((self.map_frame, base_frame_id))
            try:
                position = tree.lookup_matrix(self.map_frame, base_frame_id, stamp)[:3, 3]
            except TransformUnavailable:
                position = None
        if position is None and placement.source_moves:
            try:
                position = placement.poses.interpolate([stamp])[0][0]
            except Exception:  # a pose source that covered the cloud covers its stamp
                position = None
        if position is not None:
            self.robot_position = np.asarray(position, dtype=np.float64)

    def to_map_frame(self, points: np.ndarray, frame: str, stamp: float) -> np.ndarray:
        """Points given in ``frame`` (empty: the map frame) in the map frame, through TF at
        ``stamp``, or at the latest transform when the stamp is not covered; raises
        TransformUnavailable."""
        frame, target = frame_name(frame), self.map_frame
        if not frame or frame == target:
            return points
        if target is None:
            raise TransformUnavailable(
                "unconnected", "the map frame is not decided yet (no cloud placed)"
            )
        with self.lock:
            tree = self.tree.snapshot((target, frame))
        try:
            matrix = tree.lookup_matrix(target, frame, stamp)
        except TransformUnavailable as err:
            if err.reason in ("unconnected", "tf_conflict"):
                raise
            latest = tree.latest_common_stamp(target, frame)
            matrix = tree.lookup_matrix(target, frame, stamp if latest is None else latest)
        return points @ matrix[:3, :3].T + matrix[:3, 3]

    def describe(self) -> dict[str, Any]:
        """What ``~/status`` says of the poses: map frame, pose source, TF conflicts."""
        with self.lock:
            conflicts = self.tree.conflicts()
            frames = len(self.tree.frames())
        out: dict[str, Any] = {
            "map_frame": self.map_frame,
            "pose_source": self.pose_source,
            "odom_frame": self.odom_frame,
            "tf_frames": frames,
        }
        if conflicts:
            out["tf_conflicts"] = frame_list(f"{c} ({a} / {b})" for c, (a, b) in conflicts.items())
        return out
