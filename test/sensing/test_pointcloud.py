"""PointCloud2 parsing: real driver layouts, endianness, organized clouds, malformed input."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from mfp_mapper.sensing import pointcloud as pc
from mfp_mapper.sensing.pointcloud import (
    CloudFormatError,
    FieldSpec,
    ParsedCloud,
    parse_pointcloud2,
)
from mfp_mapper.sources.scan_files import (
    CloudMessage,
    cloud_message,
    cloud_message_from_columns,
    read_pcd,
)

STAMP = 1_700_000_000.25


def nebula_frames(shared_data: Path) -> list[Path]:
    return sorted((shared_data / "nebula_frames").glob("*.pcd"))


def random_xyz(n: int, seed: int = 0) -> NDArray[np.float64]:
    return np.random.default_rng(seed).uniform(-50.0, 50.0, size=(n, 3))


def velodyne_records(n: int, point_step: int) -> NDArray[np.void]:
    """velodyne_pointcloud layout: packed (22 bytes, ROS 2 driver) or PCL-aligned (32)."""
    offsets = [0, 4, 8, 12, 16, 18] if point_step == 22 else [0, 4, 8, 16, 20, 24]
    dtype = np.dtype(
        {
            "names": ["x", "y", "z", "intensity", "ring", "time"],
            "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
            "offsets": offsets,
            "itemsize": point_step,
        }
    )
    records = np.zeros(n, dtype=dtype)
    for axis, name in enumerate("xyz"):
        records[name] = random_xyz(n)[:, axis]
    records["intensity"] = np.arange(n) % 256
    records["ring"] = np.arange(n) % 16
    records["time"] = np.linspace(-0.1, 0.0, n)  # relative to the stamp at the scan end
    return records


def ouster_records(height: int, width: int) -> NDArray[np.void]:
    """ouster-ros PointOS: x y z (pad) intensity t reflectivity ring ambient range, 48 bytes."""
    dtype = np.dtype(
        {
            "names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
            "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2", "<u2", "<u4"],
            "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32],
            "itemsize": 48,
        }
    )
    records = np.zeros((height, width), dtype=dtype)
    xyz = random_xyz(height * width).reshape(height, width, 3)
    for axis, name in enumerate("xyz"):
        records[name] = xyz[..., axis]
    records["intensity"] = 7.0
    records["t"] = np.arange(width) * 48_828  # ns: one column every 48.8 us (10 Hz, 2048)
    records["ring"] = np.arange(height)[:, None]
    return records


def offsets(cloud: ParsedCloud) -> NDArray[np.float64]:
    assert cloud.time_offset is not None
    return cloud.time_offset


def expected_columns(records: NDArray[np.void]) -> NDArray[np.float64]:
    flat = records.reshape(-1)
    return np.stack([flat[name].astype(np.float64) for name in "xyz"], axis=1)


# --- real field layouts ------------------------------------------------------------------


def test_every_nebula_frame_parses_with_its_real_layout(shared_data: Path) -> None:
    frames = nebula_frames(shared_data)
    assert len(frames) == 12
    for path in frames:
        columns = read_pcd(path)
        msg = cloud_message_from_columns(columns, stamp=STAMP)
        cloud = parse_pointcloud2(msg)
        xyz = np.stack([columns[a].astype(np.float64) for a in "xyz"], axis=1)
        valid = np.isfinite(xyz).all(axis=1) & np.any(xyz != 0.0, axis=1)
        assert cloud.points_in == len(columns["x"]) > 10_000, path.name
        assert len(cloud) + sum(cloud.dropped.values()) == cloud.points_in
        np.testing.assert_array_equal(cloud.xyz, xyz[valid])
        assert np.isfinite(cloud.xyz).all()
        assert np.all(np.linalg.norm(cloud.xyz, axis=1) > 0.0)
        if "time_stamp" in columns:
            assert cloud.time_offset is not None, path.name
            expected = columns["time_stamp"][valid] * 1e-9
            np.testing.assert_allclose(cloud.time_offset, expected, rtol=1e-12)
            assert cloud.time_offset.min() >= 0.0 and cloud.time_offset.max() < 0.2
            assert cloud.intensity is not None and cloud.intensity.dtype == np.float32
        else:
            assert cloud.time_offset is None and cloud.intensity is None, path.name


def test_nebula_layout_is_the_autoware_point_type(shared_data: Path) -> None:
    path = next(p for p in nebula_frames(shared_data) if "time_stamp" in read_pcd(p))
    msg = cloud_message_from_columns(read_pcd(path))
    layout = [(f.name, f.offset, f.datatype) for f in msg.fields]
    assert layout == [
        ("x", 0, pc.FLOAT32),
        ("y", 4, pc.FLOAT32),
        ("z", 8, pc.FLOAT32),
        ("intensity", 12, pc.UINT8),
        ("return_type", 13, pc.UINT8),
        ("channel", 14, pc.UINT16),
        ("azimuth", 16, pc.FLOAT32),
        ("elevation", 20, pc.FLOAT32),
        ("distance", 24, pc.FLOAT32),
        ("time_stamp", 28, pc.UINT32),
    ]
    assert msg.point_step == 32


@pytest.mark.parametrize("point_step", [22, 32])
def test_velodyne_layout(point_step: int) -> None:
    records = velodyne_records(1000, point_step)
    cloud = parse_pointcloud2(cloud_message(records, STAMP))
    assert cloud.points_in == 1000 and cloud.dropped == {"nonfinite": 0, "zero_range": 0}
    np.testing.assert_array_equal(cloud.xyz, expected_columns(records))
    assert cloud.time_offset is not None and cloud.intensity is not None
    np.testing.assert_array_equal(cloud.time_offset, records["time"].astype(np.float64))
    np.testing.assert_array_equal(cloud.intensity, records["intensity"])


def test_ouster_layout_organized_with_no_return_zeros() -> None:
    records = ouster_records(16, 64)
    records[3, 5]["x"], records[3, 5]["y"], records[3, 5]["z"] = 0.0, 0.0, 0.0
    records[7, :10]["x"] = 0.0
    records[7, :10]["y"] = 0.0
    records[7, :10]["z"] = 0.0
    msg = cloud_message(records, STAMP)
    assert (msg.height, msg.width, msg.point_step) == (16, 64, 48)
    cloud = parse_pointcloud2(msg)
    assert cloud.points_in == 16 * 64
    assert cloud.dropped == {"nonfinite": 0, "zero_range": 11}
    keep = np.ones((16, 64), dtype=bool)
    keep[3, 5] = False
    keep[7, :10] = False
    np.testing.assert_array_equal(cloud.xyz, expected_columns(records[keep]))
    assert cloud.time_offset is not None
    np.testing.assert_allclose(cloud.time_offset, records["t"][keep] * 1e-9, rtol=1e-12)


def test_organized_cloud_with_nans_and_row_padding() -> None:
    records = velodyne_records(4 * 50, 32).reshape(4, 50)
    records["x"][0, 0] = np.nan
    records["z"][2, 7] = np.inf
    records["time"][3, 1] = np.nan
    row_padding = 12
    rows = [row.tobytes() + b"\xaa" * row_padding for row in records]
    msg = dataclasses.replace(
        cloud_message(records, STAMP), data=b"".join(rows), row_step=50 * 32 + row_padding
    )
    cloud = parse_pointcloud2(msg)
    assert cloud.points_in == 200
    assert cloud.dropped == {"nonfinite": 3, "zero_range": 0}
    keep = np.isfinite(expected_columns(records)).all(axis=1)
    keep &= np.isfinite(records["time"].reshape(-1))
    np.testing.assert_array_equal(cloud.xyz, expected_columns(records)[keep])
    assert cloud.intensity is not None
    assert len(offsets(cloud)) == len(cloud.intensity) == 197


def test_big_endian_and_float64_coordinates() -> None:
    xyz = random_xyz(500)
    dtype = np.dtype([("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("intensity", ">f4"), ("t", ">u4")])
    records = np.zeros(500, dtype=dtype)
    for axis, name in enumerate("xyz"):
        records[name] = xyz[:, axis]
    records["intensity"] = np.arange(500)
    records["t"] = np.arange(500) * 1000
    msg = cloud_message(records, STAMP)
    assert msg.is_bigendian and msg.fields[0].datatype == pc.FLOAT64
    cloud = parse_pointcloud2(msg)
    np.testing.assert_array_equal(cloud.xyz, xyz)
    np.testing.assert_array_equal(cloud.intensity, np.arange(500, dtype=np.float32))
    np.testing.assert_allclose(offsets(cloud), np.arange(500) * 1e-6)


@settings(max_examples=60, deadline=None)
@given(
    order=st.permutations(["x", "y", "z", "intensity", "time", "ring"]),
    gaps=st.lists(st.integers(0, 5), min_size=6, max_size=6),
    tail=st.integers(0, 9),
    coord_type=st.sampled_from(["f4", "f8"]),
    endian=st.sampled_from("<>"),
)
def test_any_field_order_padding_and_type(
    order: list[str], gaps: list[int], tail: int, coord_type: str, endian: str
) -> None:
    types = {"x": coord_type, "y": coord_type, "z": coord_type}
    types |= {"intensity": "u1", "time": "f4", "ring": "u2"}
    offsets, position = [], 0
    for name, gap in zip(order, gaps, strict=True):
        position += gap
        offsets.append(position)
        position += np.dtype(types[name]).itemsize
    dtype = np.dtype(
        {
            "names": order,
            "formats": [endian + types[name] for name in order],
            "offsets": offsets,
            "itemsize": position + tail,
        }
    )
    records = np.zeros(64, dtype=dtype)
    xyz = random_xyz(64, seed=len(order) + tail)
    for axis, name in enumerate("xyz"):
        records[name] = xyz[:, axis]
    records["intensity"] = np.arange(64)
    records["time"] = np.linspace(0.0, 0.1, 64)
    cloud = parse_pointcloud2(cloud_message(records, STAMP))
    np.testing.assert_array_equal(cloud.xyz, xyz.astype(coord_type))
    np.testing.assert_array_equal(cloud.intensity, np.arange(64, dtype=np.float32))
    np.testing.assert_array_equal(cloud.time_offset, records["time"].astype(np.float64))


# --- per-point time conventions -----------------------------------------------------------


def time_cloud(name: str, values: NDArray[np.generic]) -> CloudMessage:
    records = np.zeros(
        len(values), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), (name, values.dtype)]
    )
    records["x"] = 1.0
    records[name] = values
    return cloud_message(records, STAMP)


def test_time_field_conventions() -> None:
    rel = np.array([0.0, 0.025, 0.05])
    cases = {
        "time": rel.astype(np.float32),  # Velodyne: float32 seconds
        "t": (rel * 1e9).astype(np.uint32),  # Ouster: uint32 ns
        "time_stamp": (rel * 1e9).astype(np.uint32),  # Nebula: uint32 ns
        "timestamp": rel,  # Hesai relative float64 seconds
    }
    for name, values in cases.items():
        cloud = parse_pointcloud2(time_cloud(name, values))
        np.testing.assert_allclose(offsets(cloud), rel, atol=1e-8, err_msg=name)


def test_absolute_timestamps_become_relative_to_the_header_stamp() -> None:
    rel = np.array([-0.1, 0.0, 0.05])
    msg = time_cloud("timestamp", STAMP + rel)
    np.testing.assert_allclose(offsets(parse_pointcloud2(msg)), rel, atol=1e-6)
    given_stamp = offsets(parse_pointcloud2(msg, header_stamp=STAMP - 1.0))
    np.testing.assert_allclose(given_stamp, rel + 1.0, atol=1e-6)
    nanoseconds = time_cloud("timestamp", (STAMP + rel) * 1e9)  # Livox-style absolute ns
    np.testing.assert_allclose(offsets(parse_pointcloud2(nanoseconds)), rel, atol=1e-6)


def test_time_base_of_each_driver_layout() -> None:
    """Relative, absolute on the header clock, or an unsynced lidar clock, per driver."""
    rel = np.array([0.0, 0.031, 0.0625, 0.1])
    power_on = 5123.25  # seconds since the lidar powered on (no PTP/GPS sync)
    cases = {
        # name: (field, values, expected offsets, expected base)
        "velodyne": ("time", (rel - 0.1).astype(np.float32), rel - 0.1, "relative"),
        "ouster": ("t", (rel * 1e9).astype(np.uint32), rel, "relative"),
        "livox_ptp": ("timestamp", (STAMP + rel) * 1e9, rel, "absolute"),
        "livox_power_on": ("timestamp", (power_on + rel) * 1e9, rel, "lidar_clock"),
        "hesai_synced": ("timestamp", STAMP + rel, rel, "absolute"),
        "hesai_lidar_clock": ("timestamp", power_on + rel, rel, "lidar_clock"),
        "hesai_small_clock": ("timestamp", 3.5 + rel, rel, "lidar_clock"),
    }
    for label, (name, values, expected, base) in cases.items():
        cloud = parse_pointcloud2(time_cloud(name, values))
        assert cloud.time_base == base, label
        np.testing.assert_allclose(offsets(cloud), expected, atol=1e-6, err_msg=label)
        # Never "far in the future": every offset is within one scan of the stamp.
        assert np.abs(offsets(cloud)).max() <= 0.1 + 1e-6, label


def test_livox_nanoseconds_since_power_on_are_not_read_as_seconds() -> None:
    """A young lidar's nanosecond clock (below any epoch) is still nanoseconds."""
    values = np.array([2.0e9, 2.05e9, 2.1e9])  # 2 s after power-on, float64 ns
    cloud = parse_pointcloud2(time_cloud("timestamp", values))
    assert cloud.time_base == "lidar_clock"
    np.testing.assert_allclose(offsets(cloud), [0.0, 0.05, 0.1], atol=1e-9)


