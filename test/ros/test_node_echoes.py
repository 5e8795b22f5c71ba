"""The node over real DDS takes the drivers' dual-return clouds: Nebula's one cloud with
``return_type`` / ``channel`` / ``azimuth``, and ouster-ros ``points`` + ``points2`` (the
second returns in the same pixel layout, ``second_return_topic``). Every echo of a shot is
integrated as one process along the beam: the saved map holds exactly the expected ``n``
(one per distinct echo) and ``s`` (the chord up to each shot's last echo, less the blind
stretch after each echo)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_helpers import Feeder, NodeProcess, cloud_from_columns, odom_msg, stamp_msg

from mfp_mapper.config.sections import SensorModelSection
from mfp_mapper.mapio.loading import load_map

pytestmark = pytest.mark.ros

T0 = 500.0
BLIND = SensorModelSection().echo_blind_stretch


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("echoes")


@pytest.fixture(scope="module")
def node(ros_domain: int, workdir: Path) -> Iterator[NodeProcess]:
    params = {
        "resolution": 0.25,
        "sensor_model.max_range": 50.0,
        "lidar.translation": [0.0, 0.0, 1.0],
        "second_return_topic": "points2",
        "publish_rate": 0.0,
        "status_period": 0.2,
        "odom_wait": 1.0,
        "map_path": str(workdir / "map.npz"),
    }
    proc = NodeProcess(ros_domain, params, workdir / "node.log")
    try:
        yield proc
    finally:
        proc.stop()


@pytest.fixture(scope="module")
def feeder(node: NodeProcess) -> Iterator[tuple[Feeder, Any]]:
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    f = Feeder()
    second = f.node.create_publisher(
        PointCloud2, "points2", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    )
    try:
        assert f.wait_connected(30.0), f"node not discovered:\n{node.log()[-3000:]}"
        assert f.wait(lambda: second.get_subscription_count() > 0, 20.0)
        assert f.wait(lambda: f.status is not None, 20.0)
        for k in range(60):  # the robot stands still at the origin
            f.odom_pub.publish(odom_msg(T0 - 1.0 + 0.05 * k, np.zeros(3), 0.0))
        yield f, second
    finally:
        f.destroy()


def _saved_totals(f: Feeder, path: Path) -> tuple[float, float]:
    from std_srvs.srv import Trigger

    saved = f.call(f.save, Trigger.Request())
    assert saved.success, saved.message
    voxels = load_map(path).stored_voxels()
    return float(np.sum(voxels.s, dtype=np.float64)), float(np.sum(voxels.n, dtype=np.float64))


def _wait_integrated(f: Feeder, node: NodeProcess, count: int) -> None:
    status = f.wait_status(lambda st: st["clouds_integrated"] >= count, 30.0)
    assert status is not None and status["clouds_integrated"] == count, (
        f"status {status}\n{node.log()[-3000:]}"
    )


def _expected(ranges: list[list[float]]) -> tuple[float, float]:
    """s and n of shots whose distinct echoes are at these ranges (sorted)."""
    s = n = 0.0
    for echoes in ranges:
        s += echoes[0]
        for before, r in zip(echoes, echoes[1:], strict=False):
            s += max(0.0, r - (before + BLIND))
        n += len(echoes)
    return s, n


def test_nebula_dual_return_clouds_and_ouster_points2(
    feeder: tuple[Feeder, Any], node: NodeProcess, workdir: Path
) -> None:
    from std_srvs.srv import Empty

    f, second_pub = feeder
    # Nebula (Autoware) VLP-16 dual-return layout: 8 channels x 25 azimuths; odd azimuths
    # have two returns (first at r, last 2 m further), even ones one return published
    # twice (return_type 6, identical), and one shot with an echo inside the blind stretch
    rows, ranges = [], []
    for c in range(8):
        elevation = np.radians(-7.0 + 2.0 * c)
        for a in range(25):
            azimuth = np.radians(4.0 * a)
            r = 4.0 + 0.1 * c + 0.05 * a
            echoes = [(r, 2), (r + 2.0, 1)] if a % 2 else [(r, 6), (r, 6)]
            if (c, a) == (3, 3):
                echoes.append((r + 0.3, 7))
            for rng, kind in echoes:
                rows.append((rng, kind, c, azimuth, elevation))
            ranges.append(sorted({e[0] for e in echoes}))
    rng_m, kind, channel, azimuth, elevation = (np.array(v) for v in zip(*rows, strict=True))
    direction = np.c_[
        np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
    ]
    xyz = direction * rng_m[:, None]
    nebula = cloud_from_columns(
        {
            "x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
            "z": xyz[:, 2].astype(np.float32), "intensity": np.full(len(xyz), 50, np.uint8),
            "return_type": kind.astype(np.uint8), "channel": channel.astype(np.uint16),
            "azimuth": azimuth.astype(np.float32), "elevation": elevation.astype(np.float32),
            "distance": rng_m.astype(np.float32),
            "time_stamp": np.zeros(len(xyz), np.uint32),
        },
        "lidar",
        T0,
    )  # fmt: skip
    f.cloud_pub.publish(nebula)
    _wait_integrated(f, node, 1)
    s, n = _saved_totals(f, workdir / "map.npz")
    want_s, want_n = _expected(ranges)
    assert n == want_n  # the identical returns counted once, the blind one counted
    assert s == pytest.approx(want_s, rel=1e-5)
    assert n < len(xyz)

    f.call(f.reset, Empty.Request())
    # ouster-ros: points (first returns) and points2 (second returns), 4 x 32 pixels
    height, width = 4, 32
    el = np.radians(np.linspace(-10.0, 10.0, height))[:, None] * np.ones((1, width))
    az = np.radians(np.linspace(0.0, 180.0, width))[None, :] * np.ones((height, 1))
    unit = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    first_r = 5.0 + 0.01 * np.arange(height * width).reshape(height, width)
    first_r[0, :4] = 0.0  # no return
    second_r = np.where((np.arange(width) % 3 == 0)[None, :], first_r + 1.5, 0.0)
    second_r[first_r == 0.0] = 0.0

    def ouster(r: np.ndarray) -> Any:
        p = unit * r[..., None]
        records = np.zeros(
            (height, width),
            dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_pad", "<f4"),
                   ("intensity", "<f4"), ("t", "<u4"), ("reflectivity", "<u2"),
                   ("ring", "<u2"), ("ambient", "<u2"), ("range", "<u4")],
        )  # fmt: skip
        for k, a in enumerate("xyz"):
            records[a] = p[..., k]
        records["ring"] = np.arange(height)[:, None]
        records["range"] = np.round(r * 1000).astype(np.uint32)
        from mfp_mapper.ros.messages import cloud_msg
        from mfp_mapper.sensing.pointcloud import pack_records

        return cloud_msg(pack_records(records), "lidar", stamp_msg(T0 + 0.2))

    f.cloud_pub.publish(ouster(first_r))
    second_pub.publish(ouster(second_r))
    _wait_integrated(f, node, 2)
    s, n = _saved_totals(f, workdir / "map.npz")
    pixels = [
        [first_r[i, j]] + ([second_r[i, j]] if second_r[i, j] > 0 else [])
        for i in range(height)
        for j in range(width)
        if first_r[i, j] > 0
    ]
    want_s, want_n = _expected(pixels)
    assert n == want_n == int((first_r > 0).sum() + (second_r > 0).sum())
    assert s == pytest.approx(want_s, rel=1e-5)
    # the Nebula cloud had no second and was mapped alone; the Ouster pair was paired
    status = f.wait_status(lambda st: st.get("second_return", {}).get("paired") == 1, 10.0)
    assert status is not None
    assert status["second_return"] == {
        "paired": 1, "alone": 1, "unpaired_second": 0, "mismatched": 0,
    }  # fmt: skip
