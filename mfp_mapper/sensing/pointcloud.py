"""sensor_msgs/PointCloud2 parsing and packing with numpy only (no sensor_msgs_py).

Messages are duck-typed: anything with ``header.stamp``, ``height``, ``width``, ``fields``
(``name``, ``offset``, ``datatype``, ``count``), ``is_bigendian``, ``point_step``,
``row_step`` and a bytes-like ``data`` works — rclpy messages (``array.array``), rosbags
messages (``numpy.uint8`` array) and plain ``bytes``.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

from mfp_mapper.sensing import echoes

INT8 = 1
UINT8 = 2
INT16 = 3
UINT16 = 4
INT32 = 5
UINT32 = 6
FLOAT32 = 7
FLOAT64 = 8

POINTFIELD_DTYPES: dict[int, str] = {
    INT8: "i1",
    UINT8: "u1",
    INT16: "i2",
    UINT16: "u2",
    INT32: "i4",
    UINT32: "u4",
    FLOAT32: "f4",
    FLOAT64: "f8",
}
"""PointField datatype constant -> numpy type code (without byte order)."""

_DATATYPE_OF = {np.dtype(code): datatype for datatype, code in POINTFIELD_DTYPES.items()}
_NATIVE_ORDER = "<" if sys.byteorder == "little" else ">"

TIME_FIELDS = ("t", "time", "time_stamp", "timestamp")
"""Per-point time fields recognised, in order of preference.

Integer fields hold nanoseconds. Float fields hold seconds, or nanoseconds when their values
cannot be seconds (a spread over one cloud above ``FLOAT_NANOSECONDS_SPREAD`` or a magnitude
above ``FLOAT_NANOSECONDS_MAGNITUDE``: Livox ``timestamp``). The time base is then decided
per cloud (see :func:`time_base`): ``"relative"`` to the header stamp (Velodyne, Ouster),
``"absolute"`` on the header's clock (PTP/GPS-synced Livox, Hesai), or ``"lidar_clock"``: an
unsynced lidar clock (Livox since power-on, Hesai without sync), where only the spacing of the
points is usable and the first point is taken to be at the header stamp.
"""
RING_FIELDS = ("ring", "channel")
"""Beam index fields recognised (Velodyne/Ouster ``ring``, Hesai/Nebula ``channel``)."""
ECHO_FIELDS = ("return_type", "azimuth", "tag", "line", "target_index", "target_count")
"""Fields that tell which points are echoes of one laser shot (``sensing.echoes``): Nebula
``return_type`` with ``channel`` and ``azimuth``; Livox ``tag`` (return number in bits 4-5)
with ``line``; ``target_index`` / ``target_count`` of terrestrial scan exports."""
RELATIVE_LIMIT = 1.0
"""Offsets (s) all within +-this are relative to the header stamp."""
ABSOLUTE_TOLERANCE = 2.0
"""Absolute times within this (s) of the header stamp are on the header's clock."""
FLOAT_NANOSECONDS_SPREAD = 100.0
FLOAT_NANOSECONDS_MAGNITUDE = 1e11
TIME_BASES = ("relative", "absolute", "lidar_clock")

_NS = 1e-9


class CloudFormatError(ValueError):
    """The message does not describe a parsable point cloud."""


class _Field(Protocol):
    name: str
    offset: int
    datatype: int
    count: int


@dataclass(frozen=True)
class FieldSpec:
    """One PointField: ``name`` at byte ``offset`` of each point, ``count`` values."""

    name: str
    offset: int
    datatype: int
    count: int = 1


INTENSITY_FIELDS = ("reflectivity", "intensity")
"""Fields read as a point's return intensity, the first a cloud has (``ParsedCloud.intensity``;
``sensing.reflectivity`` bins them)."""