def test_unknown_time_field_is_reported_and_known_one_is_not() -> None:
    unknown = parse_pointcloud2(time_cloud("offset_time", np.array([0, 1000], dtype=np.uint32)))
    assert unknown.time_offset is None and unknown.time_base is None
    assert unknown.unknown_time_field == "offset_time"
    known = parse_pointcloud2(time_cloud("t", np.array([0, 1000], dtype=np.uint32)))
    assert known.unknown_time_field is None and known.time_base == "relative"
    plain = parse_pointcloud2(time_cloud("intensity", np.array([1.0, 2.0])))
    assert plain.unknown_time_field is None and plain.time_offset is None


def test_first_time_field_in_preference_order_wins() -> None:
    records = np.zeros(
        2, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("time", "<f4"), ("t", "<u4")]
    )
    records["x"] = 1.0
    records["time"] = 5.0
    records["t"] = 1000
    np.testing.assert_allclose(offsets(parse_pointcloud2(cloud_message(records))), 1e-6)


def test_stamp_seconds() -> None:
    assert pc.stamp_seconds(cloud_message(velodyne_records(1, 22), STAMP).header.stamp) == STAMP
    assert pc.stamp_seconds(12.5) == 12.5


# --- malformed messages --------------------------------------------------------------------


def valid_message() -> CloudMessage:
    return cloud_message(velodyne_records(10, 22), STAMP)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            lambda m: dataclasses.replace(m, fields=[f for f in m.fields if f.name != "z"]),
            r"no field z: expected x, y and z \(fields present: x, y, intensity, ring, time\)",
        ),
        (
            lambda m: dataclasses.replace(m, point_step=20, row_step=200),
            r"field 'time' ends at byte 22 but point_step is 20",
        ),
        (
            lambda m: dataclasses.replace(m, data=m.data[:-1]),
            r"data holds 219 bytes but height \* row_step = 220",
        ),
        (
            lambda m: dataclasses.replace(
                m, fields=[*m.fields[:4], FieldSpec("ring", 16, 9), m.fields[5]]
            ),
            r"field 'ring' has unknown datatype 9: expected 1 \(INT8\) to 8 \(FLOAT64\)",
        ),
        (
            lambda m: dataclasses.replace(m, row_step=100),
            r"row_step 100 is smaller than width \* point_step = 220",
        ),
        (
            lambda m: dataclasses.replace(
                m, fields=[FieldSpec("x", 0, pc.FLOAT32, 2), *m.fields[1:]]
            ),
            r"field 'x' has count 2: expected 1",
        ),
    ],
    ids=[
        "missing_z",
        "point_step_too_small",
        "data_short",
        "unknown_datatype",
        "row_step",
        "count",
    ],
)
def test_malformed_messages_raise(
    change: Callable[[CloudMessage], CloudMessage], message: str
) -> None:
    with pytest.raises(CloudFormatError, match=message):
        parse_pointcloud2(change(valid_message()))


