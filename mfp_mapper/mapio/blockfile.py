"""Map files of versions 3 and 4: the store's blocks as they are in memory, read by block.

A version 4 map file is an ``.npz`` (a zip of ``.npy`` arrays, every member stored, none
deflated) holding the settings of every version (``mapfile``) and the packed blocks of
``core.packed``, as parts (``PackedBlocks.parts``):

===============  ==============  =====================================================
``block_ijk``    int32 (B, 3)    block index (voxel index >> 3), sorted by x, y, z; once
``block_start``  int64 (B + 1,)  row of ``s`` where each block's voxels begin (last: M)
``hit_block``    int64 (H,)      rows of the blocks holding a return, increasing
``hit_start``    int64 (H + 1,)  row of ``n`` where each of those blocks begins (last: K)
``block_t``      float64 (B,)    time (s) the block's statistics refer to (its voxels' t_last)
``observed``     uint64 (B, 8)   bit ``i % 64`` of word ``i // 64``: the voxel of Morton
                                 place ``i`` in the block is observed (s > 0 or n > 0)
``hit``          uint64 (H, 8)   the same for the voxels with a return (n > 0)
``s``            float32 (M,)    metres of rays in each observed voxel, block by block:
                                 the float32 part of the sum
``n``            float32 (K,)    returns in each voxel with a return (float32 part)
``hi_block``     int64 (F,)      rows of the blocks with a float64 part, increasing
``hi_s``         float64 (F_s,)  the float64 part of ``s``: one per observed voxel of
                                 those blocks, block by block
``hi_n``         float64 (F_n,)  the float64 part of ``n``: one per voxel with a return
                                 of those blocks
===============  ==============  =====================================================

A voxel's ``s`` is ``float64(s) + hi_s`` where its block has a float64 part, else
``s`` (likewise ``n``): what the store holds, so that a map loads back bit for bit. Version
3 files (still read) have no ``hi_*`` members and hold the values in ``s`` and ``n``
(float32, or float64 in a file of merged or flushed sums).

The block index (``block_ijk``, ``block_start``, ``hit_block``, ``hit_start``) comes first,
so a reader that needs a few blocks reads the index, finds its blocks by binary search and
reads their masks and values where they lie (``BlockReader.packed``); a full read checks
each member's CRC-32. Arrays are little-endian. Writes go through ``mapio.atomic``."""

from __future__ import annotations

import io
import math
import os
import struct
import zipfile
import zlib
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.core.layout import (
    BLOCK_BITS,
    BLOCK_EDGE,
    MASK_WORDS,
    MAX_BLOCK_INDEX,
    PackedBlocks,
    VoxelArrays,
    as_parts,
    as_values,
    block_counts,
    compact,
    hi_starts,
    select_blocks,
    sort_keys,
    totals,
    voxel_starts,
)

BLOCK_MEMBERS = (
    "block_ijk", "block_start", "hit_block", "hit_start", "block_t", "observed", "hit", "s", "n",
    "hi_block", "hi_s", "hi_n",
)  # fmt: skip
"""The block members of a version 4 map file, in the order written (the index first)."""
HI_MEMBERS = ("hi_block", "hi_s", "hi_n")
"""The members a version 3 file lacks (it holds values, not parts)."""
TABLE_MEMBERS = ("reflectivity_ijk", "reflectivity_counts", "reflectivity_t_last")
"""The members of a map's reflectivity table with a row per voxel (``core.reflectivity.
ROW_KEYS``; numba-free here), located like the block members and read by block too."""

_DTYPES: dict[str, tuple[str, ...]] = {
    "block_ijk": ("<i4",),
    "block_start": ("<i8",),
    "hit_block": ("<i8",),
    "hit_start": ("<i8",),
    "block_t": ("<f8",),
    "observed": ("<u8",),
    "hit": ("<u8",),
    "s": ("<f4", "<f8"),
    "n": ("<f4", "<f8"),
    "hi_block": ("<i8",),
    "hi_s": ("<f8",),
    "hi_n": ("<f8",),
    # TABLE_MEMBERS
    "reflectivity_ijk": ("<i4", "<i8"),
    "reflectivity_counts": ("<f8", "<f4"),
    "reflectivity_t_last": ("<f8", "<f4"),
}
_LOCAL_HEADER = struct.Struct("<4s5H3L2H")
_LOCAL_MAGIC = b"PK\x03\x04"


