"""Echoes of one shot: grouping in the drivers' conventions and one Poisson process per shot
(exact chords against brute force)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from core.test_traversal import brute_force_chords, map_chords

from mfp_mapper import Mapper
from mfp_mapper.sensing.echoes import (
    IDENTICAL_RANGE,
    livox_shots,
    nebula_shots,
    shot_segments,
    target_shots,
)
from mfp_mapper.sensing.pointcloud import parse_pointcloud2
from mfp_mapper.sources.scan_files import cloud_message_from_columns

RES = 0.2


def _random_shots(
    rng: np.random.Generator, shots: int, sensor: np.ndarray
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Echo points (shuffled), their shot ids, and each shot's ranges (sorted)."""
    points, ids, ranges = [], [], []
    for k in range(shots):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        count = int(rng.integers(1, 5))
        r = np.sort(rng.uniform(0.5, 12.0, count))
        if count > 1 and k % 5 == 0:  # an echo inside the blind stretch of the one before
            r[1] = r[0] + 0.1
            r = np.sort(r)
        ranges.append(r)
        points += [sensor + d * x for x in r]
        ids += [k] * count
    order = rng.permutation(len(points))
    return np.array(points)[order], np.array(ids, dtype=np.int64)[order], ranges


def _brute_force(sensor: np.ndarray, points: np.ndarray, ids: np.ndarray, blind: float):
    """Per voxel: s (chords of sensor -> echo 1 and echo k-1 + blind -> echo k), n."""
    s: dict[tuple[int, int, int], float] = defaultdict(float)
    n: dict[tuple[int, int, int], float] = defaultdict(float)
    for k in np.unique(ids):
        shot = points[ids == k]
        r = np.linalg.norm(shot - sensor, axis=1)
        shot, r = shot[np.argsort(r)], np.sort(r)
        u = (shot[-1] - sensor) / r[-1]
        start = 0.0
        for x, p in zip(r, shot, strict=True):
            a = sensor + u * start
            if x > start:
                for voxel, chord in brute_force_chords(a, sensor + u * x, RES).items():
                    s[voxel] += chord
            n[tuple(np.floor(p / RES).astype(int).tolist())] += 1.0
            start = max(start, x + blind)
    return s, n


@pytest.mark.parametrize("blind", [0.0, 0.5, 1.5])
def test_a_shot_is_one_process_along_its_beam_exactly(blind: float) -> None:
    rng = np.random.default_rng(3)
    sensor = np.array([0.31, -0.07, 1.13])
    points, ids, _ = _random_shots(rng, 60, sensor)
    seg = shot_segments(points, sensor, ids, None, blind, min_range=0.4)
    mapper = Mapper(RES, max_range=100.0, min_range=0.4)
    summary = mapper.integrate(seg.points, seg.origins, 0.0, seg.no_return, continued=seg.continued)
    assert summary.rays_used == len(points)  # later segments shorter than min_range kept
    s, n = map_chords(mapper)
    want_s, want_n = _brute_force(sensor, points, ids, blind)
    for voxel, chord in want_s.items():
        if chord > 1e-5:
            assert s.get(voxel, 0.0) == pytest.approx(chord, rel=1e-4, abs=1e-5), voxel
    for voxel, chord in s.items():
        assert want_s.get(voxel, 0.0) == pytest.approx(chord, rel=1e-4, abs=1e-5), voxel
    assert n == pytest.approx(dict(want_n))
    assert np.allclose(mapper.last_origin, sensor)  # later segments' starts left out


