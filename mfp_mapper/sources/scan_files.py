"""Readers for scan files (PCD binary/ascii, PLY, KITTI ``.bin``, legacy ASCII VTK) and a
PointCloud2-like message builder, so that every file goes through the same parser
(``sensing.pointcloud``) as a recorded PointCloud2.

Each reader returns the file's columns by name (``x``, ``y``, ``z`` and whatever else it
holds, e.g. a per-point ``time_stamp``), so that per-point time reaches the de-skew.

Which reader: PLY goes through ``plyfile`` (every PLY variant; as fast as our former reader
on the 1.05 M-point ``tls_conifers`` scan). The PCD and VTK readers are ours, for a reason:
the well-kept PCD reader, Open3D, is a 400 MB dependency whose legacy reader keeps
positions, colours and normals only (a driver's ``time_stamp``, ``ring`` or ``t`` columns
would be lost, and with them the de-skew and the no-return recovery); a PCD body is one
``numpy.frombuffer`` over the header's record layout, which is what the reader does after
checking the header (``POINTS``, ``WIDTH`` x ``HEIGHT``, sizes, truncation). The legacy VTK
reader takes the ``POINTS`` section of ASCII POLYDATA only (the norlab files): ``vtk`` or
``meshio`` would add a dependency for 30 lines. KITTI ``.bin`` is raw float32 records."""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.sensing.pointcloud import FieldSpec, PackedCloud, pack_columns, pack_records

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8"} | {
    (kind, size): f"{kind.lower()}{size}" for kind in "IU" for size in (1, 2, 4, 8)
}
_SCAN_NAME = re.compile(r"cloud_(\d+)_(\d+)\.vtk$")


class DatasetFormatError(ValueError):
    """A data file is malformed or uses an unsupported variant."""


@dataclass
class Time:
    sec: int = 0
    nanosec: int = 0


@dataclass
class Header:
    stamp: Time = field(default_factory=Time)
    frame_id: str = "sensor"


@dataclass
class CloudMessage:
    """The PointCloud2 attributes :func:`mfp_mapper.sensing.pointcloud.parse_pointcloud2` reads."""

    header: Header
    height: int
    width: int
    fields: list[FieldSpec]
    is_bigendian: bool
    point_step: int
    row_step: int
    data: bytes
    is_dense: bool = False


def read_pcd(path: str | Path) -> dict[str, NDArray[np.generic]]:
    """Columns of a PCD file (``DATA binary`` or ``ascii``), in header order.

    Fields with COUNT > 1 give (N, COUNT) columns; PCL padding fields named ``_`` are
    skipped.
    """
    path = Path(path)
    header, body = _split_pcd_header(path.read_bytes(), path)
    dtype = _pcd_dtype(header, path)
    points = _pcd_int(header, "POINTS", path)
    if points < 0:
        raise DatasetFormatError(f"{path}: PCD header says POINTS {points}, a negative count")
    if "WIDTH" in header and "HEIGHT" in header:
        width, height = _pcd_int(header, "WIDTH", path), _pcd_int(header, "HEIGHT", path)
        if width < 0 or height < 0 or width * height != points:
            raise DatasetFormatError(
                f"{path}: PCD header says WIDTH {width} x HEIGHT {height} but POINTS {points}"
            )
    encoding = header["DATA"][0].lower() if header["DATA"] else ""
    if encoding == "binary":
        if len(body) < points * dtype.itemsize:
            raise DatasetFormatError(
                f"{path}: truncated, {len(body)} bytes of data for {points} points of "
                f"{dtype.itemsize} bytes ({points * dtype.itemsize} expected)"
            )
        records = np.frombuffer(body, dtype=dtype, count=points)
    elif encoding == "ascii":
        records = _pcd_ascii_records(body, dtype, points, path)
    else:
        raise DatasetFormatError(f"{path}: DATA {encoding!r} is not supported (binary or ascii)")
    return {name: records[name].copy() for name in dtype.names or () if not name.startswith("_")}


def _split_pcd_header(raw: bytes, path: Path) -> tuple[dict[str, list[str]], bytes]:
    header: dict[str, list[str]] = {}
    position = 0
    while position < len(raw):
        end = raw.find(b"\n", position)
        end = len(raw) if end < 0 else end
        line = raw[position:end].decode("ascii", errors="replace").strip()
        position = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, raw[position:]
    raise DatasetFormatError(f"{path}: not a PCD file (no DATA line in the header)")


