"""Mailboxes: visits a thread made to blocks of other shards, applied by their owners."""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import BLOCK_VOXELS, block_of_key, shard_of
from mfp_mapper.core.shard import Shard, ShardArrays, open_block
from mfp_mapper.core.visits import BATCH_VISITS, CACHE_BITS, CACHE_MASK, CACHE_SIZE, apply_visits


class MailArrays(NamedTuple):
    """A mailbox's arrays, as compiled kernels take them (see ``Mailbox``)."""

    block: NDArray[np.int64]
    local: NDArray[np.int16]
    chord: NDArray[np.float32]
    returns: NDArray[np.float32]
    used: NDArray[np.int64]
    """Entries in use (one element)."""


class Mailbox:
    """Visits a thread made to blocks of other shards: block key, voxel, chord, return."""

    def __init__(self, capacity: int = 1 << 16) -> None:
        self.count = np.zeros(1, dtype=np.int64)
        self.block = np.zeros(capacity, dtype=np.int64)
        self.local = np.zeros(capacity, dtype=np.int16)
        self.chord = np.zeros(capacity, dtype=np.float32)
        self.returns = np.zeros(capacity, dtype=np.float32)

    def reserve(self, capacity: int) -> None:
        """Make room for ``capacity`` entries in all."""
        if capacity > self.block.shape[0]:
            self.grow(capacity - int(self.count[0]))

    def arrays(self) -> MailArrays:
        """The arrays the compiled kernels work on (valid until the mailbox grows)."""
        return MailArrays(self.block, self.local, self.chord, self.returns, self.count)

    def grow(self, min_free: int) -> None:
        used = int(self.count[0])
        capacity = max(2 * self.block.shape[0], used + min_free)
        for name in ("block", "local", "chord", "returns"):
            old = getattr(self, name)
            new = np.zeros(capacity, dtype=old.dtype)
            new[:used] = old[:used]
            setattr(self, name, new)


def deliver_mail(
    mail: Mailbox,
    shard: Shard,
    shard_id: int,
    shard_mask: int,
    scan_id: int,
    stamp: float,
    decay_time: float,
) -> None:
    """Apply the visits in ``mail`` that belong to ``shard``, growing it as needed."""
    start, stop = 0, int(mail.count[0])
    while start < stop:
        start = apply_mail(
            mail.block, mail.local, mail.chord, mail.returns, start, stop, shard_id, shard_mask,
            shard.arrays(), scan_id, stamp, decay_time,
        )  # fmt: skip
        if start < stop:
            shard.grow(min_free=1024)


@nb.njit(cache=True, nogil=True)
def apply_mail(
    mail_block: NDArray[np.int64],
    mail_local: NDArray[np.int16],
    mail_chord: NDArray[np.float32],
    mail_return: NDArray[np.float32],
    start: int,
    stop: int,
    shard: int,
    shard_mask: int,
    shard_arrays: ShardArrays,
    scan_id: int,
    stamp: float,
    decay_time: float,
) -> int:
    """Apply mailbox entries ``start..stop`` that belong to ``shard``, in order.

    Returns ``stop``, or the first entry whose new block found no room (the caller grows
    the shard and calls again from there).
    """
    block_sn, block_hit, counters, block_scale = (
        shard_arrays[3],
        shard_arrays[6],
        shard_arrays[7],
        shard_arrays[8],
    )
    cache_keys = np.full(CACHE_SIZE, -1, dtype=np.int64)
    cache_blocks = np.empty(CACHE_SIZE, dtype=np.int64)
    visit_voxel = np.empty(BATCH_VISITS, dtype=np.int64)
    visit_chord = np.empty(BATCH_VISITS, dtype=np.float32)
    visit_return = np.empty(BATCH_VISITS, dtype=np.float32)
    count = 0
    last_key = -1
    block = -1
    scale = 1.0
    for j in range(start, stop):
        if count == BATCH_VISITS:
            apply_visits(
                block_sn, block_hit, visit_voxel, visit_chord, visit_return, count, counters
            )
            count = 0
        key = mail_block[j]
        if key != last_key:
            bx, by, bz = block_of_key(key)
            block = -1
            if shard_of(bx, by, bz, shard_mask) == shard:
                slot = (
                    ((bx & CACHE_MASK) << (2 * CACHE_BITS))
                    | ((by & CACHE_MASK) << CACHE_BITS)
                    | (bz & CACHE_MASK)
                )
                if cache_keys[slot] == key:
                    block = cache_blocks[slot]
                else:
                    block = open_block(bx, by, bz, shard_arrays, scan_id, stamp, decay_time)
                    cache_keys[slot] = key
                    cache_blocks[slot] = block
                if block >= 0:
                    scale = block_scale[block] if block >= 0 else 1.0
                if block < 0:
                    apply_visits(
                        block_sn,
                        block_hit,
                        visit_voxel,
                        visit_chord,
                        visit_return,
                        count,
                        counters,
                    )
                    return j
            last_key = key
        if block >= 0:
            visit_voxel[count] = block * BLOCK_VOXELS + mail_local[j]
            visit_chord[count] = mail_chord[j] * scale
            visit_return[count] = mail_return[j] * scale
            count += 1
    apply_visits(block_sn, block_hit, visit_voxel, visit_chord, visit_return, count, counters)
    return stop
