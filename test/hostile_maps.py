"""A corpus of hostile map files, generated (never committed): what disks, foreign writers
and attackers hand the readers of ``.npz`` maps and tiled maps.

``KINDS`` maps a name to (builder, words the refusal must contain, literally). A builder writes
its map under a directory and returns the path a user would pass. Every tiled kind damages
the tile at key (0, 0, 0) or the index, so a query at ``QUERY_POINT`` reads the damage.
Shared by the reader and CLI tests (test/mapio) and the node tests (test/ros).
"""

from __future__ import annotations

import functools
import io
import json
import os
import struct
import time
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mfp_mapper.mapio.blockfile import take_blocks, write_npz_stored
from mfp_mapper.mapio.mapfile import as_block_arrays, write_map_arrays
from mfp_mapper.mapio.tiles import INDEX_NAME, write_tiled

PARTIAL_READERS = {"v3_flipped_value": "query"}
"""Kinds whose damage lies where one command never reads: that command answers."""
QUERY_POINT = (0.05, 0.05, 0.05)
"""Inside voxel (0, 0, 0) of every corpus map: a query there reads tile (0, 0, 0)."""
FUTURE = 1e9
"""Seconds after now of a stamp 'far in the future' (31 years)."""

Builder = Callable[[Path], Path]


def good_arrays(**change: Any) -> dict[str, Any]:
    """A valid version-2 map of 3 voxels in two tiles of 1 block (decay 30 s, stamps 100 s)."""
    arrays: dict[str, Any] = {
        "ijk": np.array([[0, 0, 0], [1, 0, 0], [40, 0, 0]], dtype=np.int32),
        "s": np.array([1.0, 2.0, 3.0]),
        "n": np.array([0.0, 1.0, 2.0]),
        "t_last": np.array([100.0, 100.0, 99.0]),
        "resolution": np.float64(0.1),
        "origin": np.zeros(3),
        "decay_time": np.float64(30.0),
        "max_range": np.float64(40.0),
        "min_range": np.float64(0.0),
        "frame_id": np.str_("map"),
        "format": np.str_("mfp_mapper.map"),
        "version": np.int64(2),
    }
    arrays.update(change)
    return arrays


def write_legacy_map(path: Path, arrays: dict[str, Any], compress: bool = True) -> Path:
    """A version 1 or 2 map file as the writer before version 3 wrote it (commit e8b3188):
    each array through ``np.lib.format.write_array``, deflated at level 1 (the command
    line) or stored (the node)."""
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    level = 1 if compress else None
    with zipfile.ZipFile(path, "w", compression=method, compresslevel=level) as archive:
        for name, value in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
    return path


def block_members(**change: Any) -> dict[str, Any]:
    """The members of ``good_arrays`` as a version 3 file writes them, with ``change``."""
    members = as_block_arrays(good_arrays())
    members.update(change)
    return members


def _v3(d: Path, **change: Any) -> Path:
    """A version 3 file of ``block_members(**change)``, written without checks."""
    path = d / "map.npz"
    with open(path, "wb") as f:
        write_npz_stored(f, block_members(**change))
    return path


def _npz(path: Path, arrays: dict[str, Any]) -> Path:
    """Written as a foreign writer would (np.savez: any dtype, no checks)."""
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


def _members(path: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(path) as z:
        return {n: z.read(n) for n in z.namelist()}


def _rezip(path: Path, members: list[tuple[str, bytes]], method: int = zipfile.ZIP_STORED) -> Path:
    with zipfile.ZipFile(path, "w", compression=method) as z:
        for name, data in members:
            z.writestr(name, data)
    return path


def _npy_bytes(array: Any) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.asanyarray(array), allow_pickle=True)
    return buf.getvalue()


def _npy_header(descr: str, shape: tuple[int, ...]) -> bytes:
    buf = io.BytesIO()
    header = {"descr": descr, "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue()


def _raw_header(text: str) -> bytes:
    """An .npy 1.0 header of any text (numpy's writer refuses e.g. negative shapes)."""
    data = text.encode("latin1")
    pad = 64 - (10 + len(data) + 1) % 64
    data += b" " * pad + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(data)) + data


def _good(d: Path, name: str = "map.npz", **change: Any) -> Path:
    return _npz(d / name, good_arrays(**change))


