"""Threads on a real recording: the map of one thread, bit for bit, and no ray cut."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapio.mapfile import map_arrays
from mfp_mapper.sensing.poses import quaternion_to_matrix
from mfp_mapper.sources.pose_files import read_kitti_poses
from mfp_mapper.sources.scan_files import read_kitti_bin


def _ouster_scans(root: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """The OS1-128 street scans (KITTI binaries and poses, read as ``mfp-mapper replay``
    reads a scan folder), in the map frame."""
    folder = root / "ouster_street"
    if not (folder / "poses.txt").is_file():
        pytest.skip(f"no OS1-128 street scans in {folder}")
    positions, quaternions = read_kitti_poses(folder / "poses.txt")
    scans = []
    for k, (position, quaternion) in enumerate(zip(positions, quaternions, strict=True)):
        cols = read_kitti_bin(folder / "scans" / f"{k:06d}.bin")
        xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
        xyz = xyz[np.linalg.norm(xyz, axis=1) > 0.3]
        scans.append((xyz @ quaternion_to_matrix(quaternion).T + position, position))
    return scans


@pytest.mark.parametrize("threads", [2, 4])
def test_threads_map_a_real_street_as_one_thread(shared_data: Path, threads: int) -> None:
    """OS1-128 at 0.2 m with a 100 m range: each shard's first share of the scan's block
    bound was too small for its far stretches, and two threads cut 127,766 of the 322,536
    rays of the three scans (four threads 191,932) where one thread cut none."""
    scans = _ouster_scans(shared_data)
    maps = []
    for count in (1, threads):
        mapper = Mapper(0.2, threads=count, max_range=100.0)
        for k, (points, origin) in enumerate(scans):
            assert mapper.integrate(points, origin, float(k)).rays_cut_by_budget == 0
        maps.append(map_arrays(mapper))
        mapper.close()
    one, split = maps
    order_one, order_split = np.lexsort(one["ijk"].T), np.lexsort(split["ijk"].T)
    for key in ("ijk", "s", "n"):
        np.testing.assert_array_equal(one[key][order_one], split[key][order_split])