def block_arrays(packed: PackedBlocks) -> dict[str, np.ndarray]:
    """The block members of a version 4 map file for ``packed`` (as parts: ``as_parts``;
    index arrays added)."""
    p = as_parts(packed)
    return {
        "block_ijk": np.ascontiguousarray(p.block_ijk, dtype="<i4"),
        "block_start": voxel_starts(p.observed),
        "hit_block": np.ascontiguousarray(p.hit_block, dtype="<i8"),
        "hit_start": voxel_starts(p.hit),
        "block_t": np.ascontiguousarray(p.block_t, dtype="<f8"),
        "observed": np.ascontiguousarray(p.observed, dtype="<u8"),
        "hit": np.ascontiguousarray(p.hit, dtype="<u8"),
        "s": np.ascontiguousarray(p.s, dtype="<f4"),
        "n": np.ascontiguousarray(p.n, dtype="<f4"),
        "hi_block": np.ascontiguousarray(p.hi_block, dtype="<i8"),
        "hi_s": np.ascontiguousarray(p.hi_s, dtype="<f8"),
        "hi_n": np.ascontiguousarray(p.hi_n, dtype="<f8"),
    }


def packed_of(arrays: dict[str, Any]) -> PackedBlocks:
    """The packed blocks of map-file block members (``block_arrays``; of a version 3 file:
    values, no ``hi_*``)."""
    p = PackedBlocks(
        arrays["block_ijk"], arrays["block_t"], arrays["observed"], arrays["s"],
        arrays["hit_block"], arrays["hit"], arrays["n"],
    )  # fmt: skip
    if "hi_block" in arrays:
        p.parts, p.hi_block, p.hi_s, p.hi_n = True, *(arrays[k] for k in HI_MEMBERS)
    return p


def write_npz_stored(out: BinaryIO, arrays: dict[str, Any]) -> None:
    """Write ``arrays`` as an uncompressed ``.npz`` to ``out`` (what ``np.load`` reads):
    each array's bytes go to the file once, without a copy (the CRC is computed on the
    way)."""
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, value in arrays.items():
            arr = np.asanyarray(value)
            if arr.dtype.hasobject:
                raise ValueError(f"{name}: object arrays are never written")
            arr = arr if arr.flags.c_contiguous else arr.copy(order="C")  # keeps 0-d
            header = io.BytesIO()
            fmt = np.lib.format
            fmt.write_array_header_1_0(header, fmt.header_data_from_array_1_0(arr))
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                member.write(header.getvalue())
                if arr.nbytes:
                    member.write(arr.reshape(-1).view(np.uint8).data)


@dataclass(frozen=True)
class Member:
    """Where one stored ``.npy`` member's array lies in the file."""

    name: str
    offset: int  # of the array's first byte
    shape: tuple[int, ...]
    dtype: np.dtype
    header: bytes  # the .npy header (for the CRC)
    crc: int

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


class BlockFileError(ValueError):
    """A version 3 member that cannot be read (``mapfile`` names the file)."""


