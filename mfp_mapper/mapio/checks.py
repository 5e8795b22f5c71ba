"""Checks of map files before anything is allocated or trusted.

Every function here returns the problem as one sentence (``None`` when there is none) or
raises ``ValueError`` with it; the readers (``mapfile``, ``tiles``) add the file's name.
The order of a read is: the path is a regular file (``file_problem``); each ``.npy``
member's header, its shape and dtype against the zip's sizes (``member_problem``) and the
whole archive's declared bytes against the file's real size (``expansion_problem``); the
settings (``settings_problem``, ``origin_problem``); only then the voxel arrays are read,
and their values checked (``core.store.voxel_problem``, ``future_problem``). A tiled map's
``index.json`` is parsed and checked whole by ``parse_index`` before any tile is opened.

Limits (docs/mapfiles.md, "Map files that are refused"):

- ``MAX_EXPANSION``: the arrays of a map file may declare at most this many bytes per byte
  of the file (plus ``EXPANSION_SLACK``); deflate can expand data ~1030 times, real maps
  compress 1.5-4 times, so a file of zeros declaring gigabytes is refused unread.
- ``MAX_ORIGIN_VOXELS``: ``|origin| / resolution`` at most 2^36, where a float64 coordinate
  still resolves 1/65536 of a voxel (6.9e9 m at 0.1 m; any Earth-fixed frame fits).
- ``FUTURE_TOLERANCE_S``: under decay, no ``t_last`` (or index ``t_max``) more than a day
  after the file's modification time: the map would decay every later scan to nothing.
"""

from __future__ import annotations

import json
import math
import os
import stat
from collections.abc import Sequence
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from mfp_mapper.core.layout import MAX_RESOLUTION, MAX_VOXEL_INDEX, MIN_RESOLUTION

MAX_DEFLATE_RATIO = 1100
"""Deflate cannot expand data more than ~1032 times: a member claiming more is lying."""
MAX_EXPANSION = 64
"""Declared array bytes per byte of a map file, at most (plus ``EXPANSION_SLACK``)."""
EXPANSION_SLACK = 64 << 20
"""Bytes any map file may declare whatever its size (small maps of constant values)."""
MAX_ORIGIN_VOXELS = 2**36
"""Largest ``|origin| / resolution``: coordinates there still resolve 2^-16 voxel."""
FUTURE_TOLERANCE_S = 86400.0
"""Under decay, how far (s) a stamp may lie after the file's modification time."""
MAX_FRAME_ID = 256
"""Longest frame id (characters)."""
MAX_INDEX_BYTES = 256 << 20
"""Largest ``index.json`` read (about a million tiles)."""
MAX_TILE_BLOCKS = 1 << 21
"""Largest tile edge in blocks (one tile then spans the whole index range)."""
MAX_VOXELS = 1 << 40
"""Largest voxel count an index may declare."""
_BLOCK_RANGE = (MAX_VOXEL_INDEX >> 3) + 1
TILES_FORMAT = "mfp_mapper.tiles"
TILES_VERSION = 1
TILE_DIR = "tiles"
"""The tiled map's index contract (docs/mapfiles.md; ``core.tiles`` re-exports these)."""
ALLOWED_COMPRESSION = (0, 8)
"""Zip methods a map file may use: stored, deflated (what numpy writes)."""

_FLOAT_SIZES = (2, 4, 8)
MEMBER_KINDS: dict[str, tuple[tuple[int, ...] | None, str, str]] = {
    # name: (shape (None: per-voxel, checked below), dtype kinds, what it must be)
    "ijk": (None, "iu", "an integer (N, 3) array"),
    "s": (None, "f", "a float array of length N"),
    "n": (None, "f", "a float array of length N"),
    "t_last": (None, "f", "a float array of length N"),
    "resolution": ((), "iuf", "a number"),
    "decay_time": ((), "iuf", "a number"),
    "max_range": ((), "iuf", "a number"),
    "min_range": ((), "iuf", "a number"),
    "prior_shape": ((), "iuf", "a number"),
    "prior_rate": ((), "iuf", "a number"),
    "origin": ((3,), "f", "a float array of 3 metres"),
    "frame_id": ((), "U", "a string"),
    "format": ((), "U", "a string"),
    "version": ((), "iu", "an integer"),
    # the reflectivity histograms (core.reflectivity): K rows of J bins, checked below
    "reflectivity_ijk": (None, "iu", "an integer (K, 3) array"),
    "reflectivity_counts": (None, "f", "a float (K, J) array"),
    "reflectivity_t_last": (None, "f", "a float array of length K"),
    "reflectivity_edges": (None, "f", "a float array of J - 1 bin edges"),
    "reflectivity_field": ((), "U", "a string"),
}
"""The members a map file may hold; others are not read."""