def test_identical_returns_are_one_echo_and_first_only_keeps_the_nearest() -> None:
    sensor = np.zeros(3)
    u = np.array([0.6, 0.8, 0.0])
    points = np.array([u * 5.0, u * 5.0, u * (5.0 + IDENTICAL_RANGE / 2), u * 7.0, u * 3.0])
    ids = np.array([1, 1, 1, 1, 2])
    seg = shot_segments(points, sensor, ids, None, 0.5)
    assert seg.dropped == {"identical_return": 2}
    assert seg.continued.tolist() == [False, True, False]  # the input order of the shots
    assert np.allclose(seg.points, [u * 5.0, u * 7.0, u * 3.0])
    assert seg.order.tolist() == [0, 3, 4]
    assert np.allclose(seg.origins[1], u * 5.5)
    first = shot_segments(points, sensor, ids, None, 0.5, first_only=True)
    assert first.dropped == {"identical_return": 2, "later_echo": 1}
    assert np.allclose(first.points, [u * 5.0, u * 3.0])
    assert not first.continued.any()


def test_max_range_cuts_a_later_echo_and_drops_the_rest_min_range_drops_near_echoes() -> None:
    u = np.array([0.0, 0.0, 1.0])
    points = u * np.array([[0.2], [4.0], [9.0], [12.0], [15.0]])
    seg = shot_segments(points, np.zeros(3), np.zeros(5, dtype=np.int64), None, 0.5, 10.0, 0.5)
    assert seg.dropped == {"below_min_range": 1, "beyond_max_range": 1}
    assert np.allclose(seg.points, u * np.array([[4.0], [9.0], [10.0]]))
    assert np.allclose(seg.origins, u * np.array([[0.0], [4.5], [9.5]]))
    assert seg.no_return is not None and seg.no_return.tolist() == [False, False, True]


def test_an_echo_of_an_unknown_shot_is_dropped() -> None:
    seg = shot_segments(np.eye(3) * 5.0, np.zeros(3), np.array([0, -1, 1]), None, 0.5)
    assert seg.dropped == {"echo_without_first": 1} and len(seg.points) == 2


def _nebula_dual_cloud() -> tuple[Any, np.ndarray]:
    """A Nebula-layout dual-return cloud (VLP-16 field layout): 3 firings, the second with
    two returns (first, last), the third published twice (identical)."""
    azimuth = np.array([0.1, 0.2, 0.2, 0.3, 0.3], dtype=np.float32)
    channel = np.array([4, 4, 4, 7, 7], dtype=np.uint16)
    rng_m = np.array([5.0, 3.0, 6.0, 8.0, 8.0])
    return_type = np.array([3, 2, 1, 6, 6], dtype=np.uint8)
    xyz = np.c_[np.cos(azimuth), np.sin(azimuth), np.zeros(5)] * rng_m[:, None]
    msg = cloud_message_from_columns({
        "x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
        "z": xyz[:, 2].astype(np.float32), "intensity": np.full(5, 9, np.uint8),
        "return_type": return_type, "channel": channel, "azimuth": azimuth,
        "elevation": np.zeros(5, np.float32), "distance": rng_m.astype(np.float32),
        "time_stamp": np.arange(5, dtype=np.uint32) * 1000,
    }, 1.0, "lidar")  # fmt: skip
    return msg, xyz


def test_nebula_return_type_groups_a_firing_by_channel_and_azimuth() -> None:
    msg, xyz = _nebula_dual_cloud()
    cloud = parse_pointcloud2(msg)
    assert cloud.echo_field == "return_type" and cloud.shot is not None
    assert len(set(cloud.shot.tolist())) == 3
    assert cloud.shot[1] == cloud.shot[2] and cloud.shot[3] == cloud.shot[4]
    seg = shot_segments(cloud.xyz, np.zeros(3), cloud.shot, None, 0.5)
    assert seg.dropped == {"identical_return": 1}
    assert seg.continued.sum() == 1


def test_livox_tag_return_numbers_group_by_line_and_time() -> None:
    tag = np.array([0x10, 0x20, 0x10, 0x10], dtype=np.uint8)
    line = np.array([1, 1, 1, 2], dtype=np.uint8)
    time = np.array([5.0, 5.0, 6.0, 5.0])
    shot = livox_shots(tag, line, time)
    assert shot is not None and shot[0] == shot[1] and len(set(shot.tolist())) == 3
    assert livox_shots(np.zeros(4, np.uint8), line, time) is None  # single return
    assert nebula_shots(np.array([1, 1]), np.array([0.5, 0.5], np.float32)).tolist() == [0, 0]