@dataclass
class ParsedCloud:
    """Valid points of one cloud in the sensor frame.

    ``time_offset`` is in seconds relative to the header stamp; ``dropped`` counts the
    points removed: ``"nonfinite"`` (NaN/Inf coordinate or time), ``"zero_range"``
    (x = y = z = 0, the usual "no return" marker). ``grid_shape``, ``cell`` and ``ring``
    keep where the points were, for the recovery of no-return rays (``sensing.no_return``).
    """

    xyz: NDArray[np.float64]
    time_offset: NDArray[np.float64] | None
    intensity: NDArray[np.float32] | None
    points_in: int
    dropped: dict[str, int] = field(default_factory=dict)
    grid_shape: tuple[int, int] = (1, 0)
    """(height, width) of the message: height > 1 is organized (rows are beams)."""
    cell: NDArray[np.intp] | None = None
    """Flat grid index (row * width + column) of each point; None: point i is cell i."""
    ring: NDArray[np.int64] | None = None
    """Beam index of each point (a ``RING_FIELDS`` field), when the cloud has one."""
    no_return: NDArray[np.bool_] | None = None
    """Points that end recovered rays with no return (None: every point is a return)."""
    time_base: str | None = None
    """One of ``TIME_BASES`` when the cloud has a recognised time field."""
    time_field: str | None = None
    """The per-point time field read (one of ``TIME_FIELDS``), if any."""
    bad_times: int = 0
    """Points with a finite position but a NaN/Inf time (counted in ``nonfinite``)."""
    unknown_time_field: str | None = None
    """A field that looks like per-point time but is not in ``TIME_FIELDS`` (no de-skew)."""
    intensity_field: str | None = None
    """Which field ``intensity`` holds (``sensing.reflectivity.INTENSITY_FIELDS``: Ouster's
    ``reflectivity`` when present, else ``intensity``); None when neither is there."""
    shot: NDArray[np.int64] | None = None
    """Points with equal values are echoes of one laser shot (-1: of a shot whose first
    echo is missing); None: every point is its own shot (``sensing.echoes``)."""
    echo_field: str | None = None
    """The field the shots were read from (``return_type``, ``tag``, ``target_index``, or
    ``second_return`` for two clouds paired by pixel), when ``shot`` is set."""

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass(frozen=True)
class PackedCloud:
    """The layout and bytes of a PointCloud2: what every message type is built from.

    One packer (``pack_records``, ``pack_columns``, ``pack_cloud``) for the node's outputs,
    the bag writers, the scan files and the tests; the message adapters only copy these
    attributes into their own type (rclpy, rosbags, ``sources.scan_files.CloudMessage``).
    """

    fields: list[FieldSpec]
    data: bytes
    point_step: int
    width: int
    height: int = 1
    is_bigendian: bool = False

    @property
    def row_step(self) -> int:
        return self.point_step * self.width

    def layout(self) -> dict[str, Any]:
        """The PointCloud2 attributes besides header, fields, data and is_dense."""
        return {
            "height": self.height,
            "width": self.width,
            "is_bigendian": self.is_bigendian,
            "point_step": self.point_step,
            "row_step": self.row_step,
        }


def stamp_seconds(header_stamp: Any) -> float:
    """Seconds of a ``builtin_interfaces/Time`` (``sec``, ``nanosec``) or of a number."""
    if hasattr(header_stamp, "sec"):
        return float(header_stamp.sec) + float(header_stamp.nanosec) * _NS
    return float(header_stamp)


def parse_pointcloud2(msg: Any, header_stamp: float | None = None) -> ParsedCloud:
    """Parse a PointCloud2 message into finite, non-zero-range points.

    ``header_stamp`` (seconds) makes absolute per-point times relative; it defaults to
    ``msg.header.stamp``. ``time_base`` says how the time field was read (see
    ``TIME_FIELDS``). Raises CloudFormatError when the layout is inconsistent.
    """
    records = _checked_records(msg)
    xyz = _xyz(records)
    time_offset, base = _time_offset(records, msg, header_stamp)
    names = records.dtype.names or ()
    intensity_name = next((n for n in INTENSITY_FIELDS if n in names), None)
    intensity = (
        None if intensity_name is None else records[intensity_name].reshape(-1).astype(np.float32)
    )
    ring_name = next((n for n in RING_FIELDS if n in names), None)
    ring = None if ring_name is None else records[ring_name].reshape(-1).astype(np.int64)
    cloud = _drop_invalid(xyz, time_offset, intensity, ring)
    cloud.grid_shape = (int(records.shape[0]), int(records.shape[1]))
    cloud.intensity_field = intensity_name
    cloud.time_base = base
    if time_offset is not None:
        cloud.time_field = next(n for n in TIME_FIELDS if n in names)
    cloud.unknown_time_field = unknown_time_field([str(f.name) for f in msg.fields])
    _read_shots(cloud, records)
    return cloud