def test_cloud_format_error_is_a_value_error() -> None:
    assert issubclass(CloudFormatError, ValueError)


def test_empty_cloud() -> None:
    msg = dataclasses.replace(valid_message(), width=0, row_step=0, data=b"")
    cloud = parse_pointcloud2(msg)
    assert cloud.points_in == 0 and cloud.xyz.shape == (0, 3)


def test_read_xyz_keeps_every_point_in_order() -> None:
    records = velodyne_records(6, 22)
    records["x"][1] = np.nan
    records["x"][2] = records["y"][2] = records["z"][2] = 0.0
    np.testing.assert_array_equal(pc.read_xyz(cloud_message(records)), expected_columns(records))


# --- real message classes ----------------------------------------------------------------


def test_rclpy_message() -> None:
    msg_module = pytest.importorskip("sensor_msgs.msg", reason="ROS 2 sensor_msgs not installed")
    records = ouster_records(8, 32)
    source = cloud_message(records, STAMP)
    from mfp_mapper.ros.messages import cloud_msg

    stamp = msg_module.PointCloud2().header.stamp
    stamp.sec, stamp.nanosec = source.header.stamp.sec, 250_000_000
    msg = cloud_msg(pc.pack_records(records), "lidar", stamp)
    cloud = parse_pointcloud2(msg)
    np.testing.assert_array_equal(cloud.xyz, expected_columns(records))
    assert pc.stamp_seconds(msg.header.stamp) == STAMP


