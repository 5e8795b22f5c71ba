"""Eight rays at a time, in vector registers: the voxel stepping and the voxel placing of
the integrating walk (``traversal._walk_rays`` drives them and adds what they write out).

A voxel walk (Amanatides & Woo) is a chain of unpredictable three-way branches, one per
step: written for one ray, a step costs 2.5 ns (hall scene at 0.2 m, bare walk). In
``walk_lanes`` each lane of a vector is one ray, every lane takes its step at once, and the
branch becomes a select per lane: the same comparisons and the same operations in the
same order (t in fixed point, ``T_ONE``), so every lane's voxels and chords are bit-for-bit
those of the one-ray walk (``test_traversal`` checks the store against the brute-force
chords).
``place_lanes`` then turns the steps into store indices and weighted chords, the blocks
gathered per lane, and starts loading the store's cache lines.

Numba does not vectorise such loops by itself (its loop vectoriser gives up on them), so
they are written in LLVM IR with vector types; on a processor with narrower vectors than
``LANES`` values LLVM splits them. Numba caches a compiled kernel by the stamp of its own
source file: after editing this file, clear the cache (``.numba_cache``, or the
``__pycache__`` next to the modules) or ``traversal.py`` keeps the old code.

Measured (hall scene, 4.95 M steps at 0.2 m, one thread, AVX-512): 5.5 ms for the lockstep
walk writing every step out, against 12.5 ms for the one-ray walk computing its chords
only.
"""

from __future__ import annotations

from llvmlite import ir
from llvmlite.binding import llvm_version_info
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from mfp_mapper.core.blocks import BLOCK_BITS, BLOCK_CHUNKS, CHUNK_BITS, KEY_BITS, KEY_OFFSET

LANES = 8
"""Rays per lockstep walk (one AVX-512 vector of float64)."""

FLOAT_ROWS = 1
"""Rows of the float lane state: the chord of one unit of t (length / ``T_ONE``)."""
INT_ROWS = 17
"""Rows of the integer lane state: voxel x, y, z; step x, y, z; end voxel x, y, z; steps;
t_max x, y, z; t_delta x, y, z; t at the last face (t in fixed point, ``T_ONE``)."""
T_ONE = 1 << 60
"""The ray parameter t (0 at the origin, 1 at the end) in the walks' fixed point: t times
2^60, an int64. Sums of int64 are exact, so the t of a ray's j-th face along an axis,
``t_max + j * t_delta``, is the same however the walk got there: a walk can start at
any face in exactly the state the walk from the origin has there
(``traversal.split_rays``)."""
T_NEVER = (1 << 63) - 1
"""t of a face never crossed (an axis at its end voxel)."""

ENTERED_SHIFT = 3 * BLOCK_BITS
"""A step's code (``walk_lanes``) has this bit set when the step enters a new block."""
LOCAL_MASK = (1 << ENTERED_SHIFT) - 1
"""A step's code masked by this is the voxel's index in its block (``blocks.local_index``)."""
SKIPPED_VISIT = -(1 << 62)
"""``place_lanes``' store index of a step whose chord is not above 0 in float32 (below
every placed index, ``shard.FOREIGN_LIMIT`` included): the add skips it."""
_BLOCK_CHUNK_BITS = BLOCK_CHUNKS.bit_length() - 1
assert 1 << _BLOCK_CHUNK_BITS == BLOCK_CHUNKS

_AXIS_MASK = (1 << BLOCK_BITS) - 1
_SPREAD_MASK = 0b1001001
_F64 = ir.DoubleType()
_I64 = ir.IntType(64)
_I32 = ir.IntType(32)
_I16 = ir.IntType(16)
_VF = ir.VectorType(_F64, LANES)
_VI = ir.VectorType(_I64, LANES)
_VS = ir.VectorType(_I16, LANES)
_VB = ir.VectorType(ir.IntType(1), LANES)
_VF32 = ir.VectorType(ir.FloatType(), LANES)


def _splat(vector: ir.VectorType, value: float | int) -> ir.Constant:
    return ir.Constant(vector, [ir.Constant(vector.element, value)] * LANES)


def _row(builder: ir.IRBuilder, data: ir.Value, k: int, vector: ir.VectorType) -> ir.Value:
    """Row ``k`` (``LANES`` values) of a C-contiguous (rows, LANES) array."""
    pointer = builder.gep(data, [ir.Constant(_I64, k * LANES)])
    return builder.load(builder.bitcast(pointer, vector.as_pointer()), align=8)


