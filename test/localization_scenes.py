"""Scenes with known truth for scan-to-map alignment: static scans from exact poses.

Three scenes: ``box`` (the demo hall: walls, pillars, a car, a crate, two media), ``vegetation``
(an open field with a grid of media boxes of different extinction, no walls: returns mostly
inside foliage) and ``corridor`` (a long featureless corridor: the along-axis position is
not observable, the degenerate case an aligner must refuse).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from mfp_mapper.sources.scan_pattern import VLP16_ELEVATIONS_DEG, scan_directions
from mfp_mapper.sources.sim_scene import Medium, Scene, builtin_scene

FloatArray = NDArray[np.float64]

__all__ = ["LOCALIZATION_SCENES", "Pose", "localization_scene", "perturb", "static_scan"]


@dataclass(frozen=True)
class Pose:
    """world <- sensor: a point x of the sensor frame is at ``rotation @ x + translation``."""

    rotation: FloatArray
    translation: FloatArray

    def apply(self, x: FloatArray) -> FloatArray:
        return np.asarray(x) @ self.rotation.T + self.translation

    def error_to(self, other: Pose) -> tuple[float, float]:
        """(translation metres, rotation degrees) between the two poses."""
        dr = Rotation.from_matrix(self.rotation.T @ other.rotation).magnitude()
        return float(np.linalg.norm(self.translation - other.translation)), float(np.degrees(dr))


def _vegetation() -> Scene:
    rng = np.random.default_rng(7)
    media = []
    for i, x in enumerate(np.arange(-12.0, 13.0, 6.0)):
        for j, y in enumerate(np.arange(-12.0, 13.0, 6.0)):
            if abs(x) < 1 and abs(y) < 1:
                continue
            cx, cy = x + rng.uniform(-1.5, 1.5), y + rng.uniform(-1.5, 1.5)
            w, d, h = rng.uniform(1.0, 3.0, 3)
            media.append(
                Medium(
                    f"bush_{i}_{j}",
                    (cx - w / 2, cy - d / 2, 0.0),
                    (cx + w / 2, cy + d / 2, 1.0 + 2.0 * h / 3.0),
                    extinction=float(rng.uniform(0.5, 3.0)),
                )
            )
    return Scene(
        room_lo=(-40.0, -40.0, 0.0),
        room_hi=(40.0, 40.0, 10.0),
        media=tuple(media),
        enclosed=False,
        wall_height=0.0,
    )


def _corridor() -> Scene:
    return Scene(room_lo=(-60.0, -1.5, 0.0), room_hi=(60.0, 1.5, 3.0), solids=(), media=())


LOCALIZATION_SCENES = ("box", "vegetation", "corridor")


def localization_scene(name: str) -> tuple[Scene, FloatArray]:
    """The scene and a set of sensor positions (K, 3) along which scans are taken."""
    if name == "box":
        angles = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
        pos = np.stack([6.0 * np.cos(angles), 6.0 * np.sin(angles), np.full(24, 1.2)], axis=1)
        return builtin_scene(), pos
    if name == "vegetation":
        x = np.linspace(-9.0, 9.0, 24)
        pos = np.stack([x, 0.3 * x + 0.5, np.full(24, 1.5)], axis=1)
        return _vegetation(), pos
    if name == "corridor":
        x = np.linspace(-10.0, 10.0, 24)
        pos = np.stack([x, np.full(24, 0.2), np.full(24, 1.2)], axis=1)
        return _corridor(), pos
    raise ValueError(f"unknown localization scene {name!r}: expected one of {LOCALIZATION_SCENES}")


def static_scan(
    scene: Scene,
    pose: Pose,
    rng: np.random.Generator,
    *,
    elevations_deg: FloatArray = VLP16_ELEVATIONS_DEG,
    azimuths: int = 1800,
    max_range: float = 60.0,
    noise_m: float = 0.01,
) -> FloatArray:
    """First returns (N, 3) in the sensor frame of a lidar at ``pose`` (no motion), with
    Gaussian range noise ``noise_m``; rays without a return or beyond ``max_range`` are left
    out."""
    dirs = scan_directions(np.asarray(elevations_deg, dtype=np.float64), azimuths)
    world = dirs @ pose.rotation.T
    ranges, _ = scene.cast(np.broadcast_to(pose.translation, world.shape), world, rng)
    keep = np.isfinite(ranges) & (ranges < max_range)
    r = ranges[keep] + rng.normal(0.0, noise_m, int(keep.sum()))
    return dirs[keep] * r[:, None]


def pose_at(position: FloatArray, yaw: float, roll: float = 0.0, pitch: float = 0.0) -> Pose:
    rot = Rotation.from_euler("xyz", [roll, pitch, yaw]).as_matrix()
    return Pose(rot, np.asarray(position, dtype=np.float64))


def perturb(pose: Pose, rng: np.random.Generator, shift_m: float, angle_deg: float) -> Pose:
    """``pose`` moved by exactly ``shift_m`` metres in a random direction and rotated by
    exactly ``angle_deg`` degrees about a random axis (through the sensor)."""
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    dr = Rotation.from_rotvec(axis * np.radians(angle_deg)).as_matrix()
    return Pose(dr @ pose.rotation, pose.translation + shift_m * d)
