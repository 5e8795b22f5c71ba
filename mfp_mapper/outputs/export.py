"""Export a map as a PLY point cloud of voxel centres (``mfp-mapper export``).

Binary little-endian PLY, one vertex per voxel, every property ``float`` (32 bit):
``x y z`` (voxel centre, map frame, metres), ``degree_of_occupancy`` (most likely, 1 -
exp(-n/s)), ``std`` (posterior standard deviation of the degree of occupancy),
``mean_free_path`` (s/n, metres; NaN where no return was seen, i.e. infinite), ``n``
(returns) and ``s`` (metres of rays). A map with reflectivity histograms (docs/model.md)
adds ``reflectivity`` (the mean intensity of the voxel's returns, from its histogram; NaN
where it holds none) and ``reflectivity_bin`` (its fullest bin, -1 where none).
CloudCompare shows the extra properties as scalar fields; Open3D reads the points.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from mfp_mapper.core.mapper import Mapper, VoxelStats
from mfp_mapper.core.reflectivity import ReflectivityBins, mean_value, most_likely_bin
from mfp_mapper.mapio.atomic import atomic_output
from mfp_mapper.mapio.tiles import TiledMap

Reflectivity = tuple[ReflectivityBins, np.ndarray]
"""A map's bins and the reflectivity histograms (M, J) of M voxels."""
PLY_PROPERTIES = ("x", "y", "z", "degree_of_occupancy", "std", "mean_free_path", "n", "s")
PLY_DTYPE = np.dtype([(name, "<f4") for name in PLY_PROPERTIES])
REFLECTIVITY_PROPERTIES = ("reflectivity", "reflectivity_bin")
"""The properties a map with reflectivity histograms adds."""
PLY_REFLECTIVITY_DTYPE = np.dtype([(n, "<f4") for n in (*PLY_PROPERTIES, *REFLECTIVITY_PROPERTIES)])


def ply_records(stats: VoxelStats, histograms: Reflectivity | None = None) -> np.ndarray:
    """The PLY vertex records (binary body) of these voxels (``histograms``: their bins and
    reflectivity histograms, ``Mapper.reflectivity``, for the reflectivity properties)."""
    rec = np.empty(len(stats), dtype=PLY_DTYPE if histograms is None else PLY_REFLECTIVITY_DTYPE)
    if histograms is not None:
        bins, counts = histograms
        rec["reflectivity"] = mean_value(counts, bins)
        rec["reflectivity_bin"] = most_likely_bin(counts)
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


def ply_header(count: int, comments: tuple[str, ...] = (), reflectivity: bool = False) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element vertex {count}")
    names = (*PLY_PROPERTIES, *REFLECTIVITY_PROPERTIES) if reflectivity else PLY_PROPERTIES
    lines += [f"property float {name}" for name in names]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def ply_bytes(
    stats: VoxelStats, comments: tuple[str, ...] = (), histograms: Reflectivity | None = None
) -> bytes:
    """The PLY file (header + binary body) of these voxels."""
    header = ply_header(len(stats), comments, histograms is not None)
    return header + ply_records(stats, histograms).tobytes()


def _comments(
    frame_id: str, resolution: float, histograms: Reflectivity | None = None
) -> tuple[str, ...]:
    out: tuple[str, ...] = (
        "mfp_mapper voxel map (Berquin & Zell 2021 mean-free-path model)",
        f"frame_id {frame_id}",
        f"resolution {resolution}",
        "mean_free_path NaN = infinite (no return seen)",
    )
    if histograms is not None:
        bins = histograms[0]
        edges = " ".join(f"{e:g}" for e in bins.edges)
        out += (f"reflectivity field {bins.field}, bin edges {edges}",)
    return out


def export_ply(
    mapper: Mapper, path: str | Path, min_doo: float = 0.0, min_evidence: float = 0.0
) -> int:
    """Write the observed voxels of ``mapper`` with most likely DoO >= ``min_doo`` and
    s >= ``min_evidence`` to ``path`` atomically; return how many."""
    stats = mapper.voxels(min_doo=min_doo, min_evidence=min_evidence)
    histograms = mapper.reflectivity(stats.centers)
    comments = _comments(mapper.frame_id, mapper.resolution, histograms)
    with atomic_output(path) as f:
        f.write(ply_bytes(stats, comments, histograms))
    return len(stats)


def export_ply_tiled(
    tiled: TiledMap, path: str | Path, min_doo: float = 0.0, min_evidence: float = 0.0
) -> int:
    """``export_ply`` of a tiled map, one tile at a time: the records go to a scratch file
    beside ``path`` first (the header needs their count, and whether any tile holds
    reflectivity histograms), then header and records are written to ``path`` atomically."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    count = 0
    scale: ReflectivityBins | None = None
    with tempfile.TemporaryFile(dir=target.parent) as body:
        for _, tile in tiled.iter_tiles():
            stats = tile.voxels(min_doo=min_doo, min_evidence=min_evidence)
            found = tile.reflectivity(stats.centers)
            if found is not None and scale is None:
                scale = found[0]
            if found is None or found[0] != scale:  # no histograms: NaN, bin -1
                found = (scale or _NO_BINS, np.zeros((len(stats), (scale or _NO_BINS).count)))
            records = ply_records(stats, found)
            body.write(records.tobytes())
            count += len(records)
        body.seek(0)
        with atomic_output(target) as f:
            histograms = None if scale is None else (scale, np.zeros((0, scale.count)))
            f.write(ply_header(count, _comments(tiled.frame_id, tiled.resolution, histograms),
                               scale is not None))  # fmt: skip
            if scale is not None:
                shutil.copyfileobj(body, f, 1 << 22)
            else:  # no tile held histograms: the records without their columns
                chunk = 1 << 16
                while block := body.read(chunk * PLY_REFLECTIVITY_DTYPE.itemsize):
                    rec = np.frombuffer(block, dtype=PLY_REFLECTIVITY_DTYPE)
                    plain = np.empty(rec.shape[0], dtype=PLY_DTYPE)
                    for name in PLY_PROPERTIES:
                        plain[name] = rec[name]
                    f.write(plain.tobytes())
    return count


_NO_BINS = ReflectivityBins("none", ())


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """The vertex columns of a PLY file (``sources.scan_files.read_ply``, with plyfile)."""
    from mfp_mapper.sources.scan_files import read_ply as read_vertices

    return read_vertices(path)