def _with_member(d: Path, name: str, data: bytes, method: int = zipfile.ZIP_STORED) -> Path:
    path = _good(d)
    members = [(n, b) for n, b in _members(path).items() if n != name]
    return _rezip(path, [*members, (name, data)], method)


# --- .npz kinds ------------------------------------------------------------------------


def truncated(d: Path) -> Path:
    path = d / "map.npz"
    write_map_arrays(path, good_arrays())
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return path


def empty_file(d: Path) -> Path:
    (d / "map.npz").write_bytes(b"")
    return d / "map.npz"


def wrong_magic(d: Path) -> Path:
    (d / "map.npz").write_bytes(b"GIF89a" + bytes(range(256)) * 4)
    return d / "map.npz"


def npy_wrong_magic(d: Path) -> Path:
    return _with_member(d, "s.npy", b"not an npy array at all")


def bzip2_member(d: Path) -> Path:
    return _with_member(d, "s.npy", _npy_bytes(np.array([1.0, 2.0, 3.0])), zipfile.ZIP_BZIP2)


def negative_size(d: Path) -> Path:
    header = _raw_header("{'descr': '<f8', 'fortran_order': False, 'shape': (-3,), }")
    return _with_member(d, "s.npy", header + bytes(24))


def huge_claim(d: Path) -> Path:
    return _with_member(d, "s.npy", _npy_header("<f8", (10**12,)))


def duplicate_member(d: Path) -> Path:
    path = _good(d)
    members = list(_members(path).items())
    members.append(("s.npy", _npy_bytes(np.array([5.0, 6.0, 7.0]))))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zipfile warns of the duplicate name
        return _rezip(path, members)


def zip_bomb(d: Path, count: int = 10**8) -> Path:
    """3.5 MB declaring 3.6 GB: 10^8 voxels of zeros, deflated, sizes and CRCs honest."""
    members = []
    for name, descr, shape in (
        ("ijk", "<i4", (count, 3)),
        ("s", "<f8", (count,)),
        ("n", "<f8", (count,)),
        ("t_last", "<f8", (count,)),
    ):
        header = _npy_header(descr, shape)
        zeros = count * (12 if name == "ijk" else 8)
        members.append((f"{name}.npy", _deflated_zeros(header, zeros)))
    small = good_arrays()
    for name in ("resolution", "origin", "decay_time", "max_range", "min_range", "frame_id"):
        data = _npy_bytes(small[name])
        members.append((f"{name}.npy", (data, zlib.crc32(data), len(data), 0)))
    path = d / "map.npz"
    _write_raw_zip(path, members)
    return path


_MB = 1 << 20


@functools.lru_cache(maxsize=8)
def _deflated_zeros(header: bytes, zeros: int) -> tuple[bytes, int, int, int]:
    """(raw deflate of header + zeros, crc32, size, method 8), built from one deflated MiB
    repeated (full flushes make the pieces independent)."""
    comp = zlib.compressobj(9, zlib.DEFLATED, -15)
    parts = [comp.compress(header), comp.flush(zlib.Z_FULL_FLUSH)]
    piece = comp.compress(bytes(_MB)) + comp.flush(zlib.Z_FULL_FLUSH)
    whole, rest = divmod(zeros, _MB)
    parts += [piece] * whole
    parts += [comp.compress(bytes(rest)), comp.flush(zlib.Z_FINISH)]
    crc = zlib.crc32(header)
    block = bytes(_MB)
    for _ in range(whole):
        crc = zlib.crc32(block, crc)
    crc = zlib.crc32(bytes(rest), crc)
    return b"".join(parts), crc, len(header) + zeros, 8


def _write_raw_zip(path: Path, members: list[tuple[str, tuple[bytes, int, int, int]]]) -> None:
    """A plain zip (sizes below 4 GiB) of already compressed members."""
    out, central = bytearray(), bytearray()
    for name, (data, crc, size, method) in members:
        raw = name.encode()
        offset = len(out)
        out += struct.pack(
            "<IHHHHHIIIHH", 0x04034B50, 20, 0, method, 0, 0x21, crc, len(data), size, len(raw), 0
        )
        out += raw + data
        central += struct.pack(
            "<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, method, 0, 0x21, crc, len(data), size,
            len(raw), 0, 0, 0, 0, 0, offset,
        )  # fmt: skip
        central += raw
    end = struct.pack(
        "<IHHHHIIH", 0x06054B50, 0, 0, len(members), len(members), len(central), len(out), 0
    )
    path.write_bytes(bytes(out + central + end))


