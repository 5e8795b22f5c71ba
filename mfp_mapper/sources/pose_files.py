"""Pose files (``--poses``): KITTI, TUM, a nav_msgs/Odometry CSV, and ``identity`` (every
scan at the origin, for single frames); ``read_poses`` reads any of them for a recording.

Every reader gives a pose source the scan pipeline interpolates (``sensing.deskew.
PoseSource``): a ``PoseBuffer`` of ``T_map_body`` samples, or a ``FixedPose``.

- KITTI: one line per scan, the 12 numbers of a row-major 3x4 ``T_world_lidar``; line k is
  the pose of the k-th scan (in the folder's order) at that scan's stamp: scan folders only
  (a bag's clouds have no order a file could follow).
- TUM: ``timestamp x y z qx qy qz qw`` per line (``#`` comments), interpolated at the scan
  times, so the scan stamps must be real times (file names or a times file).
- CSV: nav_msgs/Odometry rows with columns named like the message fields
  (``header.stamp.sec``, ``pose.pose.position.x``...), interpolated like TUM.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from mfp_mapper.config.replay_options import ReplayError
from mfp_mapper.sensing.poses import PoseBuffer
from mfp_mapper.sources.recording import Poses
from mfp_mapper.sources.scan_files import DatasetFormatError

FloatArray = NDArray[np.float64]

POSE_FORMATS = ("kitti", "tum", "csv")
IDENTITY = "identity"
"""``--poses identity``: every scan at the origin of its own frame."""

_ODOMETRY_COLUMNS = (
    "header.stamp.sec",
    "header.stamp.nanosec",
    *(f"pose.pose.position.{axis}" for axis in "xyz"),
    *(f"pose.pose.orientation.{axis}" for axis in "xyzw"),
)

ODOMETRY_DTYPE = np.dtype([("stamp", "f8"), ("position", "f8", (3,)), ("quaternion", "f8", (4,))])
"""Rows of :func:`read_odometry_csv`: stamp seconds, position xyz, quaternion xyzw."""


@dataclass
class FixedPose:
    """One pose for all times (``--poses identity``): never too old or too new."""

    position: FloatArray
    rotation: FloatArray
    earliest_stamp: float = -math.inf
    max_gap: float = math.inf

    @classmethod
    def identity(cls) -> FixedPose:
        return cls(np.zeros(3), np.eye(3))

    @property
    def latest_stamp(self) -> float | None:
        return math.inf

    def interpolate(self, stamps: ArrayLike) -> tuple[FloatArray, FloatArray]:
        n = np.asarray(stamps, dtype=np.float64).reshape(-1).size
        return np.repeat(self.position[None], n, 0), np.repeat(self.rotation[None], n, 0)


def read_odometry_csv(path: str | Path) -> NDArray[np.void]:
    """nav_msgs/Odometry rows (columns named like the message fields) as ODOMETRY_DTYPE."""
    path = Path(path)
    with path.open(newline="") as stream:
        reader = csv.DictReader(stream)
        missing = [c for c in _ODOMETRY_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise DatasetFormatError(f"{path}: missing odometry columns {', '.join(missing)}")
        try:
            rows = [[float(row[c]) for c in _ODOMETRY_COLUMNS] for row in reader]
        except (TypeError, ValueError) as error:
            line = reader.line_num
            raise DatasetFormatError(f"{path}:{line}: bad odometry value ({error})") from None
    values = np.array(rows, dtype=np.float64).reshape(-1, len(_ODOMETRY_COLUMNS))
    odometry = np.empty(len(values), dtype=ODOMETRY_DTYPE)
    odometry["stamp"] = values[:, 0] + values[:, 1] * 1e-9
    odometry["position"] = values[:, 2:5]
    odometry["quaternion"] = values[:, 5:9]
    return odometry


def _numeric_rows(path: Path, width: int, what: str) -> FloatArray:
    rows = []
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        try:
            values = [float(v) for v in text.replace(",", " ").split()]
        except ValueError:
            raise DatasetFormatError(f"{path}:{number}: non-numeric {what} line") from None
        if len(values) != width:
            raise DatasetFormatError(
                f"{path}:{number}: {len(values)} numbers, a {what} line has {width}"
            )
        rows.append(values)
    if not rows:
        raise DatasetFormatError(f"{path}: no {what} line")
    return np.array(rows, dtype=np.float64)


def read_kitti_poses(path: str | Path) -> tuple[FloatArray, FloatArray]:
    """Positions (N, 3) and quaternions xyzw (N, 4) of a KITTI pose file (3x4 per line)."""
    path = Path(path)
    matrices = _numeric_rows(path, 12, "KITTI pose").reshape(-1, 3, 4)
    rotations = matrices[:, :, :3]
    if not np.allclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3), atol=1e-4):
        bad = int(
            np.argmax(
                ~np.all(
                    np.isclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3), atol=1e-4),
                    axis=(1, 2),
                )
            )
        )
        raise DatasetFormatError(f"{path}: pose {bad + 1} is not a rotation (R R^T != I)")
    return matrices[:, :, 3].copy(), matrix_to_quaternion(rotations)


def read_tum_poses(path: str | Path) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Stamps (N,), positions (N, 3), quaternions xyzw (N, 4) of a TUM trajectory."""
    rows = _numeric_rows(Path(path), 8, "TUM pose (t x y z qx qy qz qw)")
    return rows[:, 0].copy(), rows[:, 1:4].copy(), rows[:, 4:8].copy()