def locate_members(
    f: BinaryIO, archive: zipfile.ZipFile, names: Iterable[str], file_size: int
) -> dict[str, Member]:
    """The block members ``names`` of a version 3 or 4 file (``BLOCK_MEMBERS``, less
    ``HI_MEMBERS`` for version 3) and the ``TABLE_MEMBERS`` it has: stored, headers and
    sizes checked."""
    out: dict[str, Member] = {}
    required = set(names)
    wanted = required | set(TABLE_MEMBERS)
    for info in archive.infolist():
        name = info.filename[: -len(".npy")]
        if not info.filename.endswith(".npy") or name not in wanted:
            continue
        if name in out:
            raise BlockFileError(f"member {info.filename} appears twice")
        if info.compress_type != zipfile.ZIP_STORED:
            raise BlockFileError(f"{name} is compressed: version 3 members are stored")
        f.seek(info.header_offset)
        raw = f.read(_LOCAL_HEADER.size)
        if len(raw) != _LOCAL_HEADER.size or raw[:4] != _LOCAL_MAGIC:
            raise BlockFileError(f"{name}: no zip local header where the directory says")
        fields = _LOCAL_HEADER.unpack(raw)
        data = info.header_offset + _LOCAL_HEADER.size + fields[-2] + fields[-1]
        f.seek(data)
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        else:
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        start = f.tell()
        if fortran and len(shape) > 1:
            raise BlockFileError(f"{name} is in Fortran order (C order expected)")
        if dtype.str not in _DTYPES[name]:
            want = " or ".join(_DTYPES[name])
            raise BlockFileError(f"{name} has dtype {dtype.str}, expected {want}")
        if any(d < 0 for d in shape):
            raise BlockFileError(f"{name} declares a negative size {shape}")
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes != info.file_size - (start - data) or data + info.file_size > file_size:
            raise BlockFileError(
                f"{name} claims {nbytes} bytes ({shape} {dtype}) in a member of "
                f"{info.file_size - (start - data)}"
            )  # fmt: skip
        f.seek(data)
        header = f.read(start - data)
        out[name] = Member(name, start, tuple(shape), dtype, header, info.CRC)
    missing = [k for k in required if k not in out]
    if missing:
        raise BlockFileError(f"block map without {', '.join(sorted(missing))}")
    if "hi_block" in out and (out["s"].dtype.str != "<f4" or out["n"].dtype.str != "<f4"):
        raise BlockFileError("s and n of a version 4 file hold float32 parts (<f4)")
    problem = shape_problem({k: m.shape for k, m in out.items()})
    if problem:
        raise BlockFileError(problem)
    return out


def shape_problem(shapes: dict[str, tuple[int, ...]]) -> str | None:
    """The block members' shapes against each other (B blocks, H with a return)."""
    b = shapes["block_ijk"][0] if len(shapes["block_ijk"]) == 2 else -1
    h = shapes["hit_block"][0] if len(shapes["hit_block"]) == 1 else -1
    want = {
        "block_ijk": (b, 3), "block_start": (b + 1,), "block_t": (b,), "observed": (b, MASK_WORDS),
        "hit_block": (h,), "hit_start": (h + 1,), "hit": (h, MASK_WORDS),
    }  # fmt: skip
    for name, shape in want.items():
        if shapes[name] != shape:
            return f"{name} must have shape {shape} (B = {b} blocks, H = {h}), got {shapes[name]}"
    for name in ("s", "n", *(k for k in HI_MEMBERS if k in shapes)):
        if len(shapes[name]) != 1:
            return f"{name} must be one-dimensional, got shape {shapes[name]}"
    return None


def read_member(f: io.BufferedReader, m: Member) -> np.ndarray:
    """A whole member, its CRC-32 checked."""
    out = np.empty(m.shape, dtype=m.dtype)
    f.seek(m.offset)
    view = out.reshape(-1).view(np.uint8).data
    got = f.readinto(view) if m.nbytes else 0
    if got != m.nbytes:
        raise BlockFileError(f"{m.name} is truncated ({got} of {m.nbytes} bytes)")
    if zlib.crc32(view, zlib.crc32(m.header)) != m.crc:
        raise BlockFileError(f"{m.name} fails its CRC-32 check: the file is damaged")
    return out


def _pread_into(fd: int, raw: np.ndarray, offset: int) -> int:
    """Bytes of the file from ``offset`` into the bytes ``raw`` through ``os.preadv`` (no
    file position: another thread may read the same file); returns how many were there."""
    view, got = raw.data, 0
    while got < raw.shape[0]:
        step = os.preadv(fd, [view[got:]], offset + got)
        if step <= 0:
            break
        got += step
    return got


def _read_span(fd: int, m: Member, out: np.ndarray, lo: int, hi: int, crc: int) -> tuple[int, int]:
    """Bytes ``lo`` to ``hi`` of member ``m`` into its array ``out``, ``_PIECE`` at a time,
    each piece CRC'd (``crc`` continued) and, for float32 values, the largest of their bit
    patterns taken while it is in cache. Returns the CRC and that pattern (0 for other
    dtypes; below +inf's, 0x7F800000: every value finite and >= +0)."""
    raw = out.reshape(-1).view(np.uint8)
    float32 = m.dtype.str == "<f4"
    top = 0
    for at in range(lo, hi, _PIECE):
        piece = raw[at : min(hi, at + _PIECE)]
        got = _pread_into(fd, piece, m.offset + at)
        if got != piece.shape[0]:
            raise BlockFileError(f"{m.name} is truncated ({at + got} of {m.nbytes} bytes)")
        crc = zlib.crc32(piece.data, crc)
        if float32:
            top = max(top, int(piece.view(np.uint32).max()))
    return crc, top