def _at(builder: ir.IRBuilder, data: ir.Value, offset: ir.Value, vector: ir.VectorType) -> ir.Value:
    """Pointer to ``LANES`` values at element ``offset`` of ``data``."""
    return builder.bitcast(builder.gep(data, [offset]), vector.as_pointer())


def _gather(
    builder: ir.IRBuilder, data: ir.Value, index: ir.Value, vector: ir.VectorType
) -> ir.Value:
    """``data[index[lane]]`` for every lane (8-byte elements)."""
    pointers = _pointers(builder, data, index, vector.element)
    name = f"llvm.masked.gather.v{LANES}{'f64' if vector.element == _F64 else 'i64'}.v{LANES}p0"
    function = builder.module.globals.get(name) or ir.Function(
        builder.module, ir.FunctionType(vector, [pointers.type, _I32, _VB, vector]), name=name
    )
    every_lane = ir.Constant(_VB, [1] * LANES)
    unused = ir.Constant(vector, ir.Undefined)
    return builder.call(function, [pointers, _I32(8), every_lane, unused])


def _gather32(builder: ir.IRBuilder, data: ir.Value, index: ir.Value) -> ir.Value:
    """``data[index[lane]]`` for every lane (int32 elements)."""
    addresses = builder.add(
        _splat_value(builder, builder.ptrtoint(data, _I64)), builder.mul(index, _splat(_VI, 4))
    )
    pointers = builder.inttoptr(addresses, ir.VectorType(_I32.as_pointer(), LANES))
    vector = ir.VectorType(_I32, LANES)
    name = f"llvm.masked.gather.v{LANES}i32.v{LANES}p0"
    function = builder.module.globals.get(name) or ir.Function(
        builder.module, ir.FunctionType(vector, [pointers.type, _I32, _VB, vector]), name=name
    )
    every_lane = ir.Constant(_VB, [1] * LANES)
    return builder.call(
        function, [pointers, _I32(4), every_lane, ir.Constant(vector, ir.Undefined)]
    )


def _splat_value(builder: ir.IRBuilder, value: ir.Value) -> ir.Value:
    """``value`` (int64) in every lane."""
    lane0 = builder.insert_element(ir.Constant(_VI, ir.Undefined), value, _I32(0))
    every = ir.Constant(ir.VectorType(_I32, LANES), [0] * LANES)
    return builder.shuffle_vector(lane0, ir.Constant(_VI, ir.Undefined), every)


_LANE_NUMBERS = ir.Constant(_VI, [ir.Constant(_I64, k) for k in range(LANES)])


def _pointers(builder: ir.IRBuilder, data: ir.Value, index: ir.Value, element: ir.Type) -> ir.Value:
    """``&data[index[lane]]`` for every lane (8-byte elements)."""
    addresses = builder.add(
        _splat_value(builder, builder.ptrtoint(data, _I64)), builder.mul(index, _splat(_VI, 8))
    )
    return builder.inttoptr(addresses, ir.VectorType(element.as_pointer(), LANES))


_NATIVE_COMPRESS = llvm_version_info >= (19,)
"""LLVM has ``llvm.experimental.vector.compress`` from version 19 (llvmlite 0.45, numba
0.62); older ones (Ubuntu 24.04's numba 0.58 has LLVM 14) get ``_compress_by_lanes``."""


def _compress(builder: ir.IRBuilder, value: ir.Value, mask: ir.Value) -> ir.Value:
    """The lanes of ``value`` where ``mask`` is set, moved down to the first lanes in order
    (the rest undefined): one register instruction with AVX-512 (``vpcompressq``), a
    sequence of LLVM's own elsewhere, ``_compress_by_lanes`` before LLVM 19."""
    if not _NATIVE_COMPRESS:
        return _compress_by_lanes(builder, value, mask)
    name = f"llvm.experimental.vector.compress.v{LANES}i64"
    function = builder.module.globals.get(name) or ir.Function(
        builder.module, ir.FunctionType(_VI, [_VI, _VB, _VI]), name=name
    )
    return builder.call(function, [value, mask, ir.Constant(_VI, ir.Undefined)])


