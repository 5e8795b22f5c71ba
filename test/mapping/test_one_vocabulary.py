"""One drop vocabulary: the same bag, replayed offline and fed to the live worker (no DDS),
gets the same fate per cloud, counted under the same names."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping import loop
from mfp_mapper.mapping.live import LiveIntegrator, LiveSettings
from mfp_mapper.mapping.replay import ReplayOptions, replay
from mfp_mapper.sensing import pipeline
from mfp_mapper.sensing.pointcloud import FieldSpec, point_fields
from mfp_mapper.sensing.poses import PoseBuffer, odometry_sample, rpy_to_quaternion
from mfp_mapper.sources.simulate import VELODYNE_DTYPE, BagSink

RES = 0.25
BAND = (-5.0, 10.0)
T = 100.0
ODOM_SPANS = ((T, T + 2.0), (T + 3.0, T + 4.0))  # a 1 s odometry gap between (max_gap 0.5 s)


def _records(n: int = 40, z: float = 0.5) -> np.ndarray:
    rec = np.zeros(n, dtype=VELODYNE_DTYPE)
    angle = np.linspace(-1.0, 1.0, n)
    rec["x"], rec["y"], rec["z"] = 4.0 * np.cos(angle), 4.0 * np.sin(angle), z
    rec["intensity"], rec["ring"] = 10.0, np.arange(n) % 16
    rec["time"] = np.linspace(0.0, 0.1, n)  # a 0.1 s sweep: de-skewed
    return rec


def _fields(dtype: np.dtype) -> tuple[FieldSpec, ...]:
    return tuple(point_fields(dtype)[0])


def _clouds(sink: BagSink) -> list[tuple[float, Any, str]]:
    """(stamp, message, expected fate) of every cloud of the bag."""
    good = _records()
    holes = _records()
    holes["x"][:5] = np.nan  # 5 NaN points and 3 "no return" zeros, the rest valid
    holes["x"][5:8] = holes["y"][5:8] = holes["z"][5:8] = 0.0
    all_nan = _records(12)
    all_nan["z"] = np.nan
    xy_only = np.zeros(6, dtype=[("x", "<f4"), ("y", "<f4")])
    narrow = np.zeros(6, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    bad_type = tuple(
        FieldSpec(f.name, f.offset, 42 if f.name == "intensity" else f.datatype, f.count)
        for f in _fields(VELODYNE_DTYPE)
    )
    out: list[tuple[float, Any, str]] = []

    def add(t: float, records: np.ndarray, fate: str, fields: Any = None) -> Any:
        msg = sink.pointcloud(T + t, "base_link", records, fields)
        out.append((T + t, msg, fate))
        return msg

    add(0.5, good, "integrated")
    add(0.6, holes, "integrated")
    add(0.7, xy_only, "malformed")  # no field z
    add(0.8, narrow, "malformed", _fields(VELODYNE_DTYPE))  # fields beyond point_step
    truncated = add(0.9, good, "malformed")
    truncated.data = truncated.data[:-7]  # data shorter than width * point_step
    add(1.0, good, "malformed", bad_type)  # datatype 42
    add(1.1, all_nan, "empty")
    add(1.2, _records(z=50.0), "empty")  # every point above the height band
    add(-1.0, good, "too_old")  # before the odometry
    add(2.5, holes, "gap")  # inside the odometry gap
    add(1.95, good, "gap")  # its sweep runs into the gap
    add(9.0, good, "too_new")  # after the odometry
    add(3.5, good, "integrated")
    return out


@pytest.fixture(scope="module")
def mixed_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, int]]:
    bag = tmp_path_factory.mktemp("vocabulary") / "mixed"
    with BagSink(bag, "mcap") as sink:
        sink.add("/odom", "nav_msgs/msg/Odometry")
        sink.add("/cloud", "sensor_msgs/msg/PointCloud2")
        q = rpy_to_quaternion(0.0, 0.0, 0.1)
        for start, stop in ODOM_SPANS:
            for t in np.arange(start, stop + 1e-9, 0.05):
                xyz = np.array([0.5 * (t - T), 0.0, 0.0])
                sink.write("/odom", t, sink.odometry(t, "odom", "base_link", xyz, q, 0.5, 0.0))
        expected: dict[str, int] = {}
        for stamp, msg, fate in _clouds(sink):
            sink.write("/cloud", stamp, msg)
            expected[fate] = expected.get(fate, 0) + 1
    return bag, expected


def _live(bag: Path, opts: ReplayOptions) -> loop.ScanCounts:
    """Every odometry message, then every cloud, through the live worker's thread."""
    with AnyReader([bag]) as reader:
        by_topic: dict[str, list[Any]] = {"/odom": [], "/cloud": []}
        for conn, _, raw in reader.messages():
            by_topic[conn.topic].append(reader.deserialize(raw, conn.msgtype))
    placement = replace(opts.placement, cloud_queue_size=len(by_topic["/cloud"]), odom_wait=0.3)
    settings = LiveSettings(placement)
    worker = LiveIntegrator(
        Mapper(RES),
        settings,
        # keeps every pose, as the replay
        PoseBuffer(max_age=1e6, max_gap=opts.placement.odom_max_gap),
        # the clouds are in the odometry child frame: placed with the identity extrinsic
        log=lambda key, text, error: None,
        now=time.time,
    )
    for msg in by_topic["/odom"]:
        assert worker.add_odometry(odometry_sample(msg))
    worker.start()
    try:
        for msg in by_topic["/cloud"]:
            worker.submit(msg)
        deadline = time.monotonic() + 30.0
        c = worker.counters
        while c.clouds_integrated + c.clouds_dropped.total() < c.clouds_in:
            assert time.monotonic() < deadline, "the live worker did not finish"
            time.sleep(0.02)
    finally:
        worker.stop()
    return worker.snapshot()[0]


