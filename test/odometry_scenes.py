"""Simulated recordings for lidar odometry (KISS-ICP): structure everywhere, uneven ground.

A perfectly flat floor is a trap for scan matching: the rings a spinning lidar draws on it
move with the sensor, and ICP locks onto them (KISS-ICP recovered 1.2 m of a 3.8 m path in
the flat demo hall). Here the floor is a patchwork of tiles of random heights and the hall
holds pillars and crates of several sizes, so every scan constrains all six degrees of
freedom.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.sensing.poses import quaternion_to_matrix, rpy_to_quaternion
from mfp_mapper.sources.simulate import Circle, Scene, SimulationConfig, Solid

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class StartingCircle(Circle):
    """``Circle`` from rest: the speed ramps up with time constant ``ramp`` (s), as a robot
    starting a recording does (KISS-ICP's first scan has no motion to de-skew with)."""

    ramp: float = 0.4

    def pose(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(t, dtype=np.float64)
        travelled = t - self.ramp * (1.0 - np.exp(-t / self.ramp))
        return super().pose(travelled)


def structured_hall(seed: int = 0, tiles: tuple[int, int] = (20, 16)) -> Scene:
    """A 20 x 16 x 5 m hall: a floor of 1 m tiles of random heights (0-0.4 m), pillars
    and crates."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-10.0, -8.0, 0.0]), np.array([10.0, 8.0, 5.0])
    solids = []
    xs = np.linspace(lo[0], hi[0], tiles[0] + 1)
    ys = np.linspace(lo[1], hi[1], tiles[1] + 1)
    for i in range(tiles[0]):
        for j in range(tiles[1]):
            height = float(rng.uniform(0.0, 0.4) + 0.01)
            solids.append(
                Solid(f"tile_{i}_{j}", (xs[i], ys[j], 0.0), (xs[i + 1], ys[j + 1], height))
            )
    for k in range(16):
        while True:
            x, y = rng.uniform(lo[:2] + 1.5, hi[:2] - 1.5)
            if abs(np.hypot(x, y) - 4.0) > 1.5:  # off the robot's circle
                break
        w, d = rng.uniform(0.4, 1.6, size=2)
        h = float(rng.choice([1.0, 2.0, 6.0]))
        solids.append(Solid(f"box_{k}", (x - w / 2, y - d / 2, 0.0), (x + w / 2, y + d / 2, h)))
    return Scene(room_lo=tuple(lo), room_hi=tuple(hi), solids=tuple(solids))


def structured_recording(scans: int = 30, azimuths: int = 900, seed: int = 0) -> SimulationConfig:
    """A VLP-16 on a robot starting from rest on a 4 m-radius circle at up to 2 m/s through
    ``structured_hall``."""
    return replace(
        SimulationConfig(),
        scene=structured_hall(seed),
        path=StartingCircle(radius=4.0, speed=2.0),
        scans=scans,
        azimuths=azimuths,
        seed=seed,
    )


def lidar_truth(cfg: SimulationConfig, stamps: np.ndarray) -> np.ndarray:
    """True 4x4 poses of the lidar in the odometry frame at ``stamps``."""
    t = np.asarray(stamps) - cfg.start_time
    positions, yaw = cfg.path.pose(t)
    buffer_free = np.zeros((len(t), 4, 4))
    mount = np.eye(4)
    mount[:3, :3] = quaternion_to_matrix(rpy_to_quaternion(*cfg.lidar_rpy))
    mount[:3, 3] = cfg.lidar_translation
    for k in range(len(t)):
        base = np.eye(4)
        c, s = np.cos(yaw[k]), np.sin(yaw[k])
        base[:2, :2] = [[c, -s], [s, c]]
        base[:3, 3] = positions[k]
        buffer_free[k] = base @ mount
    return buffer_free


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    """Poses expressed in the frame of the first one."""
    return np.linalg.inv(poses[0]) @ poses


def pose_errors(estimated: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: translation error (m) and rotation error (rad), both relative to the first."""
    est, ref = relative_to_first(estimated), relative_to_first(truth)
    delta = np.linalg.inv(ref) @ est
    translation = np.linalg.norm(est[:, :3, 3] - ref[:, :3, 3], axis=1)
    cos = np.clip((np.trace(delta[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return translation, np.arccos(cos)