def _drop_identical(cloud: ParsedCloud) -> None:
    """Remove the points equal to the one before them on their beam
    (``echoes.identical_points``: a dual-return driver without a return field), counted as
    ``identical_return``."""
    assert cloud.ring is not None
    twice = echoes.identical_points(cloud.xyz, cloud.ring)
    if twice.size == 0:
        return
    keep = np.ones(len(cloud), dtype=np.bool_)
    keep[twice] = False
    cells = np.arange(len(cloud)) if cloud.cell is None else cloud.cell
    cloud.xyz = cloud.xyz[keep]
    for name in ("time_offset", "intensity", "ring", "no_return"):
        values = getattr(cloud, name)
        if values is not None:
            setattr(cloud, name, values[keep])
    cloud.cell = cells[keep]
    cloud.dropped = {**cloud.dropped, "identical_return": int(twice.size)}


def _read_shots(cloud: ParsedCloud, records: NDArray[np.void]) -> None:
    """Set ``cloud.shot`` from the echo fields of the kept points (``ECHO_FIELDS``)."""
    names = records.dtype.names or ()
    if len(cloud) == 0:
        return
    if not any(n in names for n in ECHO_FIELDS):
        if cloud.ring is not None and records.shape[0] == 1:
            _drop_identical(cloud)
        return

    def column(name: str) -> NDArray[Any] | None:
        if name not in names:
            return None
        values = records[name].reshape(-1)
        return values if cloud.cell is None else values[cloud.cell]

    if "target_index" in names and "target_count" in names:
        index, count = column("target_index"), column("target_count")
        assert index is not None and count is not None
        cloud.shot, cloud.echo_field = echoes.target_shots(cloud.xyz, index, count), "target_index"
    elif "return_type" in names and "azimuth" in names and "channel" in names:
        channel, azimuth = column("channel"), column("azimuth")
        assert channel is not None and azimuth is not None
        cloud.shot, cloud.echo_field = echoes.nebula_shots(channel, azimuth), "return_type"
    elif "tag" in names:
        tag = column("tag")
        assert tag is not None
        time_name = next((n for n in TIME_FIELDS if n in names), None)
        shot = echoes.livox_shots(
            tag, column("line"), None if time_name is None else column(time_name)
        )
        if shot is not None:
            cloud.shot, cloud.echo_field = shot, "tag"


def read_xyz(msg: Any) -> NDArray[np.float64]:
    """Every point of the message as (N, 3) float64, in order, NaN and zeros kept.

    Same layout checks as :func:`parse_pointcloud2` (for query clouds answered point by point).
    """
    return _xyz(_checked_records(msg))


def _checked_records(msg: Any) -> NDArray[np.void]:
    fields: dict[str, _Field] = {}
    for f in msg.fields:
        fields.setdefault(f.name, f)
    _check_fields(fields, int(msg.point_step))
    return _records(msg, fields)


def _xyz(records: NDArray[np.void]) -> NDArray[np.float64]:
    xyz = np.empty((records.size, 3), dtype=np.float64)
    for axis, name in enumerate("xyz"):
        xyz[:, axis] = records[name].reshape(-1)
    return xyz


def _check_fields(fields: Mapping[str, _Field], point_step: int) -> None:
    missing = [name for name in "xyz" if name not in fields]
    if missing:
        raise CloudFormatError(
            f"point cloud has no field {', '.join(missing)}: expected x, y and z "
            f"(fields present: {', '.join(fields) or 'none'})"
        )
    for f in fields.values():
        if f.datatype not in POINTFIELD_DTYPES:
            raise CloudFormatError(
                f"field {f.name!r} has unknown datatype {f.datatype}: expected 1 (INT8) "
                "to 8 (FLOAT64)"
            )
        end = f.offset + np.dtype(POINTFIELD_DTYPES[f.datatype]).itemsize * max(f.count, 1)
        if end > point_step:
            raise CloudFormatError(
                f"field {f.name!r} ends at byte {end} but point_step is {point_step}: "
                "every field must fit inside one point"
            )
    for name in ("x", "y", "z", *INTENSITY_FIELDS, *TIME_FIELDS, *RING_FIELDS, *ECHO_FIELDS):
        if name in fields and fields[name].count > 1:
            raise CloudFormatError(f"field {name!r} has count {fields[name].count}: expected 1")


