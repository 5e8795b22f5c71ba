"""Exact voxel traversal (Amanatides & Woo) of lidar rays into the block store, with numba.

A ray runs from its origin to its end point: its first return, or the point where it was
cut at ``max_range``. Every voxel it crosses gets ``s += chord`` — the exact length in
metres of the ray inside that voxel, so a ray's chords add up to its length — and a ray
that ends in a return gives its end voxel ``n += 1`` (the chord from where it entered that
voxel up to the return point is its last chord).

Threads split the space: the store has shards (four a thread: ``mapper.shard_count``), a
shard owns tiles of blocks (16 a side for two threads, 8 for more: ``blocks.tile_bits``) in a
3-D checkerboard (``blocks.shard_of``), and one
thread at a time writes to a shard. The rays are first split into their stretches in each
tile (``split_into``, parts of the rays a task), then the threads walk the shards'
stretches, a shard at a time, the shards with the most steps first. A
walk keeps t in fixed point (``lockstep.T_ONE``), where a face's t is the same whether
summed step by step or computed from its index, so a stretch starts in exactly the state
the walk from the ray's origin has there: the same voxels and chords, bit for bit. A
shard's stretches are walked tile by tile, in ray order within a tile, so every voxel gets
its chords in ray order: the store of one thread walking whole rays, whatever the number
of threads. (Before: every thread walked every
ray and added only its own shard's visits, 1.33-1.39x at 0.1 m and nothing at 0.2 m.)
"""

from __future__ import annotations

import math
import threading
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import (
    BLOCK_BITS,
    BLOCK_CHUNKS,
    CHUNK_BITS,
    CHUNK_VOXELS,
    KEY_BITS,
    MAX_VOXEL_INDEX,
    N_BLOCK_CHUNKS,
    N_CHUNK_BITS,
    N_CHUNK_VOXELS,
    block_key,
    block_of_key,
    find_block,
    local_index,
    shard_of,
    tile_bits,
    tile_z_offset,
)
from mfp_mapper.core.lockstep import (
    FLOAT_ROWS,
    INT_ROWS,
    LANES,
    LOCAL_MASK,
    T_NEVER,
    T_ONE,
    copy_table,
    place_lanes,
    prefetch_line,
    walk_lanes,
)
from mfp_mapper.core.shard import (
    FLUSH_PENDING,
    FOREIGN_LIMIT,
    NCHUNK_USED,
    NREC_USED,
    S_USED,
    Shard,
    ShardArrays,
    ValueArrays,
    open_block,
    value_arrays,
)
from mfp_mapper.core.store import BlockStore

_LOCAL_MASK = (1 << BLOCK_BITS) - 1
_N_MASK = N_CHUNK_VOXELS - 1
_SPREAD = np.array([local_index(0, 0, z) for z in range(1 << BLOCK_BITS)], dtype=np.int64)
"""Morton bits of an index in a block along one axis (z; y is this << 1, x this << 2)."""
_READ_CACHE_BITS = 4
"""``read_walk``'s block cache: 2^12 slots, indexed by the low 4 bits of each block index."""
_READ_CACHE_MASK = (1 << _READ_CACHE_BITS) - 1
_WALK_CACHE_BITS = 5
"""The integrating walk's block cache: 2^15 slots, indexed by the low 5 bits of each block
index. Against 2^12 slots (as ``read_walk``'s), cycle-counted on one scan: misses 60 k ->
29 k and the block lookups 13.6 -> 10.1 ms on OS1-128 at 0.2 m (86.9 k -> 69.2 k, 23.8 ->
20.1 ms, hall at 0.1 m); a miss costs about 110 ns (the hash, and a first touch)."""
_WALK_CACHE_MASK = (1 << _WALK_CACHE_BITS) - 1
WalkCache = NDArray[np.int64]
"""The integrating walk's block cache: each slot's block key (-1: none) at ``2 * slot`` and
its chunk-table slot (0: another shard's block) at ``2 * slot + 1``, with ``_LATE`` set
where the scan is late (the block's weight, ``ShardArrays.block_scale``, below 1). The
weight was a third array: a third line loaded an entered block, where a scan is late in
almost none (perf samples of the walk, hall at 0.2 m: 4,127-4,321 with the flag against
4,367-4,532 with the third array)."""
_LATE = 1 << 40
"""Set in a walk cache slot's chunk-table slot (at most ``BLOCK_CHUNKS`` * 2^31) where the
scan is late in its block."""
_BASE_MASK = _LATE - 1
_walk_caches = threading.local()


def _walk_cache() -> WalkCache:
    """This thread's walk cache, emptied: for one shard's walks of one scan, kept from call
    to call (a shard is walked part by part, ``_walk_part``), in memory the thread reuses.
    A cache allocated a call cost the hall's walks at 0.2 m 12-20% more CPU time with eight
    shards (32 calls a scan) than with two (8 calls)."""
    cache: WalkCache | None = getattr(_walk_caches, "cache", None)
    if cache is None:
        cache = np.full(2 << (3 * _WALK_CACHE_BITS), -1, dtype=np.int64)
        _walk_caches.cache = cache
    else:
        cache.fill(-1)
    return cache


RETURN_CHORD_FLOOR = 1e-3
"""Least chord (metres) of a return event in ``read_walk``: the range resolution of a lidar
return. A return exactly on a voxel's edge or corner has a chord of 0 in the voxel its
point floors to (the ray only touches it), probability 0 and log-likelihood -inf; the
reflection is known only to within the range resolution (about 1 mm: what lidars report,
and the rounding of exported coordinates), so the event covers at least that much ray
(docs/model.md, "A return on a voxel face")."""


@dataclass
class Rays:
    """Rays in voxel units (metres / resolution), with their lengths in metres."""

    origins_vox: NDArray[np.float64]
    ends_vox: NDArray[np.float64]
    lengths: NDArray[np.float64]
    has_return: NDArray[np.bool_]
    no_return_flagged: int = 0
    """How many of the rays had their ``no_return`` flag set (see ``prepare_rays``)."""
    source: NDArray[np.int64] | None = None
    """Index of each ray's input point (``prepare_rays`` drops some points)."""
    continued: NDArray[np.bool_] | None = None
    """Rays that continue a shot past an earlier echo (``prepare_rays``), or None: none."""
    mean_origin: NDArray[np.float64] | None = None
    """The mean origin (voxel units) of the rays that do not continue a shot (all of them
    when none does), summed as ``prepare_rays`` placed them; None: not known."""

    def __len__(self) -> int:
        return int(self.lengths.shape[0])


def prepare_rays(
    points: NDArray[np.float64],
    origins: NDArray[np.float64],
    resolution: float,
    min_range: float,
    max_range: float,
    no_return: NDArray[np.bool_] | None = None,
    continued: NDArray[np.bool_] | None = None,
    offset: NDArray[np.float64] | None = None,
) -> tuple[Rays, dict[str, int]]:
    """The usable rays in voxel units, and how many were dropped for which reason.

    ``origins`` is one origin (3,) or one per point (N, 3). A ray longer than ``max_range``
    is cut there and carries no return; so does a ray whose ``no_return`` flag (N,) is set:
    its point only marks where its credited free space ends. NaN/Inf, shorter than
    ``min_range`` (or zero), and reaching beyond the indexable range are dropped.

    ``continued`` (N,) flags rays that continue a shot past an earlier echo (their origin is
    that echo plus the blind stretch, not the sensor; ``sensing.echoes``): ``min_range``
    does not apply to them and a zero length is kept (a return with no chord: an echo
    inside the blind stretch of the one before).

    ``offset`` (3,): subtracted from points and origins first (the map's origin), in the
    same pass (``points - offset`` before took 0.3-0.5 ms of an OS1-128 scan, its fresh
    array's pages faulted in each scan).
    """
    count = points.shape[0]
    source = np.empty(count, dtype=np.int64)
    out = Rays(
        np.empty((count, 3)), np.empty((count, 3)), np.empty(count), np.empty(count, dtype=np.bool_)
    )
    drops = np.zeros(4, dtype=np.int64)  # the 3 reasons, then the flagged rays kept
    flags = np.zeros(0, dtype=np.bool_) if no_return is None else no_return
    if flags.size and flags.shape != (count,):
        raise ValueError(f"no_return must have shape ({count},), got {flags.shape}")
    later = np.zeros(0, dtype=np.bool_) if continued is None else continued
    if later.size and later.shape != (count,):
        raise ValueError(f"continued must have shape ({count},), got {later.shape}")
    shift = np.zeros(3) if offset is None else np.asarray(offset, dtype=np.float64).reshape(3)
    sensor = np.zeros(3)
    used = _prepare_rays(
        points, np.atleast_2d(origins), shift, resolution, min_range, max_range, MAX_VOXEL_INDEX,
        flags, later, out.origins_vox, out.ends_vox, out.lengths, out.has_return, source, drops,
        sensor,
    )  # fmt: skip
    dropped = {
        "nonfinite": int(drops[0]),
        "below_min_range": int(drops[1]),
        "out_of_bounds": int(drops[2]),
    }
    rays = Rays(
        out.origins_vox[:used],
        out.ends_vox[:used],
        out.lengths[:used],
        out.has_return[:used],
        int(drops[3]),
        source[:used],
        later[source[:used]] if later.size else None,
        sensor,
    )
    return rays, dropped