_POLY = 0xEDB88320
"""CRC-32's polynomial (reflected), as zlib's."""


def _mult_mod_p(a: int, b: int) -> int:
    """``a * b`` modulo CRC-32's polynomial (reflected; zlib's ``multmodp``)."""
    m, p = 1 << 31, 0
    while True:
        if a & m:
            p ^= b
            if not a & (m - 1):
                return p
        m >>= 1
        b = (b >> 1) ^ _POLY if b & 1 else b >> 1


_X2N = [1 << 30]  # x^(2^k) modulo the polynomial, k = 0..31 (zlib's x2n_table)
for _ in range(31):
    _X2N.append(_mult_mod_p(_X2N[-1], _X2N[-1]))


def crc32_combine(crc1: int, crc2: int, len2: int) -> int:
    """The CRC-32 of A + B from ``crc1`` (of A) and ``crc2`` (of B, from 0) and B's
    length in bytes (zlib's ``crc32_combine``, which Python's zlib does not expose):
    ``crc1`` times x^(8 len2), plus ``crc2``. 0.1 ms."""
    p, k = 1 << 31, 3  # x^0; x^(8 len2) = the product of x^(2^k) over len2's bits, k >= 3
    while len2:
        if len2 & 1:
            p = _mult_mod_p(_X2N[k & 31], p)
        len2 >>= 1
        k += 1
    return _mult_mod_p(p, crc1) ^ crc2


THREADED_READ_BYTES = 4 << 20
"""``s`` from this size on is read by two threads where two cores are there (``read_all``)."""
_PIECE = 4 << 20
"""Bytes of ``s`` read, CRC'd and value-checked at a time (``_read_span``)."""
_SPLIT_ALIGN = 1 << 16
"""Where the second thread's share of ``s`` begins is a multiple of this."""
F32_FINITE_BITS = 0x7F800000
"""Bit patterns of float32 values below this one (+inf's) are finite and >= +0."""


