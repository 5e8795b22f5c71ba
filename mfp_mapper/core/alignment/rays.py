"""What the solver, the curvature probes and the exact check share: the scan's rays, their
evenly spread subsets, the scaled coordinates of a correction and its composition."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ScanRays:
    """Rays ``origins`` -> ``points`` (N, 3 each, map frame, contiguous float64) of one
    scan; corrections rotate about ``center`` (the mean sensor origin)."""

    points: FloatArray
    origins: FloatArray
    center: FloatArray

    def subset(self, wanted: int) -> tuple[ScanRays, float]:
        """At most ``wanted`` rays evenly spread, and the weight that scales their sums
        to all rays."""
        sub = spread_subset(self.points.shape[0], wanted)
        weight = self.points.shape[0] / sub.size
        return ScanRays(self.points[sub], self.origins[sub], self.center), weight


def spread_subset(count: int, wanted: int) -> NDArray[np.intp]:
    """Indices of at most ``wanted`` of ``count`` items, evenly spread (deterministic)."""
    if count <= wanted:
        return np.arange(count)
    return np.unique(np.linspace(0, count - 1, wanted).round().astype(np.intp))


def axis_scale(lever: float) -> FloatArray:
    """Scaled coordinates of a correction (6,): metres, and radians times ``lever``."""
    return np.array([1.0, 1.0, 1.0, 1.0 / lever, 1.0 / lever, 1.0 / lever])


def compose(
    rotvec: FloatArray, v: FloatArray, center: FloatArray, rot: FloatArray, trans: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The correction (R', t') = [x -> dR (x - c) + c + v] o (rot, trans)."""
    d_rot = Rotation.from_rotvec(rotvec).as_matrix()
    return d_rot @ rot, d_rot @ (trans - center) + center + v
