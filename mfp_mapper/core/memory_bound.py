"""The map's memory bound: ``max_voxels`` and ``keep_radius`` (far blocks evicted)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.errors import ScanTooLargeError
from mfp_mapper.core.store import BLOCK_EDGE, BlockStore
from mfp_mapper.core.traversal import block_bounds

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