def read_all(
    f: io.BufferedReader, members: dict[str, Member]
) -> tuple[dict[str, np.ndarray], bool]:
    """Every block member, checked: CRCs, the index against the masks; and whether the
    values of ``s`` are finite and >= +0 (float32 ``s``: found on the way, in cache; False
    leaves the check to ``packed_problem``). On large maps (``THREADED_READ_BYTES``) with
    two cores, a second thread reads the end of ``s`` while this one reads the other
    members and the start of ``s``, as many bytes each; the two CRCs are combined
    (``crc32_combine``)."""
    names = [k for k in members if k not in TABLE_MEMBERS]
    m = members["s"]
    others = [k for k in names if k != "s"]
    if not hasattr(os, "preadv"):  # not on Windows: one after the other, values later
        arrays = {k: read_member(f, members[k]) for k in names}
        problem = index_problem(arrays)
        if problem:
            raise BlockFileError(problem)
        return arrays, False
    s = np.empty(m.shape, dtype=m.dtype)
    cut = m.nbytes
    if m.nbytes >= THREADED_READ_BYTES and (os.cpu_count() or 1) >= 2:
        rest = sum(members[k].nbytes for k in others)
        cut = max(0, (m.nbytes - rest) // 2) // _SPLIT_ALIGN * _SPLIT_ALIGN
    with ThreadPoolExecutor(1) as pool:
        end = (
            pool.submit(_read_span, f.fileno(), m, s, cut, m.nbytes, 0) if cut < m.nbytes else None
        )
        arrays = {k: read_member(f, members[k]) for k in others}
        crc, top = _read_span(f.fileno(), m, s, 0, cut, zlib.crc32(m.header))
        arrays["s"] = s
        problem = index_problem(arrays)
        if end is not None:
            crc_end, top_end = end.result()
            crc, top = crc32_combine(crc, crc_end, m.nbytes - cut), max(top, top_end)
    if crc != m.crc:
        raise BlockFileError("s fails its CRC-32 check: the file is damaged")
    if problem:
        raise BlockFileError(problem)
    return {k: arrays[k] for k in names}, m.dtype.str == "<f4" and top < F32_FINITE_BITS


def index_problem(a: dict[str, np.ndarray]) -> str | None:
    """``block_start`` and ``hit_start`` against the masks, ``s`` and ``n``."""
    if not np.array_equal(a["block_start"], voxel_starts(a["observed"])):
        return "block_start does not count the observed masks"
    if not np.array_equal(a["hit_start"], voxel_starts(a["hit"])):
        return "hit_start does not count the hit masks"
    if a["s"].shape[0] != a["block_start"][-1] or a["n"].shape[0] != a["hit_start"][-1]:
        return "s and n do not hold one value per bit of the masks"
    return None


class BlockReader:
    """Reads chosen blocks of a version 3 file through a memory map (only the pages of
    those blocks are read from disk). Close it (or use ``with``)."""

    def __init__(self, path: Path, members: dict[str, Member]) -> None:
        self.members = members
        self._map = np.memmap(path, dtype=np.uint8, mode="r") if path.stat().st_size else None
        self.block_ijk = self.view("block_ijk").copy()
        if self.block_ijk.size and int(np.abs(self.block_ijk).max()) > MAX_BLOCK_INDEX:
            raise BlockFileError(f"block indices beyond +-{MAX_BLOCK_INDEX}, the map's range")
        self.keys = sort_keys(self.block_ijk)
        if self.keys.shape[0] > 1 and not np.all(np.diff(self.keys) > 0):
            raise BlockFileError("blocks are not sorted by index, or a block is listed twice")

    def view(self, name: str) -> np.ndarray:
        m = self.members[name]
        if self._map is None or m.nbytes == 0:
            return np.zeros(m.shape, dtype=m.dtype)
        return np.ndarray(m.shape, dtype=m.dtype, buffer=self._map, offset=m.offset)

    def close(self) -> None:
        self._map = None

    def __enter__(self) -> BlockReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def rows_of(self, block_ijk: ArrayLike) -> NDArray[np.int64]:
        """Rows of the file's blocks among ``block_ijk`` (absent ones left out)."""
        return self.rows_of_keys(sort_keys(np.asarray(block_ijk, dtype=np.int64).reshape(-1, 3)))

    def rows_of_keys(self, keys: NDArray[np.int64]) -> NDArray[np.int64]:
        """Rows of the file's blocks whose ``sort_keys`` are among ``keys`` (sorted, unique;
        absent ones left out)."""
        want = np.unique(keys)
        pos = np.searchsorted(self.keys, want)
        found = pos < self.keys.shape[0]
        found[found] = self.keys[pos[found]] == want[found]
        return pos[found].astype(np.int64)

    def rows_in_box(self, lo: NDArray[np.int64], hi: NDArray[np.int64]) -> NDArray[np.int64]:
        """Rows of the blocks holding voxel indices in [lo, hi] (inclusive)."""
        blo, bhi = np.asarray(lo) >> BLOCK_BITS, np.asarray(hi) >> BLOCK_BITS
        inside = np.all((self.block_ijk >= blo) & (self.block_ijk <= bhi), axis=1)
        return np.flatnonzero(inside)

    def packed(self, rows: NDArray[np.int64]) -> PackedBlocks:
        """The blocks of ``rows`` (sorted, unique), read where they lie; their counts are
        checked against their masks."""
        rows = np.asarray(rows, dtype=np.int64)
        start, hstart = self.view("block_start"), self.view("hit_start")
        hit_rows = self.view("hit_block").copy()
        if hit_rows.shape[0] > 1 and not np.all(np.diff(hit_rows) > 0):
            raise BlockFileError("hit_block is not increasing")
        if hit_rows.shape[0] and (hit_rows[0] < 0 or hit_rows[-1] >= self.block_ijk.shape[0]):
            raise BlockFileError("hit_block rows outside the blocks")
        whole = PackedBlocks(
            self.block_ijk, self.view("block_t"), self.view("observed"), self.view("s"),
            hit_rows, self.view("hit"), self.view("n"),
        )  # fmt: skip
        if "hi_block" in self.members:
            whole.parts = True
            whole.hi_block, whole.hi_s, whole.hi_n = (self.view(k).copy() for k in HI_MEMBERS)
            problem = hi_index_problem(whole)
            if problem:
                raise BlockFileError(problem)
        pos = np.searchsorted(hit_rows, rows)
        has = pos < hit_rows.shape[0]
        has[has] = hit_rows[pos[has]] == rows[has]
        hpos = pos[has]
        s_lo, s_hi, n_lo, n_hi = start[rows], start[rows + 1], hstart[hpos], hstart[hpos + 1]
        counts = block_counts(whole.observed[rows])
        hit_counts = block_counts(whole.hit[hpos])
        if not (np.array_equal(s_hi - s_lo, counts) and np.array_equal(n_hi - n_lo, hit_counts)):
            raise BlockFileError("block_start or hit_start does not count the masks")
        s_total, n_total = self.members["s"].shape[0], self.members["n"].shape[0]
        if (s_lo.size and (s_lo.min() < 0 or s_hi.max() > s_total)) or (
            n_lo.size and (n_lo.min() < 0 or n_hi.max() > n_total)
        ):
            raise BlockFileError("block_start or hit_start points outside s or n")
        return select_blocks(whole, rows, start, hstart)


def hi_index_problem(p: PackedBlocks) -> str | None:
    """The float64 parts' rows and sizes against the blocks (before any is read)."""
    f, b = p.hi_block.shape[0], p.block_ijk.shape[0]
    if f and (int(p.hi_block[0]) < 0 or int(p.hi_block[-1]) >= b):
        return f"hi_block rows outside [0, {b})"
    if f > 1 and not np.all(np.diff(p.hi_block) > 0):
        return "hi_block is not increasing"
    fs, fn = hi_starts(p)
    if p.hi_s.shape != (int(fs[-1]),) or p.hi_n.shape != (int(fn[-1]),):
        return "hi_s and hi_n do not hold one value per bit of the masks of hi_block"
    return None


def take_blocks(arrays: dict[str, Any], rows: NDArray[np.int64]) -> dict[str, np.ndarray]:
    """The block members (``block_arrays``) of the blocks ``rows`` (increasing) of
    ``arrays``."""
    return block_arrays(
        select_blocks(packed_of(arrays), rows, arrays["block_start"], arrays["hit_start"])
    )


def concat_packed(parts: list[PackedBlocks], sort: bool = True) -> PackedBlocks:
    """Packed blocks of disjoint block sets (e.g. tiles) as one, sorted (a block in two
    parts is refused by ``packed_problem`` later; ``sort=False``: in the parts' order, for
    a caller that knows the sets disjoint, as a store takes them): as parts where all
    are, else values."""
    if len(parts) == 1:
        return parts[0]
    if not all(p.parts for p in parts):
        parts = [as_values(p) for p in parts]
    rows = np.cumsum([0] + [p.block_ijk.shape[0] for p in parts])

    def joined(key: str, empty: np.ndarray, offset: bool = False) -> np.ndarray:
        arrays = [getattr(p, key) + (r if offset else 0) for p, r in zip(parts, rows, strict=False)]
        return np.concatenate([empty, *arrays])

    no_mask = np.zeros((0, MASK_WORDS), np.uint64)
    whole = PackedBlocks(
        joined("block_ijk", np.zeros((0, 3), np.int32)), joined("block_t", np.zeros(0)),
        joined("observed", no_mask), joined("s", np.zeros(0, np.float32)),
        joined("hit_block", np.zeros(0, np.int64), True), joined("hit", no_mask),
        joined("n", np.zeros(0, np.float32)), bool(parts) and parts[0].parts,
        joined("hi_block", np.zeros(0, np.int64), True), joined("hi_s", np.zeros(0)),
        joined("hi_n", np.zeros(0)),
    )  # fmt: skip
    out = whole
    if sort:
        out = select_blocks(whole, np.argsort(sort_keys(whole.block_ijk), kind="stable"))
    if not out.parts:
        out.s, out.n = compact(out.s), compact(out.n)
    return out


# --- voxel lists <-> packed blocks ------------------------------------------------------

_MORTON = np.array(
    [[(i >> 2 & 1) | (i >> 4 & 2) | (i >> 6 & 4), (i >> 1 & 1) | (i >> 3 & 2) | (i >> 5 & 4),
      (i & 1) | (i >> 2 & 2) | (i >> 4 & 4)] for i in range(BLOCK_EDGE**3)],
    dtype=np.int64,
)  # fmt: skip
"""Offsets (x, y, z) in its block of the voxel of each Morton place (``blocks.local_coords``)."""
_PLACE = np.zeros((BLOCK_EDGE,) * 3, dtype=np.int64)
_PLACE[_MORTON[:, 0], _MORTON[:, 1], _MORTON[:, 2]] = np.arange(BLOCK_EDGE**3)


def packed_to_voxels(p: PackedBlocks) -> VoxelArrays:
    """The voxel list of packed blocks (float64 values, ``packed.totals``; ``t_last`` is the
    block's time),
    voxels in block order."""
    obs = np.unpackbits(p.observed.view(np.uint8), axis=1, bitorder="little").astype(bool)
    rows, place = np.nonzero(obs)
    ijk = (p.block_ijk[rows].astype(np.int64) << BLOCK_BITS) + _MORTON[place]
    hits = np.zeros_like(obs)
    hits[p.hit_block] = np.unpackbits(p.hit.view(np.uint8), axis=1, bitorder="little")
    s_all, n_all = totals(p)
    n = np.zeros(rows.shape[0])
    n[hits[obs]] = n_all
    return VoxelArrays(ijk.astype(np.int32), s_all, n, p.block_t[rows].astype(np.float64))


def voxels_to_packed(v: VoxelArrays, decay_time: float) -> PackedBlocks:
    """Voxel lists as packed blocks: voxels of one block are brought to its latest time
    (decayed, as the store does), voxels with s = n = 0 dropped; s and n stay float32 when
    that loses nothing, else float64. ValueError names a voxel listed twice."""
    ijk = np.asarray(v.ijk, dtype=np.int64).reshape(-1, 3)
    s, n, t = (np.asarray(a, dtype=np.float64) for a in (v.s, v.n, v.t_last))
    keep = (s > 0) | (n > 0)
    if not keep.all():
        ijk, s, n, t = ijk[keep], s[keep], n[keep], t[keep]
    blocks = ijk >> BLOCK_BITS
    local = ijk & (BLOCK_EDGE - 1)
    place = _PLACE[local[:, 0], local[:, 1], local[:, 2]]
    bkey = sort_keys(blocks)
    order = np.lexsort((place, bkey)) if ijk.shape[0] else np.zeros(0, dtype=np.int64)
    bkey, place = bkey[order], place[order]
    new_block = np.ones(order.shape[0], dtype=bool)
    new_block[1:] = bkey[1:] != bkey[:-1]
    twice = ~new_block[1:] & (place[1:] == place[:-1])
    if twice.any():
        raise ValueError(f"ijk lists voxel {ijk[order[1:][twice][0]].tolist()} more than once")
    heads = np.flatnonzero(new_block)
    row = np.cumsum(new_block) - 1
    s, n, t = s[order], n[order], t[order]
    block_t = np.maximum.reduceat(t, heads) if heads.size else np.zeros(0)
    if math.isfinite(decay_time):
        scale = np.exp((t - block_t[row]) / decay_time)
        s, n = s * scale, n * scale
    flat = row * MASK_WORDS + (place >> 6)
    bits = np.left_shift(np.uint64(1), (place & 63).astype(np.uint64))
    masks = np.zeros(heads.shape[0] * MASK_WORDS, dtype=np.uint64)
    if flat.size:
        runs = np.flatnonzero(np.diff(flat, prepend=-1))
        masks[flat[runs]] = np.bitwise_or.reduceat(bits, runs)
    observed = masks.reshape(-1, MASK_WORDS)
    has_n = n > 0
    hit_masks = np.zeros_like(masks)
    if has_n.any():
        fh, bh = flat[has_n], bits[has_n]
        runs = np.flatnonzero(np.diff(fh, prepend=-1))
        hit_masks[fh[runs]] = np.bitwise_or.reduceat(bh, runs)
    hit = hit_masks.reshape(-1, MASK_WORDS)
    hit_block = np.flatnonzero(hit.any(axis=1)).astype(np.int64)
    return PackedBlocks(
        blocks[order[heads]].astype(np.int32), block_t, observed, compact(s), hit_block,
        hit[hit_block], compact(n[has_n]),
    )  # fmt: skip


__all__ = [
    "BlockReader", "block_arrays", "concat_packed", "packed_to_voxels", "take_blocks",
    "voxels_to_packed",
]  # fmt: skip
