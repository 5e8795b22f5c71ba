"""The map file: a contract other programs read.

An ``.npz`` archive (never pickles, members stored, not deflated). Version 3 (written
now) holds the store's blocks as they are in memory (``mapio.blockfile``: per block its
index, time and a mask of observed voxels, then ``s`` of the observed voxels and ``n`` of
those with a return, float32 as in memory), about 5 bytes a voxel, with a block index at
its head so that a reader needing a few blocks reads only those. Every version holds

=============  ==============  ===================================================
``resolution`` float64 ()      voxel edge, metres
``origin``     float64 (3,)    map-frame position of the corner of voxel (0, 0, 0),
                               metres (version >= 2; absent in version 1: zero)
``decay_time`` float64 ()      time constant, seconds (inf = static map)
``frame_id``   str ()          the map frame
``format``     str ()          ``"mfp_mapper.map"``
``version``    int64 ()        file format version (3)
=============  ==============  ===================================================

and, for a map with a reflectivity field (docs/model.md), its histograms: ``reflectivity_ijk``
int32 (K, 3), ``reflectivity_counts`` float64 (K, J), ``reflectivity_t_last`` float64 (K,),
``reflectivity_edges`` float64 (J - 1,) and ``reflectivity_field`` str (``core.reflectivity``);
plus ``max_range`` and ``min_range`` (float64, metres) and ``prior_shape``, ``prior_rate``
(float64: the Gamma prior on the extinction the estimates use, docs/model.md; a file
without them was written with the uniform prior, 1 and 1). Versions 1 and 2 (still read)
list the voxels instead: ``ijk`` int32 (N, 3), ``s``, ``n``, ``t_last`` float64 (N,), in
no particular order. The centre of voxel ``ijk`` is ``origin + (ijk + 0.5) * resolution``
(map frame, metres). Files are written atomically (``mapio.atomic``).

Reading checks the file before allocating (``mapio.checks``): a regular file; the arrays'
shapes and dtypes from their ``.npy`` headers, sizes against the archive's own sizes and
together against the file's real size; then the settings (resolution in
[``MIN_RESOLUTION``, ``MAX_RESOLUTION``], decay time, ranges, frame, origin), and only then
the voxels: CRC-32 of each version 3 member, finite, indices within the store's range,
stamps not in the future of the file under decay, no voxel twice (version 3: blocks sorted,
masks and counts consistent). Any problem is a ``MapFileError`` naming the file.
"""

from __future__ import annotations

import io
import math
import struct
import tokenize
import zipfile
import zlib
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.errors import CoreError
from mfp_mapper.core.layout import (
    BLOCK_BITS,
    MAX_VOXEL_INDEX,
    PackedBlocks,
    VoxelArrays,
    packed_problem,
    sort_keys,
    voxel_problem,
)
from mfp_mapper.mapio.atomic import atomic_output
from mfp_mapper.mapio.blockfile import (
    BLOCK_MEMBERS,
    HI_MEMBERS,
    TABLE_MEMBERS,
    BlockFileError,
    BlockReader,
    Member,
    block_arrays,
    locate_members,
    packed_of,
    packed_to_voxels,
    read_all,
    read_member,
    voxels_to_packed,
    write_npz_stored,
)
from mfp_mapper.mapio.checks import (
    ALLOWED_COMPRESSION,
    MEMBER_KINDS,
    expansion_problem,
    file_problem,
    future_problem,
    header_problem,
    member_problem,
    origin_problem,
    prior_problem,
    settings_problem,
)

if TYPE_CHECKING:  # imported where used: reading a file loads no numba (``mapio.queries``)
    from mfp_mapper.core.mapper import Mapper
    from mfp_mapper.core.reflectivity_arrays import ReflectivityArrays

FORMAT_NAME = "mfp_mapper.map"
FORMAT_VERSION = 4
REQUIRED_KEYS = ("ijk", "s", "n", "t_last", "resolution", "decay_time", "frame_id")
"""Members of a version 1 or 2 file."""
SETTING_KEYS = ("resolution", "decay_time", "frame_id")
"""Settings every version holds."""

