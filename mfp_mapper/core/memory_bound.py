"""The map's memory bound: ``max_voxels`` and ``keep_radius`` (far blocks evicted)."""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.errors import ScanTooLargeError
from mfp_mapper.core.store import BLOCK_EDGE, BlockStore
from mfp_mapper.core.traversal import Rays, block_bounds

FloatArray = NDArray[np.float64]


class MemoryBound:
    """At most ``max_voxels`` voxels (None: no bound), and no block farther than
    ``keep_blocks`` blocks from the sensor (None: keep all). Positions in block units."""

    def __init__(self, max_voxels: int | None, keep_blocks: float | None) -> None:
        self.max_voxels = max_voxels
        self.keep_blocks = keep_blocks

    def make_room(
        self,
        store: BlockStore,
        origins_vox: FloatArray,
        ends_vox: FloatArray,
        center: FloatArray | None,
    ) -> None:
        """Before a scan: make sure it cannot take the map's blocks beyond ``max_voxels``
        (a map within the bound never has more blocks than voxels), evicting far blocks
        first; ``ScanTooLargeError`` (the map unchanged) when even an empty map could not."""
        if self.max_voxels is None:
            return
        per_ray = int(block_bounds(origins_vox, ends_vox).sum())
        lo = np.floor(np.minimum(origins_vox.min(axis=0), ends_vox.min(axis=0))) // BLOCK_EDGE
        hi = np.floor(np.maximum(origins_vox.max(axis=0), ends_vox.max(axis=0))) // BLOCK_EDGE
        worst = min(per_ray, float(np.prod(hi - lo + 1)))
        if worst > self.max_voxels:
            raise ScanTooLargeError(
                f"scan refused: its rays could create {worst:.0f} blocks of "
                f"{BLOCK_EDGE**3} voxels, more than max_voxels={self.max_voxels}"
            )
        if store.num_blocks + worst > self.max_voxels and center is not None:
            store.evict_farthest_blocks(center, int(self.max_voxels - worst))

    def enforce(self, store: BlockStore, center: FloatArray | None) -> None:
        """After a scan: evict beyond ``keep_blocks`` of the sensor, then the farthest
        blocks until the map holds at most 90% of ``max_voxels``."""
        if center is None:
            return
        if self.keep_blocks is not None:
            store.evict_beyond(center, self.keep_blocks)
        if self.max_voxels is not None and store.num_voxels > self.max_voxels:
            store.evict_farthest(center, int(0.9 * self.max_voxels))


# --- a scan's own budget ------------------------------------------------------------------

FREE_WALK_VOXELS = 2048
"""Every ray walks this far (voxels: 205 m at 0.1 m) without counting against the scan's
budget: what real sensors reach (an Ouster OS-1-128 street scan, 107,647 points up to 217 m,
has 0.1% of its rays beyond at 0.1 m). Their first blocks are shared between rays; beyond,
a ray walks alone, each block of 512 voxels for a few of them (4.1 kB a block, measured)."""
DEFAULT_SCAN_BLOCKS = 1 << 18
"""Blocks the far parts of one scan's rays may add when ``max_voxels`` is not set: 262,144
blocks, about 1 GiB. Before this budget, with ``max_range`` unlimited, 50 rays to 100 km took
310,452 blocks (1,238 MB) and 200 raised MemoryError."""


SCAN_NEW_BLOCKS = 2 * DEFAULT_SCAN_BLOCKS
"""Blocks one scan may add to the map when ``max_voxels`` is not set, near parts included:
524,288 blocks; beyond, the rays not walked yet are cut (``traversal.cut_to_blocks``). The
far budget alone left the first ``FREE_WALK_VOXELS`` of every ray free: 20,000 rays to
100 km in every direction at 0.1 m raised MemoryError (a 32 GiB reservation), 20,000 rays
of 100 m took 9.7 GB; with this bound the first takes 2.2 GB (measured)."""


def scan_new_blocks(max_voxels: int | None) -> int:
    """The blocks one scan may add in all: ``max_voxels`` when set, else ``SCAN_NEW_BLOCKS``."""
    return SCAN_NEW_BLOCKS if max_voxels is None else max(int(max_voxels), 1)


def scan_block_budget(max_voxels: int | None) -> int:
    """The blocks the far parts of one scan may walk: ``max_voxels`` when set (a map within
    the bound never has more blocks than voxels), else ``DEFAULT_SCAN_BLOCKS``."""
    return DEFAULT_SCAN_BLOCKS if max_voxels is None else max(int(max_voxels), 1)


def walk_limits(
    origins_vox: FloatArray, ends_vox: FloatArray, budget: int
) -> NDArray[np.float64] | None:
    """Per-ray walk lengths (voxels) that keep the scan's far blocks within ``budget``, or
    None when every ray may walk to its end.

    A ray's part beyond ``FREE_WALK_VOXELS`` can enter at most ``ceil(d * l1 / 8) + 2``
    blocks for a length ``d`` (``l1``: the L1 norm of its unit direction; the Manhattan
    bound of ``traversal.block_bounds``). The longest far parts are cut first: one cap on
    the far length, found by bisection, so that these bounds sum to at most ``budget``; when
    even the +2 of every long ray does not fit, long rays stop at ``FREE_WALK_VOXELS``."""
    span = ends_vox - origins_vox
    length = np.linalg.norm(span, axis=1)
    far = length - FREE_WALK_VOXELS
    long = far > 0
    if not long.any():
        return None
    far = far[long]
    l1 = np.abs(span[long]).sum(axis=1) / length[long]

    def cost(cap: float) -> float:
        return float(np.ceil(np.minimum(far, cap) * l1 / BLOCK_EDGE).sum() + 2 * far.size)

    if cost(float(far.max())) <= budget:
        return None
    lo, hi = 0.0, float(far.max())
    if cost(0.0) <= budget:
        while hi - lo > max(1.0, 1e-3 * hi):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if cost(mid) <= budget else (lo, mid)
    limits = length.copy()
    limits[long] = FREE_WALK_VOXELS + np.minimum(far, lo)
    return limits


def fit_scan_budget(rays: Rays, budget: int, resolution: float) -> tuple[Rays, int]:
    """``rays`` with the far parts cut to ``walk_limits`` (walked that far, no return), and
    how many were cut; the same ``rays`` and 0 when they fit the budget."""
    if not len(rays) or rays.lengths.max() < (FREE_WALK_VOXELS - 1) * resolution:
        return rays, 0  # every ray walks free (a quick check: lengths are in metres)
    limits = walk_limits(rays.origins_vox, rays.ends_vox, budget)
    if limits is None:
        return rays, 0
    span = rays.ends_vox - rays.origins_vox
    length = np.linalg.norm(span, axis=1)
    cut = limits < length - 1e-9
    scale = np.where(cut, limits / np.maximum(length, 1e-12), 1.0)
    ends = np.ascontiguousarray(rays.origins_vox + span * scale[:, None])
    lengths = np.where(cut, limits * resolution, rays.lengths)
    has_return = rays.has_return & ~cut
    cut_rays = dataclasses.replace(rays, ends_vox=ends, lengths=lengths, has_return=has_return)
    return cut_rays, int(cut.sum())
