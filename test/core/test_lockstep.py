"""``lockstep``'s compress of vector lanes: the plain-IR version older LLVMs get equals
``llvm.experimental.vector.compress`` and the set lanes in order, for every mask."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba as nb
import numpy as np
import pytest
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from mfp_mapper.core import lockstep
from mfp_mapper.core.lockstep import LANES


def _kernel(compress: Callable[[ir.IRBuilder, ir.Value, ir.Value], ir.Value]) -> Any:
    """A compiled ``f(values, mask, out)`` writing ``compress`` of 8 int64 lanes."""

    @intrinsic
    def lanes(typingctx, values, mask, out):  # type: ignore[no-untyped-def]
        def codegen(context, builder, sig, args):  # type: ignore[no-untyped-def]
            data = [
                context.make_array(ty)(context, builder, arg).data
                for ty, arg in zip(sig.args, args, strict=True)
            ]
            vi = ir.VectorType(ir.IntType(64), LANES)
            vb = ir.VectorType(ir.IntType(8), LANES)
            value = builder.load(builder.bitcast(data[0], vi.as_pointer()), align=8)
            bytes_ = builder.load(builder.bitcast(data[1], vb.as_pointer()), align=1)
            flags = builder.icmp_unsigned("!=", bytes_, ir.Constant(vb, [0] * LANES))
            target = builder.bitcast(data[2], vi.as_pointer())
            builder.store(compress(builder, value, flags), target, align=8)
            return context.get_dummy_value()

        return types.void(values, mask, out), codegen

    @nb.njit(cache=False)
    def run(values: np.ndarray, mask: np.ndarray, out: np.ndarray) -> None:
        lanes(values, mask, out)

    return run


@pytest.mark.parametrize(
    "compress",
    [
        pytest.param(lockstep._compress_by_lanes, id="by_lanes"),
        pytest.param(
            lockstep._compress,
            id="native",
            marks=pytest.mark.skipif(
                not lockstep._NATIVE_COMPRESS, reason="this LLVM has no vector.compress"
            ),
        ),
    ],
)
def test_compress_keeps_the_set_lanes_in_order(
    compress: Callable[[ir.IRBuilder, ir.Value, ir.Value], ir.Value],
) -> None:
    run = _kernel(compress)
    values = np.arange(101, 101 + LANES, dtype=np.int64) * 7
    for bits in range(1 << LANES):
        mask = np.array([(bits >> k) & 1 for k in range(LANES)], dtype=np.uint8)
        out = np.zeros(LANES, dtype=np.int64)
        run(values, mask, out)
        kept = values[mask.astype(bool)]
        np.testing.assert_array_equal(out[: kept.size], kept, err_msg=f"mask {mask}")