OPTIONAL_SETTINGS = {"max_range": None, "min_range": None, "prior_shape": 1.0, "prior_rate": 1.0}
"""Settings a file may lack: None, the Mapper's default; else what an older file meant."""


def optional_settings(arrays: Mapping[str, Any]) -> dict[str, float]:
    """The ``OPTIONAL_SETTINGS`` of map-file arrays: as stored, else what their absence
    means (the prior: uniform); ranges the file lacks are left out."""
    out = {k: float(arrays[k]) for k in OPTIONAL_SETTINGS if k in arrays}
    for key, meaning in OPTIONAL_SETTINGS.items():
        if meaning is not None:
            out.setdefault(key, meaning)
    return out


class MapFileError(CoreError, ValueError):
    """A map file that cannot be read: names the file and what is wrong with it."""

    def __init__(self, path: str | Path, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem


class MapSource(Protocol):
    """What ``map_arrays`` reads from a map (``Mapper`` is one)."""

    resolution: float
    decay_time: float
    max_range: float
    min_range: float
    frame_id: str

    @property
    def prior_shape(self) -> float: ...

    @property
    def prior_rate(self) -> float: ...

    @property
    def origin(self) -> tuple[float, float, float] | None: ...

    def stored_voxels(self) -> VoxelArrays: ...

    def stored_blocks(self) -> PackedBlocks: ...

    def stored_reflectivity(self) -> ReflectivityArrays | None: ...


@dataclass
class MapContents:
    """A map file's contents, checked: settings and voxels."""

    resolution: float
    origin: tuple[float, float, float]
    decay_time: float
    frame_id: str
    ranges: dict[str, float]
    """``max_range`` and ``min_range`` where the file has them; ``prior_shape`` and
    ``prior_rate`` always (1 and 1 where the file has none)."""
    voxel_lists: VoxelArrays | None
    """The voxels of a version 1 or 2 file (None: ``packed`` holds them)."""
    packed: PackedBlocks | None = None
    """The voxels of a version 3 file, as stored."""
    reflectivity: ReflectivityArrays | None = None
    """The reflectivity histograms (``reflectivity_*`` members), when the file has them."""

    @property
    def voxels(self) -> VoxelArrays:
        """The voxels as lists (of a version 3 file: unpacked, float64, the first time)."""
        if self.voxel_lists is None:
            self.voxel_lists = (
                packed_to_voxels(self.packed) if self.packed is not None else _no_voxels()
            )
        return self.voxel_lists

    @voxels.setter
    def voxels(self, voxels: VoxelArrays) -> None:
        self.voxel_lists, self.packed = voxels, None


def _no_voxels() -> VoxelArrays:
    return VoxelArrays(np.zeros((0, 3), np.int32), np.zeros(0), np.zeros(0), np.zeros(0))


def write_map(path: str | Path, mapper: MapSource) -> None:
    """Write ``mapper`` to ``path`` (.npz, version 3) atomically."""
    write_map_arrays(path, map_blocks(mapper))


def settings_arrays(mapper: MapSource) -> dict[str, np.ndarray]:
    """The settings members of ``mapper``'s map file."""
    origin = mapper.origin if mapper.origin is not None else (0.0, 0.0, 0.0)
    return {
        "format": np.str_(FORMAT_NAME),
        "version": np.int64(FORMAT_VERSION),
        "resolution": np.float64(mapper.resolution),
        "origin": np.array(origin, dtype=np.float64),
        "decay_time": np.float64(mapper.decay_time),
        "max_range": np.float64(mapper.max_range),
        "min_range": np.float64(mapper.min_range),
        "prior_shape": np.float64(mapper.prior_shape),
        "prior_rate": np.float64(mapper.prior_rate),
        "frame_id": np.str_(mapper.frame_id),
    }


def reflectivity_members(table: ReflectivityArrays | None) -> dict[str, np.ndarray]:
    """The ``reflectivity_*`` members of a map file holding ``table`` ({} for None)."""
    if table is None:
        return {}
    from mfp_mapper.core.reflectivity_arrays import to_map_arrays

    return to_map_arrays(table)


def map_blocks(mapper: MapSource) -> dict[str, np.ndarray]:
    """The members of ``mapper``'s map file (version 3: packed blocks): a snapshot,
    independent of the mapper afterwards (a caller takes it under a lock and writes it
    outside)."""
    return {
        **settings_arrays(mapper),
        **reflectivity_members(mapper.stored_reflectivity()),
        **block_arrays(mapper.stored_blocks()),
    }


def map_arrays(mapper: MapSource) -> dict[str, np.ndarray]:
    """The map as voxel lists (``ijk``, float64 ``s``, ``n``, ``t_last``) with its settings:
    what merging and tiling work on; ``write_map_arrays`` writes it (as version 3)."""
    voxels = mapper.stored_voxels()
    return {
        **settings_arrays(mapper),
        "ijk": voxels.ijk.astype(np.int32, copy=False),
        "s": voxels.s.astype(np.float64, copy=False),
        "n": voxels.n.astype(np.float64, copy=False),
        "t_last": voxels.t_last.astype(np.float64, copy=False),
        **reflectivity_members(mapper.stored_reflectivity()),
    }


def as_block_arrays(arrays: Mapping[str, Any]) -> dict[str, Any]:
    """Map-file members in version 3: ``arrays`` as they are when they hold blocks
    (``map_blocks``), voxel lists (``map_arrays``) packed (``blockfile.voxels_to_packed``:
    float32 values where that loses nothing)."""
    if "block_ijk" in arrays:
        return dict(arrays)
    voxels = VoxelArrays(arrays["ijk"], arrays["s"], arrays["n"], arrays["t_last"])
    packed = voxels_to_packed(voxels, float(arrays["decay_time"]))
    settings = {k: v for k, v in arrays.items() if k not in VOXEL_MEMBERS}
    return {**settings, "version": np.int64(FORMAT_VERSION), **block_arrays(packed)}


def num_voxels(arrays: Mapping[str, Any]) -> int:
    """The voxel count of map-file arrays (blocks or voxel lists)."""
    return int(np.asarray(arrays["s"]).shape[0])


def write_map_arrays(path: str | Path, arrays: Mapping[str, Any]) -> None:
    """Write map-file ``arrays`` (``map_blocks`` or ``map_arrays`` output) to ``path`` as a
    version 3 file, atomically: members stored (no deflate), each written once from
    memory."""
    members = as_block_arrays(arrays)
    with atomic_output(path) as tmp:
        write_npz_stored(tmp, members)


def read_map_file(path: str | Path, decay_time: float | None = None) -> MapContents:
    """Read and check a map file (any version); raises ``MapFileError`` naming the file and
    the problem (never another exception: a file is data, whatever it holds).
    ``decay_time``: the decay time (s, inf: none) its voxels will decay under, when not the
    file's own (a node's ``decay_time`` overrides it): its stamps are checked against that
    one. Version 3 contents come as ``packed`` blocks, older ones as ``voxels``."""
    path = Path(path)
    problem = file_problem(path)
    if problem:
        raise MapFileError(path, problem)
    s_checked = False
    try:
        st = path.stat()
        with open(path, "rb") as f, zipfile.ZipFile(f) as archive:
            if _holds_blocks(archive):
                settings, bins, members = _open_blocks(path, f, archive, st.st_size)
                arrays, s_checked = read_all(f, members)
                settings.packed = packed_of(arrays)
                rows = {k: read_member(f, members[k]) for k in TABLE_MEMBERS if k in members}
                settings.reflectivity = _reflectivity(path, {**bins, **rows})
            else:
                headers = check_headers(path, archive, st.st_size)
                small = {k: _read(archive, k) for k in headers if k not in VOXEL_MEMBERS}
                settings = check_settings(path, small, blocks=False)
                settings.voxels = VoxelArrays(*(_read(archive, k) for k in VOXEL_MEMBERS))
                settings.reflectivity = _reflectivity(path, small)
    except MapFileError:
        raise
    except BlockFileError as err:
        raise MapFileError(path, str(err)) from None
    except MemoryError:
        raise MapFileError(path, "not enough memory to read its arrays") from None
    except _READ_ERRORS as err:
        raise MapFileError(
            path, f"unreadable or truncated map file ({type(err).__name__}: {err})"
        ) from None
    decay = settings.decay_time if decay_time is None else decay_time
    if settings.packed is not None:
        problem = packed_problem(settings.packed, s_checked)
        t = settings.packed.block_t
    else:
        v = settings.voxels
        problem = voxel_problem(v.ijk, v.s, v.n, v.t_last)
        t = v.t_last
    if not problem and t.size:
        problem = future_problem(float(t.max()), decay, st.st_mtime, "t_last")
    problem = problem or reflectivity_problem(settings.reflectivity, decay, st.st_mtime)
    if problem:
        raise MapFileError(path, problem)
    return settings


def read_map_blocks(
    path: str | Path,
    pick: Callable[[BlockReader], NDArray[np.int64]],
    decay_time: float | None = None,
) -> MapContents | None:
    """The settings and the blocks ``pick`` chooses (rows of the file's sorted blocks) of a
    version 3 file, read where they lie (a memory map: only their pages are read) and
    checked (the stamps: of every block); None for an older file (read it whole).
    MapFileError as ``read_map_file``."""
    path = Path(path)
    problem = file_problem(path)
    if problem:
        raise MapFileError(path, problem)
    try:
        st = path.stat()
        with open(path, "rb") as f, zipfile.ZipFile(f) as archive:
            if not _holds_blocks(archive):
                return None
            settings, bins, members = _open_blocks(path, f, archive, st.st_size)
        with BlockReader(path, members) as reader:
            picked = np.unique(pick(reader))
            settings.packed = reader.packed(picked)
            rows = _table_rows(reader, reader.keys[picked])
            settings.reflectivity = _reflectivity(path, {**bins, **rows})
            t_max = float(reader.view("block_t").max(initial=-math.inf))  # of every block
    except MapFileError:
        raise
    except BlockFileError as err:
        raise MapFileError(path, str(err)) from None
    except MemoryError:
        raise MapFileError(path, "not enough memory to read its arrays") from None
    except _READ_ERRORS as err:
        raise MapFileError(
            path, f"unreadable or truncated map file ({type(err).__name__}: {err})"
        ) from None
    decay = settings.decay_time if decay_time is None else decay_time
    problem = (
        packed_problem(settings.packed)
        or future_problem(t_max, decay, st.st_mtime, "t_last")
        or reflectivity_problem(settings.reflectivity, decay, st.st_mtime)
    )
    if problem:
        raise MapFileError(path, problem)
    return settings


def _holds_blocks(archive: zipfile.ZipFile) -> bool:
    return "block_ijk.npy" in archive.NameToInfo


def _open_blocks(
    path: Path, f: io.BufferedReader, archive: zipfile.ZipFile, file_size: int
) -> tuple[MapContents, dict[str, np.ndarray], dict[str, Member]]:
    """The settings, the reflectivity bins' members and the block and reflectivity-row
    members of a version 3 file, checked (no voxel or row read)."""
    headers = check_headers(path, archive, file_size, SETTINGS_MEMBERS)
    small = {k: _read(archive, k) for k in headers if k not in TABLE_MEMBERS}
    settings = check_settings(path, small, blocks=True)
    names = BLOCK_MEMBERS if int(small["version"]) >= 4 else V3_MEMBERS
    bins = {k: v for k, v in small.items() if k.startswith("reflectivity_")}
    return settings, bins, locate_members(f, archive, names, file_size)


def _table_rows(reader: BlockReader, keys: NDArray[np.int64]) -> dict[str, np.ndarray]:
    """The reflectivity rows in the blocks of ``keys`` (``packed.sort_keys``): the voxel
    indices are read whole (12 bytes a row), the counts and times only where those rows
    lie (rows are written sorted by block: few pages)."""
    present = [k for k in TABLE_MEMBERS if k in reader.members]
    if "reflectivity_ijk" not in present:
        return {k: reader.view(k) for k in present}  # incomplete: refused as such
    if not keys.size:
        return {k: reader.view(k)[:0] for k in present}
    blocks = reader.view("reflectivity_ijk").astype(np.int64) >> BLOCK_BITS
    picked = np.flatnonzero(np.isin(sort_keys(blocks), keys))
    return {k: reader.view(k)[picked] for k in present}


def _reflectivity(path: Path, small: dict[str, np.ndarray]) -> ReflectivityArrays | None:
    """The reflectivity histograms of a map file's small members (None: it has none)."""
    if not any(k.startswith("reflectivity_") for k in small):
        return None
    from mfp_mapper.core.reflectivity_arrays import from_map_arrays

    try:
        return from_map_arrays(small)
    except ValueError as err:
        raise MapFileError(path, str(err)) from None


def reflectivity_problem(
    table: ReflectivityArrays | None, decay_time: float, written_at: float
) -> str | None:
    """The histograms' indices within the map's range, their stamps not in the future."""
    if table is None or not len(table):
        return None
    if max(-int(table.ijk.min()), int(table.ijk.max())) > MAX_VOXEL_INDEX:
        return f"reflectivity_ijk holds indices beyond +-{MAX_VOXEL_INDEX}, the map's range"
    return future_problem(float(table.t_last.max()), decay_time, written_at, "reflectivity_t_last")


VOXEL_MEMBERS = ("ijk", "s", "n", "t_last")
V3_MEMBERS = tuple(k for k in BLOCK_MEMBERS if k not in HI_MEMBERS)
"""The block members of a version 3 file (values in ``s`` and ``n``, no float64 parts)."""
SETTINGS_MEMBERS = tuple(k for k in MEMBER_KINDS if k not in VOXEL_MEMBERS)
_READ_ERRORS = (
    zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, ValueError, KeyError,
    IndexError, TypeError, ArithmeticError, UnicodeError, NotImplementedError, RuntimeError,
    zlib.error, struct.error, BlockFileError, SyntaxError, tokenize.TokenError,
)  # fmt: skip
"""What a damaged archive can raise while read (RuntimeError: an encrypted member;
zlib.error: a damaged deflate stream; SyntaxError, TokenError: a damaged ``.npy`` header)."""


def _read(archive: zipfile.ZipFile, name: str) -> np.ndarray:
    with archive.open(f"{name}.npy") as member:
        return np.lib.format.read_array(member, allow_pickle=False)


def check_headers(
    path: Path,
    archive: zipfile.ZipFile,
    file_size: int,
    names: Collection[str] = tuple(MEMBER_KINDS),
) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shapes and dtypes of the known members among ``names`` (``checks.MEMBER_KINDS``;
    others are never read), checked before any array is read: against the zip's sizes,
    together against the file's real size, and against the format
    (``checks.header_problem``)."""
    headers: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
    declared = 0
    for info in archive.infolist():
        name = info.filename[: -len(".npy")]
        if not info.filename.endswith(".npy") or name not in names:
            continue
        if name in headers:
            raise MapFileError(path, f"member {info.filename} appears twice")
        if info.compress_type not in ALLOWED_COMPRESSION:
            raise MapFileError(
                path, f"{name} uses zip compression method {info.compress_type} "
                "(only stored or deflated is read)"
            )  # fmt: skip
        with archive.open(info) as member:
            version = np.lib.format.read_magic(member)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(member)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(member)
            header_bytes = member.tell()
        problem = member_problem(
            name, shape, dtype, info.file_size - header_bytes, info.compress_size,
            info.compress_type,
        )  # fmt: skip
        if problem:
            raise MapFileError(path, problem)
        headers[name] = (shape, dtype)
        declared += math.prod(shape) * dtype.itemsize
    missing = [k for k in REQUIRED_KEYS if k not in headers and k in names]
    if missing:
        raise MapFileError(path, f"not an mfp_mapper map: missing {', '.join(missing)}")
    problem = header_problem(headers) or expansion_problem(declared, file_size)
    if problem:
        raise MapFileError(path, problem)
    return headers


def check_settings(path: Path, a: dict[str, np.ndarray], blocks: bool = False) -> MapContents:
    """The settings of a map file (its small members, read before the voxels), checked
    (``blocks``: the file holds blocks, version 3); the voxels of the returned contents are
    empty."""
    if "format" in a and str(a["format"]) != FORMAT_NAME:
        raise MapFileError(path, f"format is {str(a['format'])!r}, expected {FORMAT_NAME!r}")
    version = int(a["version"]) if "version" in a else 1
    if not 1 <= version <= FORMAT_VERSION:
        raise MapFileError(path, f"file format version {version} is not in [1, {FORMAT_VERSION}]")
    if version >= 2 and "origin" not in a:
        raise MapFileError(path, f"version {version} needs origin")
    if blocks != (version >= 3):
        held = "blocks (block_ijk)" if blocks else "voxel lists (ijk)"
        raise MapFileError(path, f"file format version {version} cannot hold {held}")
    resolution, decay_time = float(a["resolution"]), float(a["decay_time"])
    ranges = optional_settings(a)
    problem = settings_problem(
        resolution, decay_time, ranges.get("max_range", math.inf), ranges.get("min_range", 0.0),
        str(a["frame_id"]),
    ) or prior_problem(ranges["prior_shape"], ranges["prior_rate"])  # fmt: skip
    origin = np.asarray(a.get("origin", np.zeros(3)), dtype=np.float64)
    problem = problem or origin_problem(origin, resolution)
    if problem:
        raise MapFileError(path, problem)
    ox, oy, oz = (float(v) for v in origin)
    return MapContents(resolution, (ox, oy, oz), decay_time, str(a["frame_id"]), ranges, None)


def read_map_arrays(
    path: str | Path, check_duplicates: bool = True, decay_time: float | None = None
) -> dict[str, np.ndarray]:
    """The voxel lists of a map file (float64, no Mapper built; version 3 blocks unpacked,
    ``map_arrays``'s layout), checked as
    ``read_map_file`` checks them (against ``decay_time`` when given), and for voxels listed
    twice (one sort of packed keys; ``check_duplicates=False`` when a Mapper is built from
    them: its store finds them and names the voxel)."""
    c = read_map_file(path, decay_time)
    voxels = c.voxels
    if c.packed is None and check_duplicates and has_duplicates(voxels.ijk):
        raise MapFileError(path, "ijk lists a voxel more than once")
    return {
        "ijk": voxels.ijk,
        "s": voxels.s,
        "n": voxels.n,
        "t_last": voxels.t_last,
        "resolution": np.float64(c.resolution),
        "origin": np.array(c.origin, dtype=np.float64),
        "decay_time": np.float64(c.decay_time),
        **{k: np.float64(v) for k, v in c.ranges.items()},
        "frame_id": np.str_(c.frame_id),
        "format": np.str_(FORMAT_NAME),
        "version": np.int64(FORMAT_VERSION),
        **reflectivity_members(c.reflectivity),
    }


def mapper_from_arrays(
    arrays: dict[str, np.ndarray], path: str | Path = "<arrays>", **overrides: object
) -> Mapper:
    """A new Mapper holding map-file ``arrays`` (as ``read_map_arrays`` or ``map_arrays``
    give them); ``path`` names them in errors; ``overrides`` replace stored settings (not
    ``resolution`` or ``origin``), as ``load_map`` does."""
    from mfp_mapper.core.mapper import Mapper
    from mfp_mapper.core.reflectivity import from_map_arrays

    resolution = float(arrays["resolution"])
    origin = np.asarray(arrays.get("origin", np.zeros(3)), dtype=np.float64).reshape(3)
    settings = mapper_settings(arrays, path, dict(overrides))
    voxels = VoxelArrays(arrays["ijk"], arrays["s"], arrays["n"], arrays["t_last"])
    try:
        table = from_map_arrays(arrays)
        return Mapper.from_arrays(
            voxels, resolution=resolution, origin=origin, reflectivity=table, **settings
        )
    except ValueError as err:
        raise MapFileError(path, str(err)) from err


def mapper_from_contents(c: MapContents, path: str | Path, **overrides: object) -> Mapper:
    """A new Mapper holding a map file's contents (``read_map_file``); ``overrides`` as
    ``mapper_from_arrays`` takes them."""
    if c.packed is None:
        voxels = {k: getattr(c.voxels, k) for k in VOXEL_MEMBERS}
        arrays = {**contents_settings(c), **voxels, **reflectivity_members(c.reflectivity)}
        return mapper_from_arrays(arrays, path, **overrides)
    from mfp_mapper.core.mapper import Mapper

    settings = mapper_settings(contents_settings(c), path, overrides)
    try:
        return Mapper.from_blocks(
            c.packed, resolution=c.resolution, origin=np.array(c.origin),
            reflectivity=c.reflectivity, checked=True, **settings,
        )  # fmt: skip
    except ValueError as err:
        raise MapFileError(path, str(err)) from err


def contents_settings(c: MapContents) -> dict[str, np.ndarray]:
    """The settings of map-file contents as map-file arrays."""
    return {
        "resolution": np.float64(c.resolution),
        "origin": np.array(c.origin, dtype=np.float64),
        "decay_time": np.float64(c.decay_time),
        **{k: np.float64(v) for k, v in c.ranges.items()},
        "frame_id": np.str_(c.frame_id),
        "format": np.str_(FORMAT_NAME),
        "version": np.int64(FORMAT_VERSION),
    }


def mapper_settings(
    arrays: Mapping[str, Any], path: str | Path, overrides: dict[str, object]
) -> dict[str, object]:
    """The Mapper keyword arguments of map-file settings with ``overrides`` (not
    ``resolution`` or ``origin``: MapFileError)."""
    resolution = float(arrays["resolution"])
    origin = np.asarray(arrays.get("origin", np.zeros(3)), dtype=np.float64).reshape(3)
    settings: dict[str, object] = {
        "decay_time": float(arrays["decay_time"]),
        "frame_id": str(arrays["frame_id"]),
        **optional_settings(arrays),
        **overrides,
    }
    for fixed, stored in (("resolution", resolution), ("origin", origin)):
        if fixed in settings and np.any(np.asarray(settings.pop(fixed)) != stored):
            raise MapFileError(path, f"stored {fixed} {stored} cannot be changed")
    return settings


def has_duplicates(ijk: NDArray[np.integer]) -> bool:
    """Whether a row of ``ijk`` appears twice: one sort of packed int64 keys when the index
    span allows (it always does for real maps), else numpy's row-wise unique (slow)."""
    if ijk.shape[0] < 2:
        return False
    rel = ijk.astype(np.int64) - ijk.min(axis=0)
    bits = [max(1, int(v).bit_length()) for v in rel.max(axis=0)]
    if sum(bits) > 63:
        return len(np.unique(ijk, axis=0)) != ijk.shape[0]
    packed = np.sort((rel[:, 0] << (bits[1] + bits[2])) | (rel[:, 1] << bits[2]) | rel[:, 2])
    return bool(np.any(packed[1:] == packed[:-1]))
