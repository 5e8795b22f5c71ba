"""Applying voxel visits to blocks, in batches, with the visited cache lines prefetched
first (so their memory latencies overlap): the mail of other threads (``apply_visits``).
The integrating walk adds its own visits (``traversal._add_group``)."""

from __future__ import annotations

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from numpy.typing import NDArray

from mfp_mapper.core.blocks import BLOCK_VOXELS


@intrinsic
def prefetch_voxel(typingctx, array, index):  # type: ignore[no-untyped-def]
    """Ask the processor to start loading the cache line of ``array[index]`` (a row).

    A prefetch does not wait for the line (a load would hold its place in the processor's
    window until the line arrives), so many misses are in flight at once.
    """
    sig = types.void(array, index)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        array_type = signature.args[0]
        ary = context.make_array(array_type)(context, builder, args[0])
        index = [
            context.cast(builder, a, t, types.intp)
            for a, t in zip(args[1:], signature.args[1:], strict=True)
        ]
        pointer = cgutils.get_item_pointer2(
            context, builder, data=ary.data, shape=cgutils.unpack_tuple(builder, ary.shape),
            strides=cgutils.unpack_tuple(builder, ary.strides), layout=array_type.layout,
            inds=[*index, context.get_constant(types.intp, 0)], wraparound=False,
        )  # fmt: skip
        byte_pointer = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        prefetch = builder.module.declare_intrinsic(
            "llvm.prefetch",
            [byte_pointer],
            ir.FunctionType(ir.VoidType(), [byte_pointer, i32, i32, i32]),
        )
        # write access, high temporal locality, data cache
        builder.call(prefetch, [builder.bitcast(pointer, byte_pointer), i32(1), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


def _prefetch_compiles() -> bool:
    """Whether this numba/llvmlite turns ``prefetch_voxel`` into a prefetch instruction."""
    try:

        @nb.njit
        def probe(array: NDArray[np.float32]) -> None:
            prefetch_voxel(array, 0)  # type: ignore[call-arg]

        probe(np.zeros((1, 2), dtype=np.float32))
    except Exception:  # noqa: BLE001 - any failure means: use plain loads instead
        return False
    return True


PREFETCH = _prefetch_compiles()


CACHE_BITS = 4
CACHE_MASK = (1 << CACHE_BITS) - 1
CACHE_SIZE = 1 << (3 * CACHE_BITS)
BATCH_VISITS = 8192
"""Voxel visits gathered (from several rays) before they are applied to the blocks."""


@nb.njit(cache=True, nogil=True)
def apply_visits(
    block_sn: NDArray[np.float32],
    block_hit: NDArray[np.bool_],
    visit_voxel: NDArray[np.int64],
    visit_chord: NDArray[np.float32],
    visit_return: NDArray[np.float32],
    count: int,
    counters: NDArray[np.int64],
) -> None:
    """Add the buffered visits, in order, to their voxels: s += chord, n += return (and
    mark the blocks that hold a return).

    ``visit_voxel`` holds ``block * BLOCK_VOXELS + index in block``.
    """
    sn = block_sn.reshape((-1, 2))
    # first only fetch every visited cache line, so that many misses are in flight at once;
    # the additions then find the lines in cache. Without a prefetch instruction: plain
    # loads, which do not depend on each other either
    touch = np.float32(0.0)
    for i in range(count):
        if PREFETCH:
            prefetch_voxel(sn, visit_voxel[i])  # type: ignore[call-arg]
        else:
            touch += sn[visit_voxel[i], 1]
    new = 0
    for i in range(count):
        v = visit_voxel[i]
        if sn[v, 0] == 0.0 and sn[v, 1] == 0.0:
            new += 1
        sn[v, 0] += visit_chord[i]
        if visit_return[i] > 0.0:
            sn[v, 1] += visit_return[i]
            block_hit[v // BLOCK_VOXELS] = True
    counters[1] += new
    counters[3] += count + (touch < 0.0)  # touch is never negative; using it keeps the loads
