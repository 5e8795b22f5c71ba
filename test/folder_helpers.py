"""Writing a simulated bag's clouds and poses as a scan folder (test helper)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mfp_mapper.sensing.pointcloud import stamp_seconds
from mfp_mapper.sources.bags import open_reader


def bag_contents(bag: Path) -> tuple[list[tuple[float, np.ndarray]], np.ndarray]:
    """The clouds ((stamp, structured records)) and odometry rows (t x y z qx qy qz qw)."""
    reader = open_reader(bag)
    clouds: list[tuple[float, np.ndarray]] = []
    odometry = []
    try:
        for conn, _, raw in reader.messages():
            msg: Any = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == "sensor_msgs/msg/PointCloud2":
                dtype = np.dtype(
                    {
                        "names": [f.name for f in msg.fields],
                        "formats": [
                            {7: "<f4", 4: "<u2", 8: "<f8", 2: "u1"}[f.datatype] for f in msg.fields
                        ],
                        "offsets": [f.offset for f in msg.fields],
                        "itemsize": msg.point_step,
                    }
                )
                records = np.frombuffer(bytes(msg.data), dtype=dtype)
                clouds.append((stamp_seconds(msg.header.stamp), records))
            elif conn.msgtype == "nav_msgs/msg/Odometry":
                p, o = msg.pose.pose.position, msg.pose.pose.orientation
                odometry.append(
                    [stamp_seconds(msg.header.stamp), p.x, p.y, p.z, o.x, o.y, o.z, o.w]
                )
    finally:
        reader.close()
    return clouds, np.array(odometry)


def write_pcd(path: Path, columns: dict[str, np.ndarray], binary: bool = True) -> None:
    names = list(columns)
    arrays = [np.asarray(columns[n]) for n in names]
    types = ["F" if a.dtype.kind == "f" else ("U" if a.dtype.kind == "u" else "I") for a in arrays]
    header = (
        "# .PCD v0.7\nVERSION 0.7\n"
        f"FIELDS {' '.join(names)}\nSIZE {' '.join(str(a.dtype.itemsize) for a in arrays)}\n"
        f"TYPE {' '.join(types)}\nCOUNT {' '.join('1' for _ in names)}\n"
        f"WIDTH {len(arrays[0])}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(arrays[0])}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    )
    _write_records(path, header, names, arrays, binary)


def write_ply(path: Path, columns: dict[str, np.ndarray], binary: bool = True) -> None:
    names = list(columns)
    types = {"f4": "float", "f8": "double", "u2": "ushort", "u1": "uchar", "i4": "int"}
    arrays = [np.asarray(columns[n]) for n in names]
    header = (
        f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\ncomment test\n"
        f"element vertex {len(arrays[0])}\n"
        + "".join(
            f"property {types[a.dtype.str[1:]]} {n}\n" for n, a in zip(names, arrays, strict=True)
        )
        + "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    )
    _write_records(path, header, names, arrays, binary)


def _write_records(
    path: Path, header: str, names: list[str], arrays: list[np.ndarray], binary: bool
) -> None:
    """The header, then the columns as little-endian records or ASCII rows."""
    dtype = np.dtype([(n, a.dtype.newbyteorder("<")) for n, a in zip(names, arrays, strict=True)])
    records = np.empty(len(arrays[0]), dtype=dtype)
    for n, a in zip(names, arrays, strict=True):
        records[n] = a
    if binary:
        path.write_bytes(header.encode() + records.tobytes())
    else:
        rows = "\n".join(" ".join(repr(v.item()) for v in row) for row in records)
        path.write_text(header + rows + "\n")