def _pcd_dtype(header: Mapping[str, list[str]], path: Path) -> np.dtype[np.void]:
    """Packed little-endian record dtype; padding fields ``_`` become ``_<index>``."""
    for key in ("FIELDS", "SIZE", "TYPE"):
        if key not in header:
            raise DatasetFormatError(f"{path}: PCD header has no {key} line")
    names, sizes, kinds = header["FIELDS"], header["SIZE"], header["TYPE"]
    counts = header.get("COUNT", ["1"] * len(names))
    if not len(names) == len(sizes) == len(kinds) == len(counts):
        raise DatasetFormatError(
            f"{path}: FIELDS, SIZE, TYPE and COUNT need one entry per field, got "
            f"{len(names)}, {len(sizes)}, {len(kinds)}, {len(counts)}"
        )
    formats: list[str | tuple[str, tuple[int]]] = []
    for name, size, kind, count in zip(names, sizes, kinds, counts, strict=True):
        code = _PCD_TYPES.get((kind.upper(), int(size))) if size.isdigit() else None
        if code is None or not count.isdigit() or int(count) < 1:
            raise DatasetFormatError(
                f"{path}: field {name!r} has unsupported TYPE {kind} SIZE {size} COUNT {count}"
            )
        formats.append(("<" + code, (int(count),)) if int(count) > 1 else "<" + code)
    unique = [f"_{i}" if name == "_" else name for i, name in enumerate(names)]
    return np.dtype({"names": unique, "formats": formats})


def _pcd_int(header: Mapping[str, list[str]], key: str, path: Path) -> int:
    try:
        return int(header[key][0])
    except (KeyError, IndexError, ValueError):
        raise DatasetFormatError(f"{path}: PCD header needs an integer {key} line") from None


def _pcd_ascii_records(
    body: bytes, dtype: np.dtype[np.void], points: int, path: Path
) -> NDArray[np.void]:
    names = dtype.names or ()
    widths = [int(np.prod(dtype[name].shape)) for name in names]
    try:
        values = np.array(body.split(), dtype=np.float64)
    except ValueError as error:
        raise DatasetFormatError(f"{path}: non-numeric ascii data ({error})") from None
    if values.size != points * sum(widths):
        raise DatasetFormatError(
            f"{path}: {values.size} ascii values, expected {points} points x {sum(widths)}"
        )
    flat = values.reshape(points, sum(widths))
    records = np.empty(points, dtype=dtype)
    starts = np.cumsum([0, *widths])
    for name, start, width in zip(names, starts, widths, strict=False):
        records[name] = flat[:, start : start + width].reshape(records[name].shape)
    return records


def read_vtk_points(path: str | Path) -> NDArray[np.float64]:
    """The (N, 3) ``POINTS`` of an ASCII legacy VTK POLYDATA file."""
    path = Path(path)
    lines = path.read_text(encoding="ascii", errors="replace").splitlines()
    if len(lines) < 5 or not lines[0].startswith("# vtk DataFile"):
        raise DatasetFormatError(f"{path}: not a legacy VTK file (no '# vtk DataFile' line)")
    if lines[2].strip().upper() != "ASCII":
        raise DatasetFormatError(f"{path}: only ASCII VTK is supported, file says {lines[2]!r}")
    if lines[3].split()[1:2] != ["POLYDATA"]:
        raise DatasetFormatError(f"{path}: expected DATASET POLYDATA, got {lines[3]!r}")
    row = next((i for i, line in enumerate(lines) if line.startswith("POINTS")), None)
    if row is None:
        raise DatasetFormatError(f"{path}: no POINTS section")
    try:
        count = int(lines[row].split()[1])
    except (IndexError, ValueError):
        raise DatasetFormatError(f"{path}: bad POINTS line {lines[row]!r}") from None
    tokens: list[str] = []
    for line in lines[row + 1 :]:
        if len(tokens) >= 3 * count:
            break
        tokens.extend(line.split())
    try:
        values = np.array(tokens[: 3 * count], dtype=np.float64)
    except ValueError as error:
        raise DatasetFormatError(f"{path}: non-numeric POINTS data ({error})") from None
    if values.size != 3 * count:
        raise DatasetFormatError(f"{path}: POINTS {count} but only {values.size} values")
    return values.reshape(count, 3)