def _records(msg: Any, fields: Mapping[str, _Field]) -> NDArray[np.void]:
    """Zero-copy (height, width) structured view of the fields this module uses."""
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    if row_step < width * point_step:
        raise CloudFormatError(
            f"row_step {row_step} is smaller than width * point_step = {width * point_step}"
        )
    raw = _as_uint8(msg.data)
    if raw.size < height * row_step:
        raise CloudFormatError(
            f"data holds {raw.size} bytes but height * row_step = {height * row_step} "
            f"(height {height}, row_step {row_step}) were expected"
        )
    order = ">" if msg.is_bigendian else "<"
    used = [
        name
        for name in ("x", "y", "z", *INTENSITY_FIELDS, *TIME_FIELDS, *RING_FIELDS, *ECHO_FIELDS)
        if name in fields
    ]
    dtype = np.dtype(
        {
            "names": used,
            "formats": [order + POINTFIELD_DTYPES[fields[n].datatype] for n in used],
            "offsets": [fields[n].offset for n in used],
            "itemsize": point_step,
        }
    )
    if height * width == 0:
        return np.empty((height, width), dtype=dtype)
    return np.ndarray((height, width), dtype=dtype, buffer=raw, strides=(row_step, point_step))


def _as_uint8(data: Any) -> NDArray[np.uint8]:
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:  # a sequence of ints
        return np.asarray(data, dtype=np.uint8)


def _time_offset(
    records: NDArray[np.void], msg: Any, header_stamp: float | None
) -> tuple[NDArray[np.float64] | None, str | None]:
    names = records.dtype.names or ()
    name = next((n for n in TIME_FIELDS if n in names), None)
    if name is None:
        return None, None
    stamp = stamp_seconds(msg.header.stamp) if header_stamp is None else header_stamp
    return time_base(records[name].reshape(-1), stamp)


def unknown_time_field(names: Sequence[str]) -> str | None:
    """The first field that looks like per-point time when none of ``TIME_FIELDS`` is there."""
    if any(n in TIME_FIELDS for n in names):
        return None
    looks_like_time = ("time", "stamp")
    return next((n for n in names if any(w in n.lower() for w in looks_like_time)), None)


def time_base(column: NDArray[Any], stamp: float) -> tuple[NDArray[np.float64], str]:
    """Per-point offsets (s) from the header ``stamp`` and the time base they were read in."""
    values = column.astype(np.float64)
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return values, "relative"
    lo, hi = float(finite.min()), float(finite.max())
    if column.dtype.kind in "iu":
        scale = _NS
    else:
        is_ns = (
            hi - lo > FLOAT_NANOSECONDS_SPREAD
            or max(abs(lo), abs(hi)) > FLOAT_NANOSECONDS_MAGNITUDE
        )
        scale = _NS if is_ns else 1.0
    # Offsets from the first point (exact in the field's unit), then that point's offset.
    from_first = (values - lo) * scale
    first_s, last_s = lo * scale, hi * scale
    if first_s >= -RELATIVE_LIMIT and last_s <= RELATIVE_LIMIT:
        return values * scale, "relative"
    if first_s - ABSOLUTE_TOLERANCE <= stamp <= last_s + ABSOLUTE_TOLERANCE:
        # Subtract in the field's unit so that epoch nanoseconds keep their precision.
        return from_first + (lo - stamp / scale) * scale, "absolute"
    return from_first, "lidar_clock"


def _drop_invalid(
    xyz: NDArray[np.float64],
    time_offset: NDArray[np.float64] | None,
    intensity: NDArray[np.float32] | None,
    ring: NDArray[np.int64] | None = None,
) -> ParsedCloud:
    finite = _finite_rows(xyz)
    bad_times = 0
    if time_offset is not None:
        finite_time = np.isfinite(time_offset)
        bad_times = int(np.count_nonzero(finite & ~finite_time))
        finite &= finite_time
    zero = (xyz[:, 0] == 0.0) & (xyz[:, 1] == 0.0) & (xyz[:, 2] == 0.0)
    keep = finite & ~zero
    points_in = int(xyz.shape[0])
    n_finite = int(np.count_nonzero(finite))
    dropped = {"nonfinite": points_in - n_finite, "zero_range": n_finite - int(keep.sum())}
    if dropped["nonfinite"] == 0 and dropped["zero_range"] == 0:  # (so no bad time either)
        return ParsedCloud(xyz, time_offset, intensity, points_in, dropped, ring=ring)
    return ParsedCloud(
        xyz[keep],
        None if time_offset is None else time_offset[keep],
        None if intensity is None else intensity[keep],
        points_in,
        dropped,
        cell=np.flatnonzero(keep),
        ring=None if ring is None else ring[keep],
        bad_times=bad_times,
    )