@nb.njit(cache=True, nogil=True)
def _prepare_rays(
    points: NDArray[np.float64],
    origins: NDArray[np.float64],
    offset: NDArray[np.float64],
    resolution: float,
    min_range: float,
    max_range: float,
    max_index: float,
    no_return: NDArray[np.bool_],
    continued: NDArray[np.bool_],
    origins_vox: NDArray[np.float64],
    ends_vox: NDArray[np.float64],
    lengths: NDArray[np.float64],
    has_return: NDArray[np.bool_],
    source: NDArray[np.int64],
    drops: NDArray[np.int64],
    sensor: NDArray[np.float64],
) -> int:
    """One pass over the points less ``offset``: fill the first rays of the outputs, count
    the drops ([nonfinite, below_min_range, out_of_bounds], then the flagged rays kept);
    returns how many rays are usable; ``source`` receives each ray's point index, ``sensor``
    the mean origin of the usable rays that do not continue a shot (all, when none does).
    ``no_return`` is empty (every point a return) or one flag per point; ``continued`` is
    empty (every ray from the sensor) or one flag per point."""
    k = 0
    per_point = origins.shape[0] > 1
    flagged = no_return.shape[0] > 0
    any_continued = continued.shape[0] > 0
    ox0, oy0, oz0 = offset[0], offset[1], offset[2]
    # one origin: divided once (the same quotient as per ray; three divisions a ray fewer)
    first_origin = (0.0, 0.0, 0.0)
    if origins.shape[0] == 1:
        first_origin = (
            (origins[0, 0] - ox0) / resolution,
            (origins[0, 1] - oy0) / resolution,
            (origins[0, 2] - oz0) / resolution,
        )
    sx = sy = sz = 0.0
    sensors = 0
    for i in range(points.shape[0]):
        o = i if per_point else 0
        px, py, pz = points[i, 0] - ox0, points[i, 1] - oy0, points[i, 2] - oz0
        qx, qy, qz = origins[o, 0] - ox0, origins[o, 1] - oy0, origins[o, 2] - oz0
        dx = px - qx
        dy = py - qy
        dz = pz - qz
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        if not math.isfinite(length):  # NaN or Inf in the point or its origin
            drops[0] += 1
            continue
        if (length < min_range or length == 0.0) and not (any_continued and continued[i]):
            drops[1] += 1
            continue
        reach = min(length, max_range)
        scale = reach / length if length > 0.0 else 1.0
        inside = True
        for axis, d, p, q in ((0, dx, px, qx), (1, dy, py, qy), (2, dz, pz, qz)):
            o_vox = q / resolution if per_point else first_origin[axis]
            # the end, divided exactly as Mapper.voxel_index does: a return lands in floor(p/res)
            e_vox = (p if scale == 1.0 else q + d * scale) / resolution
            inside = inside and abs(o_vox) < max_index and abs(e_vox) < max_index
            origins_vox[k, axis] = o_vox
            ends_vox[k, axis] = e_vox
        if not inside:
            drops[2] += 1
            continue
        if per_point and not (any_continued and continued[i]):
            sx += origins_vox[k, 0]
            sy += origins_vox[k, 1]
            sz += origins_vox[k, 2]
        sensors += not (any_continued and continued[i])
        lengths[k] = reach
        if flagged and no_return[i]:
            has_return[k] = False
            drops[3] += 1
        else:
            has_return[k] = length <= max_range
        source[k] = i
        k += 1
    if not per_point:  # one origin: the mean is that origin, exactly
        sx, sy, sz = first_origin
    elif sensors == 0:  # every ray continues a shot: the mean of theirs
        for r in range(k):
            sx += origins_vox[r, 0]
            sy += origins_vox[r, 1]
            sz += origins_vox[r, 2]
        sensors = max(k, 1)
    if per_point:
        sx, sy, sz = sx / sensors, sy / sensors, sz / sensors
    sensor[0] = sx
    sensor[1] = sy
    sensor[2] = sz
    return k