def test_target_index_joins_echoes_seen_in_one_direction() -> None:
    u = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    tilt = np.array([0.0, 1e-4, 0.0])  # 0.006 deg: one shot's echoes are not exactly collinear
    xyz = np.array([u[0] * 2, (u[0] + tilt) * 5, u[1] * 3, u[2] * 9, u[1] * 4])
    index = np.array([1, 2, 1, 2, 2])
    count = np.array([2, 2, 1, 2, 2])
    shot = target_shots(xyz, index, count)
    assert shot[0] == shot[1]
    assert shot[3] == -1  # its first echo is not in the cloud
    assert shot[4] == -1  # the first echo in its direction had one echo only
    msg = cloud_message_from_columns({
        "x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
        "z": xyz[:, 2].astype(np.float32),
        "target_index": index.astype(np.uint8), "target_count": count.astype(np.uint8),
    }, 0.0, "scanner")  # fmt: skip
    cloud = parse_pointcloud2(msg)
    assert cloud.echo_field == "target_index"
    assert cloud.shot is not None and cloud.shot.tolist() == shot.tolist()


def _simulated_shots(
    rate: float, blind: float, max_echoes: int, wall: float, shots: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """A sensor at the origin in a medium of extinction ``rate`` (1/m) closed by a wall at
    ``wall`` m: each shot's echoes are a Poisson process along its beam (exponential free
    paths), the sensor blind for ``blind`` m after each echo, at most ``max_echoes`` echoes
    (the wall returns the beam when it gets there). Echo points and their shot ids."""
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(shots, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pos = np.zeros(shots)
    alive = np.ones(shots, dtype=bool)
    points, ids = [], []
    for _ in range(max_echoes):
        pos = pos + rng.exponential(1.0 / rate, shots)
        at_wall = alive & (pos >= wall)
        echo = alive & ~at_wall
        for mask, r in ((echo, pos), (at_wall, np.full(shots, wall))):
            points.append(dirs[mask] * r[mask, None])
            ids.append(np.flatnonzero(mask))
        alive &= ~at_wall
        pos = pos + blind
    return np.concatenate(points), np.concatenate(ids).astype(np.int64)


def _pooled_rate(mapper: Mapper, inner: float, outer: float) -> float:
    """sum n / sum s over the voxels wholly inside the medium between ``inner`` and
    ``outer`` metres of the sensor."""
    vox = mapper.voxels()
    half = mapper.resolution * np.sqrt(3.0) / 2.0
    dist = np.linalg.norm(vox.centers, axis=1)
    inside = (dist - half > inner) & (dist + half < outer)
    return float(vox.n[inside].sum() / vox.s[inside].sum())


def test_simulated_medium_all_echoes_recover_the_extinction_independent_rays_do_not() -> None:
    rate, blind, wall = 0.4, 0.75, 10.0
    points, ids = _simulated_shots(rate, blind, 4, wall, 12_000)
    assert np.bincount(np.bincount(ids))[2:].sum() > 5_000  # many shots with several echoes
    seg = shot_segments(points, np.zeros(3), ids, None, blind)
    shots = Mapper(0.5, max_range=100.0)
    shots.integrate(seg.points, seg.origins, 0.0, seg.no_return, continued=seg.continued)
    independent = Mapper(0.5, max_range=100.0)
    independent.integrate(points, np.zeros(3), 0.0)  # each echo a ray from the sensor
    one_process = _pooled_rate(shots, 1.0, wall - 0.5)
    as_rays = _pooled_rate(independent, 1.0, wall - 0.5)
    assert one_process == pytest.approx(rate, rel=0.03)
    assert abs(as_rays / rate - 1.0) > 0.15  # double-counted free space: biased low
    assert as_rays < rate
    no_blind = shot_segments(points, np.zeros(3), ids, None, 0.0)
    unaware = Mapper(0.5, max_range=100.0)
    unaware.integrate(no_blind.points, no_blind.origins, 0.0, continued=no_blind.continued)
    assert _pooled_rate(unaware, 1.0, wall - 0.5) < 0.9 * rate  # the blind stretch counted


def test_a_real_nebula_dual_return_frame_groups_firings_into_shots(shared_data: Path) -> None:
    """Nebula's VLP-16 frame (dual return: types 4, 5, 6, 9, 10): the echoes of a shot lie
    on one beam, its identical returns are removed, its later echoes lie behind."""
    from mfp_mapper.sources.scan_files import read_pcd

    cols = read_pcd(shared_data / "nebula_frames" / "velodyne_vlp16_1673400472138016708.pcd")
    cloud = parse_pointcloud2(cloud_message_from_columns(cols))
    assert cloud.echo_field == "return_type" and cloud.shot is not None
    seg = shot_segments(cloud.xyz, np.zeros(3), cloud.shot, None, 0.75)
    assert seg.dropped["identical_return"] >= 100
    later = np.flatnonzero(seg.continued)
    assert later.size > 1000
    unit = cloud.xyz / np.linalg.norm(cloud.xyz, axis=1, keepdims=True)
    for k in later:  # each later echo's shot: the same beam, the echo before it nearer
        mine = seg.order[seg.shot == seg.shot[k]]
        assert np.all(unit[mine] @ unit[seg.order[k]] > np.cos(np.radians(0.01)))
        assert np.linalg.norm(seg.points[k]) > np.linalg.norm(seg.origins[k]) - 1e-9


def test_identical_blocks_of_a_driver_without_a_return_field_are_removed() -> None:
    """ros-drivers/velodyne, Hesai's driver: the two blocks of a dual-return firing are
    published next to each other, identical when one return was seen."""
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(64, 3)).astype(np.float32) * 5
    ring = np.tile(np.arange(16, dtype=np.uint16), 4)
    second = xyz.copy()
    second[::3] *= 1.5  # a real second return where the beam saw two
    # per firing (16 beams), its first block then its second block
    blocks = [a[16 * f : 16 * f + 16] for f in range(4) for a in (xyz, second)]
    both = np.concatenate(blocks)
    cols = {"x": both[:, 0], "y": both[:, 1], "z": both[:, 2], "ring": np.tile(ring[:16], 8)}
    cloud = parse_pointcloud2(cloud_message_from_columns(cols))
    twice = 64 - len(range(0, 64, 3))
    assert cloud.dropped["identical_return"] == twice
    assert len(cloud) == 128 - twice
    assert cloud.cell is not None and cloud.ring is not None and len(cloud.ring) == len(cloud)


def test_a_livox_multi_return_cloud_is_read_by_tag_line_and_timestamp() -> None:
    """livox_ros_driver2's PointCloud2 (xfer_format 0): x y z intensity tag line timestamp;
    two returns of one firing share line and timestamp, bits 4-5 of tag number them."""
    u = np.array([0.0, 0.8, 0.6])
    xyz = np.array([u * 3.0, u * 5.0, u * 4.0, u * 4.0 + 0.5])
    msg = cloud_message_from_columns(
        {
            "x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
            "z": xyz[:, 2].astype(np.float32), "intensity": np.full(4, 20.0, np.float32),
            "tag": np.array([0x00, 0x10, 0x00, 0x00], np.uint8),
            "line": np.array([2, 2, 3, 2], np.uint8),
            "timestamp": np.array([7e9, 7e9, 7e9, 7.1e9]),
        },
        7.0,
        "livox_frame",
    )  # fmt: skip
    cloud = parse_pointcloud2(msg)
    assert cloud.echo_field == "tag" and cloud.shot is not None
    assert cloud.shot[0] == cloud.shot[1] and len(set(cloud.shot.tolist())) == 3
    seg = shot_segments(cloud.xyz, np.zeros(3), cloud.shot, None, 0.75)
    assert seg.continued.tolist() == [False, True, False, False]
    assert np.allclose(seg.origins[1], u * 3.75, atol=1e-6)
