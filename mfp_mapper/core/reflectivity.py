"""The reflectivity field (Appendix B, Eq. B1-B3): per voxel, a histogram of return intensity.

A return whose intensity falls in bin ``j`` adds one to ``n_jK`` of the voxel ``K`` holding
it (the voxel whose ``n`` it adds to); the most likely reflectivity histogram of ``K`` is
``n_jK / sum_i n_iK`` (Eq. B3, independent of the extinction). Only a few percent of the
observed voxels hold returns, so the histograms live in a sparse table of their own beside
the block store (``ReflectivityTable``): an open-addressing hash from voxel index to a row
of ``J`` float32 counts and the time they refer to.

Decay (Eq. 28-30) scales the counts as it scales ``n``: each row keeps the time ``t`` its
counts refer to; a return at ``stamp >= t`` first brings its row to ``stamp`` (scale by
``exp(-(stamp - t) / T)``), a late return adds ``exp(-(t - stamp) / T)`` and leaves ``t``.
So a row is the exact decayed sum of its returns, whatever the order of the scans, and its
total equals the voxel's ``n`` read at the same time (up to float32 rounding) when every
return had an intensity. Tables merge exactly (``merge_reflectivity``): every row brought to
the latest time of its inputs, then added.

Rows follow their voxels: blocks evicted by the memory bound (``max_voxels``, ``keep_radius``)
and voxels cleared (``clear_box``) drop their rows (``Mapper``). One case is not followed: a
ray whose return a shard's walk cut to keep one scan within its block budget
(``traversal.cut_to_blocks``, a scan far beyond ``max_voxels``) keeps its histogram count.

The core knows nothing of sensors: it takes intensity values and bin edges
(``ReflectivityBins``: a label naming the field they came from, and the edges). The
sensing layer chooses the edges per field (``sensing.reflectivity``); maps merge only when
label and edges are equal.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

ARRAY_KEYS = (
    "reflectivity_ijk",
    "reflectivity_counts",
    "reflectivity_t_last",
    "reflectivity_edges",
    "reflectivity_field",
)
"""The arrays of a map holding a reflectivity field (``to_map_arrays``), beside its voxels'."""
MAX_BINS = 64
"""Most bins a histogram may have."""
_EMPTY = 0  # a hash slot holds row + 1; 0 is free


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


