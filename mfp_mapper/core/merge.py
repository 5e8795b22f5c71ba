"""Exact merge of maps: partial maps of disjoint sets of scans add up to the map of all scans.

A voxel's statistics are sums of contributions (docs/model.md). With decay time ``T``, each
map's statistics refer to the time ``t_last`` of their block; the merge brings every block
to a common time, the latest of its inputs' times, by scaling the older statistics by
``exp(-(t_common - t) / T)``, and adds. That is what a sequential replay of the same scans
computes (decay is a uniform scaling; a late scan's data is scaled to the block's time), so
the merge equals it up to the rounding of the summation order. Static maps (``T = inf``)
are plain sums. Maps of different resolutions, frames, decay times or origins are refused.

The work is one sort of packed int64 keys (block index in the high bits, the voxel's place
in its block in the low 9) and segmented sums: about 1 s per 10 M voxels.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.reflectivity import (
    ARRAY_KEYS as REFLECTIVITY_KEYS,
)
from mfp_mapper.core.reflectivity import (
    from_map_arrays,
    merge_reflectivity,
    to_map_arrays,
)
from mfp_mapper.core.store import BLOCK_BITS, VoxelArrays

MapArrays = Mapping[str, np.ndarray]
"""The arrays of a map file (``mapfile.map_arrays``): ijk, s, n, t_last and the settings."""

MUST_MATCH = ("resolution", "frame_id", "decay_time", "origin")
"""Settings two maps must share to be merged (``origin`` where the format stores one)."""

_LOCAL_BITS = 3 * BLOCK_BITS


class MergeError(ValueError):
    """Maps that cannot be merged exactly: says which setting differs, and where."""


def _setting(arrays: MapArrays, key: str) -> object:
    if key == "origin":
        value = arrays.get("origin")
        return tuple(np.zeros(3) if value is None else np.asarray(value, dtype=np.float64).ravel())
    value = arrays[key]
    return str(value) if key == "frame_id" else float(value)


def check_mergeable(maps: Sequence[MapArrays], names: Sequence[str] | None = None) -> None:
    """Raise MergeError unless every map has the first one's resolution, frame, decay time
    and origin."""
    if not maps:
        raise MergeError("nothing to merge: no map given")
    labels = list(names) if names is not None else [f"map {i + 1}" for i in range(len(maps))]
    for key in MUST_MATCH:
        first = _setting(maps[0], key)
        for label, arrays in zip(labels[1:], maps[1:], strict=True):
            value = _setting(arrays, key)
            if value != first:
                raise MergeError(
                    f"cannot merge maps with different {key.replace('_', ' ')}: "
                    f"{labels[0]} has {_show(first)}, {label} has {_show(value)}"
                )
    scales = [
        (label, (str(m["reflectivity_field"]), tuple(np.ravel(m["reflectivity_edges"]).tolist())))
        for label, m in zip(labels, maps, strict=True)
        if "reflectivity_edges" in m and "reflectivity_field" in m
    ]
    for label, scale in scales[1:]:
        if scale != scales[0][1]:
            raise MergeError(
                f"cannot merge maps with different reflectivity bins: {scales[0][0]} has "
                f"{scales[0][1][0]} {list(scales[0][1][1])}, {label} has {scale[0]} "
                f"{list(scale[1])}"
            )


def _show(value: object) -> str:
    return repr(value) if isinstance(value, str) else f"{value}"


def merge_voxels(parts: Sequence[VoxelArrays], decay_time: float) -> VoxelArrays:
    """Per-voxel sums of ``parts`` (each voxel at most once per part), every block brought to
    the latest time any part gives it. Output sorted by block, then by place in the block."""
    parts = [p for p in parts if p.s.shape[0]]
    if not parts:
        return VoxelArrays(np.zeros((0, 3), np.int32), np.zeros(0), np.zeros(0), np.zeros(0))
    ijk = np.concatenate([p.ijk for p in parts]).astype(np.int64, copy=False)
    order, block_key, voxel_key = _sorted_keys(ijk)
    s, n, t = (np.concatenate([getattr(p, k) for p in parts])[order] for k in ("s", "n", "t_last"))
    block_start = _starts(block_key)
    t_block = np.maximum.reduceat(t, block_start)
    t_common = np.repeat(t_block, np.diff(np.append(block_start, t.shape[0])))
    if math.isfinite(decay_time):
        scale = np.exp((t - t_common) / decay_time)
        s, n = s * scale, n * scale
    voxel_start = _starts(voxel_key)
    return VoxelArrays(
        ijk[order[voxel_start]].astype(np.int32),
        np.add.reduceat(s, voxel_start),
        np.add.reduceat(n, voxel_start),
        t_common[voxel_start],
    )


def _starts(sorted_keys: NDArray[np.int64]) -> NDArray[np.intp]:
    """Indices where a run of equal keys begins."""
    change = np.empty(sorted_keys.shape[0], dtype=bool)
    change[:1] = True
    np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=change[1:])
    return np.flatnonzero(change)


def _sorted_keys(
    ijk: NDArray[np.int64],
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """The order that sorts voxels by block, then by place in the block; and, in that order,
    a key per block and a key per voxel (equal keys = same block, same voxel)."""
    blocks = ijk >> BLOCK_BITS
    local = ijk & ((1 << BLOCK_BITS) - 1)
    local_key = (local[:, 0] << (2 * BLOCK_BITS)) | (local[:, 1] << BLOCK_BITS) | local[:, 2]
    rel = blocks - blocks.min(axis=0)
    bits = [max(1, int(rel[:, a].max()).bit_length()) for a in range(3)]
    key_bits = sum(bits) + _LOCAL_BITS
    if key_bits <= 63:
        block_key = (rel[:, 0] << (bits[1] + bits[2])) | (rel[:, 1] << bits[2]) | rel[:, 2]
        voxel_key = (block_key << _LOCAL_BITS) | local_key
        index_bits = max(1, int(ijk.shape[0] - 1).bit_length())
        if key_bits + index_bits <= 63:  # the row number rides in the low bits: one np.sort
            packed = np.sort((voxel_key << index_bits) | np.arange(ijk.shape[0]))
            order = packed & ((1 << index_bits) - 1)
            voxel_key = packed >> index_bits
        else:
            order = np.argsort(voxel_key)
            voxel_key = voxel_key[order]
        return order, voxel_key >> _LOCAL_BITS, voxel_key
    # a map too wide for one int64 key: sort by columns, number the runs
    order = np.lexsort((local_key, rel[:, 2], rel[:, 1], rel[:, 0]))
    sorted_blocks = rel[order]
    new_block = np.ones(order.shape[0], dtype=bool)
    new_block[1:] = np.any(sorted_blocks[1:] != sorted_blocks[:-1], axis=1)
    sorted_local = local_key[order]
    new_voxel = new_block.copy()
    new_voxel[1:] |= sorted_local[1:] != sorted_local[:-1]
    return order, np.cumsum(new_block) - 1, np.cumsum(new_voxel) - 1


def merge_map_arrays(
    maps: Sequence[MapArrays], names: Sequence[str] | None = None
) -> dict[str, np.ndarray]:
    """The map-file arrays of the exact merge of ``maps`` (settings of the first; they must
    agree on resolution, frame, decay time and origin: MergeError otherwise)."""
    check_mergeable(maps, names)
    decay_time = float(maps[0]["decay_time"])
    merged = merge_voxels(
        [VoxelArrays(m["ijk"], m["s"], m["n"], m["t_last"]) for m in maps], decay_time
    )
    out = {
        k: v
        for k, v in maps[0].items()
        if k not in ("ijk", "s", "n", "t_last") and k not in REFLECTIVITY_KEYS
    }
    out.update(ijk=merged.ijk, s=merged.s, n=merged.n, t_last=merged.t_last)
    try:
        tables = [t for t in (from_map_arrays(m) for m in maps) if t is not None]
        table = merge_reflectivity(tables, decay_time)
    except ValueError as err:
        raise MergeError(f"cannot merge the reflectivity histograms: {err}") from None
    if table is not None:
        out.update(to_map_arrays(table))
    return out