def file_problem(path: Path, what: str = "map file") -> str | None:
    """Whether ``path`` (symlinks followed) is a regular file: never open a FIFO, a device
    or a directory as a map."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            return f"dangling symbolic link to {os.readlink(path)!r}"
        return "no such file"
    except OSError as err:  # a symlink loop, a permission
        return f"cannot be opened ({err.strerror or err})"
    if stat.S_ISDIR(st.st_mode):
        return f"is a directory, expected a {what}"
    if not stat.S_ISREG(st.st_mode):
        return f"is not a regular file (a FIFO, socket or device), expected a {what}"
    return None


def member_problem(
    name: str,
    shape: tuple[int, ...],
    dtype: np.dtype,
    data_bytes: int,
    compressed: int,
    method: int,
) -> str | None:
    """One ``.npy`` member's header against what the zip says it holds: sizes non-negative,
    dtypes plain, the declared bytes within the member's size (``data_bytes``) and, when
    deflated (``method`` 8), deflate's ratio to its ``compressed`` size."""
    if any(d < 0 for d in shape):
        return f"{name} declares a negative size {shape}"
    if dtype.hasobject:
        return f"{name} holds Python objects (pickles are never loaded)"
    if dtype.fields is not None or dtype.subdtype is not None or dtype.kind not in "iufU":
        return f"{name} has dtype {dtype}, not a plain number or string"
    nbytes = math.prod(shape) * dtype.itemsize
    limit = data_bytes
    if method != 0:
        limit = min(limit, MAX_DEFLATE_RATIO * compressed + (1 << 20))
    if nbytes > limit:
        return f"{name} claims {nbytes} bytes ({shape} {dtype}) but holds at most {limit}"
    return None


def header_problem(headers: dict[str, tuple[tuple[int, ...], np.dtype]]) -> str | None:
    """The shapes and dtypes of a map file's known members."""
    ijk = headers.get("ijk")
    for name, (shape, dtype) in headers.items():
        want, kinds, text = MEMBER_KINDS[name]
        if want is None and name.startswith("reflectivity_"):
            want = _reflectivity_shape(name, headers)
        elif want is None:
            count = ijk[0][0] if ijk and len(ijk[0]) == 2 else -1
            want = (count, 3) if name == "ijk" else (count,)
            text = text.replace("length N", f"length {count} (the rows of ijk)")
        ok = shape == want and dtype.kind in kinds
        if dtype.kind == "f" and dtype.itemsize not in _FLOAT_SIZES:
            ok = False  # float128 values may not fit a float64
        if dtype.kind in "iu" and dtype.itemsize > 8:
            ok = False
        if dtype.kind == "U" and dtype.itemsize > 4 * MAX_FRAME_ID:
            return (
                f"{name} is a string of {dtype.itemsize // 4} characters (at most {MAX_FRAME_ID})"
            )
        if not ok:
            return f"{name} must be {text}, got {dtype} {shape}"
    return None


def _reflectivity_shape(
    name: str, headers: dict[str, tuple[tuple[int, ...], np.dtype]]
) -> tuple[int, ...]:
    """The shape a reflectivity member must have: K rows (of ``reflectivity_ijk``), J bins
    (one more than ``reflectivity_edges``)."""
    rows_shape = headers.get("reflectivity_ijk", ((-1, 3), np.dtype(np.int32)))[0]
    rows = rows_shape[0] if len(rows_shape) == 2 else -1
    edges_shape = headers.get("reflectivity_edges", ((-1,), np.dtype(np.float64)))[0]
    bins = edges_shape[0] + 1 if len(edges_shape) == 1 else -1
    return {
        "reflectivity_ijk": (rows, 3),
        "reflectivity_counts": (rows, bins),
        "reflectivity_t_last": (rows,),
        "reflectivity_edges": (bins - 1,) if 1 <= bins <= 64 else (-1,),
    }[name]


def expansion_problem(declared: int, file_size: int) -> str | None:
    """The arrays' declared bytes against the file's real size (``MAX_EXPANSION``)."""
    limit = MAX_EXPANSION * file_size + EXPANSION_SLACK
    if declared > limit:
        return (
            f"its arrays declare {_size(declared)} in a file of {_size(file_size)} "
            f"(more than {MAX_EXPANSION} times the file plus {_size(EXPANSION_SLACK)}): "
            "refused before reading, as a damaged or hostile file"
        )
    return None