def dtype_int_s(d: Path) -> Path:
    return _good(d, s=np.array([1, 2, 3], dtype=np.int64))


def dtype_float_ijk(d: Path) -> Path:
    return _good(d, ijk=np.zeros((3, 3)))


def dtype_float128(d: Path) -> Path:
    return _good(d, s=np.array([1.0, 2.0, 3.0], dtype=np.longdouble))


def dtype_structured(d: Path) -> Path:
    return _good(d, n=np.zeros(3, dtype=[("a", "<f8")]))


def pickled_frame(d: Path) -> Path:
    return _good(d, frame_id=np.array([{"evil": "object"}], dtype=object))


def frame_not_string(d: Path) -> Path:
    return _good(d, frame_id=np.int64(7))


def long_frame(d: Path) -> Path:
    return _good(d, frame_id=np.str_("x" * 100_000))


def control_frame(d: Path) -> Path:
    return _good(d, frame_id=np.str_("map\n[ERROR] forged log line"))


def mismatched_lengths(d: Path) -> Path:
    return _good(d, s=np.array([1.0, 2.0]))


def nan_resolution(d: Path) -> Path:
    return _good(d, resolution=np.float64(np.nan))


def huge_resolution(d: Path) -> Path:
    return _good(d, resolution=np.float64(1e300))


def nan_decay(d: Path) -> Path:
    return _good(d, decay_time=np.float64(np.nan))


def negative_decay(d: Path) -> Path:
    return _good(d, decay_time=np.float64(-5.0))


def inverted_ranges(d: Path) -> Path:
    return _good(d, min_range=np.float64(50.0))


def inf_version(d: Path) -> Path:
    return _good(d, version=np.float64(np.inf))


def huge_version(d: Path) -> Path:
    return _good(d, version=np.int64(2**62))


def ijk_out_of_range(d: Path) -> Path:
    return _good(d, ijk=np.array([[0, 0, 0], [1, 0, 0], [2**30, 0, 0]], dtype=np.int32))


def origin_plus_1e300(d: Path) -> Path:
    return _good(d, origin=np.array([1e300, 0.0, 0.0]))


def origin_minus_1e300(d: Path) -> Path:
    return _good(d, origin=np.array([0.0, -1e300, 0.0]))


def origin_1e15(d: Path) -> Path:
    return _good(d, origin=np.array([1e15, 1e15, 0.0]))


def origin_nan(d: Path) -> Path:
    return _good(d, origin=np.array([0.0, np.nan, 0.0]))


def future_t_last(d: Path) -> Path:
    return _good(d, t_last=np.full(3, time.time() + FUTURE))


def nan_t_last(d: Path) -> Path:
    return _good(d, t_last=np.array([np.nan, 100.0, 100.0]))


def negative_s(d: Path) -> Path:
    return _good(d, s=np.array([1.0, -2.0, 3.0]))


def inf_n(d: Path) -> Path:
    return _good(d, n=np.array([np.inf, 1.0, 2.0]))


def duplicate_voxels(d: Path) -> Path:
    return _good(d, ijk=np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0]], dtype=np.int32))


def directory_as_file(d: Path) -> Path:
    (d / "map.npz").mkdir()
    return d / "map.npz"


def fifo(d: Path) -> Path:
    os.mkfifo(d / "map.npz")
    return d / "map.npz"


def symlink_to_fifo(d: Path) -> Path:
    os.mkfifo(d / "pipe")
    (d / "map.npz").symlink_to(d / "pipe")
    return d / "map.npz"


def dangling_symlink(d: Path) -> Path:
    (d / "map.npz").symlink_to(d / "gone.npz")
    return d / "map.npz"


def symlink_loop(d: Path) -> Path:
    (d / "map.npz").symlink_to(d / "map.npz")
    return d / "map.npz"


# --- tiled kinds -----------------------------------------------------------------------


def _tiled(d: Path, **change: Any) -> Path:
    root = d / "tiled"
    write_tiled(root, good_arrays(**change), tile_blocks=1)
    return root


