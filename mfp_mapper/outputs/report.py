"""What the CLI prints: simulation lines, voxel query rows, JSON-safe values."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # a query of map-file points loads no numba (``mapio.queries``)
    from mfp_mapper.core.mapper import Mapper


def jsonable(value: Any) -> Any:
    """``value`` with tuples as lists, numpy scalars as Python numbers, inf/nan as None."""
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if hasattr(value, "item"):
        return jsonable(value.item())
    return value


def simulation_lines(result: Any) -> list[str]:
    """What a simulation wrote: bag, truth, media, rays without return."""
    t = result.truth
    rays = t["rays"]
    lines = [
        f"bag          {result.bag} ({t['storage']}, {t['scans']} scans, {rays['rays']:,} rays)",
        f"truth        {result.truth_path}",
    ]
    for m in t["scene"]["media"]:
        lines.append(
            f"medium       {m['name']}: extinction {m['extinction']:g} /m in {m['lo']}..{m['hi']}"
        )
    if rays["omitted"]:
        lines.append(
            f"no return    {rays['omitted']:,} rays left the scene and are not in the bag "
            f"({rays['omitted_through_media']:,} of them crossed a medium)"
        )
    return lines


def query_rows(
    mapper: Mapper, points: NDArray[np.float64], stamp: float | None = None
) -> list[dict[str, Any]]:
    """The statistics of the voxel holding each point (90% credible DoO interval included),
    decayed to ``stamp`` when given. A never-observed voxel is unknown: ``observed`` false
    and every estimate None (its prior's numbers, a DoO of about 0.02 with the default
    prior, would read as free space)."""
    st = mapper.query(points, stamp)
    lo, hi = st.doo_interval(0.9)
    rows = []
    for k in range(len(st)):
        seen = bool(st.observed[k])
        row: dict[str, Any] = {
            "point": points[k].tolist(),
            "voxel": st.ijk[k].tolist(),
            "observed": seen,
            "n": float(st.n[k]),
            "s": float(st.s[k]),
        }
        estimates = {
            "degree_of_occupancy": float(st.most_likely_doo[k]),
            "mean_degree_of_occupancy": float(st.mean_doo[k]),
            "std": float(st.std[k]),
            "doo_interval_90": [float(lo[k]), float(hi[k])],
            "hit_probability": float(st.hit_probability[k]),
            "mean_free_path": float(st.mean_free_path[k]),
        }
        rows.append({**row, **{key: (v if seen else None) for key, v in estimates.items()}})
    for row, refl in zip(rows, reflectivity_rows(mapper, points, stamp), strict=False):
        row["reflectivity"] = refl
    return rows


def reflectivity_rows(
    mapper: Any, points: NDArray[np.float64], stamp: float | None = None
) -> list[dict[str, Any]]:
    """The reflectivity histogram of the voxel holding each point (Appendix B: decayed
    return counts per intensity bin, their mean intensity and fullest bin; None for those
    where the voxel holds no return); [] when the map keeps no histograms."""
    found = mapper.reflectivity(points, stamp)
    if found is None:
        return []
    from mfp_mapper.core.reflectivity_arrays import mean_value, most_likely_bin

    bins, counts = found
    means = mean_value(counts, bins)
    fullest = most_likely_bin(counts)
    return [
        {
            "field": bins.field,
            "edges": list(bins.edges),
            "counts": counts[k].tolist(),
            "mean": None if fullest[k] < 0 else float(means[k]),
            "most_likely_bin": None if fullest[k] < 0 else int(fullest[k]),
        }
        for k in range(counts.shape[0])
    ]


def query_lines(rows: list[dict[str, Any]]) -> list[str]:
    """One line per ``query_rows`` row."""
    lines = []
    for row in rows:
        x, y, z = row["point"]
        head = f"({x:.2f}, {y:.2f}, {z:.2f}) voxel {tuple(row['voxel'])}: "
        if not row["observed"]:
            lines.append(head + "unknown (never observed: no ray crossed it)")
            continue
        mfp = row["mean_free_path"]
        lines.append(
            head
            + f"DoO {row['degree_of_occupancy']:.3f} (mean {row['mean_degree_of_occupancy']:.3f}"
            f", std {row['std']:.3f}, 90% [{row['doo_interval_90'][0]:.3f}, "
            f"{row['doo_interval_90'][1]:.3f}]), p_hit {row['hit_probability']:.3f}, "
            f"n {row['n']:g}, s {row['s']:.2f} m, mean free path "
            + (f"{mfp:.2f} m" if math.isfinite(mfp) else "inf")
        )
        refl = row.get("reflectivity")
        if refl is not None and refl["mean"] is not None:
            lines[-1] += (
                f", {refl['field']} mean {refl['mean']:.1f} (fullest bin "
                f"{refl['most_likely_bin']} of {len(refl['counts'])})"
            )
    return lines


def segment_rows(
    mapper: Mapper,
    starts: NDArray[np.float64],
    ends: NDArray[np.float64],
    stamp: float | None = None,
) -> list[dict[str, Any]]:
    """``Mapper.query_segments`` of each segment as a row (ValueError as it raises)."""
    st = mapper.query_segments(starts, ends, stamp)
    return [
        {
            "start": starts[k].tolist(),
            "end": ends[k].tolist(),
            "length": float(st.length[k]),
            "clear_probability": float(st.clear_probability[k]),
            "unknown_length": float(st.unknown_length[k]),
        }
        for k in range(len(st))
    ]


def segment_lines(rows: list[dict[str, Any]]) -> list[str]:
    """One line per ``segment_rows`` row."""
    lines = []
    for row in rows:
        a = ", ".join(f"{v:.2f}" for v in row["start"])
        b = ", ".join(f"{v:.2f}" for v in row["end"])
        unknown = row["unknown_length"]
        lines.append(
            f"({a}) -> ({b}), {row['length']:.2f} m: clear with probability "
            f"{row['clear_probability']:.4g}; "
            + (f"{unknown:.2f} m never observed" if unknown > 0 else "all of it observed")
        )
    return lines
