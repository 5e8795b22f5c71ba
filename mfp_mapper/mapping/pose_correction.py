"""How the live worker's placed scans reach the map frame: a ``PoseCorrection``.

Mapping (``NoCorrection``): clouds are placed in the map frame itself and integrated by the
walker thread while the worker places the next one. Localization (``LocalizerCorrection``,
backed by a ``LiveLocalizer``): clouds are placed in the odometry frame, aligned against the
map and moved by the correction ``map <- odom``, each integrated (unless the map is frozen)
before the next is aligned; a wide search runs in the background while the worker keeps
taking clouds (the newest one placed meanwhile is aligned after it).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from mfp_mapper.config.frames import frame_name
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.live_localization import LiveLocalizer, pose_matrix
from mfp_mapper.sensing.pipeline import PlacedScan
from mfp_mapper.sensing.pose_inputs import PoseInputs
from mfp_mapper.sensing.poses import PoseUnavailable

RobotPose = Callable[[float], np.ndarray | None]
"""The robot's pose (4x4, placement frame) at a stamp, None where not covered."""


class PoseCorrection(Protocol):
    """What the live worker asks of the correction between where clouds are placed and the
    map frame."""

    @property
    def aligns(self) -> bool:
        """Each scan is aligned against the map with the scans before it: the worker
        integrates it itself, in order, instead of handing it to the walker thread."""
        ...

    @property
    def integrates(self) -> bool:
        """The placed scans go into the map (false: a frozen map, only localized against)."""
        ...

    @property
    def names_map(self) -> bool:
        """The placement frame is the map's frame: the map takes its name."""
        ...

    def placement_frame(self, map_frame: str) -> str:
        """The frame clouds are placed in, given the map frame known at start ("" when
        decided at the first cloud)."""
        ...

    def map_frame(self, placement_frame: str) -> str:
        """The run's map frame, given the placement frame ("" while undecided)."""
        ...

    def position(self, position: Any) -> Any:
        """A position (3,) of the placement frame in the map frame (None stays None)."""
        ...

    def to_map_frame(
        self, points: np.ndarray, frame: str, to_placement: Callable[[np.ndarray, str], np.ndarray]
    ) -> np.ndarray:
        """Points given in ``frame`` in the map frame; ``to_placement`` moves points of a
        frame into the placement frame (raises TransformUnavailable)."""
        ...

    def correct(
        self, placed: PlacedScan, robot_pose: RobotPose, done: Callable[[], None] | None = None
    ) -> PlacedScan | None:
        """A scan placed in the placement frame, in the map frame. With ``done``, a long
        alignment may run in the background: then None, ``done()`` is called when it ended
        and ``finished()`` gives the scan."""
        ...

    @property
    def searching(self) -> bool:
        """An alignment started by ``correct`` runs in the background."""
        ...

    def finished(self) -> PlacedScan | None:
        """The scan of the background alignment once it ended (once; None before)."""
        ...

    def map_grew(self, mapper: Mapper, whole_map: Any) -> None:
        """A scan went into ``mapper``."""
        ...

    def clock_jumped(self, now: float) -> None:
        """The clock jumped back to ``now`` (a bag replayed in a loop)."""
        ...


class NoCorrection:
    """Mapping: clouds are placed in the map frame; nothing to correct."""

    aligns = False
    integrates = True
    names_map = True

    def placement_frame(self, map_frame: str) -> str:
        return map_frame

    def map_frame(self, placement_frame: str) -> str:
        return placement_frame

    def position(self, position: Any) -> Any:
        return position

    def to_map_frame(
        self, points: np.ndarray, frame: str, to_placement: Callable[[np.ndarray, str], np.ndarray]
    ) -> np.ndarray:
        return to_placement(points, frame)

    searching = False

    def correct(
        self, placed: PlacedScan, robot_pose: RobotPose, done: Callable[[], None] | None = None
    ) -> PlacedScan:
        return placed

    def finished(self) -> PlacedScan | None:
        return None

    def map_grew(self, mapper: Mapper, whole_map: Any) -> None:
        pass

    def clock_jumped(self, now: float) -> None:
        pass


class LocalizerCorrection:
    """Localization: clouds placed in ``localizer``'s odometry frame, aligned and moved into
    its global frame by its correction (``LiveLocalizer.localize``)."""

    aligns = True
    names_map = False

    def __init__(self, localizer: LiveLocalizer) -> None:
        self.localizer = localizer

    @property
    def integrates(self) -> bool:
        return not self.localizer.settings.freeze_map

    def placement_frame(self, map_frame: str) -> str:
        return self.localizer.odom_frame

    def map_frame(self, placement_frame: str) -> str:
        return self.localizer.global_frame

    def position(self, position: Any) -> Any:
        if position is None:
            return None
        m, _, _ = self.localizer.transform()
        return m[:3, :3] @ np.asarray(position, dtype=np.float64) + m[:3, 3]

    def to_map_frame(
        self, points: np.ndarray, frame: str, to_placement: Callable[[np.ndarray, str], np.ndarray]
    ) -> np.ndarray:
        frame = frame_name(frame)
        if not frame or frame == self.localizer.global_frame:
            return points
        in_odom = to_placement(points, frame)
        m, _, _ = self.localizer.transform()
        return np.asarray(in_odom) @ m[:3, :3].T + m[:3, 3]

    def correct(
        self, placed: PlacedScan, robot_pose: RobotPose, done: Callable[[], None] | None = None
    ) -> PlacedScan | None:
        return self.localizer.localize(placed, robot_pose, done)

    @property
    def searching(self) -> bool:
        return self.localizer.searching

    def finished(self) -> PlacedScan | None:
        return self.localizer.finished()

    def map_grew(self, mapper: Mapper, whole_map: Any) -> None:
        self.localizer.build_in_background(mapper, whole_map)

    def clock_jumped(self, now: float) -> None:
        self.localizer.clock_jumped(now)

    def robot_in_odom(self, inputs: PoseInputs, stamp: float) -> np.ndarray | None:
        """The robot (the odometry child) in the localizer's odometry frame (4x4) at
        ``stamp``, or at the latest odometry when the stamp is not covered; None without
        odometry in that frame (then ``/initialpose`` waits for the next cloud)."""
        with inputs.lock:
            if inputs.odom_frame != self.localizer.odom_frame or not len(inputs.poses):
                return None
            poses = inputs.poses.snapshot()
        latest, earliest = poses.latest_stamp, poses.earliest_stamp
        if latest is None:
            return None
        covered = earliest is not None and earliest <= stamp <= latest
        try:
            t, r = poses.interpolate([stamp if covered else latest])
        except PoseUnavailable:
            return None
        return pose_matrix(t[0], r[0])