def _finite_rows(xyz: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Rows of ``xyz`` (N, 3) whose three coordinates are finite (column by column: numpy's
    ``all(axis=1)`` over three values is several times slower)."""
    finite = np.isfinite(xyz[:, 0])
    finite &= np.isfinite(xyz[:, 1])
    finite &= np.isfinite(xyz[:, 2])
    return finite


def pack_records(records: NDArray[Any]) -> PackedCloud:
    """A cloud holding structured ``records`` ((N,) or (height, width)) byte for byte.

    The dtype's field offsets, itemsize and byte order become the layout, so any driver
    layout (padding, big-endian, float64, organized clouds) can be reproduced with numpy.
    """
    if records.ndim not in (1, 2) or not records.dtype.names:
        raise ValueError("a cloud needs a 1-D or 2-D structured array")
    height, width = (1, records.shape[0]) if records.ndim == 1 else records.shape
    fields, big_endian = point_fields(records.dtype)
    data = np.ascontiguousarray(records).tobytes()
    return PackedCloud(fields, data, records.dtype.itemsize, int(width), int(height), big_endian)


def pack_columns(
    columns: Mapping[str, ArrayLike], dtype: DTypeLike | None = None, big_endian: bool = False
) -> PackedCloud:
    """Equal-length columns packed in order, each in ``dtype`` or else its own dtype; a 2-D
    column (N, COUNT) becomes one field of COUNT values (PCD frames)."""
    if not columns:
        raise ValueError("a cloud needs at least one column")
    arrays = {name: np.asarray(values, dtype=dtype) for name, values in columns.items()}
    lengths = {name: a.shape[0] if a.ndim else None for name, a in arrays.items()}
    if len(set(lengths.values())) != 1 or None in lengths.values():
        raise ValueError(f"columns must be of equal length, got {lengths}")
    order: Literal["<", ">"] = ">" if big_endian else "<"
    layout = np.dtype([(n, a.dtype.newbyteorder(order), a.shape[1:]) for n, a in arrays.items()])
    records = np.empty(len(next(iter(arrays.values()))), dtype=layout)
    for name, values in arrays.items():
        records[name] = values
    return pack_records(records)


def pack_cloud(columns: Mapping[str, Any]) -> PackedCloud:
    """Equal-length 1-D columns as consecutive little-endian float32 fields (map outputs)."""
    if not columns:
        raise ValueError("pack_cloud needs at least one column")
    shapes = {name: np.shape(values) for name, values in columns.items()}
    width = next(iter(shapes.values()))
    if any(len(shape) != 1 or shape != width for shape in shapes.values()):
        raise ValueError(f"pack_cloud columns must be 1-D and of equal length, got {shapes}")
    return pack_columns(columns, "<f4")


def point_fields(dtype: np.dtype[np.void]) -> tuple[list[FieldSpec], bool]:
    """The PointField list of a numpy record type (offsets as laid out), and whether it is
    big endian. Raises ValueError for types PointCloud2 cannot hold."""
    fields, orders = [], set()
    for name in dtype.names or ():
        subtype, offset = dtype.fields[name][:2]  # type: ignore[index]
        base = subtype.base
        datatype = _DATATYPE_OF.get(np.dtype(f"{base.kind}{base.itemsize}"))
        if datatype is None:
            raise ValueError(f"field {name!r} of dtype {base} has no PointField datatype")
        fields.append(FieldSpec(name, offset, datatype, max(int(np.prod(subtype.shape)), 1)))
        if base.itemsize > 1:
            orders.add(base.byteorder if base.byteorder != "=" else _NATIVE_ORDER)
    if len(orders) > 1:
        raise ValueError(f"fields mix byte orders {sorted(orders)}: PointCloud2 has one")
    return fields, orders == {">"}