def settings_problem(
    resolution: float, decay_time: float, max_range: float, min_range: float, frame_id: str
) -> str | None:
    """The stored mapper settings, each in its range."""
    if not (math.isfinite(resolution) and MIN_RESOLUTION <= resolution <= MAX_RESOLUTION):
        return (
            f"resolution must be positive, within [{MIN_RESOLUTION}, {MAX_RESOLUTION}] m, "
            f"got {resolution}"
        )
    if not decay_time > 0:
        return f"decay_time must be > 0 seconds (inf = static), got {decay_time}"
    if not (max_range > min_range >= 0 and math.isfinite(min_range)):
        return f"need max_range > min_range >= 0 (finite min_range), got {max_range}, {min_range}"
    return frame_problem(frame_id)


def prior_problem(shape: float, rate: float) -> str | None:
    """The stored Gamma prior on the extinction: shape and rate finite and > 0."""
    if not (math.isfinite(shape) and shape > 0 and math.isfinite(rate) and rate > 0):
        return f"prior_shape and prior_rate must be finite and > 0, got {shape}, {rate}"
    return None


def frame_problem(frame_id: str) -> str | None:
    if len(frame_id) > MAX_FRAME_ID or not frame_id.isprintable():
        return f"frame_id must be at most {MAX_FRAME_ID} printable characters, got {frame_id!r:.80}"
    return None


def origin_problem(origin: Sequence[float] | np.ndarray, resolution: float) -> str | None:
    """The origin: three finite metres within ``MAX_ORIGIN_VOXELS`` voxels of zero."""
    o = np.asarray(origin, dtype=np.float64)
    if o.shape != (3,) or not np.isfinite(o).all():
        return f"origin must be 3 finite metres, got {o.tolist()}"
    limit = MAX_ORIGIN_VOXELS * resolution
    if np.abs(o).max() > limit:
        return (
            f"origin {o.tolist()} m lies beyond +-{limit:.4g} m (2^36 voxels of "
            f"{resolution:g} m), where coordinates no longer resolve a voxel; every scan "
            "would fall outside the map's index range"
        )
    return None


def future_problem(t_max: float, decay_time: float, written_at: float, what: str) -> str | None:
    """Under decay, a newest stamp ``t_max`` more than ``FUTURE_TOLERANCE_S`` after the file
    was written (its modification time ``written_at``): every later scan would decay away."""
    if math.isinf(decay_time) or not t_max > written_at + FUTURE_TOLERANCE_S:
        return None
    return (
        f"{what} reaches {t_max:.6g} s, {t_max - written_at:.3g} s after the file was written "
        f"(modification time {written_at:.6g} s; tolerance {FUTURE_TOLERANCE_S:g} s): with "
        f"decay_time {decay_time:g} s every later scan would add nothing; if its clock is "
        "right, give the file a later modification time (touch)"
    )


def _size(nbytes: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if nbytes >= scale:
            return f"{nbytes / scale:.3g} {unit}"
    return f"{nbytes} bytes"


# --- index.json ------------------------------------------------------------------------


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"key {key!r} appears twice in one object")
        out[key] = value
    return out


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _int(obj: dict[str, Any], key: str, lo: int, hi: int, where: str = "") -> int:
    value = obj.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise ValueError(f"{where}{key} must be an integer in [{lo}, {hi}], got {value!r:.40}")
    return value


def _number(
    obj: dict[str, Any], key: str, lo: float, hi: float = math.inf, null: float | None = None
) -> float:
    """A finite JSON number in [lo, hi] (``null`` stands for ``null`` when allowed)."""
    value = obj.get(key, ...)
    if value is None and null is not None:
        return null
    if not _is_number(value) or not math.isfinite(value) or not lo <= value <= hi:
        allowed = " or null" if null is not None else ""
        raise ValueError(
            f"{key} must be a finite number in [{lo}, {hi}]{allowed}, got {value!r:.40}"
        )
    return float(value)


def read_index(path: Path) -> dict[str, Any]:
    """``index.json`` read and checked whole (``parse_index``); ValueError on any problem."""
    problem = file_problem(path, "JSON file")
    if problem:
        raise ValueError(problem)
    size = path.stat().st_size
    if size > MAX_INDEX_BYTES:
        raise ValueError(f"is {_size(size)}, more than the {_size(MAX_INDEX_BYTES)} read")
    with open(path, "rb") as f:
        raw = f.read(MAX_INDEX_BYTES + 1)
    return parse_index(raw.decode("utf-8"))


