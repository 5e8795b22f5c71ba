"""Recovery of no-return firings from organized (velodyne NaN, Ouster zero) and ring clouds."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mfp_mapper.sensing.no_return import recover_no_return, with_no_return_rays
from mfp_mapper.sensing.pointcloud import parse_pointcloud2
from mfp_mapper.sources.scan_files import cloud_message, cloud_message_from_columns, read_pcd

VLP16_ELEVATIONS = np.arange(-15.0, 16.0, 2.0)
OUSTER_ELEVATIONS = np.sort(np.random.default_rng(5).uniform(-22.5, 22.5, 64))
OUSTER_STAGGER = np.tile([3.1, 1.05, -1.05, -3.1], 16)
DATA = Path(__file__).resolve().parents[2] / "../shared/data/nebula_frames"


def _grid(
    elevations_deg: np.ndarray,
    stagger_deg: np.ndarray,
    width: int,
    seed: int,
    wobble: float = 0.002,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unit directions (H, W, 3) of a clockwise-spinning lidar with uneven rotation (up to
    ``wobble`` turns off), ranges, a no-return mask (random dropouts and a patch of sky)
    and times."""
    rng = np.random.default_rng(seed)
    height = elevations_deg.size
    column = np.arange(width)
    turn = 2.0 * math.pi * (column / width + wobble * np.sin(2.0 * math.pi * column / width))
    azimuth = 1.3 - turn[None, :] + np.radians(stagger_deg)[:, None]
    elevation = np.radians(elevations_deg)[:, None] * np.ones((1, width))
    directions = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
         np.sin(elevation)], axis=-1,
    )  # fmt: skip
    ranges = rng.uniform(2.0, 40.0, (height, width))
    missing = rng.random((height, width)) < 0.3
    missing[height // 2 :, width // 4 : width // 2] = True  # sky over a quarter turn
    times = np.broadcast_to(column / width * 0.1, (height, width)).copy()
    return directions, ranges, missing, times


def _nearest_deg(directions: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Angle (deg) from each direction to the nearest true one."""
    chord, _ = cKDTree(truth).query(directions)
    return np.degrees(2.0 * np.arcsin(np.minimum(chord / 2.0, 1.0)))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def test_organized_velodyne_nan_cells_get_their_beam_direction() -> None:
    directions, ranges, missing, times = _grid(VLP16_ELEVATIONS, np.zeros(16), 1800, 1)
    records = np.zeros(
        missing.shape, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                              ("ring", "<u2"), ("time", "<f4")],
    )  # fmt: skip
    xyz = directions * ranges[..., None]
    xyz[missing] = np.nan
    for axis, name in enumerate("xyz"):
        records[name] = xyz[..., axis]
    records["ring"] = np.arange(16)[:, None]
    records["time"] = times
    cloud = parse_pointcloud2(cloud_message(records))
    assert cloud.dropped["nonfinite"] == int(missing.sum())
    found = recover_no_return(cloud)
    assert found.pattern == "organized" and found.reason is None
    assert len(found) == int(missing.sum())
    assert _angle_deg(found.directions, directions[missing]).max() < 0.1
    assert found.time_offset is not None
    np.testing.assert_allclose(found.time_offset, times[missing], atol=1e-6)


def test_organized_ouster_zero_cells_with_staggered_beams() -> None:
    directions, ranges, missing, times = _grid(OUSTER_ELEVATIONS, OUSTER_STAGGER, 1024, 2)
    records = np.zeros(
        missing.shape, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_pad", "<f4"),
                              ("intensity", "<f4"), ("t", "<u4"), ("ring", "<u2")],
    )  # fmt: skip
    xyz = directions * ranges[..., None]
    xyz[missing] = 0.0
    for axis, name in enumerate("xyz"):
        records[name] = xyz[..., axis]
    records["t"] = np.round(times * 1e9)
    cloud = parse_pointcloud2(cloud_message(records))
    assert cloud.dropped["zero_range"] == int(missing.sum())
    found = recover_no_return(cloud)
    assert len(found) == int(missing.sum())
    assert _angle_deg(found.directions, directions[missing]).max() < 0.1


def test_shuffled_columns_are_refused_before_recovery() -> None:
    """Columns jittered out of firing order (by up to 5 places): the per-column corrections
    absorb it where a column has points, but the 40 empty columns' azimuths come from their
    shuffled neighbours (before the check: 384 of 5,877 rays more than 0.5 deg off)."""
    directions, ranges, missing, _ = _grid(VLP16_ELEVATIONS, np.zeros(16), 900, 4)
    missing[:, 300:340] = True
    order = np.argsort(np.arange(900) + np.random.default_rng(0).uniform(0, 5, 900))
    xyz = directions * ranges[..., None]
    xyz[missing] = np.nan
    shuffled = np.zeros(missing.shape, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    in_order = shuffled.copy()
    for axis, name in enumerate("xyz"):
        shuffled[name] = xyz[:, order, axis]
        in_order[name] = xyz[..., axis]
    found = recover_no_return(parse_pointcloud2(cloud_message(shuffled)))
    assert len(found) == 0 and found.reason is not None
    assert "columns are not in firing order" in found.reason
    found = recover_no_return(parse_pointcloud2(cloud_message(in_order)))
    assert len(found) == int(missing.sum())
    assert _angle_deg(found.directions, directions[missing]).max() < 0.1


def test_an_empty_row_is_left_out_and_said_so() -> None:
    directions, ranges, missing, _ = _grid(VLP16_ELEVATIONS, np.zeros(16), 900, 3)
    missing[15] = True
    xyz = (directions * ranges[..., None]).astype(np.float32)
    xyz[missing] = np.nan
    records = np.zeros(missing.shape, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    for axis, name in enumerate("xyz"):
        records[name] = xyz[..., axis]
    found = recover_no_return(parse_pointcloud2(cloud_message(records)))
    assert found.reason is not None and "1 of 16 rows" in found.reason
    assert len(found) == int(missing[:15].sum())


def _unorganized(
    directions: np.ndarray, ranges: np.ndarray, missing: np.ndarray, times: np.ndarray
) -> np.ndarray:
    keep = ~missing
    xyz = directions[keep] * ranges[keep][:, None]
    records = np.zeros(
        int(keep.sum()), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("ring", "<u2"),
                                ("time", "<f4")],
    )  # fmt: skip
    for axis, name in enumerate("xyz"):
        records[name] = xyz[:, axis]
    records["ring"] = np.broadcast_to(np.arange(missing.shape[0])[:, None], missing.shape)[keep]
    records["time"] = times[keep]
    return records


def test_ring_cloud_gaps_become_rays_along_their_beams() -> None:
    directions, ranges, missing, times = _grid(VLP16_ELEVATIONS, np.zeros(16), 1800, 4, wobble=0.0)
    cloud = parse_pointcloud2(cloud_message(_unorganized(directions, ranges, missing, times)))
    found = recover_no_return(cloud)
    assert found.pattern == "beams" and found.reason is None
    assert len(found) == int(missing.sum())
    truth = directions[missing]
    assert _nearest_deg(found.directions, truth).max() < 0.1


def test_a_partial_scan_keeps_its_edges_open() -> None:
    directions, ranges, missing, times = _grid(VLP16_ELEVATIONS, np.zeros(16), 1800, 6, wobble=0.0)
    sector = np.zeros_like(missing)
    sector[:, :1350] = True  # a 270 deg scan: the driver cut the rest
    cloud = parse_pointcloud2(
        cloud_message(_unorganized(directions, ranges, missing | ~sector, times))
    )
    found = recover_no_return(cloud)
    assert found.reason is not None and "not a full turn" in found.reason
    truth = directions[missing & sector]
    assert _nearest_deg(found.directions, truth).max() < 0.1
    assert len(found) <= int((missing & sector).sum())


def test_an_irregular_or_ringless_cloud_is_not_recovered_and_says_why() -> None:
    rng = np.random.default_rng(7)
    xyz = rng.normal(size=(500, 3)).astype(np.float32)
    plain = cloud_message_from_columns({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    found = recover_no_return(parse_pointcloud2(plain))
    assert len(found) == 0 and found.reason is not None and "ring" in found.reason
    ringed = cloud_message_from_columns(
        {
            "x": xyz[:, 0],
            "y": xyz[:, 1],
            "z": xyz[:, 2],
            "ring": rng.integers(0, 4, 500).astype(np.uint16),
        }
    )
    found = recover_no_return(parse_pointcloud2(ringed))
    assert len(found) == 0 and found.reason is not None


def test_with_no_return_rays_appends_flagged_points_at_the_range() -> None:
    directions, ranges, missing, times = _grid(VLP16_ELEVATIONS, np.zeros(16), 900, 8, wobble=0.0)
    cloud = parse_pointcloud2(cloud_message(_unorganized(directions, ranges, missing, times)))
    extended, found = with_no_return_rays(cloud, 25.0)
    assert extended.no_return is not None
    assert len(extended) == len(cloud) + len(found)
    assert not extended.no_return[: len(cloud)].any() and extended.no_return[len(cloud) :].all()
    np.testing.assert_allclose(np.linalg.norm(extended.xyz[len(cloud) :], axis=1), 25.0)
    assert extended.time_offset is not None and extended.time_offset.shape == (len(extended),)


def test_nebula_vlp16_frame_is_declined_with_a_reason() -> None:
    """The real Nebula VLP-16 frame (channel + azimuth + time_stamp): its per-channel
    azimuths are not one regular grid (about 14% of the gaps fall between 0.2 deg steps),
    so no ray is invented."""
    path = DATA / "velodyne_vlp16_1673400472138016708.pcd"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    cloud = parse_pointcloud2(cloud_message_from_columns(read_pcd(path), 1673400472.0))
    assert cloud.ring is not None and np.unique(cloud.ring).size == 15
    found = recover_no_return(cloud)
    assert len(found) == 0 and found.reason is not None and "regular grid" in found.reason
