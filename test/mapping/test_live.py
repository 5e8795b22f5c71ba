"""The live worker without ROS: queue, waiting for odometry, drops and counters."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from live_helpers import drain, odom_sample

from mfp_mapper.config.sections import PlacementSection, SensorModelSection
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.live import LiveIntegrator, LiveSettings
from mfp_mapper.sensing.poses import PoseBuffer
from mfp_mapper.sources.scan_files import cloud_message_from_columns

T0 = 500.0


def _settings(**changes: Any) -> LiveSettings:
    """The placement section with a short queue and wait, and the fields given; a sensor
    model only when one of its fields is given."""
    sensor = {k: changes.pop(k) for k in ("no_return_range",) if k in changes}
    placement = PlacementSection(**{"cloud_queue_size": 3, "odom_wait": 0.2, **changes})
    return LiveSettings(placement, SensorModelSection(**sensor) if sensor else None)


def _worker(**changes: Any) -> tuple[LiveIntegrator, list[tuple[str, str, bool]]]:
    logs: list[tuple[str, str, bool]] = []
    worker = LiveIntegrator(
        Mapper(0.2),
        _settings(**changes),
        PoseBuffer(max_age=10.0, max_gap=0.5),
        log=lambda key, text, error: logs.append((key, text, error)),
        now=lambda: T0 + 1.0,
    )
    return worker, logs


def _cloud(stamp: float, n: int = 30, frame: str = "base_link") -> Any:
    xyz = np.random.default_rng(0).uniform(1.0, 4.0, (n, 3)).astype(np.float32)
    return cloud_message_from_columns({a: xyz[:, k] for k, a in enumerate("xyz")}, stamp, frame)


def test_queue_keeps_the_newest_clouds() -> None:
    worker, logs = _worker(cloud_queue_size=2)
    for k in range(5):
        worker.submit(_cloud(T0 + k))
    assert worker.queued == 2
    assert worker.counters.clouds_in == 5 and worker.counters.clouds_dropped == {"queue_full": 3}
    assert [item.msg.header.stamp.sec for item in worker._queue] == [503, 504]
    assert any("queue_full" in key for key, _, _ in logs)


def test_waits_for_odometry_then_integrates() -> None:
    worker, _ = _worker(odom_wait=5.0)
    worker.add_odometry(odom_sample(T0 - 0.1))
    worker.submit(_cloud(T0))
    item = worker._queue.popleft()
    assert worker.process(item) is False  # odometry does not cover it yet: wait
    worker.add_odometry(odom_sample(T0 + 0.1))
    assert worker.process(item) is True
    c = worker.counters
    assert c.clouds_integrated == 1 and c.rays_used == 30 and not c.clouds_dropped
    assert worker.mapper.num_voxels > 0 and worker.map_frame == "odom"


def test_drops_after_odom_wait_with_the_reason() -> None:
    worker, logs = _worker(odom_wait=0.05)
    worker.submit(_cloud(T0))
    drain(worker)
    worker.add_odometry(odom_sample(T0 - 1.0))
    worker.submit(_cloud(T0))
    drain(worker)
    assert worker.counters.clouds_dropped == {"no_poses": 1, "too_new": 1}
    assert worker.counters.clouds_integrated == 0
    texts = [text for _, text, _ in logs]
    assert any("dropped cloud (no_poses)" in t for t in texts)
    assert any("dropped cloud (too_new)" in t for t in texts)


def test_malformed_cloud_is_counted_and_logged_as_an_error() -> None:
    worker, logs = _worker()
    worker.add_odometry(odom_sample(T0))
    worker.submit(cloud_message_from_columns({"x": np.ones(3, np.float32)}, T0))
    drain(worker)
    assert worker.counters.clouds_dropped == {"malformed": 1}
    assert any(error and "malformed" in text for _, text, error in logs)


def test_odometry_frame_change_and_order_are_rejected() -> None:
    worker, _ = _worker()
    assert worker.add_odometry(odom_sample(T0)) and not worker.add_odometry(
        odom_sample(T0 + 1, "other")
    )
    assert not worker.add_odometry(odom_sample(T0))  # not newer
    assert worker.counters.odom_rejected == {"frame": 1, "out_of_order_or_invalid": 1}


def test_worker_thread_integrates_and_publishes_between_scans() -> None:
    published: list[int] = []
    worker, _ = _worker(odom_wait=2.0)
    worker.set_publish(lambda: published.append(worker.mapper.version))
    worker.start()
    try:
        worker.add_odometry(odom_sample(T0 - 0.2))
        for k in range(3):
            worker.submit(_cloud(T0 + 0.1 * k))
        worker.add_odometry(odom_sample(T0 + 0.25))
        deadline = time.monotonic() + 20.0
        while worker.counters.clouds_integrated < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        worker.request_publish()
        while not published and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        worker.stop()
    assert worker.counters.clouds_integrated == 3
    assert published == [worker.mapper.version]


def _organized_cloud(stamp: float) -> Any:
    """A 4 x 90 organized cloud (4 beams, 4 deg steps) with NaN in every third cell."""
    elevation = np.radians([-3.0, -1.0, 1.0, 3.0])[:, None]
    azimuth = np.radians(np.arange(90) * 4.0)[None, :]
    xyz = 5.0 * np.stack(
        np.broadcast_arrays(
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ),
        axis=-1,
    )
    xyz.reshape(-1, 3)[::3] = np.nan
    records = np.zeros((4, 90), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    for k, axis in enumerate("xyz"):
        records[axis] = xyz[..., k]
    from mfp_mapper.sources.scan_files import cloud_message

    return cloud_message(records, stamp, "base_link")


def test_no_return_rays_are_recovered_and_counted_when_enabled() -> None:
    for no_return_range, expected in ((0.0, 0), (8.0, 120)):
        worker, logs = _worker(no_return_range=no_return_range)
        worker.add_odometry(odom_sample(T0 - 0.1))
        worker.add_odometry(odom_sample(T0 + 0.1))
        worker.submit(_organized_cloud(T0))
        drain(worker)
        c = worker.counters
        assert c.clouds_integrated == 1 and c.rays_no_return == expected
        assert c.rays_used == 240 + expected and c.points_dropped["nonfinite"] == 120
        assert not any(key == "no_return" for key, _, _ in logs)


def test_a_cloud_without_pattern_says_why_once() -> None:
    worker, logs = _worker(no_return_range=8.0)
    for k in range(5):
        worker.add_odometry(odom_sample(T0 - 0.1 + 0.3 * k))
    for k in range(3):
        worker.submit(_cloud(T0 + 0.5 * k))
    drain(worker)
    assert worker.counters.clouds_integrated == 3 and worker.counters.rays_no_return == 0
    notes = [text for key, text, _ in logs if key == "no_return"]
    assert len(notes) == 1 and "ring" in notes[0]
    assert "ring" in worker.counters.no_return_note


def test_an_unplaceable_cloud_does_not_block_those_behind_it() -> None:
    """A cloud its poses will never cover waits apart: the placeable clouds behind it are
    integrated at once, none is lost to the queue, and the waiting one is dropped after
    odom_wait (the worker thread, as in the node)."""
    worker, _ = _worker(cloud_queue_size=3, odom_wait=1.0)
    for k in range(12):
        worker.add_odometry(odom_sample(T0 - 0.1 + 0.1 * k))
    worker.start()
    try:
        worker.submit(_cloud(T0 + 5.0))  # never covered (and not far enough ahead to refuse)
        for k in range(8):
            worker.submit(_cloud(T0 + 0.1 * k))
            deadline = time.monotonic() + 5.0
            while worker.counters.clouds_integrated < k + 1 and time.monotonic() < deadline:
                time.sleep(0.005)
        integrated_before_drop = worker.counters.clouds_integrated
        deadline = time.monotonic() + 5.0
        while worker.queued and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        worker.stop()
    c = worker.counters
    assert integrated_before_drop == 8 and c.clouds_integrated == 8
    assert c.clouds_dropped == {"too_new": 1}
    worker.submit(_cloud(T0 + 100.0))  # 99 s ahead of the clock: refused at once
    worker.drain(timeout=0.05)
    assert c.clouds_dropped == {"too_new": 1, "ahead_of_clock": 1}


def test_a_full_queue_drops_the_waiting_cloud_first() -> None:
    worker, _ = _worker(cloud_queue_size=2, odom_wait=5.0)
    worker.add_odometry(odom_sample(T0 - 0.1))
    worker.submit(_cloud(T0 + 5.0))
    worker.drain(timeout=0.05)  # tried once: it waits
    worker.submit(_cloud(T0 + 6.0))
    worker.submit(_cloud(T0 - 0.05))  # full: the waiting one goes, not this one
    assert worker.counters.clouds_dropped == {"queue_full": 1} and worker.queued == 2
    worker.add_odometry(odom_sample(T0 + 0.1))
    worker.drain(timeout=0.2)
    assert worker.counters.clouds_integrated == 1


def test_empty_and_slashed_cloud_frames() -> None:
    worker, logs = _worker()
    worker.add_odometry(odom_sample(T0 - 0.1))
    worker.add_odometry(odom_sample(T0 + 0.1))
    worker.submit(_cloud(T0, frame=""))
    worker.submit(_cloud(T0, frame="/base_link"))
    worker.submit(_cloud(T0 + 0.05, frame="/base_link"))
    drain(worker)
    assert worker.counters.clouds_dropped == {"no_frame": 1}
    assert worker.counters.clouds_integrated == 2
    assert sum("leading slash" in text for _, text, _ in logs) == 1
    told, _ = _worker(cloud_frame_id="base_link")
    told.add_odometry(odom_sample(T0 - 0.1))
    told.add_odometry(odom_sample(T0 + 0.1))
    told.submit(_cloud(T0, frame=""))
    drain(told)
    assert told.counters.clouds_integrated == 1


def test_the_map_frame_is_decided_once() -> None:
    """frame_id "": the odometry frame at the first cloud; odometry in another frame later
    is refused, and the map frame, the Mapper's frame and ~/status never change."""
    infos: list[str] = []
    worker = LiveIntegrator(
        Mapper(0.2),
        _settings(),
        PoseBuffer(max_age=10.0, max_gap=0.5),
        log=lambda key, text, error: None,
        info=infos.append,
        now=lambda: T0 + 1.0,
    )
    assert worker.map_frame == ""
    worker.add_odometry(odom_sample(T0 - 0.1))
    worker.add_odometry(odom_sample(T0 + 0.1))
    worker.submit(_cloud(T0))
    drain(worker)
    assert worker.map_frame == "odom" == worker.mapper.frame_id
    assert not worker.add_odometry(odom_sample(T0 + 0.2, frame="map"))
    assert worker.map_frame == "odom" == worker.mapper.frame_id
    assert any("map frame 'odom'" in line for line in infos)
    assert worker.pose_inputs.describe()["map_frame"] == "odom"


