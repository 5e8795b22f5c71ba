"""A map's reflectivity histograms as arrays, numba-free: the bins, the table as a map file
holds it (``ReflectivityArrays``, ``to_map_arrays``, ``from_map_arrays``), the rows' block
order, and what a histogram tells (mean, fullest bin). ``core.reflectivity`` (the table the
Mapper keeps, compiled) re-exports them; a process reading histograms from a map file
(``mapio.queries``) imports only this module, not numba."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.core.layout import BLOCK_BITS, BLOCK_EDGE, KEY_BITS, KEY_OFFSET, MAX_VOXEL_INDEX

FloatArray = NDArray[np.float64]

ARRAY_KEYS = (
    "reflectivity_ijk",
    "reflectivity_counts",
    "reflectivity_t_last",
    "reflectivity_edges",
    "reflectivity_field",
)
"""The arrays of a map holding a reflectivity field (``to_map_arrays``), beside its voxels'."""
ROW_KEYS = ARRAY_KEYS[:3]
"""The members with a row per voxel (the others give the bins)."""
MAX_BINS = 64
"""Most bins a histogram may have."""


@dataclass(frozen=True)
class ReflectivityBins:
    """How intensities are binned: ``field`` names where they came from (a label the map
    keeps), ``edges`` are the ``J - 1`` increasing inner edges: bin 0 holds values below
    ``edges[0]``, bin ``j`` holds ``edges[j-1] <= v < edges[j]``, bin ``J-1`` the rest."""

    field: str
    edges: tuple[float, ...]

    def __post_init__(self) -> None:
        e = np.asarray(self.edges, dtype=np.float64)
        if e.ndim != 1 or not 1 <= e.size + 1 <= MAX_BINS:
            raise ValueError(f"need 0 to {MAX_BINS - 1} inner bin edges, got {e.size}")
        if not (np.isfinite(e).all() and np.all(np.diff(e) > 0)):
            raise ValueError(f"bin edges must be finite and increasing, got {list(self.edges)}")

    @property
    def count(self) -> int:
        """J, the number of bins."""
        return len(self.edges) + 1

    def bin_of(self, values: ArrayLike) -> NDArray[np.int64]:
        """The bin of each value; -1 for NaN (not counted)."""
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        out = np.searchsorted(np.asarray(self.edges, dtype=np.float64), v, side="right")
        out[np.isnan(v)] = -1
        return out.astype(np.int64)

    def centers(self) -> FloatArray:
        """A representative value of each bin (for a mean): the geometric mean of its edges
        when both are positive, else the middle; the outer bins take their inner edge
        scaled by the neighbouring bin's ratio (or its edge when there is none)."""
        e = np.asarray(self.edges, dtype=np.float64)
        if e.size == 0:
            return np.zeros(1)
        lo = np.concatenate([[e[0] * e[0] / e[1] if e.size > 1 and e[1] > 0 else e[0]], e])
        hi = np.concatenate([e, [e[-1] * e[-1] / e[-2] if e.size > 1 and e[-2] > 0 else e[-1]]])
        with np.errstate(invalid="ignore"):
            geo = np.sqrt(lo * hi)
        return np.where((lo > 0) & (hi > 0), geo, 0.5 * (lo + hi))


@dataclass
class ReflectivityArrays:
    """A reflectivity table as arrays: its bins, voxel indices (K, 3) relative to the map's
    origin, counts (K, J) and the time (s) each row refers to (K,)."""

    bins: ReflectivityBins
    ijk: NDArray[np.int32]
    counts: FloatArray
    t_last: FloatArray

    def __len__(self) -> int:
        return int(self.ijk.shape[0])


def to_map_arrays(table: ReflectivityArrays) -> dict[str, np.ndarray]:
    """The map-file members of a table (``ARRAY_KEYS``), rows sorted by block and place in
    the block (as a ``ReflectivityTable`` holds them: a reader finds a block's rows on few
    pages)."""
    order = block_order(table.ijk)
    return {
        "reflectivity_ijk": table.ijk[order].astype(np.int32, copy=False),
        "reflectivity_counts": table.counts[order].astype(np.float64, copy=False),
        "reflectivity_t_last": table.t_last[order].astype(np.float64, copy=False),
        "reflectivity_edges": np.asarray(table.bins.edges, dtype=np.float64),
        "reflectivity_field": np.str_(table.bins.field),
    }


def from_map_arrays(arrays: Mapping[str, np.ndarray]) -> ReflectivityArrays | None:
    """The table held by map-file arrays, None when they hold none; ValueError naming what
    is wrong (shapes, values: ``table_problem``)."""
    if "reflectivity_counts" not in arrays:
        return None
    missing = [k for k in ARRAY_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"reflectivity field incomplete: missing {', '.join(missing)}")
    edges = np.asarray(arrays["reflectivity_edges"], dtype=np.float64).reshape(-1)
    bins = ReflectivityBins(str(arrays["reflectivity_field"]), tuple(float(e) for e in edges))
    table = ReflectivityArrays(
        bins,
        np.asarray(arrays["reflectivity_ijk"]),
        np.asarray(arrays["reflectivity_counts"], dtype=np.float64),
        np.asarray(arrays["reflectivity_t_last"], dtype=np.float64),
    )
    problem = table_problem(table)
    if problem:
        raise ValueError(problem)
    return table