class ScanReflectivity(NamedTuple):
    """The intensity of each point of a scan (N,) and how to bin it."""

    values: ArrayLike
    bins: ReflectivityBins


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
    """The map-file members of a table (``ARRAY_KEYS``)."""
    return {
        "reflectivity_ijk": table.ijk.astype(np.int32, copy=False),
        "reflectivity_counts": table.counts.astype(np.float64, copy=False),
        "reflectivity_t_last": table.t_last.astype(np.float64, copy=False),
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
    for key in ARRAY_KEYS[:3]:
        out[key] = np.asarray(arrays[key])[keep]
    return out


def rows_within(
    arrays: Mapping[str, np.ndarray], lo: NDArray[np.int64], hi: NDArray[np.int64]
) -> NDArray[np.bool_]:
    """Which table rows of map-file ``arrays`` have a voxel index within [lo, hi]."""
    ijk = np.asarray(arrays.get("reflectivity_ijk", np.zeros((0, 3), np.int32)))
    return np.all((ijk >= lo) & (ijk <= hi), axis=1)


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


@nb.njit(inline="always", cache=True)
def _slot_of(x: int, y: int, z: int, mask: int) -> int:
    h = (
        np.uint64(x & 0xFFFFFF) * np.uint64(0x9E3779B97F4A7C15)
        ^ np.uint64(y & 0xFFFFFF) * np.uint64(0xC2B2AE3D27D4EB4F)
        ^ np.uint64(z & 0xFFFFFF) * np.uint64(0x165667B19E3779F9)
    )
    return int(h >> np.uint64(32)) & mask


@nb.njit(cache=True, nogil=True)
def _find(slots: NDArray[np.int32], rows_ijk: NDArray[np.int32], x: int, y: int, z: int) -> int:
    """Row of voxel (x, y, z), or -(slot + 1) of the free slot where it would go."""
    mask = slots.shape[0] - 1
    i = _slot_of(x, y, z, mask)
    while True:
        r = slots[i] - 1
        if r < 0:
            return -(i + 1)
        if rows_ijk[r, 0] == x and rows_ijk[r, 1] == y and rows_ijk[r, 2] == z:
            return r
        i = (i + 1) & mask


@nb.njit(cache=True, nogil=True)
def _rehash(slots: NDArray[np.int32], rows_ijk: NDArray[np.int32], used: int) -> None:
    slots[:] = _EMPTY
    for r in range(used):
        free = _find(slots, rows_ijk, rows_ijk[r, 0], rows_ijk[r, 1], rows_ijk[r, 2])
        slots[-free - 1] = r + 1


@nb.njit(cache=True, nogil=True)
def _add(
    ijk: NDArray[np.int64],
    bins: NDArray[np.int64],
    stamp: float,
    decay_time: float,
    slots: NDArray[np.int32],
    rows_ijk: NDArray[np.int32],
    counts: NDArray[np.float32],
    t: NDArray[np.float64],
    used: int,
) -> int:
    """Add one return per row of ``ijk`` in bin ``bins`` (< 0: skipped) at ``stamp``; rows
    are created as needed (the caller leaves room for all). Returns the rows used."""
    decays = math.isfinite(decay_time)
    for j in range(ijk.shape[0]):
        b = bins[j]
        if b < 0:
            continue
        x, y, z = ijk[j, 0], ijk[j, 1], ijk[j, 2]
        r = _find(slots, rows_ijk, x, y, z)
        if r < 0:
            slots[-r - 1] = used + 1
            r = used
            used += 1
            rows_ijk[r, 0], rows_ijk[r, 1], rows_ijk[r, 2] = x, y, z
            counts[r, :] = 0.0
            t[r] = stamp
        w = 1.0
        if decays and stamp > t[r]:
            f = math.exp(-(stamp - t[r]) / decay_time)
            for k in range(counts.shape[1]):
                counts[r, k] = counts[r, k] * f
            t[r] = stamp
        elif decays and stamp < t[r]:
            w = math.exp(-(t[r] - stamp) / decay_time)
        counts[r, b] += w
    return used


@nb.njit(cache=True, nogil=True)
def _lookup(
    ijk: NDArray[np.int64], slots: NDArray[np.int32], rows_ijk: NDArray[np.int32]
) -> NDArray[np.int64]:
    out = np.empty(ijk.shape[0], dtype=np.int64)
    for j in range(ijk.shape[0]):
        r = _find(slots, rows_ijk, ijk[j, 0], ijk[j, 1], ijk[j, 2])
        out[j] = r if r >= 0 else -1
    return out


@nb.njit(cache=True, nogil=True)
def _assign(ijk: NDArray[np.int64], slots: NDArray[np.int32], rows_ijk: NDArray[np.int32]) -> int:
    """Insert every voxel as row j; returns -1, or the index of a voxel listed twice."""
    for j in range(ijk.shape[0]):
        r = _find(slots, rows_ijk, ijk[j, 0], ijk[j, 1], ijk[j, 2])
        if r >= 0:
            return j
        slots[-r - 1] = j + 1
        rows_ijk[j, 0], rows_ijk[j, 1], rows_ijk[j, 2] = ijk[j, 0], ijk[j, 1], ijk[j, 2]
    return -1


def _pow2_at_least(x: int) -> int:
    return 1 << max(int(x - 1).bit_length(), 4)


class ReflectivityTable:
    """Histograms of return intensity of the voxels that hold returns (module docstring).

    Rows are float32 counts (``J`` a row), their time (float64) and voxel index (int32 x 3);
    the hash keeps at most half of its slots full. Not thread-safe (the Mapper's lock)."""

    def __init__(self, bins: ReflectivityBins, capacity: int = 1024) -> None:
        self.bins = bins
        self._used = 0
        self._ijk = np.zeros((capacity, 3), dtype=np.int32)
        self._counts = np.zeros((capacity, bins.count), dtype=np.float32)
        self._t = np.zeros(capacity)
        self._slots = np.zeros(_pow2_at_least(2 * capacity), dtype=np.int32)

    def __len__(self) -> int:
        return self._used

    def _reserve(self, rows: int) -> None:
        """Room for ``rows`` more rows (capacity doubles, slots rehashed)."""
        need = self._used + rows
        if need <= self._t.shape[0]:
            return
        capacity = max(need, 2 * self._t.shape[0])
        used = self._used
        ijk = np.zeros((capacity, 3), dtype=np.int32)
        counts = np.zeros((capacity, self.bins.count), dtype=np.float32)
        t = np.zeros(capacity)
        ijk[:used], counts[:used], t[:used] = self._ijk[:used], self._counts[:used], self._t[:used]
        self._ijk, self._counts, self._t = ijk, counts, t
        self._slots = np.zeros(_pow2_at_least(2 * capacity), dtype=np.int32)
        _rehash(self._slots, self._ijk, used)

    def add(
        self, ijk: NDArray[np.integer], bins: NDArray[np.integer], stamp: float, decay_time: float
    ) -> None:
        """One return in voxel ``ijk[j]`` (index relative to the map origin) and bin
        ``bins[j]`` (< 0: none) for each j, made at ``stamp``, decayed with time constant
        ``decay_time`` (s, inf: none)."""
        ijk = np.ascontiguousarray(ijk, dtype=np.int64).reshape(-1, 3)
        bins_ = np.ascontiguousarray(bins, dtype=np.int64).reshape(-1)
        if bins_.shape[0] != ijk.shape[0]:
            raise ValueError(f"{ijk.shape[0]} voxels but {bins_.shape[0]} bins")
        if bins_.size and bins_.max() >= self.bins.count:
            raise ValueError(f"bin {int(bins_.max())} beyond the {self.bins.count} bins")
        self._reserve(ijk.shape[0])
        self._used = _add(
            ijk, bins_, float(stamp), float(decay_time), self._slots, self._ijk, self._counts,
            self._t, self._used,
        )  # fmt: skip

    def lookup(self, ijk: NDArray[np.integer]) -> NDArray[np.int64]:
        """The row of each voxel, -1 where it holds no histogram."""
        ijk = np.ascontiguousarray(ijk, dtype=np.int64).reshape(-1, 3)
        return _lookup(ijk, self._slots, self._ijk)

    def histograms(
        self, ijk: NDArray[np.integer], stamp: float | None = None, decay_time: float = math.inf
    ) -> tuple[FloatArray, FloatArray]:
        """Counts (M, J) of each voxel (zeros where none) and the time they refer to
        (-inf where none): decayed to ``stamp`` when given (and ``decay_time`` finite)."""
        rows = self.lookup(ijk)
        found = rows >= 0
        counts = np.zeros((rows.shape[0], self.bins.count))
        t = np.full(rows.shape[0], -np.inf)
        counts[found] = self._counts[rows[found]]
        t[found] = self._t[rows[found]]
        if stamp is not None and math.isfinite(decay_time):
            counts[found] *= np.exp(-(float(stamp) - t[found]) / decay_time)[:, None]
        return counts, t

    def export(self) -> ReflectivityArrays:
        """Every row, as stored (a copy)."""
        used = self._used
        return ReflectivityArrays(
            self.bins,
            self._ijk[:used].copy(),
            self._counts[:used].astype(np.float64),
            self._t[:used].copy(),
        )

    def assign(self, table: ReflectivityArrays) -> None:
        """Set the rows of an empty table (a map file's); ValueError naming a voxel listed
        twice or a problem of the arrays (the table is then empty again)."""
        if self._used:
            raise ValueError("assign needs an empty table")
        if table.bins != self.bins:
            raise ValueError(f"bins {table.bins} differ from the table's {self.bins}")
        problem = table_problem(table)
        if problem:
            raise ValueError(problem)
        self._reserve(len(table))
        ijk = np.ascontiguousarray(table.ijk, dtype=np.int64)
        twice = _assign(ijk, self._slots, self._ijk)
        if twice >= 0:
            self._slots[:] = _EMPTY
            raise ValueError(f"reflectivity_ijk lists voxel {ijk[twice].tolist()} more than once")
        self._counts[: len(table)] = table.counts
        self._t[: len(table)] = table.t_last
        self._used = len(table)

    def keep(self, mask: NDArray[np.bool_]) -> int:
        """Keep the rows where ``mask`` (over ``len(self)`` rows) is True; returns how many
        were dropped."""
        used = self._used
        kept = int(np.count_nonzero(mask))
        if kept == used:
            return 0
        for arr in (self._ijk, self._counts, self._t):
            arr[:kept] = arr[:used][mask]
            arr[kept:used] = 0
        self._used = kept
        _rehash(self._slots, self._ijk, kept)
        return used - kept

    def voxel_indices(self) -> NDArray[np.int32]:
        """The voxel index of every row (a view: valid until the table changes)."""
        return self._ijk[: self._used]

    def clear_box(self, lo: NDArray[np.int64], hi: NDArray[np.int64]) -> int:
        """Drop the rows of the voxels with index in [lo, hi]; returns how many."""
        ijk = self.voxel_indices()
        inside = np.all((ijk >= lo) & (ijk <= hi), axis=1)
        return self.keep(~inside)

    @property
    def nbytes(self) -> int:
        """Memory in use: the rows used (capacity beyond is untouched zeroed pages) and the
        hash slots."""
        row = self._ijk[0].nbytes + self._counts[0].nbytes + self._t[0].nbytes
        return self._used * row + self._slots.nbytes


def merge_reflectivity(
    parts: Sequence[ReflectivityArrays], decay_time: float
) -> ReflectivityArrays | None:
    """Per-voxel sums of the tables (each voxel at most once per part), every row brought
    to the latest time any part gives it (exact, like ``merge.merge_voxels``); None when
    no part is given. ValueError when the parts' bins differ."""
    if not parts:
        return None
    bins = parts[0].bins
    for part in parts[1:]:
        if part.bins != bins:
            raise ValueError(
                f"reflectivity bins differ: {bins.field} {list(bins.edges)} and "
                f"{part.bins.field} {list(part.bins.edges)}"
            )
    ijk = np.concatenate([p.ijk for p in parts]).astype(np.int64).reshape(-1, 3)
    counts = np.concatenate([p.counts for p in parts]).reshape(-1, bins.count)
    t = np.concatenate([p.t_last for p in parts])
    if not ijk.shape[0]:
        return ReflectivityArrays(bins, ijk.astype(np.int32), counts, t)
    unique, inverse = np.unique(ijk, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    t_common = np.full(unique.shape[0], -np.inf)
    np.maximum.at(t_common, inverse, t)
    if math.isfinite(decay_time):
        counts = counts * np.exp((t - t_common[inverse]) / decay_time)[:, None]
    summed = np.zeros((unique.shape[0], bins.count))
    np.add.at(summed, inverse, counts)
    return ReflectivityArrays(bins, unique.astype(np.int32), summed, t_common)


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