def test_the_two_threads_map_what_the_offline_loop_maps() -> None:
    """Worker (parse, place) and walker (stage, merge) in their threads, clouds arriving
    while earlier ones integrate: the map is the offline loop's of the same clouds (the
    staged merge sums each scan first: s and n equal to float32 rounding)."""
    from mfp_mapper.mapping.loop import ScanLoop
    from mfp_mapper.sensing.poses import Extrinsic, OdometrySample

    rng = np.random.default_rng(3)
    clouds = []
    for k in range(8):
        xyz = rng.uniform(-6.0, 6.0, (2000, 3)).astype(np.float32)
        cols = {a: xyz[:, i] for i, a in enumerate("xyz")}
        cols["t"] = np.linspace(0, 0.09e9, len(xyz)).astype(np.uint32)
        clouds.append(cloud_message_from_columns(cols, T0 + 0.1 * k, "base_link"))
    stamps = T0 - 0.1 + 0.02 * np.arange(50)
    samples = [
        OdometrySample(float(t), "odom", "base_link", np.array([0.5 * (t - T0), 0.1, 0.0]),
                       np.array([0.0, 0.0, np.sin(0.1 * (t - T0)), np.cos(0.1 * (t - T0))]))
        for t in stamps
    ]  # fmt: skip
    worker, _ = _worker(cloud_queue_size=len(clouds), odom_wait=5.0)
    worker.start()
    try:
        for sample in samples:
            worker.add_odometry(sample)
        for msg in clouds:
            worker.submit(msg)
        deadline = time.monotonic() + 30.0
        while worker.counters.clouds_integrated < len(clouds) and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        worker.stop()
    assert worker.counters.clouds_integrated == len(clouds), worker.counters
    assert worker.counters.stage_seconds["walk"] > 0.0

    poses = PoseBuffer(max_age=10.0, max_gap=0.5)
    for sample in samples:
        poses.add(sample.stamp, sample.position, sample.quaternion)
    offline = Mapper(0.2)
    settings = _settings()
    loop = ScanLoop(offline, settings.placement, SensorModelSection())
    for msg in clouds:
        assert loop.map_cloud(msg, poses, lambda frame: Extrinsic()).integrated
    live, ref = worker.mapper.voxels(), offline.voxels()
    assert np.array_equal(live.ijk, ref.ijk)
    np.testing.assert_allclose(live.s, ref.s, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(live.n, ref.n, rtol=1e-5, atol=1e-6)


def _spied_worker() -> tuple[LiveIntegrator, list[tuple[str, tuple]]]:
    """A worker whose Mapper records every ``integrate`` and ``stage`` call (the path each
    scan took and its inputs)."""
    worker, _ = _worker(odom_wait=5.0, cloud_queue_size=10)
    mapper, calls = worker.mapper, []
    for name in ("integrate", "stage"):
        real = getattr(mapper, name)

        def spy(*args: Any, _name: str = name, _real: Any = real, **kw: Any) -> Any:
            calls.append((_name, args))
            return _real(*args, **kw)

        setattr(mapper, name, spy)
    return worker, calls


def _scans(worker: LiveIntegrator, count: int) -> None:
    for t in np.arange(T0 - 0.1, T0 + 0.1 * count + 0.3, 0.1):
        worker.add_odometry(odom_sample(float(t)))
    for k in range(count):
        xyz = np.random.default_rng(k).uniform(-6.0, 6.0, (400, 3)).astype(np.float32)
        cols = {a: xyz[:, i] for i, a in enumerate("xyz")}
        worker.submit(cloud_message_from_columns(cols, T0 + 0.1 * k, "base_link"))
    drain(worker)
    assert worker.counters.clouds_integrated == count


def test_quick_scans_integrate_straight_into_the_map_bit_for_bit() -> None:
    """The first scan (no time per ray known yet) is staged and merged, the next ones,
    expected well within ``DIRECT_MAX_S``, go through ``Mapper.integrate``: the map is bit
    for bit that of the same calls on a Mapper of its own."""
    worker, calls = _spied_worker()
    _scans(worker, 4)
    assert [name for name, _ in calls] == ["stage", "integrate", "integrate", "integrate"]
    reference = Mapper(0.2)
    for _, args in calls:
        reference.integrate(*args)
    got, want = worker.mapper.stored_voxels(), reference.stored_voxels()
    for field in ("ijk", "s", "n", "t_last"):
        assert np.array_equal(getattr(got, field), getattr(want, field)), field


def test_scans_expected_to_hold_the_map_long_are_staged(monkeypatch: Any) -> None:
    """With ``DIRECT_MAX_S`` 0 every scan is staged and merged (readers wait for merges
    only): the map is bit for bit that of ``stage`` + ``commit`` of the same scans."""
    import mfp_mapper.mapping.live as live

    monkeypatch.setattr(live, "DIRECT_MAX_S", 0.0)
    worker, calls = _spied_worker()
    _scans(worker, 3)
    assert [name for name, _ in calls] == ["stage"] * 3
    reference = Mapper(0.2)
    for _, args in calls:
        reference.commit(reference.stage(*args))
    got, want = worker.mapper.stored_voxels(), reference.stored_voxels()
    for field in ("ijk", "s", "n", "t_last"):
        assert np.array_equal(getattr(got, field), getattr(want, field)), field


def test_rays_cut_by_the_scan_block_bound_are_counted(monkeypatch: Any) -> None:
    """A scan that would add more blocks than its bound walks its later rays part of their
    way: the counters (``~/status`` ``rays_cut_by_budget``, the replay's summary) say how
    many, where before nothing did."""
    from mfp_mapper.core import memory_bound

    monkeypatch.setattr(memory_bound, "SCAN_NEW_BLOCKS", 20)
    direction = np.random.default_rng(1).normal(size=(200, 3))
    xyz = (40.0 * direction / np.linalg.norm(direction, axis=1, keepdims=True)).astype(np.float32)
    cloud = cloud_message_from_columns({a: xyz[:, k] for k, a in enumerate("xyz")}, T0, "base_link")
    for threads in (1, 2):
        worker = LiveIntegrator(
            Mapper(0.2, threads=threads), _settings(), PoseBuffer(max_age=10.0, max_gap=0.5),
            log=lambda key, text, error: None, now=lambda: T0 + 1.0,
        )  # fmt: skip
        worker.add_odometry(odom_sample(T0 - 0.1))
        worker.add_odometry(odom_sample(T0 + 0.1))
        worker.submit(cloud)
        drain(worker)
        c = worker.counters
        assert c.clouds_integrated == 1 and 0 < c.rays_cut_by_budget <= c.rays_used == 200
        worker.mapper.close()
