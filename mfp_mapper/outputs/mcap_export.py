"""A map as a ROS 2 bag in mcap storage, for Foxglove or ``ros2 bag play``.

One message per topic, stamped with the map's last update, in the map frame; the topics
and fields are the node's (``ros/map_outputs.py``):

- ``/mfp_mapper/degree_of_occupancy`` (sensor_msgs/PointCloud2): voxel centres ``x y z``
  and ``degree_of_occupancy`` (most likely), voxels with DoO >= ``min_doo`` and evidence
  s >= ``min_evidence``;
- ``/mfp_mapper/std`` (PointCloud2): ``x y z std`` of the same voxels;
- ``/mfp_mapper/projected_map`` (nav_msgs/OccupancyGrid): the height band projected like
  the node's projected map: round(100 x hit probability), -1 unknown.

Written with rosbags into a temporary directory renamed into place, so a failed export
leaves no partial bag.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.sensing.pointcloud import PackedCloud, pack_cloud

DOO_TOPIC = "/mfp_mapper/degree_of_occupancy"
STD_TOPIC = "/mfp_mapper/std"
GRID_TOPIC = "/mfp_mapper/projected_map"


def export_mcap(
    mapper: Mapper,
    out_dir: str | Path,
    z_min: float,
    z_max: float,
    min_doo: float = 0.0,
    min_evidence: float = 0.0,
) -> dict[str, int]:
    """Write the bag directory ``out_dir`` (must not exist); returns points/cells per topic."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    out = Path(out_dir)
    if out.exists():
        raise FileExistsError(f"{out} exists: a bag is written into a new directory")
    store = get_typestore(Stores.ROS2_JAZZY)
    stats = mapper.voxels(min_doo=min_doo, min_evidence=min_evidence)
    grid = mapper.hit_probability_grid(z_min, z_max)
    stamp = mapper.last_stamp if mapper.last_stamp is not None else 0.0
    frame = mapper.frame_id or "map"
    xyz = {axis: stats.centers[:, k] for k, axis in enumerate("xyz")}
    doo = pack_cloud({**xyz, "degree_of_occupancy": stats.most_likely_doo})
    std = pack_cloud({**xyz, "std": stats.std})
    header = _header(store, stamp, frame)
    messages: list[tuple[str, str, Any]] = [
        (DOO_TOPIC, "sensor_msgs/msg/PointCloud2", _cloud(store, doo, header)),
        (STD_TOPIC, "sensor_msgs/msg/PointCloud2", _cloud(store, std, header)),
        (GRID_TOPIC, "nav_msgs/msg/OccupancyGrid", _grid(store, grid, header, z_min)),
    ]
    parent = out.parent if str(out.parent) else Path(".")
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=parent))
    try:
        bag = staging / out.name
        with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            for topic, msgtype, msg in messages:
                conn = writer.add_connection(topic, msgtype, typestore=store)
                writer.write(conn, int(round(stamp * 1e9)), store.serialize_cdr(msg, msgtype))
        bag.rename(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return {DOO_TOPIC: len(stats), STD_TOPIC: len(stats), GRID_TOPIC: int(grid.data.size)}


def _header(store: Any, stamp: float, frame: str) -> Any:
    sec = math.floor(stamp)
    time = store.types["builtin_interfaces/msg/Time"](
        sec=int(sec), nanosec=min(int(round((stamp - sec) * 1e9)), 999_999_999)
    )
    return store.types["std_msgs/msg/Header"](stamp=time, frame_id=frame)


def _cloud(store: Any, packed: PackedCloud, header: Any) -> Any:
    field = store.types["sensor_msgs/msg/PointField"]
    return store.types["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=1,
        width=packed.width,
        fields=[
            field(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
            for f in packed.fields
        ],  # fmt: skip
        is_bigendian=False,
        point_step=packed.point_step,
        row_step=packed.row_step,
        data=np.frombuffer(packed.data, dtype=np.uint8),
        is_dense=True,
    )


def _grid(store: Any, grid: Any, header: Any, z: float) -> Any:
    t = store.types
    origin = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=grid.origin[0], y=grid.origin[1], z=float(z)),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=header.stamp,
        resolution=float(grid.resolution),
        width=grid.width,
        height=grid.height,
        origin=origin,
    )
    data = np.ascontiguousarray(grid.data, dtype=np.int8).reshape(-1)
    return t["nav_msgs/msg/OccupancyGrid"](header=header, info=info, data=data)