def _both(bag: Path) -> tuple[Any, loop.ScanCounts]:
    opts = ReplayOptions.of(
        resolution=RES, odom_max_gap=0.5, point_cloud_min_z=BAND[0], point_cloud_max_z=BAND[1]
    )
    return replay(bag, opts, progress=False).summary, _live(bag, opts)


def _assert_same(summary: Any, live: loop.ScanCounts, expected: dict[str, int]) -> None:
    expected = dict(expected)
    integrated = expected.pop("integrated")
    assert summary.clouds_dropped == expected
    assert summary.scans_used == integrated
    assert dict(live.clouds_dropped) == expected
    assert live.clouds_integrated == integrated
    assert set(expected) <= set(pipeline.DROP_REASONS)
    assert live.points_in == summary.points_in
    assert dict(live.points_dropped) == summary.points_dropped
    assert live.rays_used == summary.rays_used and live.rays_truncated == summary.rays_truncated


def test_replay_and_live_worker_drop_the_same_clouds_for_the_same_reasons(
    mixed_bag: tuple[Path, dict[str, int]],
) -> None:
    bag, expected = mixed_bag
    summary, live = _both(bag)
    _assert_same(summary, live, expected)
    # every point parsing or the band dropped is counted, whatever became of its cloud
    # (5 NaN + 3 zeros in an integrated cloud and again in the gap cloud, 12 NaN, 40 above)
    assert summary.points_dropped == {"nonfinite": 22, "zero_range": 6, "z_band": 40}
    assert summary.rays_used == 3 * 40 - 8


def test_an_unexpected_failure_is_an_error_in_both(
    mixed_bag: tuple[Path, dict[str, int]], monkeypatch: pytest.MonkeyPatch
) -> None:
    bag, expected = mixed_bag
    integrate, merge = loop.integrate_scan, loop.merge_scan  # the replay's, the live one's

    def failing(mapper: Mapper, placed: pipeline.PlacedScan, *lock: Any) -> Any:
        if abs(placed.stamp - (T + 3.5)) < 1e-6:
            raise RuntimeError("a bug in the core")
        return merge(mapper, placed, *lock) if lock else integrate(mapper, placed)

    monkeypatch.setattr(loop, "integrate_scan", failing)
    monkeypatch.setattr(loop, "merge_scan", failing)
    summary, live = _both(bag)
    _assert_same(summary, live, {**expected, "integrated": expected["integrated"] - 1, "error": 1})
