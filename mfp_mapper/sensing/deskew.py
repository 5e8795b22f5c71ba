"""De-skew: points of a cloud into the map frame, each at the pose of its own time.

``p_map = R_pose (R_ext p + t_ext) + t_pose``, with the pose interpolated from a pose
source at the cloud stamp (one pose) or at every point's time (de-skew).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.sensing.pointcloud import ParsedCloud
from mfp_mapper.sensing.poses import Extrinsic

FloatArray = NDArray[np.float64]

DESKEW_TIME_RESOLUTION = 1e-5
"""Seconds within which de-skewed points share one interpolated pose (10 µs)."""
_DENSE_BINS_LIMIT = 1 << 22


class PoseSource(Protocol):
    """Where poses come from (odometry's PoseBuffer today, a TF chain tomorrow).

    ``interpolate`` returns positions (N, 3) and rotation matrices (N, 3, 3) of the robot
    frame in the map frame at ``stamps``, or raises ``poses.PoseUnavailable``.
    """

    @property
    def latest_stamp(self) -> float | None: ...

    def interpolate(self, stamps: ArrayLike) -> tuple[FloatArray, FloatArray]: ...


def cloud_to_map(
    cloud: ParsedCloud,
    stamp: float,
    buffer: PoseSource,
    extrinsic: Extrinsic,
    deskew: bool = True,
    time_resolution: float = DESKEW_TIME_RESOLUTION,
) -> tuple[FloatArray, FloatArray]:
    """Points of ``cloud`` in the map frame, and the sensor origin(s) they were seen from.

    ``p_map = R_odom (R_ext p + t_ext) + t_odom``. With ``deskew`` and per-point times, each
    point uses the pose at ``stamp + time_offset`` (offsets closer than ``time_resolution``
    share one pose; 0 for exact) and origins are (N, 3); otherwise one pose at ``stamp``
    and one origin (3,). Raises PoseUnavailable.
    """
    if deskew and cloud.time_offset is not None and len(cloud) > 0:
        offsets, bin_of_point = _time_bins(cloud.time_offset, time_resolution)
        rotations, origins = _sensor_poses(buffer, stamp + offsets, extrinsic)
        return _transform_binned(cloud.xyz, rotations, origins, bin_of_point), origins[bin_of_point]
    rotations, origins = _sensor_poses(buffer, np.array([stamp]), extrinsic)
    return cloud.xyz @ rotations[0].T + origins[0], origins[0]


def _sensor_poses(
    buffer: PoseSource, stamps: FloatArray, extrinsic: Extrinsic
) -> tuple[FloatArray, FloatArray]:
    """Sensor-to-map rotations (N, 3, 3) and sensor origins in the map (N, 3) at ``stamps``."""
    positions, odom_rotations = buffer.interpolate(stamps)
    origins = odom_rotations @ extrinsic.translation + positions
    return odom_rotations @ extrinsic.rotation, origins


def _transform_binned(
    points: FloatArray, rotations: FloatArray, translations: FloatArray, bins: NDArray[np.intp]
) -> FloatArray:
    """``rotations[bins[k]] @ points[k] + translations[bins[k]]`` for every k, gathering
    scalars per matrix element (much faster than gathering (N, 3, 3) matrices)."""
    x, y, z = np.ascontiguousarray(points.T)
    elements = np.ascontiguousarray(rotations.reshape(-1, 9).T)
    offsets = np.ascontiguousarray(translations.T)
    out = np.empty((points.shape[0], 3), dtype=np.float64)
    for row in range(3):
        r0, r1, r2 = elements[3 * row : 3 * row + 3]
        out[:, row] = r0[bins] * x + r1[bins] * y + r2[bins] * z + offsets[row][bins]
    return out


def _time_bins(offsets: FloatArray, resolution: float) -> tuple[FloatArray, NDArray[np.intp]]:
    """Representative offsets (U,) and each offset's index into them.

    Offsets are rounded to multiples of ``resolution`` from the smallest one (exact
    unique values when ``resolution`` is 0); representatives stay within the offsets' range.
    """
    if resolution <= 0.0:
        unique, inverse = np.unique(offsets, return_inverse=True)
        return unique, inverse.reshape(-1)
    start, stop = float(offsets.min()), float(offsets.max())
    keys = np.rint((offsets - start) / resolution).astype(np.intp)
    if keys.max() < _DENSE_BINS_LIMIT:
        occupied = np.zeros(int(keys.max()) + 1, dtype=bool)
        occupied[keys] = True
        bins, inverse = np.flatnonzero(occupied), (np.cumsum(occupied) - 1)[keys]
    else:
        bins, inverse = np.unique(keys, return_inverse=True)
    return np.clip(start + bins * resolution, start, stop), inverse.reshape(-1)
