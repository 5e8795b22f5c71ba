"""The live worker's pose inputs: odometry, TF and the node clock (``PoseInputs``).

Odometry and transforms arrive on the node's executor: they are stored under ``pose_lock``
(never the map lock: the executor must never wait for a scan), stamps far off their stream
are held back until confirmed, and a clock that jumps back clears the buffers.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.sensing.placement import StampGuard
from mfp_mapper.sensing.poses import OdometrySample, PoseBuffer
from mfp_mapper.sensing.tf_tree import TfTree, TransformUnavailable

if TYPE_CHECKING:
    from mfp_mapper.mapping.live import LiveCounters, LiveSettings

CLOCK_JUMP_BACK = 1.0
"""Seconds the clock must go back to count as a jump (bag loop, simulation restart)."""

Log = Callable[[str, str, bool], None]
"""``log(key, text, error)``: a throttled warning (or error) keyed by ``key``."""


class PoseInputs:
    """Odometry, TF and clock handling of ``LiveIntegrator`` (which sets the state)."""

    mapper: Mapper
    settings: LiveSettings
    poses: PoseBuffer
    counters: LiveCounters
    pose_lock: threading.Lock
    tree: TfTree
    odom_frame: str | None
    odom_child: str | None
    robot_position: np.ndarray | None
    tf_map_frame: str | None
    _odom_guard: StampGuard
    _last_clock: float | None
    _log: Log
    _now: Callable[[], float]
    _cv: threading.Condition
    _queue: deque[Any]

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
        refused = self._odom_guard.check(sample.stamp, self._now())
        self.counters.odom_in += 1
        if refused is not None:
            self.counters.odom_rejected[refused] += 1
            self._log(
                f"odom_{refused}",
                f"odometry stamped {sample.stamp:.3f} ignored ({refused}: latest "
                f"{self._odom_guard.latest}, clock {self._now():.3f}); a second message "
                "confirms a real jump",
                True,
            )
            return False
        with self.pose_lock:
            if self._odom_guard.jumped:
                self.poses.clear()
            ok = self.poses.add(sample.stamp, sample.position, sample.quaternion)
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
            wanted = self.settings.frame_id
            if wanted and wanted != frame:
                self._log(
                    "odom_frame",
                    f"odometry is in frame {frame!r}, the map in frame_id {wanted!r}: "
                    f"{wanted} -> {frame} is taken from TF (if TF never has it, set "
                    f"frame_id to {frame!r})",
                    False,
                )
            self._adopt_map_frame()
        self.robot_position = np.asarray(sample.position, dtype=np.float64)
        with self._cv:
            self._cv.notify_all()
        return True

    def add_transforms(self, msg: Any, static: bool) -> int:
        """Store a tf2_msgs/TFMessage (``/tf`` or ``/tf_static``); how many were kept."""
        with self.pose_lock:
            before = sum(self.tree.rejected.values())
            kept = self.tree.add_message(msg, static, now=self._now())
            refused = sum(self.tree.rejected.values()) - before
        if refused:
            self._log(
                "tf_rejected",
                f"{refused} transform(s) ignored (far off the stream or the clock, or invalid;"
                f" so far: {dict(self.tree.rejected)})",
                False,
            )
        with self._cv:
            self._cv.notify_all()
        return kept

    def observe_clock(self, now: float) -> bool:
        """Note the node clock; on a jump back (bag loop) clear poses, TF and the queue."""
        last, self._last_clock = self._last_clock, now
        if last is None or now >= last - CLOCK_JUMP_BACK:
            return False
        with self.pose_lock:
            self.poses.clear()
            self.tree.clear()
            self._odom_guard.reset()
        with self._cv:
            dropped = len(self._queue)
            self._queue.clear()
            for _ in range(dropped):
                self.counters.drop("clock_jump")
        self._log(
            "clock_jump",
            f"clock jumped back {last - now:.3f} s (to {now:.3f}): pose and TF buffers "
            f"cleared, {dropped} queued cloud(s) dropped; the map is kept",
            False,
        )
        return True

    def to_map_frame(self, points: np.ndarray, frame: str, stamp: float) -> np.ndarray:
        """Points given in ``frame`` (empty: the map frame) in the map frame, through TF at
        ``stamp``, or at the latest transform when the stamp is not covered; raises
        TransformUnavailable."""
        frame, target = frame.lstrip("/"), self.map_frame
        if not frame or frame == target:
            return points
        with self.pose_lock:
            tree = self.tree.snapshot()
        try:
            matrix = tree.lookup_matrix(target, frame, stamp)
        except TransformUnavailable as err:
            if err.reason == "unconnected":
                raise
            latest = tree.latest_common_stamp(target, frame)
            matrix = tree.lookup_matrix(target, frame, stamp if latest is None else latest)
        return points @ matrix[:3, :3].T + matrix[:3, 3]

    def _adopt_map_frame(self) -> None:
        # no map lock here: this runs on the executor, which must never wait for a scan
        # (a str attribute is replaced atomically; the voxel count only words a warning)
        if self.mapper.num_voxels and self.mapper.frame_id != self.map_frame:
            self._log(
                "map_frame",
                f"loaded map is in frame {self.mapper.frame_id!r}, mapping in "
                f"{self.map_frame!r}: the map is used as if it were in {self.map_frame!r}",
                False,
            )
        self.mapper.frame_id = self.map_frame

    @property
    def map_frame(self) -> str:
        return (
            self.settings.frame_id or self.odom_frame or self.tf_map_frame or self.mapper.frame_id
        )