def parse_index(text: str) -> dict[str, Any]:
    """The index as plain values, every one checked (types, finiteness, ranges, duplicate
    keys and tiles, tile files inside ``tiles/``); infinite settings stand for ``null``."""
    try:
        index = json.loads(text, object_pairs_hook=_unique_keys)
    except RecursionError:
        raise ValueError("nested too deeply to be an index") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"not valid JSON ({err})") from None
    if not isinstance(index, dict):
        raise ValueError(f"must hold a JSON object, got {type(index).__name__}")
    if index.get("format") != TILES_FORMAT:
        raise ValueError(f"format is {index.get('format')!r:.40}, expected {TILES_FORMAT!r}")
    out: dict[str, Any] = {"version": _int(index, "version", 1, TILES_VERSION)}
    res = out["resolution"] = _number(index, "resolution", MIN_RESOLUTION, MAX_RESOLUTION)
    out["decay_time"] = _number(index, "decay_time", 0.0, null=math.inf)
    if out["decay_time"] <= 0:
        raise ValueError(f"decay_time must be > 0 seconds or null, got {out['decay_time']}")
    out["max_range"] = _number(index, "max_range", 0.0, null=math.inf)
    out["min_range"] = _number(index, "min_range", 0.0)
    # an index without a prior was written with the uniform prior
    for key in ("prior_shape", "prior_rate"):
        out[key] = _number(index, key, 0.0) if key in index else 1.0
    problem = prior_problem(out["prior_shape"], out["prior_rate"])
    if problem:
        raise ValueError(problem)
    if not isinstance(index.get("frame_id"), str):
        raise ValueError(f"frame_id must be a string, got {index.get('frame_id')!r:.40}")
    out["frame_id"] = index["frame_id"]
    problem = settings_problem(
        res, out["decay_time"], out["max_range"], out["min_range"], out["frame_id"]
    )
    if problem:
        raise ValueError(problem)
    out["origin"] = None
    if "origin" in index:
        origin = index["origin"]
        if not (isinstance(origin, list) and len(origin) == 3 and all(map(_is_number, origin))):
            raise ValueError(f"origin must be a list of 3 numbers, got {origin!r:.60}")
        problem = origin_problem(origin, res)
        if problem:
            raise ValueError(problem)
        out["origin"] = [float(v) for v in origin]
    blocks = out["tile_blocks"] = _int(index, "tile_blocks", 1, MAX_TILE_BLOCKS)
    tiles = index.get("tiles")
    if not isinstance(tiles, list):
        raise ValueError(f"tiles must be a list, got {type(tiles).__name__}")
    out["tiles"] = entries = [_tile_entry(e, k, blocks, TILE_DIR) for k, e in enumerate(tiles)]
    keys = {e[0] for e in entries}
    if len(keys) != len(entries):
        raise ValueError("a tile is listed more than once")
    if len({e[1] for e in entries}) != len(entries):
        raise ValueError("a tile file is listed more than once")
    total = _int(index, "voxels", 0, MAX_VOXELS)
    if total != sum(e[2] for e in entries):
        raise ValueError(f"voxels is {total} but the tiles list {sum(e[2] for e in entries)}")
    out["voxels"] = total
    return out


def _tile_entry(e: Any, k: int, tile_blocks: int, tile_dir: str) -> tuple[Any, ...]:
    """(key, file, voxels, t_max) of entry ``k`` of ``tiles``."""
    where = f"tiles[{k}]."
    if not isinstance(e, dict):
        raise ValueError(f"tiles[{k}] must be an object, got {type(e).__name__}")
    key = e.get("tile")
    lo, hi = -_BLOCK_RANGE // tile_blocks - 1, _BLOCK_RANGE // tile_blocks
    if not (isinstance(key, list) and len(key) == 3) or not all(
        isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi for v in key
    ):
        raise ValueError(f"{where}tile must be 3 integers in [{lo}, {hi}], got {key!r:.60}")
    if "blocks" in e:
        b0 = [v * tile_blocks for v in key]
        if e["blocks"] != [b0, [v + tile_blocks for v in b0]]:
            raise ValueError(f"{where}blocks {e['blocks']!r:.60} do not match tile {key}")
    name = e.get("file")
    parts = PurePosixPath(name).parts if isinstance(name, str) and "\\" not in name else ()
    if len(parts) != 2 or parts[0] != tile_dir or not parts[1].endswith(".npz"):
        raise ValueError(f"{where}file must name a .npz file in {tile_dir}/, got {name!r:.80}")
    voxels = _int(e, "voxels", 0, MAX_VOXELS, where)
    t_max = -math.inf
    if voxels:  # an empty tile's t_max is -Infinity (or null)
        try:
            t_max = _number(e, "t_max", -math.inf)
        except ValueError as err:
            raise ValueError(f"{where}{err}") from None
    return (key[0], key[1], key[2]), name, voxels, t_max