def _edit_index(d: Path, edit: Callable[[dict[str, Any]], Any]) -> Path:
    root = _tiled(d)
    path = root / INDEX_NAME
    index = json.loads(path.read_text())
    edit(index)
    path.write_text(json.dumps(index))
    return root


def _replace_in_index(d: Path, old: str, new: str, count: int = 1) -> Path:
    root = _tiled(d)
    path = root / INDEX_NAME
    text = json.dumps(json.loads(path.read_text()))
    assert old in text, (old, text)
    path.write_text(text.replace(old, new, count))
    return root


def _tile0(root: Path) -> Path:
    index = json.loads((root / INDEX_NAME).read_text())
    entry = next(e for e in index["tiles"] if e["tile"] == [0, 0, 0])
    return root / entry["file"]


def index_tile_blocks_1e400(d: Path) -> Path:
    return _replace_in_index(d, '"tile_blocks": 1', '"tile_blocks": 1e400')


def index_tile_key_1e400(d: Path) -> Path:
    return _replace_in_index(d, '"tile": [0, 0, 0]', '"tile": [1e400, 0, 0]')


def index_tile_key_huge_int(d: Path) -> Path:
    return _replace_in_index(d, '"tile": [0, 0, 0]', f'"tile": [{10**30}, 0, 0]')


def index_nan_resolution(d: Path) -> Path:
    return _replace_in_index(d, '"resolution": 0.1', '"resolution": NaN')


def index_infinity_decay(d: Path) -> Path:
    return _replace_in_index(d, '"decay_time": 30.0', '"decay_time": Infinity')


def index_zero_tile_blocks(d: Path) -> Path:
    return _edit_index(d, lambda i: i.update(tile_blocks=0))


def index_bool_tile_blocks(d: Path) -> Path:
    return _replace_in_index(d, '"tile_blocks": 1', '"tile_blocks": true')