def test_rosbags_message_after_cdr_round_trip(shared_data: Path) -> None:
    typesys = pytest.importorskip("rosbags.typesys", reason="rosbags not installed")
    store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    types = store.types
    path = next(p for p in nebula_frames(shared_data) if "time_stamp" in read_pcd(p))
    source = cloud_message_from_columns(read_pcd(path), stamp=STAMP)
    packed = pc.pack_columns(read_pcd(path))
    msg = types["sensor_msgs/msg/PointCloud2"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](
                sec=source.header.stamp.sec, nanosec=250_000_000
            ),
            frame_id="lidar",
        ),
        fields=[
            types["sensor_msgs/msg/PointField"](
                name=f.name, offset=f.offset, datatype=f.datatype, count=f.count
            )
            for f in packed.fields
        ],
        data=np.frombuffer(packed.data, dtype=np.uint8),
        is_dense=True,
        **packed.layout(),
    )
    raw = store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")
    decoded = store.deserialize_cdr(raw, "sensor_msgs/msg/PointCloud2")
    assert isinstance(decoded.data, np.ndarray)
    cloud = parse_pointcloud2(decoded)
    assert cloud.xyz.shape == parse_pointcloud2(source).xyz.shape
    np.testing.assert_array_equal(cloud.xyz, parse_pointcloud2(source).xyz)
    assert cloud.time_offset is not None


