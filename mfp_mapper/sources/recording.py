"""A recording opened for mapping (``Recording``): its clouds, where their poses come from,
the lidar extrinsic and the map frame, whatever it was read from.

Kinds, each opened by ``sources.opener.open_recording``:

- a bag (ROS 1 ``.bag``, ROS 2 sqlite3 or mcap; ``sources.bags``): poses from its
  nav_msgs/Odometry topic or its ``/tf`` chain, a pose file matched by stamp, or KISS-ICP;
- a folder of scan files (``sources.scan_folder``): poses from a pose file
  (``sources.pose_files``: KITTI, TUM, odometry CSV, ``identity``) or KISS-ICP;
- KISS-ICP-estimated poses (``sources.lidar_odometry``), for either of the above;
- the simulator (``sources.simulate.open_simulation``): clouds made on the fly, poses from
  its ground truth.

With ``second_return_topic`` set, a bag's clouds are paired with the clouds of that topic
(ouster-ros ``points`` + ``points2``) as the node pairs them: ``load()`` then gives a
``sensing.pipeline.ReturnPair`` (or a first cloud alone), and ``second_returns()`` the counts.

The clouds are read lazily: ``clouds()`` gives ``(position, load)`` pairs in recording order,
``load()`` returning the PointCloud2(-like) message stamped in its header, so that a
selection by position reads nothing it skips and a damaged message is met (and counted) where
it lies. ``clouds()`` may be called again: each call reads the recording from its start.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from mfp_mapper.sensing.deskew import PoseSource
from mfp_mapper.sensing.poses import Extrinsic
from mfp_mapper.sensing.return_pairs import ReturnPairer


@dataclass
class Poses:
    """Where a recording's poses come from: ``buffer`` interpolates the pose of the ``body``
    frame in ``map_frame`` (a ``PoseBuffer``, or any ``sensing.deskew.PoseSource``);
    ``source`` says whence, in words (the replay's summary)."""

    buffer: Any
    body: str
    map_frame: str
    source: str


class RecordedCloud(NamedTuple):
    """One cloud of a recording: its position in it (0 = the first) and how to read it."""

    position: int
    load: Callable[[], Any]


def _nothing() -> None:
    return None


def _no_pairer() -> ReturnPairer | None:
    return None


@dataclass
class Recording:
    """An opened recording; ``close()`` it (or use it as a context manager) when done."""

    name: str
    """What was opened (its path), as the replay's summary names it."""
    cloud_source: str
    """Where the clouds come from: the bag's topic, or the scan files and their stamps."""
    cloud_frame: str
    """The frame of the first cloud."""
    cloud_count: int
    """How many clouds the recording holds."""
    poses: Poses
    extrinsic_source: str
    """Where the extrinsic of ``cloud_frame`` comes from, in words."""
    read_clouds: Callable[[], Iterator[RecordedCloud]]
    """A fresh pass over the clouds (``clouds()``)."""
    extrinsic_of: Callable[[str], Extrinsic]
    """The lidar extrinsic (pose of a cloud frame in the body frame of the poses)."""
    release: Callable[[], None] = field(default=_nothing)
    """What ``close()`` does (closes the bag reader)."""
    seconds_poses: float = 0.0
    """Time spent reading (or estimating) the poses when it was opened."""
    second_return_topic: str = ""
    """The bag topic of second-return clouds paired with the clouds (setting
    ``second_return_topic``), or ""."""
    second_returns: Callable[[], ReturnPairer | None] = field(default=_no_pairer)
    """The pairer of the latest pass over ``clouds()`` when second returns are paired: its
    ``counts()`` (paired, alone, unpaired_second, mismatched), as the node's ``~/status``
    reports them; else None."""

    @property
    def map_frame(self) -> str:
        return self.poses.map_frame

    @property
    def pose_source(self) -> PoseSource:
        """The poses the scan pipeline interpolates (``poses.buffer``)."""
        buffer: PoseSource = self.poses.buffer
        return buffer

    def clouds(self) -> Iterator[RecordedCloud]:
        """Every cloud, in recording order, from the first."""
        return self.read_clouds()

    def close(self) -> None:
        self.release()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
