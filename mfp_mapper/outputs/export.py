"""Export a map as a PLY point cloud of voxel centres (``mfp-mapper export``).

Binary little-endian PLY, one vertex per voxel, every property ``float`` (32 bit):
``x y z`` (voxel centre, map frame, metres), ``degree_of_occupancy`` (most likely, 1 -
exp(-n/s)), ``std`` (posterior standard deviation of the degree of occupancy),
``mean_free_path`` (s/n, metres; NaN where no return was seen, i.e. infinite), ``n``
(returns) and ``s`` (metres of rays). CloudCompare shows the extra properties as scalar
fields; Open3D reads the points.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from mfp_mapper.core.mapper import Mapper, VoxelStats
from mfp_mapper.mapio.atomic import atomic_output
from mfp_mapper.mapio.tiles import TiledMap

PLY_PROPERTIES = ("x", "y", "z", "degree_of_occupancy", "std", "mean_free_path", "n", "s")
PLY_DTYPE = np.dtype([(name, "<f4") for name in PLY_PROPERTIES])


def ply_records(stats: VoxelStats) -> np.ndarray:
    """The PLY vertex records (binary body) of these voxels."""
    rec = np.empty(len(stats), dtype=PLY_DTYPE)
    with np.errstate(over="ignore"):  # float64 -> float32 may overflow to inf: refused below
        rec["x"], rec["y"], rec["z"] = stats.centers[:, 0], stats.centers[:, 1], stats.centers[:, 2]
        rec["degree_of_occupancy"] = stats.most_likely_doo
        rec["std"] = stats.std
        mfp = stats.mean_free_path
        rec["mean_free_path"] = np.where(np.isfinite(mfp), mfp, np.nan)
        rec["n"] = stats.n
        rec["s"] = stats.s
    for name in ("x", "y", "z", "n", "s"):
        if not np.isfinite(rec[name]).all():
            raise ValueError(f"voxel {name} values beyond float32's range: no PLY written")
    return rec


def ply_header(count: int, comments: tuple[str, ...] = ()) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element vertex {count}")
    lines += [f"property float {name}" for name in PLY_PROPERTIES]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def ply_bytes(stats: VoxelStats, comments: tuple[str, ...] = ()) -> bytes:
    """The PLY file (header + binary body) of these voxels."""
    return ply_header(len(stats), comments) + ply_records(stats).tobytes()


def _comments(frame_id: str, resolution: float) -> tuple[str, ...]:
    return (
        "mfp_mapper voxel map (Berquin & Zell 2021 mean-free-path model)",
        f"frame_id {frame_id}",
        f"resolution {resolution}",
        "mean_free_path NaN = infinite (no return seen)",
    )


def export_ply(
    mapper: Mapper, path: str | Path, min_doo: float = 0.0, min_evidence: float = 0.0
) -> int:
    """Write the observed voxels of ``mapper`` with most likely DoO >= ``min_doo`` and
    s >= ``min_evidence`` to ``path`` atomically; return how many."""
    stats = mapper.voxels(min_doo=min_doo, min_evidence=min_evidence)
    with atomic_output(path) as f:
        f.write(ply_bytes(stats, _comments(mapper.frame_id, mapper.resolution)))
    return len(stats)


def export_ply_tiled(
    tiled: TiledMap, path: str | Path, min_doo: float = 0.0, min_evidence: float = 0.0
) -> int:
    """``export_ply`` of a tiled map, one tile at a time: the records go to a scratch file
    beside ``path`` first (the header needs their count), then header and records are
    written to ``path`` atomically."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    count = 0
    with tempfile.TemporaryFile(dir=target.parent) as body:
        for _, tile in tiled.iter_tiles():
            records = ply_records(tile.voxels(min_doo=min_doo, min_evidence=min_evidence))
            body.write(records.tobytes())
            count += len(records)
        body.seek(0)
        with atomic_output(target) as f:
            f.write(ply_header(count, _comments(tiled.frame_id, tiled.resolution)))
            shutil.copyfileobj(body, f, 1 << 22)
    return count


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """The vertex columns of a PLY file (``sources.scan_files.read_ply``, with plyfile)."""
    from mfp_mapper.sources.scan_files import read_ply as read_vertices

    return read_vertices(path)