def index_truncated(d: Path) -> Path:
    root = _tiled(d)
    text = (root / INDEX_NAME).read_text()
    (root / INDEX_NAME).write_text(text[: len(text) // 2])
    return root


def index_duplicate_keys(d: Path) -> Path:
    return _replace_in_index(d, '"resolution": 0.1', '"resolution": 0.1, "resolution": 0.2')


def index_origin_1e300(d: Path) -> Path:
    return _edit_index(d, lambda i: i.update(origin=[1e300, 0.0, 0.0]))


def index_origin_1e15(d: Path) -> Path:
    return _edit_index(d, lambda i: i.update(origin=[0.0, 0.0, 1e15]))


def index_file_escapes(d: Path) -> Path:
    def edit(index: dict[str, Any]) -> None:
        index["tiles"][0]["file"] = "../../outside.npz"

    return _edit_index(d, edit)


def index_file_absolute(d: Path) -> Path:
    def edit(index: dict[str, Any]) -> None:
        index["tiles"][0]["file"] = "/etc/passwd"

    return _edit_index(d, edit)


def tile_missing(d: Path) -> Path:
    root = _tiled(d)
    _tile0(root).unlink()
    return root


def tile_is_directory(d: Path) -> Path:
    root = _tiled(d)
    tile = _tile0(root)
    tile.unlink()
    tile.mkdir()
    return root


def tile_symlink_to_fifo(d: Path) -> Path:
    root = _tiled(d)
    tile = _tile0(root)
    tile.unlink()
    os.mkfifo(d / "pipe")
    tile.symlink_to(d / "pipe")
    return root


def tile_truncated(d: Path) -> Path:
    root = _tiled(d)
    tile = _tile0(root)
    tile.write_bytes(tile.read_bytes()[:100])
    return root


def index_is_directory(d: Path) -> Path:
    root = _tiled(d)
    (root / INDEX_NAME).unlink()
    (root / INDEX_NAME).mkdir()
    return root


def index_is_fifo(d: Path) -> Path:
    root = _tiled(d)
    (root / INDEX_NAME).unlink()
    os.mkfifo(root / INDEX_NAME)
    return root


def index_future_t_max(d: Path) -> Path:
    def edit(index: dict[str, Any]) -> None:
        for e in index["tiles"]:
            e["t_max"] = time.time() + FUTURE

    return _edit_index(d, edit)


def tile_future_t_last(d: Path) -> Path:
    """Tiles stamped far in the future, their index edited to say 100 s."""
    root = _tiled(d, t_last=np.full(3, time.time() + FUTURE))
    path = root / INDEX_NAME
    index = json.loads(path.read_text())
    for e in index["tiles"]:
        e["t_max"] = 100.0
    path.write_text(json.dumps(index))
    return root


def tile_after_index_t_max(d: Path) -> Path:
    def edit(index: dict[str, Any]) -> None:
        index["tiles"][0]["t_max"] = 50.0

    return _edit_index(d, edit)


def tile_wrong_voxels(d: Path) -> Path:
    """Tile (0, 0, 0)'s file holds another tile's voxels."""
    root = _tiled(d)
    index = json.loads((root / INDEX_NAME).read_text())
    files = {tuple(e["tile"]): root / e["file"] for e in index["tiles"]}
    files[(0, 0, 0)].write_bytes(files[(5, 0, 0)].read_bytes())
    return root


def tile_other_resolution(d: Path) -> Path:
    root = _tiled(d)
    write_map_arrays(_tile0(root), good_arrays(resolution=np.float64(0.2), **_tile0_voxels()))
    return root


def _tile0_voxels() -> dict[str, Any]:
    a = good_arrays()
    return {k: a[k][:2] for k in ("ijk", "s", "n", "t_last")}


def index_duplicate_tile(d: Path) -> Path:
    def edit(index: dict[str, Any]) -> None:
        index["tiles"].append(dict(index["tiles"][0]))
        index["voxels"] += index["tiles"][0]["voxels"]

    return _edit_index(d, edit)


def index_tiles_not_list(d: Path) -> Path:
    return _edit_index(d, lambda i: i.update(tiles={"a": 1}))


def index_voxels_mismatch(d: Path) -> Path:
    return _edit_index(d, lambda i: i.update(voxels=4))


def index_voxels_huge(d: Path) -> Path:
    return _edit_index(d, lambda i: i.update(voxels=10**15))


def index_entry_voxels_huge(d: Path) -> Path:
    def edit(index: dict[str, Any]) -> None:
        index["tiles"][0]["voxels"] = 10**18

    return _edit_index(d, edit)


def index_deeply_nested(d: Path) -> Path:
    root = _tiled(d)
    (root / INDEX_NAME).write_text("[" * 100_000 + "]" * 100_000)
    return root


def index_not_utf8(d: Path) -> Path:
    root = _tiled(d)
    (root / INDEX_NAME).write_bytes(b'{"format": "\xff\xfe\xfa"}')
    return root


def index_not_object(d: Path) -> Path:
    root = _tiled(d)
    (root / INDEX_NAME).write_text("[1, 2, 3]")
    return root


def index_huge_sparse(d: Path) -> Path:
    root = _tiled(d)
    with open(root / INDEX_NAME, "r+b") as f:
        f.truncate(300 << 20)  # sparse: 300 MB of NUL bytes after the JSON
    return root


def index_no_format(d: Path) -> Path:
    return _edit_index(d, lambda i: i.pop("format"))


# --- version 3 kinds ---------------------------------------------------------------------


def v3_flipped_value(d: Path) -> Path:
    """A bit of one s value flipped on disk (still a plausible number): the CRC finds it.
    ``query`` reads only the blocks it needs (block (0, 0, 0) here) and answers: CRCs are
    checked by whole reads (``PARTIAL_READERS``)."""
    path = d / "map.npz"
    write_map_arrays(path, good_arrays())
    raw = bytearray(path.read_bytes())
    s_data = raw.find(b"\n", raw.find(b"'descr': '<f4'")) + 1  # s comes before n
    raw[s_data + 8] ^= 1  # the third voxel's s (3.0, in block (5, 0, 0)) changes a little
    path.write_bytes(bytes(raw))
    return path


def v3_unsorted_blocks(d: Path) -> Path:
    return _v3(d, **take_blocks(block_members(), np.array([1, 0])))


def v3_block_start_lies(d: Path) -> Path:
    return _v3(d, block_start=np.array([0, 1, 3], dtype="<i8"))


def v3_hit_not_observed(d: Path) -> Path:
    hit = block_members()["hit"].copy()
    hit[0, 7] |= np.uint64(1)  # voxel 448 of block (0, 0, 0): not observed
    n = np.array([1.0, 0.5, 2.0], dtype="<f4")
    return _v3(d, hit=hit, n=n, hit_start=np.array([0, 2, 3], dtype="<i8"))


def v3_deflated(d: Path) -> Path:
    path = _v3(d)
    members = list(_members(path).items())
    return _rezip(path, members, zipfile.ZIP_DEFLATED)


def v3_negative_s(d: Path) -> Path:
    return _v3(d, s=np.array([1.0, -2.0, 3.0], dtype="<f4"))


def v3_nan_block_t(d: Path) -> Path:
    return _v3(d, block_t=np.array([np.nan, 99.0]))


def v3_block_out_of_range(d: Path) -> Path:
    return _v3(d, block_ijk=np.array([[0, 0, 0], [2**22, 0, 0]], dtype="<i4"))


def v3_mask_shape(d: Path) -> Path:
    return _v3(d, observed=np.zeros((2, 4), dtype="<u8"))


def v3_int_s(d: Path) -> Path:
    return _v3(d, s=np.array([1, 2, 3], dtype="<i4"))


def v3_as_version_2(d: Path) -> Path:
    return _v3(d, version=np.int64(2))


def v3_missing_hit(d: Path) -> Path:
    members = block_members()
    del members["hit"]
    path = d / "map.npz"
    with open(path, "wb") as f:
        write_npz_stored(f, members)
    return path


def tiled_without_index(d: Path) -> Path:
    root = _tiled(d)
    (root / INDEX_NAME).unlink()
    return root


KINDS: dict[str, tuple[Builder, str]] = {
    # .npz: the archive
    "v3_flipped_value": (v3_flipped_value, "fails its CRC-32 check"),
    "v3_unsorted_blocks": (v3_unsorted_blocks, "not sorted by index"),
    "v3_block_start_lies": (v3_block_start_lies, "does not count"),
    "v3_hit_not_observed": (v3_hit_not_observed, "not marked observed"),
    "v3_deflated": (v3_deflated, "version 3 members are stored"),
    "v3_negative_s": (v3_negative_s, "s holds negative"),
    "v3_nan_block_t": (v3_nan_block_t, "block times hold NaN"),
    "v3_block_out_of_range": (v3_block_out_of_range, "block indices beyond"),
    "v3_mask_shape": (v3_mask_shape, "observed must have shape (2, 8)"),
    "v3_int_s": (v3_int_s, "s has dtype <i4"),
    "v3_as_version_2": (v3_as_version_2, "version 2 cannot hold blocks"),
    "v3_missing_hit": (v3_missing_hit, "map without hit"),
    "truncated": (truncated, "unreadable or truncated"),
    "empty_file": (empty_file, "unreadable or truncated"),
    "wrong_magic": (wrong_magic, "unreadable or truncated"),
    "npy_wrong_magic": (npy_wrong_magic, "unreadable or truncated"),
    "bzip2_member": (bzip2_member, "compression method 12"),
    "duplicate_member": (duplicate_member, "appears twice"),
    "zip_bomb": (zip_bomb, "declare 3.6 GB in a file of 3.56 MB"),
    # .npz: headers
    "negative_size": (negative_size, "negative size"),
    "huge_claim": (huge_claim, "claims 8000000000000 bytes"),
    "dtype_int_s": (dtype_int_s, "s must be a float array"),
    "dtype_float_ijk": (dtype_float_ijk, "ijk must be an integer"),
    "dtype_float128": (dtype_float128, "s must be a float array"),
    "dtype_structured": (dtype_structured, "not a plain number"),
    "pickled_frame": (pickled_frame, "pickles are never loaded"),
    "frame_not_string": (frame_not_string, "frame_id must be a string"),
    "long_frame": (long_frame, "frame_id is a string of 100000"),
    "mismatched_lengths": (mismatched_lengths, "s must be a float array of length 3"),
    "inf_version": (inf_version, "version must be an integer"),
    # .npz: values
    "huge_version": (huge_version, "version 4611686018427387904 is not in"),
    "nan_resolution": (nan_resolution, "resolution must be positive"),
    "huge_resolution": (huge_resolution, "resolution must be positive"),
    "nan_decay": (nan_decay, "decay_time must be > 0"),
    "negative_decay": (negative_decay, "decay_time must be > 0"),
    "inverted_ranges": (inverted_ranges, "need max_range > min_range"),
    "control_frame": (control_frame, "printable characters"),
    "origin_plus_1e300": (origin_plus_1e300, "origin [1e+300, 0.0, 0.0] m lies beyond"),
    "origin_minus_1e300": (origin_minus_1e300, "origin [0.0, -1e+300, 0.0] m lies beyond"),
    "origin_1e15": (origin_1e15, "origin [1000000000000000.0, 1000000000000000.0, 0.0] m"),
    "origin_nan": (origin_nan, "origin must be 3 finite metres"),
    "ijk_out_of_range": (ijk_out_of_range, "indices beyond"),
    "nan_t_last": (nan_t_last, "t_last holds NaN"),
    "future_t_last": (future_t_last, "after the file was written"),
    "negative_s": (negative_s, "s holds negative"),
    "inf_n": (inf_n, "n holds negative, NaN or infinite"),
    "duplicate_voxels": (duplicate_voxels, "more than once"),
    # .npz: the path
    "directory_as_file": (directory_as_file, "not a tiled map"),
    "fifo": (fifo, "not a regular file"),
    "symlink_to_fifo": (symlink_to_fifo, "not a regular file"),
    "dangling_symlink": (dangling_symlink, "dangling symbolic link"),
    "symlink_loop": (symlink_loop, "cannot be opened"),
    # tiled: index.json numbers and types
    "index_tile_blocks_1e400": (index_tile_blocks_1e400, "tile_blocks must be an integer"),
    "index_tile_key_1e400": (index_tile_key_1e400, "tiles[0].tile must be 3 integers"),
    "index_tile_key_huge_int": (index_tile_key_huge_int, "tiles[0].tile must be 3 integers"),
    "index_nan_resolution": (index_nan_resolution, "resolution must be a finite number"),
    "index_infinity_decay": (index_infinity_decay, "decay_time must be a finite number"),
    "index_zero_tile_blocks": (index_zero_tile_blocks, "tile_blocks must be an integer in"),
    "index_bool_tile_blocks": (index_bool_tile_blocks, "tile_blocks must be an integer"),
    "index_origin_1e300": (index_origin_1e300, "lies beyond"),
    "index_origin_1e15": (index_origin_1e15, "lies beyond"),
    "index_voxels_mismatch": (index_voxels_mismatch, "voxels is 4 but the tiles list 3"),
    "index_voxels_huge": (index_voxels_huge, "voxels must be an integer in"),
    "index_entry_voxels_huge": (index_entry_voxels_huge, "tiles[0].voxels must be an integer"),
    "index_future_t_max": (index_future_t_max, "t_max reaches"),
    # tiled: index.json structure
    "index_truncated": (index_truncated, "not valid JSON"),
    "index_duplicate_keys": (index_duplicate_keys, "key 'resolution' appears twice"),
    "index_duplicate_tile": (index_duplicate_tile, "listed more than once"),
    "index_tiles_not_list": (index_tiles_not_list, "tiles must be a list"),
    "index_deeply_nested": (index_deeply_nested, "nested too deeply"),
    "index_not_utf8": (index_not_utf8, "unreadable tile index"),
    "index_not_object": (index_not_object, "must hold a JSON object"),
    "index_no_format": (index_no_format, "format is None"),
    "index_huge_sparse": (index_huge_sparse, "more than the"),
    "index_file_escapes": (index_file_escapes, "must name a .npz file in tiles/"),
    "index_file_absolute": (index_file_absolute, "must name a .npz file in tiles/"),
    # tiled: the files
    "tiled_without_index": (tiled_without_index, "no index.json"),
    "index_is_directory": (index_is_directory, "is a directory"),
    "index_is_fifo": (index_is_fifo, "not a regular file"),
    "tile_missing": (tile_missing, "no such file"),
    "tile_is_directory": (tile_is_directory, "is a directory"),
    "tile_symlink_to_fifo": (tile_symlink_to_fifo, "not a regular file"),
    "tile_truncated": (tile_truncated, "unreadable or truncated"),
    "tile_future_t_last": (tile_future_t_last, "after the file was written"),
    "tile_after_index_t_max": (tile_after_index_t_max, "after the index's t_max"),
    "tile_wrong_voxels": (tile_wrong_voxels, "does not hold the 2 voxels of tile"),
    "tile_other_resolution": (tile_other_resolution, "resolution"),
}