def integrate_rays(
    store: BlockStore,
    rays: Rays,
    scan_id: int,
    stamp: float,
    decay_time: float,
    run_parallel: Callable[[Callable[[int], None], Sequence[int]], object],
    max_new_blocks: int | None = None,
) -> int:
    """Add every ray's chords and returns to the store (scan ``scan_id`` at ``stamp``): the
    rays are split into their stretches in each shard's tiles (``split_into``, parts of at
    most ``SPLIT_RAYS`` rays a task, as many for each thread, into one buffer of the scan's
    stretches kept from scan to scan, each shard's in the order it walks them), then the
    shards' stretches are walked, a shard a task (one compiled call each), the shards with
    the most work first, so that the threads end together.
    ``run_parallel(fn, items)`` calls ``fn`` on every item, in parallel, taking the items
    in order.

    ``max_new_blocks``: the blocks the scan may add in all (``_walk_shares``: each shard a
    share, the shares of those that did not need them handed on): where the scan would
    add more, the shards cut the rays they have not walked yet (``cut_to_blocks``), so a
    scan's memory is bounded whatever its rays. Returns the rays cut (most of any shard)."""
    scan = ScanStamp(scan_id, float(stamp), float(decay_time))
    shards = len(store.shards)
    if shards == 1:
        share = None if max_new_blocks is None else int(max_new_blocks)
        return _walk_whole(rays, store.shards[0], scan, share)
    threads = max(shards // SHARDS_PER_THREAD, 1)
    # parts of at most SPLIT_RAYS rays, as many for each thread, of equal size (4 parts of
    # 7,200 rays for 28,800, not 3 of 8,192 and one of 4,224: the split's round ends when
    # its longer thread does)
    per_thread = max(-(-len(rays) // (SPLIT_RAYS * threads)), 1)
    size = max(-(-len(rays) // (per_thread * threads)), 1)
    parts = -(-len(rays) // size)
    part_at = np.zeros(parts + 1, dtype=np.int64)
    # two tasks, each counting the parts of its half of the rays
    halves = (0, min((parts + 1) // 2 * size, len(rays)), len(rays))

    def count_half(h: int) -> None:
        piece_counts(
            rays.origins_vox, rays.ends_vox, halves[h], halves[h + 1], size, store.shard_mask,
            part_at,
        )  # fmt: skip

    run_parallel(count_half, range(2))
    np.cumsum(part_at, out=part_at)
    # the rays' bounds: only a cut (cut_to_blocks) reads them, and computes its own
    unbounded = np.zeros(len(rays), dtype=np.int64)
    whole = RayArrays(
        rays.origins_vox, rays.ends_vox, rays.lengths, rays.has_return, unbounded, unbounded
    )
    pieces = _flat_pieces(store, int(part_at[-1]), len(rays))
    segments = np.zeros((parts, shards, 2), dtype=np.int64)  # each part's pieces per shard
    work = np.zeros((parts, 2, shards), dtype=np.int64)  # per part: work, room

    def split_part(c: int) -> None:
        start = c * size
        split_into(
            rays.origins_vox, rays.ends_vox, rays.has_return, start, min(start + size, len(rays)),
            store.shard_mask, pieces, int(part_at[c]),
            *_split_scratch(int(part_at[c + 1] - part_at[c])), segments[c], work[c],
        )  # fmt: skip

    run_parallel(split_part, range(parts))
    walks = [ShardWalk(whole, pieces, segments, k) for k in range(shards)]
    largest_first = [int(k) for k in np.argsort(-work[:, 0].sum(axis=0), kind="stable")]
    if max_new_blocks is None:

        def walk_free(k: int) -> None:
            _walk_part(walks[k], store.shards[k], k, store.shard_mask, scan, None, True)

        run_parallel(walk_free, largest_first)
    else:
        _walk_shares(store, walks, work[:, 1].sum(axis=0), largest_first, scan, run_parallel,
                     int(max_new_blocks))  # fmt: skip
    return max(w.cut for w in walks)


def _walk_shares(
    store: BlockStore,
    walks: list[ShardWalk],
    room: NDArray[np.int64],
    largest_first: list[int],
    scan: ScanStamp,
    run_parallel: Callable[[Callable[[int], None], Sequence[int]], object],
    max_new_blocks: int,
) -> None:
    """Walk every shard's ``walks`` so that the scan adds at most ``max_new_blocks`` blocks
    in all, cutting rays only where the scan as a whole would outgrow it.

    Each shard takes a share of the blocks in proportion to ``room`` (the blocks its
    stretches can create; an upper bound, loose where rays share blocks); a shard that
    reaches its share pauses, and the blocks the others left go to the paused shards in
    another round, until they are walked, the scan's blocks are spent or a round makes no
    progress: then the paused shards cut the rays they have not walked (``_walk_part``).
    Before, a shard cut at its first share: two threads cut 63k of the 107k rays of a later
    OS1-128 scan at 0.2 m, where one thread cut none. The shares depend on block counts
    only, not on the threads' timing: the same map whatever the threads."""
    shards = store.shards
    start = [shard.used for shard in shards]
    left_room = [int(r) for r in room]
    pending = largest_first
    last = len(shards) + 1  # a round frees at least one shard's share, or ends in cuts
    for rounds in range(last + 1):
        spare = max_new_blocks - sum(shard.used - s for shard, s in zip(shards, start, strict=True))
        total = max(sum(left_room[k] for k in pending), 1)
        limits = {k: shards[k].used + max(spare, 0) * left_room[k] // total for k in pending}
        final = rounds == last or spare <= 0
        before = {k: (walks[k].first, shards[k].used) for k in pending}

        def walk(k: int, limits: dict[int, int] = limits, final: bool = final) -> None:
            _walk_part(walks[k], shards[k], k, store.shard_mask, scan, limits[k], final)

        run_parallel(walk, pending)
        pending = [k for k in pending if not walks[k].done]
        if not pending:
            return
        if all((walks[k].first, shards[k].used) == before[k] for k in pending):
            last = rounds + 1  # no progress: the next round cuts
        for k in pending:
            left_room[k] = walks[k].room_left()


PIECE_STEPS = 16
"""What starting a stretch costs the walk, in steps (``shard_work``): about 40 ns of walk a
stretch (lane set-up and a group's fixed costs) against about 6 ns a step (OS1-128 at 0.2 m,
this 2-core machine; docs/performance.md "Two threads"). It weighs the shards' work only, to
deal the heaviest first: no map depends on it."""


@nb.njit(cache=True, nogil=True)
def shard_work(pieces: Pieces, offsets: NDArray[np.int64], out: NDArray[np.int64]) -> None:
    """Each shard's walk of ``split_rays``' pieces, estimated: ``out[0, k]`` its steps plus
    ``PIECE_STEPS`` a stretch, ``out[1, k]`` the blocks its stretches can create."""
    for k in range(offsets.shape[0] - 1):
        steps = 0
        room = 0
        for i in range(offsets[k], offsets[k + 1]):
            p = pieces.order[i]
            steps += pieces.voxel[p, 3] + 1 + PIECE_STEPS
            room += pieces.room[p]
        out[0, k] = steps
        out[1, k] = room


SHARDS_PER_THREAD = 4
"""Shards of the store per thread (``mapper.shard_count``). A scan's steps are uneven among
the tiles: the sensor's tile holds the most, and one of the two colours of a checkerboard
held 0.51-0.58 of an OS1-128 scan at 0.2 m (median over sensor positions; 0.65 at the 90th
percentile). With four shards a thread, the threads take the shards' walks most work first
(``integrate_rays``), and two threads share a scan within 0.51-0.52 (0.525 at the 90th
percentile)."""
SPLIT_RAYS = 8192
"""At most the rays split in one task (``split_into``; the parts are of equal size, as many
for each thread): a part's stretches (25 bytes each) are written
to a scratch the thread keeps, then put in walk order. When each part allocated its
pieces, parts of 53k rays (OS1-128, 2 threads) took twice as long a ray, faulting their
fresh pages in, and parts of 32768 rays 1.6 times as long; with the scratch kept, parts
of 2048 to 16384 rays gave the same split and walks within the noise of this machine."""


def block_bounds(
    origins_vox: NDArray[np.float64], ends_vox: NDArray[np.float64]
) -> NDArray[np.int64]:
    """Upper bound of the blocks each ray can create: Manhattan block distance plus slack."""
    return ray_bounds(origins_vox, ends_vox)[0]


def visit_bounds(
    origins_vox: NDArray[np.float64], ends_vox: NDArray[np.float64]
) -> NDArray[np.int64]:
    """Upper bound of the voxels each ray visits: Manhattan voxel distance plus one."""
    return ray_bounds(origins_vox, ends_vox)[1]


@nb.njit(cache=True, nogil=True)
def ray_bounds(
    origins_vox: NDArray[np.float64], ends_vox: NDArray[np.float64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``block_bounds`` and ``visit_bounds`` in one pass (ten numpy passes took 2 ms of a
    50 ms scan at 0.2 m)."""
    count = origins_vox.shape[0]
    blocks = np.empty(count, dtype=np.int64)
    visits = np.empty(count, dtype=np.int64)
    for r in range(count):
        block_steps = 0
        steps = 0
        for axis in range(3):
            lo = int(np.floor(origins_vox[r, axis]))
            hi = int(np.floor(ends_vox[r, axis]))
            steps += abs(hi - lo)
            block_steps += abs((hi >> BLOCK_BITS) - (lo >> BLOCK_BITS))
        blocks[r] = block_steps + 2
        visits[r] = steps + 1
    return blocks, visits


class RayArrays(NamedTuple):
    """The rays of one walk, as the compiled walk takes them (voxel units)."""

    origins_vox: NDArray[np.float64]
    ends_vox: NDArray[np.float64]
    lengths: NDArray[np.float64]
    has_return: NDArray[np.bool_]
    room_needed: NDArray[np.int64]
    """Upper bound of the blocks each ray can create (``block_bounds``)."""
    visits_needed: NDArray[np.int64]
    """Upper bound of the voxels each ray visits (``visit_bounds``)."""


class ScanStamp(NamedTuple):
    """The scan being integrated: its id, its time, and the map's decay time (s)."""

    scan_id: int
    stamp: float
    decay_time: float


def _ray_arrays(rays: Rays) -> RayArrays:
    """``rays`` as the walk takes them, with their bounds."""
    room, visits = ray_bounds(rays.origins_vox, rays.ends_vox)
    return RayArrays(rays.origins_vox, rays.ends_vox, rays.lengths, rays.has_return, room, visits)


class ShardWalk:
    """One shard's walk of a scan's stretches (``_walk_part``), kept between the rounds of
    ``_walk_shares``: where it stands, and the rays it cut."""

    def __init__(
        self, walk: RayArrays, pieces: Pieces, segments: NDArray[np.int64], shard: int
    ) -> None:
        self.walk = walk
        self.pieces = pieces
        """The scan's pieces; shard ``shard``'s (``shard_order``) from the first round on (put
        in order by the thread that walks them)."""
        self._segments: NDArray[np.int64] | None = segments
        self._shard = shard
        self.first = 0
        """The first of ``pieces.order`` not walked yet."""
        self.cut = 0
        """The rays cut (``cut_to_blocks``)."""
        self.cut_done = False
        self.done = False
        self.visits = self.left = np.zeros(0, dtype=np.int64)

    def ordered(self) -> None:
        """The shard's pieces in the order to walk them, and their visits (``piece_room``)."""
        if self._segments is not None:
            self.pieces = self.pieces._replace(order=shard_order(self._segments, self._shard))
            self.visits, self.left = piece_room(self.pieces.voxel, self.pieces.order)
            self._segments = None

    def room_left(self) -> int:
        """The blocks the stretches not walked yet can create."""
        return int(self.pieces.room[self.pieces.order[self.first :]].sum())


def _walk_part(
    state: ShardWalk,
    shard: Shard,
    shard_id: int,
    shard_mask: int,
    scan: ScanStamp,
    limit: int | None,
    final: bool,
) -> None:
    """Walk ``state``'s pieces (``split_into``: the stretches of the rays in ``shard``'s
    tiles, by tile, in ray order within a tile) into ``shard``, in one compiled call unless
    the shard needs room, from where ``state`` stands. Grows the shard when it runs out of
    room, up to ``limit`` blocks in all (None: no bound). At the limit, it pauses
    (``state.done`` stays False; ``_walk_shares`` may give it more blocks), or, when
    ``final``, cuts the rays not walked whole yet (``cut_to_blocks``; their stretches walked
    already stay) and splits them again, by ray; ``state.cut``: how many were cut."""
    state.ordered()
    walk, pieces = state.walk, state.pieces
    count = len(walk.lengths)
    most = _NO_LIMIT if limit is None else limit
    cache = _walk_cache()
    first = state.first
    piece_visits, left = state.visits, state.left
    try:
        while first < len(pieces.order):
            _make_room(shard, piece_visits, left, first)
            first = _walk_rays(
                walk, pieces, first, shard_id, shard_mask, shard.arrays(), scan, most, cache
            )
            if first == len(pieces.order):
                break
            # the next group of pieces (see _walk_rays) did not fit in the blocks (else
            # only in the chunks: room is made again)
            need = int(pieces.room[pieces.order[first : first + LANES]].sum())
            if not _blocks_short(shard, need, most):
                continue
            if limit is not None and shard.used + need > limit and not final:
                return  # paused: more blocks may come
            if limit is not None and shard.used + need > limit and not state.cut_done:
                # the rays not walked whole are cut; their stretches walked stay
                rest = pieces.order[first:]
                ray = int(pieces.ray[rest].min())
                cut_rays = cut_to_blocks(walk, ray, limit - shard.used)
                if cut_rays is None:  # not even a step each: the rest is not walked
                    state.cut = count - ray
                    first = len(pieces.order)
                    break
                (walk, state.cut), state.cut_done = cut_rays, True
                walked = {
                    (int(pieces.ray[p]), *pieces.voxel[p, :3].tolist())
                    for p in pieces.order[:first]
                    if pieces.ray[p] >= ray
                }
                split, offsets = split_rays(
                    walk.origins_vox, walk.ends_vox, walk.has_return, ray, count, shard_mask, False
                )
                pieces = _shard_pieces(split, offsets, shard_id)
                keep = [
                    (int(pieces.ray[p]), *pieces.voxel[p, :3].tolist()) not in walked
                    for p in pieces.order
                ]
                pieces = pieces._replace(order=pieces.order[np.array(keep, dtype=bool)])
                piece_visits, left = piece_room(pieces.voxel, pieces.order)
                first = 0
                continue
            if limit is not None and shard.used + need > limit:  # cut, and still too many
                state.cut = max(state.cut, count - int(pieces.ray[pieces.order[first:]].min()))
                first = len(pieces.order)
                break
            shard.grow(min_free=need, at_most=limit)  # the limit is checked at each growth
    finally:
        state.walk, state.pieces, state.first = walk, pieces, first
        state.visits, state.left = piece_visits, left
        state.done = first >= len(pieces.order)


_NO_LIMIT = 1 << 62
"""``_walk_rays``' block limit when a scan may add any number of blocks."""


def _walk_whole(rays: Rays, shard: Shard, scan: ScanStamp, share: int | None = None) -> int:
    """``_walk_part`` for a store of one shard: the rays whole, in order (the same walk)."""
    walk = _ray_arrays(rays)
    visits = walk.visits_needed
    limit = None if share is None else shard.used + share
    most = _NO_LIMIT if limit is None else limit
    none = np.empty(0, dtype=np.int64)
    none32 = none.astype(np.int32)
    no_pieces = Pieces(
        none32, none32.reshape(0, 4), none32, none.astype(bool), none.reshape(0, 6), none
    )
    first, cut, cut_done = 0, 0, False
    cache = _walk_cache()
    left = np.cumsum(visits[::-1])[::-1]  # visits of rays r.., at most as many new chunks
    while first < len(rays):
        _make_room(shard, visits, left, first)
        first = _walk_rays(walk, no_pieces, first, 0, 0, shard.arrays(), scan, most, cache)
        need = int(walk.room_needed[first : first + LANES].sum())
        if first < len(rays) and _blocks_short(shard, need, most):  # the next group of
            # rays (see _walk_rays) did not fit in the blocks (else only in the chunks)
            if limit is not None and shard.used + need > limit and not cut_done:
                rest = cut_to_blocks(walk, first, limit - shard.used)
                if rest is None:  # not even a step each: the rest is not walked
                    return len(rays) - first
                (walk, cut), cut_done = rest, True
                continue
            if limit is not None and shard.used + need > limit:  # cut, and still too many
                return max(cut, len(rays) - first)
            shard.grow(min_free=need, at_most=limit)  # the limit is checked at each growth
    return cut


def _make_room(
    shard: Shard, visits: NDArray[np.int64], left: NDArray[np.int64], first: int
) -> None:
    """Room in ``shard``'s pools for the chunks of the next groups' ``visits`` from
    ``first`` at least (``left``: the visits from each on, at most as many new chunks) and
    for their returns; grown by a quarter, so that the walk returns for more room a few
    times a map only."""
    pools = shard.pools
    next_groups = int(visits[first : first + 2 * LANES].sum())
    spare = int(pools[S_USED]) // 4 + 4096
    shard.ensure_room(
        min(int(left[first]), max(next_groups, spare)),
        max(4 * LANES, int(pools[NCHUNK_USED]) // 4 + 256),
    )


def _blocks_short(shard: Shard, need: int, most: int) -> bool:
    """Whether ``need`` more blocks do not fit in ``shard``'s free blocks (as
    ``_walk_rays`` checks, ``most`` its block limit)."""
    capacity = min(shard.capacity, shard.table_keys.shape[0] // 2, most)
    return shard.used + need > capacity


def _shard_pieces(pieces: Pieces, offsets: NDArray[np.int64], shard: int) -> Pieces:
    """Shard ``shard``'s pieces of ``split_rays``'."""
    return pieces._replace(order=pieces.order[offsets[shard] : offsets[shard + 1]])


def cut_to_blocks(walk: RayArrays, first: int, blocks: int) -> tuple[RayArrays, int] | None:
    """``walk`` with rays ``first:`` shortened (no return where cut) so that their block
    bounds (``ray_bounds``) add up to at most ``blocks``: one cap on their length, the
    longest cut first (bisection); the rays cut; None when even zero-length rays do not fit."""
    origins, ends = walk.origins_vox[first:], walk.ends_vox[first:]
    span = ends - origins
    length = np.sqrt((span * span).sum(axis=1))

    def capped(cap: float) -> NDArray[np.float64]:
        scale = np.minimum(1.0, cap / np.maximum(length, 1e-12))
        return np.ascontiguousarray(origins + span * scale[:, None])

    def cost(cap: float) -> int:
        return int(ray_bounds(origins, capped(cap))[0].sum())

    if cost(0.0) > blocks:
        return None
    lo, hi = 0.0, float(length.max(initial=0.0))
    while hi - lo > 1.0:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cost(mid) <= blocks else (lo, mid)
    new_ends = capped(lo)
    shortened = length > lo
    scale = np.where(shortened, lo / np.maximum(length, 1e-12), 1.0)
    room, visits = ray_bounds(origins, new_ends)
    cat = np.concatenate
    rays = RayArrays(
        walk.origins_vox,
        cat([walk.ends_vox[:first], new_ends]),
        cat([walk.lengths[:first], walk.lengths[first:] * scale]),
        cat([walk.has_return[:first], walk.has_return[first:] & ~shortened]),
        cat([walk.room_needed[:first], room]),
        cat([walk.visits_needed[:first], visits]),
    )
    return rays, int(shortened.sum())


@nb.njit(cache=True, nogil=True, inline="always")
def _fixed(t: float) -> int:
    """t (at least 0) in the walks' fixed point (``lockstep.T_ONE``), at most 2."""
    return int(min(t, 2.0) * T_ONE)


@nb.njit(cache=True, nogil=True, inline="always")
def _ray_start(origins_vox, ends_vox, r):  # type: ignore[no-untyped-def]
    """Ray ``r``'s start for a voxel walk (voxel units): first voxel, end voxel, steps per
    axis, where each axis' next face is crossed and the t between its faces (ray
    parameter t in [0, 1], in fixed point: ``lockstep.T_ONE``), and the number of steps.
    An axis already at the end voxel's index is never stepped again (t_max =
    ``T_NEVER``), so a walk takes exactly ``steps`` steps and ends in floor(end), whatever
    the rounding. The j-th face of an axis is at ``t_max + j * t_delta``, exactly. Shared
    by ``_walk_rays``, ``split_rays`` and ``read_walk``: same voxels, same chords."""
    ox = origins_vox[r, 0]
    oy = origins_vox[r, 1]
    oz = origins_vox[r, 2]
    dx = ends_vox[r, 0] - ox
    dy = ends_vox[r, 1] - oy
    dz = ends_vox[r, 2] - oz
    vx = int(np.floor(ox))
    vy = int(np.floor(oy))
    vz = int(np.floor(oz))
    ex = int(np.floor(ends_vox[r, 0]))
    ey = int(np.floor(ends_vox[r, 1]))
    ez = int(np.floor(ends_vox[r, 2]))
    step_x = 1 if ex > vx else -1
    step_y = 1 if ey > vy else -1
    step_z = 1 if ez > vz else -1
    t_max_x = _fixed(((vx + (dx > 0)) - ox) / dx) if ex != vx else T_NEVER
    t_max_y = _fixed(((vy + (dy > 0)) - oy) / dy) if ey != vy else T_NEVER
    t_max_z = _fixed(((vz + (dz > 0)) - oz) / dz) if ez != vz else T_NEVER
    t_delta_x = _fixed(abs(1.0 / dx)) if ex != vx else 0
    t_delta_y = _fixed(abs(1.0 / dy)) if ey != vy else 0
    t_delta_z = _fixed(abs(1.0 / dz)) if ez != vz else 0
    steps = abs(ex - vx) + abs(ey - vy) + abs(ez - vz)
    return (vx, vy, vz, ex, ey, ez, step_x, step_y, step_z, t_max_x, t_max_y, t_max_z,
            t_delta_x, t_delta_y, t_delta_z, steps)  # fmt: skip


@nb.njit(cache=True, nogil=True, inline="always")
def _piece_start(origins_vox, ends_vox, faces, r, vx, vy, vz):  # type: ignore[no-untyped-def]
    """Ray ``r``'s walk (``_ray_start``; ``faces``: its first faces and the t between
    faces, ``Pieces.faces``) from voxel ``(vx, vy, vz)`` of it on: that voxel, the end
    voxel, the steps, each axis' next face there and the t between its faces, and the t
    where the walk entered the voxel. An axis has crossed ``|v - v0|`` faces there, the
    j-th at ``t_first + j * t_delta`` exactly, so its next face is the one after, and the
    walk entered at the last face it crossed, the latest of each axis' last: the state the
    walk from the origin has there, bit for bit. (A piece once stored that state: 57 bytes
    a piece, not 25 and 48 a ray; with the faces computed here, three divisions more a
    piece, the walks took as much more time as the split saved.)"""
    ex = int(np.floor(ends_vox[r, 0]))
    ey = int(np.floor(ends_vox[r, 1]))
    ez = int(np.floor(ends_vox[r, 2]))
    v0x = int(np.floor(origins_vox[r, 0]))
    v0y = int(np.floor(origins_vox[r, 1]))
    v0z = int(np.floor(origins_vox[r, 2]))
    step_x = 1 if ex > v0x else -1
    step_y = 1 if ey > v0y else -1
    step_z = 1 if ez > v0z else -1
    crossed_x = (vx - v0x) * step_x
    crossed_y = (vy - v0y) * step_y
    crossed_z = (vz - v0z) * step_z
    t_delta_x, t_delta_y, t_delta_z = faces[r, 3], faces[r, 4], faces[r, 5]
    t_max_x = faces[r, 0] + crossed_x * t_delta_x if vx != ex else T_NEVER
    t_max_y = faces[r, 1] + crossed_y * t_delta_y if vy != ey else T_NEVER
    t_max_z = faces[r, 2] + crossed_z * t_delta_z if vz != ez else T_NEVER
    t_entered = 0
    if crossed_x > 0:
        t_entered = max(t_entered, faces[r, 0] + (crossed_x - 1) * t_delta_x)
    if crossed_y > 0:
        t_entered = max(t_entered, faces[r, 1] + (crossed_y - 1) * t_delta_y)
    if crossed_z > 0:
        t_entered = max(t_entered, faces[r, 2] + (crossed_z - 1) * t_delta_z)
    return (vx, vy, vz, ex, ey, ez, step_x, step_y, step_z, t_max_x, t_max_y, t_max_z,
            t_delta_x, t_delta_y, t_delta_z, min(t_entered, T_ONE))  # fmt: skip


class Pieces(NamedTuple):
    """The stretches of rays one shard walks (``split_rays``): each is walked from exactly
    the state the walk from the ray's origin has where it starts."""

    ray: NDArray[np.int32]
    """The ray each piece is a stretch of."""
    voxel: NDArray[np.int32]
    """(P, 4): the piece's first voxel, and its steps (it ends in the voxel that many
    steps further). The walk's state there follows from the ray (``_piece_start``): 25
    bytes a piece (with the state, 57: the split wrote, copied and the walks read 2.3
    times the bytes)."""
    room: NDArray[np.int32]
    """Upper bound of the blocks the piece can create."""
    has_return: NDArray[np.bool_]
    """The piece ends the ray, and the ray has a return."""
    faces: NDArray[np.int64]
    """(R, 6), by ray: where each axis' first face is crossed and the t between its faces
    (``_ray_start``), written once a ray by the split, so that a piece's walk starts
    without a division (``_piece_start``)."""
    order: NDArray[np.int64]
    """The pieces to walk, in the order to walk them (indices)."""


@nb.njit(cache=True, nogil=True, inline="always")
def _faces_before(faces, t_first, t_delta, t, strict):  # type: ignore[no-untyped-def]
    """How many of an axis' ``faces`` (the j-th at ``t_first + j * t_delta``) the walk
    crosses before t (``strict``: those at t itself come after)."""
    if faces == 0 or t < t_first or (strict and t == t_first):
        return 0
    # faces j with t_first + j * t_delta < t (or <= t)
    span = t - t_first
    count = (span + t_delta - 1) // t_delta if strict else span // t_delta + 1
    return min(count, faces)


_TILE_BUCKET_BITS = 4
"""``split_rays`` orders a shard's pieces by tile, by the low 4 bits of each tile index."""


@nb.njit(cache=True, nogil=True, inline="always")
def _tile_geometry(shard_mask: int) -> tuple[int, int]:
    """The voxel index bits of a tile side of a store of ``shard_mask + 1`` shards, and how
    many voxels its z faces sit below multiples of a tile (``blocks.tile_bits``)."""
    return BLOCK_BITS + tile_bits(shard_mask), tile_z_offset(shard_mask) << BLOCK_BITS


@nb.njit(cache=True, nogil=True, inline="always")
def _piece_bound(origins_vox, ends_vox, r, shard_mask):  # type: ignore[no-untyped-def]
    """At most how many pieces ray ``r`` is split into (``split_rays``): one, and one a
    tile face it crosses."""
    bound = 1
    if shard_mask:
        tile_shift, z_offset = _tile_geometry(shard_mask)
        for axis in range(3):
            off = z_offset if axis == 2 else 0
            lo = (int(np.floor(origins_vox[r, axis])) + off) >> tile_shift
            hi = (int(np.floor(ends_vox[r, axis])) + off) >> tile_shift
            bound += abs(hi - lo)
    return bound


@nb.njit(cache=True, nogil=True)
def split_rays(
    origins_vox: NDArray[np.float64],
    ends_vox: NDArray[np.float64],
    has_return: NDArray[np.bool_],
    first: int,
    stop: int,
    shard_mask: int,
    by_tile: bool,
) -> tuple[Pieces, NDArray[np.int64]]:
    """The stretches of rays ``first:stop`` in each shard's tiles (``blocks.shard_of``),
    and where each shard's are: shard k's are pieces ``offsets[k]:offsets[k + 1]``. One
    piece a ray with one shard.

    A ray's walk is a merge of three sorted sequences, the t of each axis' faces (the
    j-th at ``t_max + j * t_delta``, exact in fixed point: ``lockstep.T_ONE``), taken in
    order of t, x before y before z at equal t. A tile is entered at one of its faces, at
    that face's t: the voxel there, and every axis' next face, follow from counting each
    axis' faces before that t (``_faces_before``), so the piece's walk takes the steps and
    chords of the whole walk, bit for bit.

    A shard's pieces are in ray order, a ray's in the order of its walk; with
    ``by_tile``, by tile (the low bits of its index), in ray order within each: two
    pieces that can share a voxel are in one tile, so every voxel still gets its chords
    in ray order, as from one thread walking whole rays, while neighbouring lanes
    (``LANES``) walk alike stretches of one tile."""
    bound = 0
    for r in range(first, stop):
        bound += _piece_bound(origins_vox, ends_vox, r, shard_mask)
    pieces = _new_pieces(bound, stop)
    owner = np.empty(bound, dtype=np.int64)
    k = _split_write(
        origins_vox, ends_vox, has_return, first, stop, shard_mask, pieces, owner, 0,
        pieces.faces,
    )  # fmt: skip
    pieces = Pieces(
        pieces.ray[:k], pieces.voxel[:k], pieces.room[:k], pieces.has_return[:k],
        pieces.faces, np.arange(k),
    )  # fmt: skip
    if shard_mask == 0:
        return pieces, np.array([0, k], dtype=np.int64)
    bits = _TILE_BUCKET_BITS if by_tile else 0
    bucket, starts = _bucket_starts(owner, pieces.voxel, k, shard_mask, bits, np.empty(k, np.int64))
    offsets = starts[:: 1 << (3 * bits)].copy()
    order = np.empty(k, dtype=np.int64)
    for p in range(k):
        order[starts[bucket[p]]] = p
        starts[bucket[p]] += 1
    return Pieces(
        pieces.ray, pieces.voxel, pieces.room, pieces.has_return, pieces.faces, order
    ), offsets


@nb.njit(cache=True, nogil=True)
def _new_pieces(count: int, rays: int) -> Pieces:
    """Room for ``count`` pieces of ``rays`` rays (``order`` empty)."""
    return Pieces(
        np.empty(count, dtype=np.int32), np.empty((count, 4), dtype=np.int32),
        np.empty(count, dtype=np.int32), np.empty(count, dtype=np.bool_),
        np.empty((rays, 6), dtype=np.int64), np.empty(0, dtype=np.int64),
    )  # fmt: skip


_split_room: weakref.WeakKeyDictionary[BlockStore, Pieces] = weakref.WeakKeyDictionary()
"""Each store's room for a scan's pieces, kept from scan to scan."""


_split_scratches = threading.local()


def _split_scratch(count: int) -> tuple[Pieces, NDArray[np.int64]]:
    """This thread's room for the pieces of one part (``split_into``), kept from call to
    call: allocated a call, pages faulted in each time, it cost the split of OS1-128 at
    0.1 m 11 of 37 ms."""
    scratch: tuple[Pieces, NDArray[np.int64]] | None = getattr(_split_scratches, "room", None)
    if scratch is None or scratch[0].ray.shape[0] < count:
        scratch = _new_pieces(max(count, 1024), 0), np.empty((2, max(count, 1024)), np.int64)
        _split_scratches.room = scratch
    return scratch


def _flat_pieces(store: BlockStore, count: int, rays: int) -> Pieces:
    """Room for a whole scan's pieces, of ``rays`` rays (``split_into``; ``order`` empty),
    in memory kept from scan to scan (fresh memory each scan: its pages faulted in by the
    split, 20-40% more CPU time in the split of OS1-128 at 0.2 m)."""
    room = _split_room.get(store)
    if room is None or room.ray.shape[0] < count or room.faces.shape[0] < rays:
        room = _new_pieces(max(count, count + count // 4), max(rays, rays + rays // 4))
        _split_room[store] = room
    return room


@nb.njit(cache=True, nogil=True)
def _bucket_starts(owner, voxel, k, shard_mask, bits, bucket):  # type: ignore[no-untyped-def]
    """A stable counting sort's keys of pieces ``:k``: by shard, then by tile bucket (the
    low ``bits`` of each tile index), written to ``bucket``; where each key's pieces
    start."""
    tile_shift, z_offset = _tile_geometry(shard_mask)
    mask = (1 << bits) - 1
    starts = np.zeros(((shard_mask + 1) << (3 * bits)) + 1, dtype=np.int64)
    for p in range(k):
        key = owner[p]
        for b in range(3):
            off = z_offset if b == 2 else 0
            key = (key << bits) | (((voxel[p, b] + off) >> tile_shift) & mask)
        bucket[p] = key
        starts[key + 1] += 1
    for key in range(1, starts.shape[0]):
        starts[key] += starts[key - 1]
    return bucket, starts


@nb.njit(cache=True, nogil=True)
def piece_counts(
    origins_vox: NDArray[np.float64],
    ends_vox: NDArray[np.float64],
    first: int,
    stop: int,
    size: int,
    shard_mask: int,
    part_at: NDArray[np.int64],
) -> None:
    """Adds to ``part_at[c + 1]`` how many pieces the rays of part ``c`` (rays ``c * size``
    on) among rays ``first:stop`` can have (``_piece_bound``): where each part's start in a
    scan's split (``split_into``), once summed."""
    for r in range(first, stop):
        part_at[r // size + 1] += _piece_bound(origins_vox, ends_vox, r, shard_mask)


@nb.njit(cache=True, nogil=True)
def split_into(
    origins_vox: NDArray[np.float64],
    ends_vox: NDArray[np.float64],
    has_return: NDArray[np.bool_],
    first: int,
    stop: int,
    shard_mask: int,
    out: Pieces,
    at: int,
    scratch: Pieces,
    keys: NDArray[np.int64],
    segments: NDArray[np.int64],
    work: NDArray[np.int64],
) -> int:
    """``split_rays`` of rays ``first:stop`` (by tile), written into ``out`` from piece
    ``at`` on through ``scratch`` and ``keys`` (2, n) (room for the part's pieces at least,
    ``piece_counts``; ``_split_scratch``), in the order to walk
    them: shard k's are pieces ``segments[k, 0]:segments[k, 1]``, so that its walk reads
    them one after another (read through a shuffled ``order`` as ``split_rays`` gives
    them, the walks of OS1-128 at 0.2 m took 5-8% more CPU time, more than the copy
    costs the split); ``work[0, k]`` their steps plus ``PIECE_STEPS`` a stretch,
    ``work[1, k]`` the blocks they can create (``shard_work``). Returns how many pieces."""
    owner = keys[0]
    k = _split_write(
        origins_vox, ends_vox, has_return, first, stop, shard_mask, scratch, owner, 0, out.faces
    )
    bucket, starts = _bucket_starts(owner, scratch.voxel, k, shard_mask, _TILE_BUCKET_BITS, keys[1])
    shards = shard_mask + 1
    per_shard = starts.shape[0] // shards
    for s in range(shards):
        segments[s, 0] = at + starts[s * per_shard]
        segments[s, 1] = at + starts[(s + 1) * per_shard]
    ray, voxel, room, returns = out.ray, out.voxel, out.room, out.has_return
    steps = np.zeros(shards, dtype=np.int64)
    blocks = np.zeros(shards, dtype=np.int64)
    for p in range(k):
        q = at + starts[bucket[p]]
        starts[bucket[p]] += 1
        ray[q] = scratch.ray[p]
        for c in range(4):
            voxel[q, c] = scratch.voxel[p, c]
        room[q] = scratch.room[p]
        returns[q] = scratch.has_return[p]
        s = owner[p]
        steps[s] += scratch.voxel[p, 3] + 1 + PIECE_STEPS
        blocks[s] += scratch.room[p]
    # summed apart and written once: the threads write neighbouring rows of ``work``
    work[0] = steps
    work[1] = blocks
    return k


@nb.njit(cache=True, nogil=True)
def shard_order(segments: NDArray[np.int64], shard: int) -> NDArray[np.int64]:
    """Shard ``shard``'s pieces of a scan's split (``split_into``), part after part."""
    total = 0
    for c in range(segments.shape[0]):
        total += segments[c, shard, 1] - segments[c, shard, 0]
    order = np.empty(total, dtype=np.int64)
    i = 0
    for c in range(segments.shape[0]):
        for p in range(segments[c, shard, 0], segments[c, shard, 1]):
            order[i] = p
            i += 1
    return order


@nb.njit(cache=True, nogil=True)
def piece_room(
    voxel: NDArray[np.int32], order: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The visits of each piece in ``order``, and of the pieces from each on (at most as
    many new chunks: ``_make_room``)."""
    visits = np.empty(order.shape[0], dtype=np.int64)
    left = np.empty(order.shape[0], dtype=np.int64)
    total = 0
    for i in range(order.shape[0] - 1, -1, -1):
        visits[i] = voxel[order[i], 3] + 1
        total += visits[i]
        left[i] = total
    return visits, left


@nb.njit(cache=True, nogil=True)
def _split_write(origins_vox, ends_vox, has_return, first, stop, shard_mask, out, owner, k, faces):  # type: ignore[no-untyped-def]
    """The pieces of rays ``first:stop`` (``split_rays``), in ray order, written to ``out``
    from piece ``k`` on, their shards to ``owner`` (from 0), and the rays' faces to their
    rows of ``faces`` (``Pieces.faces``); returns the piece after the last."""
    tile_shift, z_offset = _tile_geometry(shard_mask)
    k_first = k
    ray, voxel, room, returns = out.ray, out.voxel, out.room, out.has_return
    v = np.empty(3, dtype=np.int64)
    v0 = np.empty(3, dtype=np.int64)
    end = np.empty(3, dtype=np.int64)
    step = np.empty(3, dtype=np.int64)
    t_first = np.empty(3, dtype=np.int64)
    t_delta = np.empty(3, dtype=np.int64)
    tile = np.empty(3, dtype=np.int64)
    crossings = np.empty(3, dtype=np.int64)
    t_cross = np.empty(3, dtype=np.int64)
    count = np.empty(3, dtype=np.int64)
    for r in range(first, stop):
        (v0[0], v0[1], v0[2], end[0], end[1], end[2], step[0], step[1], step[2],
         t_first[0], t_first[1], t_first[2], t_delta[0], t_delta[1], t_delta[2],
         steps) = _ray_start(origins_vox, ends_vox, r)  # fmt: skip
        for axis in range(3):
            faces[r, axis] = t_first[axis]
            faces[r, 3 + axis] = t_delta[axis]
            v[axis] = v0[axis]
            off = z_offset if axis == 2 else 0
            tile[axis] = (v0[axis] + off) >> tile_shift
            crossings[axis] = (
                abs(((end[axis] + off) >> tile_shift) - tile[axis]) if shard_mask else 0
            )
            t_cross[axis] = T_NEVER  # the t of the axis' next tile face (none left)
            if crossings[axis] > 0:
                face = ((tile[axis] + (step[axis] > 0)) << tile_shift) - off
                j = (face - v0[axis] - (step[axis] > 0)) * step[axis]
                t_cross[axis] = t_first[axis] + j * t_delta[axis]
        here = (tile[0] + tile[1] + tile[2]) & shard_mask
        start_steps = 0
        while True:
            # the next tile face the walk crosses: least t, x before y before z
            if t_cross[0] <= t_cross[1] and t_cross[0] <= t_cross[2]:
                a = 0
            elif t_cross[1] <= t_cross[2]:
                a = 1
            else:
                a = 2
            if crossings[a] == 0:  # no tile face left
                a = -1
                there = -1
                at = steps + 1
                t_enter = T_ONE
            else:
                t_enter = t_cross[a]
                tile[a] += step[a]
                crossings[a] -= 1
                t_cross[a] = T_NEVER
                if crossings[a] > 0:
                    face = ((tile[a] + (step[a] > 0)) << tile_shift) - (z_offset if a == 2 else 0)
                    j = (face - v0[a] - (step[a] > 0)) * step[a]
                    t_cross[a] = t_first[a] + j * t_delta[a]
                there = (tile[0] + tile[1] + tile[2]) & shard_mask
                if there != here:
                    # the voxel the walk enters there, after how many steps
                    if step[a] > 0:
                        count[a] = (tile[a] << tile_shift) - (z_offset if a == 2 else 0) - v0[a]
                    else:
                        count[a] = (
                            v0[a] - ((tile[a] + 1) << tile_shift) + (z_offset if a == 2 else 0) + 1
                        )
                    for b in range(3):
                        if b != a:
                            count[b] = _faces_before(
                                abs(end[b] - v0[b]), t_first[b], t_delta[b], t_enter, b > a
                            )
                    at = count[0] + count[1] + count[2]
                else:
                    at = 0
            if there != here:  # the piece up to here
                owner[k - k_first] = here
                ray[k] = r
                voxel[k, 0] = v[0]
                voxel[k, 1] = v[1]
                voxel[k, 2] = v[2]
                voxel[k, 3] = at - 1 - start_steps
                blocks = 2
                for b in range(3):
                    last = end[b] if a < 0 else v0[b] + step[b] * (count[b] - (b == a))
                    blocks += abs((last >> BLOCK_BITS) - (v[b] >> BLOCK_BITS))
                room[k] = blocks
                returns[k] = a < 0 and has_return[r]
                k += 1
            if a < 0:
                break
            if there != here:  # where the walk enters the next tile
                for b in range(3):
                    v[b] = v0[b] + step[b] * count[b]
                start_steps = at
            here = there
    return k


@nb.njit(cache=True, nogil=True, inline="always")
def _walk_cache_slot(key: int) -> int:
    """The walk cache's slot of a block key: the low bits of each block index
    (``KEY_OFFSET`` is a multiple of the cache, so they are the index's own)."""
    return (
        (((key >> (2 * KEY_BITS)) & _WALK_CACHE_MASK) << (2 * _WALK_CACHE_BITS))
        | (((key >> KEY_BITS) & _WALK_CACHE_MASK) << _WALK_CACHE_BITS)
        | (key & _WALK_CACHE_MASK)
    )


@nb.njit(cache=True, nogil=True)
def _walk_rays(
    rays: RayArrays,
    pieces: Pieces,
    first: int,
    shard: int,
    shard_mask: int,
    shard_arrays: ShardArrays,
    scan: ScanStamp,
    block_limit: int,
    walk_cache: WalkCache,
) -> int:
    """Walk pieces ``first..`` of ``rays`` (voxel units; ``split_rays``: the stretches of
    the rays in ``shard``'s tiles) and add their visits to ``shard``'s blocks; with one
    shard (``shard_mask`` 0), rays ``first..`` whole (``pieces`` unused: splitting whole
    rays into one piece each cost 5-8% of a scan of OS1-128 at 0.2 m).

    The pieces go ``LANES`` at a time, a group. ``lockstep.walk_lanes`` steps them all at
    once and writes every step out, and the keys of the blocks the rays enter; those in
    the walk cache give their chunk tables there and then, in one pass over the entries
    (a second pass, ray by ray, took about 10% of the walk's samples), the others are
    looked up (lookups independent of each other, so their memory latencies overlap) and
    opened ray by ray, in the order of the one-ray walk;
    ``lockstep.place_lanes`` turns the steps into store indices and weighted chords and
    starts loading their cache lines; a ray's return starts loading its ``n`` line (its
    block's ``n`` row read a group ahead, where the add read chunk owner, row and ``n``
    chunk one after another; with the read-only lookup of the group's new blocks, a later
    hall scan at 0.2 m walks in 28.3-28.5 ms of thread CPU against 30.0-30.8 without).
    Then the group before, whose lines were loaded meanwhile, is added (``_add_group``),
    piece by piece in ray order. Before each group, checks there is room for the blocks it
    may create; returns the index of the first piece not walked (the caller grows and
    calls again), or their number; the shard holds at most ``block_limit`` blocks (the
    caller cuts the rays beyond). ``walk_cache``: the blocks of ``shard`` this scan opened
    (``_walk_cache``), kept from call to call.
    """
    origins_vox, ends_vox, lengths = rays.origins_vox, rays.ends_vox, rays.lengths
    has_return, ray_room, ray_visits = rays.has_return, rays.room_needed, rays.visits_needed
    piece_ray, piece_voxel, room_needed, piece_return, ray_faces, order = pieces
    whole = shard_mask == 0
    scan_id, stamp, decay_time = scan
    sa = shard_arrays
    counters, block_scale, pools = sa.counters, sa.block_scale, sa.pools
    capacity = min(sa.block_t.shape[0], sa.table_keys.shape[0] // 2, block_limit)
    chunk_room = sa.chunk_owner.shape[0]
    n_room = min(sa.n_recs.shape[0] - pools[NREC_USED], sa.n_pool.shape[0] - pools[NCHUNK_USED])
    values = value_arrays(sa)
    block_chunks = sa.block_chunks
    block_nrec, n_recs, n_pool = sa.block_nrec, sa.n_recs, sa.n_pool
    table_keys, table_blocks = sa.table_keys, sa.table_blocks
    # the shard's blocks opened in this scan, direct-mapped by their low index bits: neighbouring
    # rays cross the same blocks, and this table (768 KiB) stays in cache where the hash does not
    cache = walk_cache
    total = lengths.shape[0] if whole else order.shape[0]
    longest = 1
    for i in range(first, total):
        longest = max(longest, ray_visits[i] if whole else piece_voxel[order[i], 3] + 1)
    # the group's steps (step k of lane l at k * LANES + l) and the blocks each ray enters
    step_code = np.empty(longest * LANES, dtype=np.int16)
    entered_key = np.empty((LANES, longest), dtype=np.int64)
    entered_chunks = np.empty((LANES, longest * BLOCK_CHUNKS), dtype=np.int32)  # their tables
    entered_weight = np.empty((LANES, longest))
    weight_flat = entered_weight.reshape(-1)
    base_flat = np.empty(LANES * longest, dtype=np.int64)  # their chunk tables' start
    missed = np.empty((LANES, longest), dtype=np.int64)  # entries not in the walk cache
    missed_key = np.empty((LANES, longest), dtype=np.int64)
    missed_count = np.zeros(LANES, dtype=np.int64)
    lane_blocks = np.empty(LANES, dtype=np.int64)
    entries = np.empty((2, (longest + 1) * LANES), dtype=np.int64)  # walk_lanes' entries
    entry_count = np.zeros(1, dtype=np.int64)
    lane_floats = np.empty((FLOAT_ROWS, LANES))
    lane_ints = np.empty((INT_ROWS, LANES), dtype=np.int64)
    # placed visits of two groups: the one being walked and the one waiting to be added
    placed_voxel = np.empty((2, longest * LANES), dtype=np.int64)
    placed_chord = np.empty((2, longest * LANES))  # the steps' chords, then weighted
    placed_added = np.empty((2, longest * LANES), dtype=np.float32)  # as the store adds them
    placed_steps = np.zeros((2, LANES), dtype=np.int64)
    return_weight = np.zeros((2, LANES))  # 0: no return (or another shard's end voxel)
    return_block = np.zeros((2, LANES), dtype=np.int64)  # the end voxel's block
    return_place = np.zeros((2, LANES), dtype=np.int64)  # and its index there
    group = 0
    waiting = 0  # rays of the group waiting to be added
    waiting_visits = 0  # their visits: at most as many new s chunks
    n_start = pools[NCHUNK_USED]  # n chunks (and rows) made since: at most one a return
    group_first = first
    while True:
        lanes = min(LANES, total - group_first)
        blocks_needed = 0
        visits = 0
        for lane in range(lanes):
            i = group_first + lane
            blocks_needed += ray_room[i] if whole else room_needed[order[i]]
            visits += ray_visits[i] if whole else piece_voxel[order[i], 3] + 1
        if (
            lanes == 0
            or counters[0] + blocks_needed > capacity
            or pools[S_USED] + waiting_visits + visits > chunk_room
            or pools[NCHUNK_USED] - n_start + 2 * LANES > n_room
        ):
            _add_group(
                values, placed_voxel[1 - group], placed_added[1 - group],
                placed_chord[1 - group], placed_steps[1 - group], return_weight[1 - group],
                return_block[1 - group], return_place[1 - group], waiting,
            )  # fmt: skip
            return group_first
        steps = 0
        for lane in range(LANES):  # lanes past the last piece repeat the group's first
            i = group_first + (lane if lane < lanes else 0)
            if whole:
                r = i
                (vx, vy, vz, ex, ey, ez, step_x, step_y, step_z, t_max_x, t_max_y, t_max_z,
                 t_delta_x, t_delta_y, t_delta_z, piece_steps) = _ray_start(
                    origins_vox, ends_vox, r)  # fmt: skip
                t_prev = 0
            else:  # a piece: the ray's walk from the piece's first voxel on
                p = order[i]
                r = piece_ray[p]
                (vx, vy, vz, ex, ey, ez, step_x, step_y, step_z, t_max_x, t_max_y, t_max_z,
                 t_delta_x, t_delta_y, t_delta_z, t_prev) = _piece_start(
                    origins_vox, ends_vox, ray_faces, r, piece_voxel[p, 0], piece_voxel[p, 1],
                    piece_voxel[p, 2])  # fmt: skip
                piece_steps = piece_voxel[p, 3]
            lane_floats[0, lane] = lengths[r] / T_ONE
            lane_ints[0, lane] = vx
            lane_ints[1, lane] = vy
            lane_ints[2, lane] = vz
            lane_ints[3, lane] = step_x
            lane_ints[4, lane] = step_y
            lane_ints[5, lane] = step_z
            lane_ints[6, lane] = ex
            lane_ints[7, lane] = ey
            lane_ints[8, lane] = ez
            lane_ints[9, lane] = piece_steps
            lane_ints[10, lane] = t_max_x
            lane_ints[11, lane] = t_max_y
            lane_ints[12, lane] = t_max_z
            lane_ints[13, lane] = t_delta_x
            lane_ints[14, lane] = t_delta_y
            lane_ints[15, lane] = t_delta_z
            lane_ints[16, lane] = t_prev
            placed_steps[group, lane] = piece_steps
            steps = max(steps, piece_steps + 1)
        step_chord = placed_chord[group]
        walk_lanes(  # type: ignore[call-arg]
            lane_floats, lane_ints, steps, entered_key, lane_blocks, step_code, step_chord,
            entries, entry_count,
        )  # fmt: skip
        # the entered blocks' keys put in each ray's row; a block in the walk cache gives
        # its chunk table there and then (a lane repeating the first ray: no block); the
        # others are looked up (read only) all at once, their chunk tables loaded
        # (independent lookups whose memory latencies overlap), and opened after, ray by
        # ray in order, as the one-ray walk opens them
        late = 0  # _LATE set where the scan is late in a block
        missed_count[:] = 0
        repeats_from = lanes * longest  # entries of the lanes repeating the first ray
        for e in range(entry_count[0]):
            key = entries[0, e]
            at = entries[1, e]
            slot = _walk_cache_slot(key)
            if at >= repeats_from:
                base = 0
            elif cache[2 * slot] == key:
                base = cache[2 * slot + 1]
            else:
                lane = at // longest
                missed[lane, missed_count[lane]] = at
                missed_key[lane, missed_count[lane]] = key
                missed_count[lane] += 1
                bx, by, bz = block_of_key(key)
                found = find_block(table_keys, table_blocks, block_key(bx, by, bz))
                if found >= 0:
                    prefetch_line(block_chunks, BLOCK_CHUNKS * (found + 1))
                continue
            copy_table(entered_chunks, at * BLOCK_CHUNKS, block_chunks, base & _BASE_MASK)
            base_flat[at] = base
            late |= base
        for lane in range(lanes):
            for m in range(missed_count[lane]):
                at = missed[lane, m]
                key = missed_key[lane, m]
                slot = _walk_cache_slot(key)
                if cache[2 * slot] != key:
                    bx, by, bz = block_of_key(key)
                    block = -1
                    if shard_of(bx, by, bz, shard_mask) == shard:
                        block = open_block(bx, by, bz, shard_arrays, scan_id, stamp, decay_time)
                    cache[2 * slot] = key
                    cache[2 * slot + 1] = 0
                    if block >= 0:
                        cache[2 * slot + 1] = BLOCK_CHUNKS * (block + 1)
                        if block_scale[block] != 1.0:
                            cache[2 * slot + 1] |= _LATE
                base = cache[2 * slot + 1]
                copy_table(entered_chunks, at * BLOCK_CHUNKS, block_chunks, base & _BASE_MASK)
                base_flat[at] = base
                late |= base
        weighted = (late & _LATE) != 0
        if weighted:  # rare: the weight of every entered block, for placing
            for e in range(entry_count[0]):
                at = entries[1, e]
                base = base_flat[at]
                late_block = (base & _BASE_MASK) // BLOCK_CHUNKS - 1
                weight_flat[at] = block_scale[late_block] if base & _LATE else 1.0
        for lane in range(lanes):
            i = group_first + lane
            blocks = lane_blocks[lane]
            base = base_flat[lane * longest + blocks - 1]  # the end voxel's block
            ends = has_return[i] if whole else piece_return[order[i]]
            ends_here = ends and base > 0
            return_weight[group, lane] = 0.0
            if ends_here:  # its n chunk's line, loaded while the group before is added
                block = (base & _BASE_MASK) // BLOCK_CHUNKS - 1
                return_weight[group, lane] = block_scale[block]
                place = step_code[placed_steps[group, lane] * LANES + lane] & LOCAL_MASK
                return_block[group, lane] = block
                return_place[group, lane] = place
                row = block_nrec[block]
                if row >= 0:
                    chunk = n_recs[row, place >> N_CHUNK_BITS]
                    if chunk >= 0:
                        prefetch_line(n_pool, chunk * N_CHUNK_VOXELS + (place & _N_MASK))
        place_lanes(
            step_code, step_chord, entered_chunks, entered_weight, weighted, steps, sa.s_pool,
            placed_voxel[group], placed_added[group],
        )  # fmt: skip
        _add_group(
            values, placed_voxel[1 - group], placed_added[1 - group], placed_chord[1 - group],
            placed_steps[1 - group], return_weight[1 - group], return_block[1 - group],
            return_place[1 - group], waiting,
        )  # fmt: skip
        waiting = lanes
        waiting_visits = visits
        group = 1 - group
        group_first += lanes


@nb.njit(cache=True, nogil=True)
def _add_group(
    values: ValueArrays,
    voxels: NDArray[np.int64],
    added: NDArray[np.float32],
    chords: NDArray[np.float64],
    steps: NDArray[np.int64],
    return_weight: NDArray[np.float64],
    return_block: NDArray[np.int64],
    return_place: NDArray[np.int64],
    lanes: int,
) -> None:
    """Add a group's placed visits (``lockstep.place_lanes``: an index in the ``s`` chunks,
    or negative: a chunk not allocated when placed, another shard's, or a visit skipped:
    its float32 chord is not above 0) to the blocks, ray by ray in order: ``s +=
    added`` (the float32 chord) for every visit in this shard, then the ray's return,
    ``n += float32(return_weight)`` in its end voxel (none where the weight is 0;
    ``return_block``, ``return_place``: its block and its index there, known from the
    walk, so the add reads no chunk owner), whose block is marked; ``chords``: the
    float64 chords, a return's visit counted where its chord is not above 0. Counts the
    voxels that became observed (``counters[1]``; a voxel's ``s`` is +0 exactly while
    unobserved: ``shard``'s module notes) and the visits (``counters[3]``); marks for a
    flush into float64 the blocks where a float32 part reached its limit (``limits``).

    The arrays are taken out of their tuple once: numba counts references of every array
    a helper takes, on every call, even inlined (about 40 cycles an array), so the paths
    of this loop use no helper."""
    (block_chunks, s_pool, chunk_owner, block_nrec, n_recs, n_pool, block_href, hi_pool,
     block_hit, block_flush, pools, counters, limits) = values  # fmt: skip
    observed = 0
    visits = 0
    lines = s_pool.reshape(-1)
    marks = lines.view(np.uint32)  # 0 exactly where a voxel is unobserved
    n_limit = limits[1]
    # the least float32 at or above limits[0]: a float32 sum passes it exactly where it
    # passes limits[0] (no conversion a visit)
    s_limit = np.float32(limits[0])
    if s_limit < limits[0]:
        s_limit = np.nextafter(s_limit, np.float32(np.inf))
    for lane in range(lanes):
        last = steps[lane]
        visits += last + 1  # less the steps skipped below
        for k in range(last + 1):
            voxel = voxels[k * LANES + lane]
            if voxel < 0:  # rare: one test on the common path
                if voxel < FOREIGN_LIMIT:  # another shard's, or skipped
                    visits -= 1
                    continue
                # its chunk is new (since it was placed): shard.s_index
                slot = (-voxel - 1) >> CHUNK_BITS
                chunk = block_chunks[slot]
                if chunk < 0:
                    chunk = pools[S_USED]
                    pools[S_USED] = chunk + 1
                    block_chunks[slot] = chunk
                    chunk_owner[chunk] = slot
                voxel = chunk * CHUNK_VOXELS + (voxel & (CHUNK_VOXELS - 1))
                voxels[k * LANES + lane] = voxel
            at = np.uint64(voxel)  # >= 0 here: unsigned, no wraparound test
            observed += marks[at] == 0  # a first visit (shard.UNOBSERVED)
            after = lines[at] + added[k * LANES + lane]
            lines[at] = after
            if after >= s_limit:  # rare: a flush due
                block_flush[chunk_owner[voxel >> CHUNK_BITS] // BLOCK_CHUNKS - 1] = True
                pools[FLUSH_PENDING] = 1
        if return_weight[lane] <= 0.0:
            continue
        # the end voxel takes the return; an end point exactly on a face gives a zero
        # chord there (a skipped visit), still with its return (shard.s_index,
        # shard.n_index)
        block = return_block[lane]
        place = return_place[lane]
        slot = BLOCK_CHUNKS * (block + 1) + (place >> CHUNK_BITS)
        chunk = block_chunks[slot]
        if chunk < 0:
            chunk = pools[S_USED]
            pools[S_USED] = chunk + 1
            block_chunks[slot] = chunk
            chunk_owner[chunk] = slot
        voxel = chunk * CHUNK_VOXELS + (place & (CHUNK_VOXELS - 1))
        row = block_nrec[block]
        if row < 0:
            row = pools[NREC_USED]
            pools[NREC_USED] = row + 1
            block_nrec[block] = row
            for part in range(N_BLOCK_CHUNKS):
                n_recs[row, part] = -1
        chunk = n_recs[row, place >> N_CHUNK_BITS]
        if chunk < 0:
            chunk = pools[NCHUNK_USED]
            pools[NCHUNK_USED] = chunk + 1
            n_recs[row, place >> N_CHUNK_BITS] = chunk
        if marks[voxel] == 0:  # observed now, s still 0: its mark (shard.UNOBSERVED)
            observed += 1
            lines[voxel] = np.float32(-0.0)
        n = n_pool[chunk, place % N_CHUNK_VOXELS] + np.float32(return_weight[lane])
        n_pool[chunk, place % N_CHUNK_VOXELS] = n
        block_hit[block] = True
        if n >= n_limit:
            block_flush[block] = True
            pools[FLUSH_PENDING] = 1
        visits += chords[last * LANES + lane] <= 0.0
    counters[1] += observed
    counters[3] += visits


StoreView = tuple[ShardArrays, ...]
"""The arrays of every shard, as a read-only walk reads them (``store_view``)."""


def store_view(store: BlockStore) -> StoreView:
    """The store's arrays for ``read_walk`` (valid until the store next changes)."""
    return tuple(sh.arrays() for sh in store.shards)


@nb.njit(cache=True, nogil=True)
def read_walk(
    origins_vox: NDArray[np.float64],
    ends_vox: NDArray[np.float64],
    lengths: NDArray[np.float64],
    has_return: NDArray[np.bool_],
    view: StoreView,
    shard_mask: int,
    stamp: float,
    decay_time: float,
    shape: float,
    rate: float,
    ray_log_likelihood: NDArray[np.float64],
    record: bool,
    event_ray: NDArray[np.int64],
    event_ijk: NDArray[np.int32],
    event_s: NDArray[np.float64],
    event_n: NDArray[np.float64],
    event_chord: NDArray[np.float64],
    event_hit: NDArray[np.bool_],
) -> int:
    """The read-only twin of ``_walk_rays``: the same steps and chords, nothing written
    to the store. Returns the number of events.

    Events of a ray: every voxel it crosses with a positive chord before its end voxel is a
    pass over that chord; its end voxel is a return over the voxel's FULL chord (from where
    the ray entered it to where it would leave it) when the ray has a return, else a pass
    over the chord up to the end point. A voxel's statistics are its block's, decayed to
    ``stamp`` by ``exp(-|stamp - t_block| / decay_time)`` (``model.decay``); absent blocks
    are never observed (s = n = 0). With the Gamma(``shape``, ``rate``) prior on the
    extinction the pass probability over a chord l is ``((s+rate)/(s+rate+l))^(n+shape)``
    and a return's probability 1 minus that. ``ray_log_likelihood[r]`` receives the sum
    of the log-probabilities of ray r's events. With ``record``, event k is written to the
    ``event_*`` arrays (ray, voxel index, decayed s and n, chord, whether a return),
    which must hold ``visit_bounds`` events per ray.
    """
    decays = math.isfinite(decay_time)
    events = 0
    # blocks found so far (block number, -1 when absent; shard), direct-mapped as in
    # _walk_rays: neighbouring rays cross the same blocks and the hash costs more
    cache_keys = np.full(1 << (3 * _READ_CACHE_BITS), -1, dtype=np.int64)
    cache_blocks = np.empty(cache_keys.shape[0], dtype=np.int64)
    tiny = 1e-280
    for r in range(lengths.shape[0]):
        length = lengths[r]
        # the stepping below is _walk_rays' (test_likelihood checks the chords); the ray's
        # origin and direction are also needed where it would leave its end voxel
        ox, oy, oz = origins_vox[r, 0], origins_vox[r, 1], origins_vox[r, 2]
        dx, dy, dz = ends_vox[r, 0] - ox, ends_vox[r, 1] - oy, ends_vox[r, 2] - oz
        (vx, vy, vz, ex, ey, ez, step_x, step_y, step_z, t_max_x, t_max_y, t_max_z,
         t_delta_x, t_delta_y, t_delta_z, steps) = _ray_start(origins_vox, ends_vox, r)  # fmt: skip
        t_prev = 0
        per_t = length / T_ONE
        morton_x = _SPREAD[vx & _LOCAL_MASK] << 2
        morton_y = _SPREAD[vy & _LOCAL_MASK] << 1
        morton_z = _SPREAD[vz & _LOCAL_MASK]
        wrap_x = 0 if step_x > 0 else _LOCAL_MASK
        wrap_y = 0 if step_y > 0 else _LOCAL_MASK
        wrap_z = 0 if step_z > 0 else _LOCAL_MASK
        shard = 0
        block = -1
        f = 1.0  # decay factor of the current block
        total = 0.0
        # passes of voxels without returns (exponent ``shape``): their ratios are
        # multiplied, one log at the end (a division per voxel instead of a log)
        product = 1.0
        new_block = True
        while True:
            if new_block:
                bx = vx >> BLOCK_BITS
                by = vy >> BLOCK_BITS
                bz = vz >> BLOCK_BITS
                shard = shard_of(bx, by, bz, shard_mask)
                key = block_key(bx, by, bz)
                slot = (
                    ((bx & _READ_CACHE_MASK) << (2 * _READ_CACHE_BITS))
                    | ((by & _READ_CACHE_MASK) << _READ_CACHE_BITS)
                    | (bz & _READ_CACHE_MASK)
                )
                here = view[shard]
                if cache_keys[slot] == key:
                    block = cache_blocks[slot]
                else:
                    block = find_block(here.table_keys, here.table_blocks, key)
                    cache_keys[slot] = key
                    cache_blocks[slot] = block
                f = 1.0
                if block >= 0 and decays:
                    f = math.exp(-abs(stamp - here.block_t[block]) / decay_time)
                # the shard's statistics, out of their tuple once a block (shard.voxel_stats)
                block_chunks, s_pool, block_nrec = here.block_chunks, here.s_pool, here.block_nrec
                n_recs, n_pool, block_href, hi_pool = (
                    here.n_recs,
                    here.n_pool,
                    here.block_href,
                    here.hi_pool,
                )
            local = morton_x | morton_y | morton_z
            cx, cy, cz = vx, vy, vz
            s = 0.0
            n = 0.0
            if block >= 0:
                chunk = block_chunks[BLOCK_CHUNKS * (block + 1) + (local >> CHUNK_BITS)]
                if chunk >= 0:
                    s = np.float64(s_pool[chunk, local % CHUNK_VOXELS]) + 0.0  # (not -0)
                row = block_nrec[block]
                if row >= 0:
                    chunk = n_recs[row, local >> N_CHUNK_BITS]
                    if chunk >= 0:
                        n = np.float64(n_pool[chunk, local % N_CHUNK_VOXELS])
                hi = block_href[block]
                if hi >= 0:
                    s += hi_pool[hi, local, 0]
                    n += hi_pool[hi, local, 1]
                s *= f
                n *= f
            if steps == 0:
                break
            if t_max_x <= t_max_y and t_max_x <= t_max_z:
                t_next = t_max_x
                vx += step_x
                t_max_x = t_max_x + t_delta_x if vx != ex else T_NEVER
                axis_local = vx & _LOCAL_MASK
                morton_x = _SPREAD[axis_local] << 2
                new_block = axis_local == wrap_x
            elif t_max_y <= t_max_z:
                t_next = t_max_y
                vy += step_y
                t_max_y = t_max_y + t_delta_y if vy != ey else T_NEVER
                axis_local = vy & _LOCAL_MASK
                morton_y = _SPREAD[axis_local] << 1
                new_block = axis_local == wrap_y
            else:
                t_next = t_max_z
                vz += step_z
                t_max_z = t_max_z + t_delta_z if vz != ez else T_NEVER
                axis_local = vz & _LOCAL_MASK
                morton_z = _SPREAD[axis_local]
                new_block = axis_local == wrap_z
            t_next = min(t_next, T_ONE)
            chord = (t_next - t_prev) * per_t
            t_prev = t_next
            steps -= 1
            if chord > 0.0:
                # log P(pass) = (n + shape) log((s + rate) / (s + rate + chord))
                if n == 0.0:
                    product *= (s + rate) / (s + rate + chord)
                    if product < tiny:
                        total += shape * math.log(product)
                        product = 1.0
                else:
                    total -= (n + shape) * math.log1p(chord / (s + rate))
                if record:
                    event_ray[events] = r
                    event_ijk[events, 0] = cx
                    event_ijk[events, 1] = cy
                    event_ijk[events, 2] = cz
                    event_s[events] = s
                    event_n[events] = n
                    event_chord[events] = chord
                    event_hit[events] = False
                events += 1
        # the end voxel (vx, vy, vz)
        if has_return[r]:
            # where the ray would leave the end voxel: its nearest exit face beyond the end
            t_exit = np.inf
            if dx != 0.0:
                t_exit = min(t_exit, ((vx + (dx > 0)) - ox) / dx)
            if dy != 0.0:
                t_exit = min(t_exit, ((vy + (dy > 0)) - oy) / dy)
            if dz != 0.0:
                t_exit = min(t_exit, ((vz + (dz > 0)) - oz) / dz)
            chord = max((max(t_exit, 1.0) - t_prev / T_ONE) * length, RETURN_CHORD_FLOOR)
            total += math.log(-math.expm1(-(n + shape) * math.log1p(chord / (s + rate))))
            hit = True
        else:
            chord = (T_ONE - t_prev) * per_t
            hit = False
            if chord > 0.0:
                total -= (n + shape) * math.log1p(chord / (s + rate))
        total += shape * math.log(product)
        if hit or chord > 0.0:
            if record:
                event_ray[events] = r
                event_ijk[events, 0] = vx
                event_ijk[events, 1] = vy
                event_ijk[events, 2] = vz
                event_s[events] = s
                event_n[events] = n
                event_chord[events] = chord
                event_hit[events] = hit
            events += 1
        ray_log_likelihood[r] = total
    return events