def read_vtk(path: str | Path) -> dict[str, NDArray[np.generic]]:
    """``x``, ``y``, ``z`` columns of an ASCII legacy VTK POLYDATA file."""
    xyz = read_vtk_points(path)
    return {"x": xyz[:, 0].copy(), "y": xyz[:, 1].copy(), "z": xyz[:, 2].copy()}


def read_kitti_bin(path: str | Path) -> dict[str, NDArray[np.generic]]:
    """A KITTI velodyne scan: float32 ``x y z intensity`` records, little-endian."""
    path = Path(path)
    raw = np.fromfile(path, dtype="<f4")
    if raw.size % 4:
        raise DatasetFormatError(
            f"{path}: {raw.size * 4} bytes is not a whole number of 16-byte x y z intensity "
            "records (KITTI .bin)"
        )
    records = raw.reshape(-1, 4)
    return {name: records[:, k].copy() for k, name in enumerate(("x", "y", "z", "intensity"))}


def read_ply(path: str | Path) -> dict[str, NDArray[np.generic]]:
    """Columns of the ``vertex`` element of a PLY file, native byte order.

    Read with ``plyfile`` (every PLY variant: ascii, binary little- and big-endian, other
    elements before or after the vertices). On the 1,046,843-point binary scan of
    ``tls_conifers`` recording it reads as fast as the hand-written reader it replaced
    (0.015-0.12 s each, interleaved, within the noise). List properties on the vertex
    element are refused.
    """
    from plyfile import PlyData  # type: ignore[import-untyped]

    path = Path(path)
    try:
        with path.open("rb") as stream:
            data = PlyData.read(stream)
        vertex = data["vertex"].data
    except KeyError:
        raise DatasetFormatError(f"{path}: no vertex element") from None
    except OSError:
        raise
    except Exception as err:  # plyfile's PlyParseError, numpy's errors on short data...
        text = " ".join(str(err).split()) or type(err).__name__
        raise DatasetFormatError(f"{path}: not a readable PLY file ({text})") from None
    names = vertex.dtype.names or ()
    lists = [n for n in names if vertex.dtype[n].kind == "O"]
    if lists:
        raise DatasetFormatError(f"{path}: list properties on the vertex element: {lists}")
    if not names:
        raise DatasetFormatError(f"{path}: no vertex element with properties")
    return {n: vertex[n].astype(vertex.dtype[n].newbyteorder("=")) for n in names}


def list_vtk_scans(directory: str | Path) -> list[tuple[float, Path]]:
    """``(stamp seconds, path)`` of every ``cloud_<sec>_<nanosec>.vtk``, in time order.

    The nanoseconds are not zero-padded, so sorting by file name would be wrong.
    """
    scans = []
    for path in Path(directory).glob("cloud_*.vtk"):
        match = _SCAN_NAME.search(path.name)
        if match:
            scans.append((int(match[1]) + int(match[2]) * 1e-9, path))
    return sorted(scans)


def cloud_message(
    records: NDArray[Any], stamp: float = 0.0, frame_id: str = "sensor"
) -> CloudMessage:
    """A PointCloud2-like message holding structured ``records`` ((N,) or (height, width))
    byte for byte (``sensing.pointcloud.pack_records``)."""
    return packed_cloud_message(pack_records(records), stamp, frame_id)


def cloud_message_from_columns(
    columns: Mapping[str, NDArray[np.generic]], stamp: float = 0.0, frame_id: str = "sensor"
) -> CloudMessage:
    """A message with ``columns`` packed in order, keeping their dtypes (e.g. a PCD frame)."""
    return packed_cloud_message(pack_columns(columns), stamp, frame_id)


def packed_cloud_message(packed: PackedCloud, stamp: float, frame_id: str) -> CloudMessage:
    """A message of an already packed cloud (``sensing.pointcloud.PackedCloud``), stamped
    ``stamp`` seconds, in ``frame_id``."""
    sec = int(np.floor(stamp))
    header = Header(Time(sec, round((stamp - sec) * 1e9)), frame_id)
    return CloudMessage(header=header, fields=packed.fields, data=packed.data, **packed.layout())
