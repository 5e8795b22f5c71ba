"""Helpers of the tests that drive the live worker (``mapping.live``) without ROS."""

from __future__ import annotations

import numpy as np

from mfp_mapper.mapping.live import LiveIntegrator
from mfp_mapper.sensing.poses import OdometrySample


def odom_sample(stamp: float, frame: str = "odom") -> OdometrySample:
    """An odometry pose at the origin of ``frame`` (child ``base_link``) at ``stamp``."""
    return OdometrySample(stamp, frame, "base_link", np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))


def drain(worker: LiveIntegrator) -> None:
    """Process every queued cloud on this thread (what ``run()`` does), waiting when told to."""
    worker.drain()