# --- packing -------------------------------------------------------------------------------


def test_pack_cloud_round_trip() -> None:
    xyz = random_xyz(100).astype(np.float32)
    packed = pc.pack_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "doo": np.ones(100)})
    assert packed.point_step == 16 and packed.width == 100 and packed.row_step == 1600
    assert [(f.name, f.offset, f.datatype, f.count) for f in packed.fields][3] == ("doo", 12, 7, 1)
    assert len(packed.data) == 1600
    header = cloud_message(velodyne_records(1, 22)).header
    msg = CloudMessage(header=header, fields=packed.fields, data=packed.data, **packed.layout())
    np.testing.assert_array_equal(parse_pointcloud2(msg).xyz, xyz)


def test_pack_cloud_rejects_bad_columns() -> None:
    with pytest.raises(ValueError, match="at least one column"):
        pc.pack_cloud({})
    with pytest.raises(ValueError, match="1-D and of equal length"):
        pc.pack_cloud({"x": np.zeros(3), "y": np.zeros(4)})
    with pytest.raises(ValueError, match="1-D and of equal length"):
        pc.pack_cloud({"x": np.zeros((3, 2))})


def test_datatype_constants() -> None:
    assert (pc.INT8, pc.UINT8, pc.INT16, pc.UINT16) == (1, 2, 3, 4)
    assert (pc.INT32, pc.UINT32, pc.FLOAT32, pc.FLOAT64) == (5, 6, 7, 8)


# --- speed ---------------------------------------------------------------------------------


def test_parsing_131k_points_takes_milliseconds() -> None:
    msg = cloud_message(ouster_records(128, 1024), STAMP)
    durations = []
    for _ in range(5):
        start = time.perf_counter()
        cloud = parse_pointcloud2(msg)
        durations.append(time.perf_counter() - start)
    assert len(cloud) == 131_072
    assert min(durations) < 0.05, f"best of 5 parses took {min(durations) * 1e3:.1f} ms"