def _compress_by_lanes(builder: ir.IRBuilder, value: ir.Value, mask: ir.Value) -> ir.Value:
    """``_compress`` in plain IR any LLVM takes: every lane written at the count of set
    lanes before it, that count raised by its own bit (an unset lane's write lands past the
    set ones, where the result is undefined, or is overwritten by the next set lane)."""
    out = ir.Constant(_VI, ir.Undefined)
    at = ir.Constant(_I64, 0)
    for lane in range(LANES):
        k = ir.Constant(ir.IntType(32), lane)
        out = builder.insert_element(out, builder.extract_element(value, k), at)
        at = builder.add(at, builder.zext(builder.extract_element(mask, k), _I64))
    return out


def _spread(builder: ir.IRBuilder, index: ir.Value) -> ir.Value:
    """The 3 low bits of every lane placed 3 apart (``blocks._spread_bits``)."""
    spread = builder.or_(index, builder.shl(index, _splat(_VI, 2)))
    spread = builder.or_(spread, builder.shl(index, _splat(_VI, 4)))
    return builder.and_(spread, _splat(_VI, _SPREAD_MASK))


@intrinsic
def walk_lanes(  # type: ignore[no-untyped-def]
    typingctx,
    float_state,
    int_state,
    steps,
    entered_key,
    lane_blocks,
    out_code,
    out_chord,
    entries,
    entry_count,
):
    """Take ``steps`` steps of ``LANES`` rays at once, from the lane state (C-contiguous
    ``float_state`` (FLOAT_ROWS, LANES) float64, ``int_state`` (INT_ROWS, LANES) int64, as
    ``traversal._ray_start`` gives them, or a stretch of a ray ``traversal.split_rays``
    starts mid-ray, with its t at entry; t in fixed point, ``T_ONE``; neither is
    changed).

    Step k writes, for every lane, the voxel the ray is in before it leaves it: at
    ``out_code[k * LANES + lane]`` (int16) its index in its block (``blocks.local_index``)
    with the bit ``ENTERED_SHIFT`` set when the ray enters that block there (step 0
    enters the first); at ``out_chord`` the chord up to where the ray leaves it,
    ``(min(t_next, 1) - t_prev) * length``. A ray of n steps is in its end voxel at step
    n, where every t_max is infinite, so that step's chord is the one up to the end
    point, ``(1 - t_prev) * length``; later steps of that lane are garbage and enter no
    block. The keys (``blocks.block_key``) of the blocks each ray enters, in step order,
    go to ``entries[0]`` and the flat index in ``entered_key`` (C-contiguous (LANES, at
    least n + 1)) where each belongs (the ray's row, in order) to ``entries[1]`` (int64,
    C-contiguous (2, at least (steps + 1) * LANES)); their number to ``entry_count[0]``
    (``traversal._walk_rays`` puts them in place); the number each ray enters to
    ``lane_blocks``. The entries of a step are the lanes that enter a block, compressed
    to the front of a vector (``vpcompressq``) and stored whole: a masked scatter into
    ``entered_key`` there (microcoded on AMD Zen 4) cost more.
    """
    arguments = (
        float_state,
        int_state,
        steps,
        entered_key,
        lane_blocks,
        out_code,
        out_chord,
        entries,
        entry_count,
    )
    sig = types.void(*arguments)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        floats, ints, count, keys, blocks, codes, chords, entry, entry_total = (
            context.make_array(t)(context, builder, a) if isinstance(t, types.Array) else a
            for t, a in zip(signature.args, args, strict=True)
        )
        count = context.cast(builder, count, signature.args[2], types.intp)
        per_t = _row(builder, floats.data, 0, _VF)
        voxel = [_row(builder, ints.data, k, _VI) for k in range(3)]
        step = [_row(builder, ints.data, 3 + k, _VI) for k in range(3)]
        end = [_row(builder, ints.data, 6 + k, _VI) for k in range(3)]
        t_max = [_row(builder, ints.data, 10 + k, _VI) for k in range(3)]
        t_delta = [_row(builder, ints.data, 13 + k, _VI) for k in range(3)]
        t_prev0 = _row(builder, ints.data, 16, _VI)
        last = _row(builder, ints.data, 9, _VI)
        # element index in ``entered_key`` of each lane's row start, minus one
        row_start = builder.mul(
            _splat_value(builder, cgutils.unpack_tuple(builder, keys.shape)[1]), _LANE_NUMBERS
        )
        # the first voxel's block key and index in its block; later voxels' are stepped
        key0 = zero = _splat(_VI, 0)
        local0 = zero
        for axis in range(3):
            block = builder.add(
                builder.ashr(voxel[axis], _splat(_VI, BLOCK_BITS)), _splat(_VI, KEY_OFFSET)
            )
            key0 = builder.or_(key0, builder.shl(block, _splat(_VI, (2 - axis) * KEY_BITS)))
            spread = _spread(builder, builder.and_(voxel[axis], _splat(_VI, _AXIS_MASK)))
            local0 = builder.or_(local0, builder.shl(spread, _splat(_VI, 2 - axis)))
        # per axis: its bits in the index in the block, whether it steps up, and the change
        # of the key when it enters the next block
        axis_bits = [_splat(_VI, _SPREAD_MASK << (2 - axis)) for axis in range(3)]
        up = [builder.icmp_signed(">", s, zero) for s in step]
        key_step = [
            builder.shl(s, _splat(_VI, (2 - axis) * KEY_BITS)) for axis, s in enumerate(step)
        ]
        # loop-carried lane state in stack slots; LLVM keeps them in registers
        t_slots = [cgutils.alloca_once_value(builder, v) for v in t_max]
        v_slots = [cgutils.alloca_once_value(builder, v) for v in voxel]
        t_prev_slot = cgutils.alloca_once_value(builder, t_prev0)
        key_slot = cgutils.alloca_once_value(builder, key0)
        local_slot = cgutils.alloca_once_value(builder, local0)
        every = ir.Constant(_VB, [1] * LANES)
        entering_slot = cgutils.alloca_once_value(builder, every)  # step 0 enters a block
        entered_slot = cgutils.alloca_once_value(builder, builder.sub(row_start, _splat(_VI, 1)))
        never, one = _splat(_VI, T_NEVER), _splat(_VI, T_ONE)
        entry_keys = entry.data
        entry_places = builder.gep(
            entry.data, [cgutils.unpack_tuple(builder, entry.shape)[1]]
        )  # row 1
        entries_slot = cgutils.alloca_once_value(builder, _I64(0))
        popcount = builder.module.globals.get("llvm.ctpop.i8") or ir.Function(
            builder.module, ir.FunctionType(ir.IntType(8), [ir.IntType(8)]), name="llvm.ctpop.i8"
        )
        with cgutils.for_range(builder, count) as loop:
            t = [builder.load(s) for s in t_slots]
            v = [builder.load(s) for s in v_slots]
            t_prev = builder.load(t_prev_slot)
            key = builder.load(key_slot)
            local = builder.load(local_slot)
            offset = builder.mul(loop.index, _I64(LANES))
            walking = builder.icmp_signed(">=", last, _splat_value(builder, loop.index))
            entered = builder.and_(builder.load(entering_slot), walking)
            entered_index = builder.add(builder.load(entered_slot), builder.zext(entered, _VI))
            builder.store(entered_index, entered_slot)
            at = builder.load(entries_slot)
            builder.store(
                _compress(builder, key, entered), _at(builder, entry_keys, at, _VI), align=8
            )
            builder.store(
                _compress(builder, entered_index, entered),
                _at(builder, entry_places, at, _VI),
                align=8,
            )
            many = builder.call(popcount, [builder.bitcast(entered, ir.IntType(8))])
            builder.store(builder.add(at, builder.zext(many, _I64)), entries_slot)
            code = builder.or_(
                local, builder.shl(builder.zext(entered, _VI), _splat(_VI, ENTERED_SHIFT))
            )
            builder.store(builder.trunc(code, _VS), _at(builder, codes.data, offset, _VS), align=2)
            # leave through the nearest face, as the one-ray walk chooses it: x when
            # t_x <= t_y and t_x <= t_z, else y when t_y <= t_z, else z
            take_x = builder.and_(
                builder.icmp_signed("<=", t[0], t[1]), builder.icmp_signed("<=", t[0], t[2])
            )
            y_before_z = builder.icmp_signed("<=", t[1], t[2])
            take = [
                take_x,
                builder.and_(builder.not_(take_x), y_before_z),
                builder.not_(builder.or_(take_x, y_before_z)),
            ]
            t_next = builder.select(take[0], t[0], builder.select(take[1], t[1], t[2]))
            t_next = builder.select(builder.icmp_signed("<", one, t_next), one, t_next)
            chord = builder.fmul(builder.sitofp(builder.sub(t_next, t_prev), _VF), per_t)
            builder.store(chord, _at(builder, chords.data, offset, _VF), align=8)
            builder.store(t_next, t_prev_slot)
            for axis in range(3):
                moved = builder.add(v[axis], builder.select(take[axis], step[axis], zero))
                at_end = builder.icmp_signed("==", moved, end[axis])
                after = builder.select(at_end, never, builder.add(t[axis], t_delta[axis]))
                builder.store(moved, v_slots[axis])
                builder.store(builder.select(take[axis], after, t[axis]), t_slots[axis])
            rising = builder.select(take[0], up[0], builder.select(take[1], up[1], up[2]))
            # the next voxel's index in its block: the stepped axis' bits counted up or
            # down within their own positions (a wrap enters the next block)
            bits = builder.select(
                take[0], axis_bits[0], builder.select(take[1], axis_bits[1], axis_bits[2])
            )
            others = builder.and_(local, builder.not_(bits))
            counted_up = builder.and_(
                builder.add(builder.or_(local, builder.not_(bits)), _splat(_VI, 1)), bits
            )
            counted_down = builder.and_(
                builder.sub(builder.and_(local, bits), _splat(_VI, 1)), bits
            )
            counted = builder.select(rising, counted_up, counted_down)
            builder.store(builder.or_(others, counted), local_slot)
            wrapped = builder.icmp_signed("==", counted, builder.select(rising, zero, bits))
            builder.store(wrapped, entering_slot)
            key_change = builder.select(
                take[0], key_step[0], builder.select(take[1], key_step[1], key_step[2])
            )
            builder.store(builder.add(key, builder.select(wrapped, key_change, zero)), key_slot)
        entered_count = builder.sub(builder.load(entered_slot), row_start)
        blocks_pointer = _at(builder, blocks.data, _I64(0), _VI)
        builder.store(builder.add(entered_count, _splat(_VI, 1)), blocks_pointer, align=8)
        builder.store(builder.load(entries_slot), entry_total.data)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def copy_table(typingctx, destination, at, source, start):  # type: ignore[no-untyped-def]
    """``destination.flat[at : at + BLOCK_CHUNKS] = source[start : start + BLOCK_CHUNKS]``
    (int32, C-contiguous, no bounds checked) as one vector load and store: a block's chunk
    table copied into ``entered_chunks`` (``place_lanes``)."""
    sig = types.void(destination, types.intp, source, types.intp)
    table = ir.VectorType(_I32, BLOCK_CHUNKS)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        to = context.make_array(signature.args[0])(context, builder, args[0])
        source_array = context.make_array(signature.args[2])(context, builder, args[2])
        at_value = context.cast(builder, args[1], signature.args[1], types.intp)
        start_value = context.cast(builder, args[3], signature.args[3], types.intp)
        load_from = builder.bitcast(
            builder.gep(source_array.data, [start_value]), table.as_pointer()
        )
        store_to = builder.bitcast(builder.gep(to.data, [at_value]), table.as_pointer())
        builder.store(builder.load(load_from, align=4), store_to, align=4)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def prefetch_line(typingctx, array, at):  # type: ignore[no-untyped-def]
    """Asks the processor to start loading the cache line of ``array.flat[at]`` (C-contiguous;
    any ``at`` is harmless: a prefetch does not fault)."""
    sig = types.void(array, types.intp)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        at_value = context.cast(builder, args[1], signature.args[1], types.intp)
        byte_pointer = ir.IntType(8).as_pointer()
        prefetch = builder.module.declare_intrinsic(
            "llvm.prefetch",
            [byte_pointer],
            ir.FunctionType(ir.VoidType(), [byte_pointer, _I32, _I32, _I32]),
        )
        pointer = builder.bitcast(builder.gep(data, [at_value]), byte_pointer)
        builder.call(prefetch, [pointer, _I32(1), _I32(3), _I32(1)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def place_lanes(  # type: ignore[no-untyped-def]
    typingctx,
    codes,
    chords,
    entered_chunks,
    entered_weight,
    weighted,
    steps,
    lines,
    out_voxel,
    out_chord,
):
    """The store index of ``steps`` steps of ``LANES`` rays, as ``walk_lanes`` wrote them
    (``codes``, ``chords``).

    ``entered_weight`` (C-contiguous (LANES, n)) holds, per lane, the scan's weight in each
    block the ray enters, in order, and ``entered_chunks`` (C-contiguous int32 (LANES,
    n * BLOCK_CHUNKS)) the chunk-table entries of those blocks (``shard.ShardArrays
    .block_chunks``, copied when the block was entered: one gather a step, not two; the
    chained gather cost 1.5x main's placing). Step k of a lane writes ``entry *
    CHUNK_VOXELS + place in chunk`` at ``out_voxel[k * LANES + lane]``, ``entry`` its
    chunk's entry (the chunk's index in ``lines``, or negative), multiplies its chord by
    the weight in place when ``weighted`` (else every weight is 1), writes the chord as
    the store adds it, in float32, at ``out_chord[k * LANES + lane]``, and asks the
    processor to start loading the voxel's cache line in ``lines`` (the ``s`` chunks,
    flat: one float32 a voxel). A step whose float32 chord is not above 0 is placed at
    ``SKIPPED_VISIT``, so that the add tests one value a visit (with the float32 chords
    converted here, eight at once, the add takes 14 instructions a visit, not 17: about
    1,040 perf samples of a hall run at 0.2 m against 1,220, placing 890-930 against 800).
    """
    arguments = (
        codes, chords, entered_chunks, entered_weight, weighted, steps, lines, out_voxel,
        out_chord,
    )  # fmt: skip
    sig = types.void(*arguments)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        code_a, chord_a, chunks_a, weight_a, weighted, count, lines_a, voxel_a, c32_a = (
            context.make_array(t)(context, builder, a) if isinstance(t, types.Array) else a
            for t, a in zip(signature.args, args, strict=True)
        )
        count = context.cast(builder, count, signature.args[5], types.intp)
        weighted = context.cast(builder, weighted, signature.args[4], types.boolean)
        per_lane = cgutils.unpack_tuple(builder, weight_a.shape)[1]
        # element index of each lane's row, minus one: a lane's first step enters a block
        row_start = builder.sub(
            builder.mul(_splat_value(builder, per_lane), _LANE_NUMBERS), _splat(_VI, 1)
        )
        entered_slot = cgutils.alloca_once_value(builder, row_start)
        line_start = builder.ptrtoint(lines_a.data, _I64)
        byte_pointer = ir.IntType(8).as_pointer()
        prefetch = builder.module.declare_intrinsic(
            "llvm.prefetch",
            [byte_pointer],
            ir.FunctionType(ir.VoidType(), [byte_pointer, _I32, _I32, _I32]),
        )

        def place(weigh: bool) -> None:
            with cgutils.for_range(builder, count) as loop:
                offset = builder.mul(loop.index, _I64(LANES))
                code = builder.load(_at(builder, code_a.data, offset, _VS), align=2)
                code = builder.zext(code, _VI)
                block = builder.add(
                    builder.load(entered_slot), builder.lshr(code, _splat(_VI, ENTERED_SHIFT))
                )
                builder.store(block, entered_slot)
                local = builder.and_(code, _splat(_VI, LOCAL_MASK))
                slot = builder.add(
                    builder.shl(block, _splat(_VI, _BLOCK_CHUNK_BITS)),
                    builder.lshr(local, _splat(_VI, CHUNK_BITS)),
                )
                entry = builder.sext(_gather32(builder, chunks_a.data, slot), _VI)
                voxel = builder.add(
                    builder.shl(entry, _splat(_VI, CHUNK_BITS)),
                    builder.and_(local, _splat(_VI, (1 << CHUNK_BITS) - 1)),
                )
                chord_pointer = _at(builder, chord_a.data, offset, _VF)
                chord = builder.load(chord_pointer, align=8)
                if weigh:
                    weight = _gather(builder, weight_a.data, block, _VF)
                    chord = builder.fmul(chord, weight)
                    builder.store(chord, chord_pointer, align=8)
                # the chord the store adds, and no visit where it is not above 0 in float32
                added = builder.fptrunc(chord, _VF32)
                builder.store(added, _at(builder, c32_a.data, offset, _VF32), align=4)
                taken = builder.fcmp_ordered(">", added, ir.Constant(_VF32, [0.0] * LANES))
                placed = builder.select(taken, voxel, _splat(_VI, SKIPPED_VISIT))
                builder.store(placed, _at(builder, voxel_a.data, offset, _VI), align=8)
                # one float32 a voxel: byte offset 4 * voxel (negative ones: another
                # shard's, a new chunk, or past a ray's end; a prefetch of any address is
                # harmless)
                for lane in range(LANES):
                    index = builder.extract_element(voxel, _I32(lane))
                    address = builder.add(line_start, builder.shl(index, _I64(2)))
                    pointer = builder.inttoptr(address, byte_pointer)
                    builder.call(prefetch, [pointer, _I32(1), _I32(3), _I32(1)])

        with builder.if_else(weighted) as (then, otherwise):
            with then:
                place(weigh=True)
            with otherwise:
                place(weigh=False)
        return context.get_dummy_value()

    return sig, codegen
