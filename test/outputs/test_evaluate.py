"""The physics check of docs/model.md through the whole offline chain, and the evaluation itself."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.replay import ReplayOptions, replay
from mfp_mapper.outputs.evaluate import evaluate_map, inside_voxels
from mfp_mapper.sensing.poses import quaternion_to_matrix, rpy_to_quaternion
from mfp_mapper.sources.simulate import generate_scans, preset, simulate


def test_inside_voxels_are_fully_inside() -> None:
    ijk = inside_voxels((-0.8, -0.8, 0.4), (0.8, 0.8, 2.0), 0.2)
    assert ijk.shape == (8 * 8 * 8, 3)
    lo, hi = ijk.min(axis=0) * 0.2, (ijk.max(axis=0) + 1) * 0.2
    np.testing.assert_allclose(lo, [-0.8, -0.8, 0.4])
    np.testing.assert_allclose(hi, [0.8, 0.8, 2.0])
    assert inside_voxels((0.05, 0, 0), (0.15, 1, 1), 0.2).shape == (0, 3)


def test_physics_closed_scene_bag_replay_recovers_extinction(tmp_path: Path) -> None:
    """Every ray returns (closed room): pooled n/s within 5% of lambda, 90% coverage ~ 90%.

    Simulated bag (mcap) -> replay with de-skew -> evaluation; seeded, ~350k rays.
    """
    cfg = replace(preset("small"), scans=40, seed=0)
    sim = simulate(tmp_path / "physics", cfg, "mcap")
    assert sim.truth["rays"]["omitted"] == 0
    result = replay(sim.bag, ReplayOptions.of(resolution=0.2), progress=False)
    ev = evaluate_map(result.mapper, sim.truth)
    (cube,) = ev.media
    assert cube.voxels_observed == cube.voxels_inside == 512
    assert cube.returns > 5000
    assert abs(cube.pooled / cube.extinction - 1.0) < 0.05
    assert 0.85 <= cube.coverage <= 0.95
    assert ev.free_air.voxels_observed > 10_000
    assert ev.free_air.voxels_with_returns == 0
    assert not ev.warnings
    text = ev.format()
    assert "pooled n/s" in text and "90% interval" in text


def _yaw_transform(p: np.ndarray, yaw: np.ndarray, pos: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]], 1) + pos


def _map_in_memory(name: str, scans: int, **settings: float) -> tuple[Mapper, dict]:
    """The same simulation fed straight to the core (no bag): faster, exact poses."""
    cfg = replace(preset(name), scans=scans, azimuths=360, seed=3)
    mapper = Mapper(0.2, **settings)
    r_ext = quaternion_to_matrix(rpy_to_quaternion(*cfg.lidar_rpy))
    t_ext = np.array(cfg.lidar_translation)
    omitted_through = 0
    for k, scan in enumerate(generate_scans(cfg)):
        pos, yaw = cfg.path.pose(k * cfg.scan_period + scan.time.astype(np.float64))
        p_base = scan.xyz.astype(np.float64) @ r_ext.T + t_ext
        o_base = np.broadcast_to(t_ext, p_base.shape)
        mapper.integrate(
            _yaw_transform(p_base, yaw, pos), _yaw_transform(o_base, yaw, pos), float(k)
        )
        omitted_through += scan.omitted_through_media
    truth = {
        "scene": cfg.scene.to_json(),
        "rays": {"omitted_through_media": omitted_through},
        "frames": {"odom": "map"},
    }
    return mapper, truth


def test_rays_without_return_dropped_bias_extinction_upward() -> None:
    """Why the built-in scenes are closed: a driver omits rays with no return, so the space
    they crossed is lost and n/s is biased upward; evaluate says so."""
    closed, truth_closed = _map_in_memory("small", 20)
    opened, truth_open = _map_in_memory("open", 20)
    good = evaluate_map(closed, truth_closed).media[0]
    bad_ev = evaluate_map(opened, truth_open)
    bad = bad_ev.media[0]
    assert abs(good.pooled - 1.0) < 0.05
    assert bad.pooled > 1.15 * good.pooled
    assert bad.coverage < good.coverage
    assert any("biased upward" in w for w in bad_ev.warnings)


def test_unobserved_medium_is_reported() -> None:
    mapper = Mapper(0.5)
    truth = preset("small").scene.to_json()
    ev = evaluate_map(mapper, {"scene": truth, "rays": {}})
    assert ev.media[0].voxels_observed == 0
    assert "none of its" in ev.format()


@pytest.mark.parametrize("level", [0.5, 0.99])
def test_coverage_grows_with_the_credible_level(level: float) -> None:
    """With the uniform prior (the default prior, fitted on real scenes of empty space and
    surfaces, under-covers a homogeneous medium seen by few rays: docs/performance.md)."""
    mapper, truth = _map_in_memory("small", 8, prior_shape=1.0, prior_rate=1.0)
    ev = evaluate_map(mapper, truth, level=level)
    cov = ev.media[0].coverage
    assert (cov < 0.7) if level == 0.5 else (cov > 0.95)