def read_stamped_poses(path: str | Path, kind: str) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Stamps, positions and quaternions (xyzw) of a ``kind`` "tum" or "csv" (odometry)
    pose file: the poses a recording's clouds are matched with by stamp."""
    if kind == "tum":
        return read_tum_poses(path)
    rows = read_odometry_csv(path)
    return rows["stamp"], rows["position"], rows["quaternion"]


def matrix_to_quaternion(rotations: ArrayLike) -> FloatArray:
    """Quaternions xyzw (N, 4) of rotation matrices (N, 3, 3) (scipy; a matrix a little off
    orthogonal, as in text pose files, gives the nearest rotation's quaternion)."""
    r = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    return np.asarray(Rotation.from_matrix(r).as_quat(), dtype=np.float64).reshape(-1, 4)


def pose_buffer(
    stamps: ArrayLike, positions: ArrayLike, quaternions: ArrayLike, max_gap: float, what: str
) -> PoseBuffer:
    """A PoseBuffer (kept whole) of these samples, sorted by time; error on a bad sample."""
    t = np.asarray(stamps, dtype=np.float64)
    order = np.argsort(t, kind="stable")
    buffer = PoseBuffer(max_age=math.inf, max_gap=max_gap)
    p, q = np.asarray(positions, np.float64), np.asarray(quaternions, np.float64)
    for k in order:
        buffer.add(float(t[k]), p[k], q[k])
    if buffer.rejected["invalid"]:
        raise DatasetFormatError(f"{what}: {buffer.rejected['invalid']} non-finite pose(s)")
    if buffer.rejected["out_of_order"]:
        raise DatasetFormatError(f"{what}: {buffer.rejected['out_of_order']} repeated stamp(s)")
    return buffer


def guess_pose_format(path: Path) -> str:
    """``csv`` for .csv files; else ``kitti`` or ``tum`` from the first data line's width."""
    if path.suffix.lower() == ".csv":
        return "csv"
    for line in path.read_text(errors="replace").splitlines():
        text = line.strip()
        if text and not text.startswith("#"):
            width = len(text.replace(",", " ").split())
            if width in (8, 12):
                return "tum" if width == 8 else "kitti"
            break
    raise DatasetFormatError(
        f"{path}: cannot tell the pose format (12 numbers a line: KITTI, 8: TUM, .csv: odometry)"
    )


def read_poses(
    poses: str | Path,
    frame: str,
    max_gap: float,
    scan_stamps: ArrayLike | None = None,
    note: str = "",
) -> Poses:
    """The poses of a recording's clouds (of lidar frame ``frame``) from ``--poses``:
    ``identity``, a KITTI file (one pose per scan, at ``scan_stamps``; None: the clouds
    have no order a KITTI file could follow, as a bag's), a TUM file or an odometry CSV
    (matched by stamp). ReplayError says what is wrong (``note`` is added to a count
    mismatch)."""
    if str(poses) == IDENTITY:
        return Poses(FixedPose.identity(), frame, frame, IDENTITY)
    path = Path(poses)
    try:
        kind = guess_pose_format(path)
        if kind == "kitti":
            if scan_stamps is None:
                raise ReplayError(
                    f"{path}: KITTI poses have no stamps; a bag's clouds need TUM poses "
                    "('t x y z qx qy qz qw') or an odometry CSV, matched by stamp"
                )
            stamps = np.asarray(scan_stamps, dtype=np.float64)
            positions, quaternions = read_kitti_poses(path)
            if len(positions) != len(stamps):
                raise DatasetFormatError(
                    f"{path}: {len(positions)} KITTI poses for {len(stamps)} scans (one per "
                    f"scan){note}"
                )
        else:
            stamps, positions, quaternions = read_stamped_poses(path, kind)
        buffer = pose_buffer(stamps, positions, quaternions, max_gap, str(path))
    except (DatasetFormatError, OSError) as err:
        raise ReplayError(str(err)) from None
    what = "odometry CSV, T_map_body" if kind == "csv" else f"{kind.upper()}, T_world_lidar"
    return Poses(buffer, frame, "world", f"{path} ({what})")