def select_rows(arrays: Mapping[str, np.ndarray], keep: NDArray[np.bool_]) -> dict[str, np.ndarray]:
    """The table members of map-file ``arrays`` with only the rows where ``keep`` (over its
    rows) is True; {} when they hold no table."""
    if "reflectivity_counts" not in arrays:
        return {}
    out = {k: arrays[k] for k in ARRAY_KEYS if k in arrays}
    for key in ROW_KEYS:
        out[key] = np.asarray(arrays[key])[keep]
    return out


def rows_within(
    arrays: Mapping[str, np.ndarray], lo: NDArray[np.int64], hi: NDArray[np.int64]
) -> NDArray[np.bool_]:
    """Which table rows of map-file ``arrays`` have a voxel index within [lo, hi]."""
    ijk = np.asarray(arrays.get("reflectivity_ijk", np.zeros((0, 3), np.int32)))
    return np.all((ijk >= lo) & (ijk <= hi), axis=1)


def block_order(ijk: ArrayLike) -> NDArray[np.int64] | slice:
    """The order of voxel indices ``ijk`` (K, 3) by block (``packed.sort_keys``), then by
    place in the block; ``slice(None)`` when they are in that order already."""
    keys, places, _ = row_keys(np.asarray(ijk, dtype=np.int64).reshape(-1, 3))
    later = (keys[1:] > keys[:-1]) | ((keys[1:] == keys[:-1]) & (places[1:] > places[:-1]))
    return slice(None) if later.all() else np.lexsort((places, keys))


def concatenate_tables(parts: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The table members of disjoint map-file arrays (e.g. tiles) as one; {} when none
    holds a table. ValueError when their bins differ."""
    tables = [t for t in (from_map_arrays(p) for p in parts) if t is not None]
    if not tables:
        return {}
    for other in tables[1:]:
        if other.bins != tables[0].bins:
            raise ValueError(f"reflectivity bins differ: {tables[0].bins} and {other.bins}")
    return to_map_arrays(
        ReflectivityArrays(
            tables[0].bins,
            np.concatenate([t.ijk for t in tables]).astype(np.int32),
            np.concatenate([t.counts for t in tables]),
            np.concatenate([t.t_last for t in tables]),
        )
    )


def table_problem(table: ReflectivityArrays) -> str | None:
    """What is wrong with a table's arrays (duplicates are found when stored), or None."""
    rows = len(table)
    if table.ijk.ndim != 2 or table.ijk.shape[1] != 3:
        return f"reflectivity_ijk must have shape (K, 3), got {table.ijk.shape}"
    if table.counts.shape != (rows, table.bins.count) or table.t_last.shape != (rows,):
        return (
            f"reflectivity arrays disagree: {rows} voxels, counts {table.counts.shape} for "
            f"{table.bins.count} bins, t_last {table.t_last.shape}"
        )
    if not (np.isfinite(table.counts).all() and table.counts.min(initial=0.0) >= 0):
        return "reflectivity_counts holds negative, NaN or infinite values"
    if not np.isfinite(table.t_last).all():
        return "reflectivity_t_last holds NaN or infinite values (seconds expected)"
    return None


def row_keys(
    ijk: NDArray[np.int64],
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]:
    """The block key (``blocks.block_key``), the voxel's place in its block (0-511) and
    whether the index is within the map's range (``MAX_VOXEL_INDEX``) of each voxel."""
    inside = np.all(np.abs(ijk) <= MAX_VOXEL_INDEX, axis=1)
    b = (ijk >> BLOCK_BITS) + KEY_OFFSET
    keys = (b[:, 0] << (2 * KEY_BITS)) | (b[:, 1] << KEY_BITS) | b[:, 2]
    low = ijk & (BLOCK_EDGE - 1)
    local = (low[:, 0] << (2 * BLOCK_BITS)) | (low[:, 1] << BLOCK_BITS) | low[:, 2]
    return keys, local, inside


def most_likely_bin(counts: FloatArray) -> NDArray[np.int64]:
    """The fullest bin of each histogram (M, J); -1 for an empty one."""
    out = np.argmax(counts, axis=1).astype(np.int64) if counts.shape[1] else np.zeros(0, np.int64)
    out[counts.sum(axis=1) <= 0] = -1
    return out


def mean_value(counts: FloatArray, bins: ReflectivityBins) -> FloatArray:
    """The mean intensity of each histogram (M, J) with the bins' ``centers``; NaN for an
    empty one."""
    total = counts.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, counts @ bins.centers() / total, np.nan)


def smoothed(counts: FloatArray, background: FloatArray, concentration: float) -> FloatArray:
    """Posterior predictive histograms (M, J) under a Dirichlet prior of total weight
    ``concentration`` centred on ``background`` (J, sums to 1): (n_j + c g_j) / (n + c)."""
    total = counts.sum(axis=1, keepdims=True)
    return (counts + concentration * background) / (total + concentration)
