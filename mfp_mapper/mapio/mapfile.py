"""The map file: a contract other programs read.

An ``.npz`` archive (never pickles) holding

=============  ==============  ===================================================
``ijk``        int32 (N, 3)    voxel index relative to ``origin``:
                               floor((coordinate - origin) / resolution), map frame
``s``          float64 (N,)    metres travelled by rays inside the voxel
``n``          float64 (N,)    first returns inside the voxel (real after decay)
``t_last``     float64 (N,)    time (s) the statistics refer to (last update)
``resolution`` float64 ()      voxel edge, metres
``origin``     float64 (3,)    map-frame position of the corner of voxel (0, 0, 0),
                               metres (version 2; absent in version 1: zero)
``decay_time`` float64 ()      time constant, seconds (inf = static map)
``frame_id``   str ()          the map frame
``format``     str ()          ``"mfp_mapper.map"``
``version``    int64 ()        file format version (2)
=============  ==============  ===================================================

and, for a map with a reflectivity field (docs/model.md), its histograms: ``reflectivity_ijk``
int32 (K, 3), ``reflectivity_counts`` float64 (K, J), ``reflectivity_t_last`` float64 (K,),
``reflectivity_edges`` float64 (J - 1,) and ``reflectivity_field`` str (``core.reflectivity``);
plus ``max_range`` and ``min_range`` (float64, metres) and ``prior_shape``, ``prior_rate``
(float64: the Gamma prior on the extinction the estimates use, docs/model.md; a file
without them was written with the uniform prior, 1 and 1). The centre of voxel ``ijk`` is
``origin + (ijk + 0.5) * resolution`` (map frame, metres). Every voxel is listed once, in no
particular order. Files are written atomically (``mapio.atomic``).

Reading checks the file before allocating (``mapio.checks``): a regular file; the arrays'
shapes and dtypes from their ``.npy`` headers, sizes against the archive's own sizes and
together against the file's real size; then the settings (resolution in
[``MIN_RESOLUTION``, ``MAX_RESOLUTION``], decay time, ranges, frame, origin), and only then
the voxels: finite, indices within the store's range, stamps not in the future of the file
under decay, no voxel twice (checked while the voxels are stored, in compiled code). Any
problem is a ``MapFileError`` naming the file.
"""

from __future__ import annotations

import math
import struct
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.errors import CoreError
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.reflectivity import (
    ReflectivityArrays,
    from_map_arrays,
    to_map_arrays,
)
from mfp_mapper.core.store import MAX_VOXEL_INDEX, VoxelArrays, voxel_problem
from mfp_mapper.mapio.atomic import atomic_output
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

FORMAT_NAME = "mfp_mapper.map"
FORMAT_VERSION = 2
REQUIRED_KEYS = ("ijk", "s", "n", "t_last", "resolution", "decay_time", "frame_id")

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
    voxels: VoxelArrays
    reflectivity: ReflectivityArrays | None = None
    """The reflectivity histograms (``reflectivity_*`` members), when the file has them."""


def write_map(path: str | Path, mapper: MapSource) -> None:
    """Write ``mapper`` to ``path`` (.npz) atomically."""
    write_map_arrays(path, map_arrays(mapper))


def map_arrays(mapper: MapSource) -> dict[str, np.ndarray]:
    """The arrays of the map file: a snapshot, independent of the mapper afterwards (so a
    caller can take it under a lock and compress and write it outside)."""
    voxels = mapper.stored_voxels()
    origin = mapper.origin if mapper.origin is not None else (0.0, 0.0, 0.0)
    return {
        "ijk": voxels.ijk.astype(np.int32, copy=False),
        "s": voxels.s.astype(np.float64, copy=False),
        "n": voxels.n.astype(np.float64, copy=False),
        "t_last": voxels.t_last.astype(np.float64, copy=False),
        "resolution": np.float64(mapper.resolution),
        "origin": np.array(origin, dtype=np.float64),
        "decay_time": np.float64(mapper.decay_time),
        "max_range": np.float64(mapper.max_range),
        "min_range": np.float64(mapper.min_range),
        "prior_shape": np.float64(mapper.prior_shape),
        "prior_rate": np.float64(mapper.prior_rate),
        "frame_id": np.str_(mapper.frame_id),
        "format": np.str_(FORMAT_NAME),
        "version": np.int64(FORMAT_VERSION),
        **reflectivity_members(mapper.stored_reflectivity()),
    }


def reflectivity_members(table: ReflectivityArrays | None) -> dict[str, np.ndarray]:
    """The ``reflectivity_*`` members of a map file holding ``table`` ({} for None)."""
    return {} if table is None else to_map_arrays(table)


def write_map_arrays(path: str | Path, arrays: dict[str, Any], compress: bool = True) -> None:
    """Write ``map_arrays`` output to ``path`` (.npz) atomically.

    Deflated at level 1 (what ``np.load`` reads like any ``.npz``): 5x faster than
    ``np.savez_compressed``'s level 6, for a file about 6% larger. ``compress=False``
    stores the arrays as they are (scratch files that are read back soon).
    """
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with (
        atomic_output(path) as tmp,
        zipfile.ZipFile(
            tmp, "w", compression=method, compresslevel=1 if compress else None, allowZip64=True
        ) as archive,
    ):
        for name, value in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)


def read_map_file(path: str | Path, decay_time: float | None = None) -> MapContents:
    """Read and check a map file; raises ``MapFileError`` naming the file and the problem
    (never another exception: a file is data, whatever it holds). ``decay_time``: the decay
    time (s, inf: none) its voxels will decay under, when not the file's own (a node's
    ``decay_time`` overrides it): its stamps are checked against that one."""
    path = Path(path)
    problem = file_problem(path)
    if problem:
        raise MapFileError(path, problem)
    try:
        st = path.stat()
        with zipfile.ZipFile(path) as archive:
            headers = check_headers(path, archive, st.st_size)
            small = {k: _read(archive, k) for k in headers if k not in VOXEL_MEMBERS}
            settings = check_settings(path, small)
            voxels = VoxelArrays(*(_read(archive, k) for k in VOXEL_MEMBERS))
            try:
                settings.reflectivity = from_map_arrays(small)
            except ValueError as err:
                raise MapFileError(path, str(err)) from None
    except MapFileError:
        raise
    except MemoryError:
        raise MapFileError(path, "not enough memory to read its arrays") from None
    except _READ_ERRORS as err:
        raise MapFileError(
            path, f"unreadable or truncated map file ({type(err).__name__}: {err})"
        ) from None
    problem = voxel_problem(voxels.ijk, voxels.s, voxels.n, voxels.t_last)
    decay = settings.decay_time if decay_time is None else decay_time
    if not problem and voxels.t_last.size:
        t_max = float(voxels.t_last.max())
        problem = future_problem(t_max, decay, st.st_mtime, "t_last")
    table = settings.reflectivity
    if not problem and table is not None and len(table):
        if max(-int(table.ijk.min()), int(table.ijk.max())) > MAX_VOXEL_INDEX:
            problem = f"reflectivity_ijk holds indices beyond +-{MAX_VOXEL_INDEX}, the map's range"
        else:
            t_max = float(table.t_last.max())
            problem = future_problem(t_max, decay, st.st_mtime, "reflectivity_t_last")
    if problem:
        raise MapFileError(path, problem)
    settings.voxels = voxels
    return settings


VOXEL_MEMBERS = ("ijk", "s", "n", "t_last")
_READ_ERRORS = (
    zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, ValueError, KeyError,
    IndexError, TypeError, ArithmeticError, UnicodeError, NotImplementedError, RuntimeError,
    zlib.error, struct.error,
)  # fmt: skip
"""What a damaged archive can raise while read (RuntimeError: an encrypted member;
zlib.error: a damaged deflate stream)."""


def _read(archive: zipfile.ZipFile, name: str) -> np.ndarray:
    with archive.open(f"{name}.npy") as member:
        return np.lib.format.read_array(member, allow_pickle=False)


def check_headers(
    path: Path, archive: zipfile.ZipFile, file_size: int
) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shapes and dtypes of the known members (``checks.MEMBER_KINDS``; others are never
    read), checked before any array is read: against the zip's sizes, together against the
    file's real size, and against the format (``checks.header_problem``)."""
    headers: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
    declared = 0
    for info in archive.infolist():
        name = info.filename[: -len(".npy")]
        if not info.filename.endswith(".npy") or name not in MEMBER_KINDS:
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
    missing = [k for k in REQUIRED_KEYS if k not in headers]
    if missing:
        raise MapFileError(path, f"not an mfp_mapper map: missing {', '.join(missing)}")
    problem = header_problem(headers) or expansion_problem(declared, file_size)
    if problem:
        raise MapFileError(path, problem)
    return headers


def check_settings(path: Path, a: dict[str, np.ndarray]) -> MapContents:
    """The settings of a map file (its small members, read before the voxels), checked;
    the voxels of the returned contents are empty."""
    if "format" in a and str(a["format"]) != FORMAT_NAME:
        raise MapFileError(path, f"format is {str(a['format'])!r}, expected {FORMAT_NAME!r}")
    version = int(a["version"]) if "version" in a else 1
    if not 1 <= version <= FORMAT_VERSION:
        raise MapFileError(path, f"file format version {version} is not in [1, {FORMAT_VERSION}]")
    if version >= 2 and "origin" not in a:
        raise MapFileError(path, f"version {version} needs origin")
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
    empty = VoxelArrays(np.zeros((0, 3), np.int32), np.zeros(0), np.zeros(0), np.zeros(0))
    return MapContents(resolution, (ox, oy, oz), decay_time, str(a["frame_id"]), ranges, empty)


def read_map_arrays(
    path: str | Path, check_duplicates: bool = True, decay_time: float | None = None
) -> dict[str, np.ndarray]:
    """The arrays of a map file as stored (float64 sums kept, no Mapper built), checked as
    ``read_map_file`` checks them (against ``decay_time`` when given), and for voxels listed
    twice (one sort of packed keys; ``check_duplicates=False`` when a Mapper is built from
    them: its store finds them and names the voxel)."""
    c = read_map_file(path, decay_time)
    if check_duplicates and has_duplicates(c.voxels.ijk):
        raise MapFileError(path, "ijk lists a voxel more than once")
    return {
        "ijk": c.voxels.ijk,
        "s": c.voxels.s,
        "n": c.voxels.n,
        "t_last": c.voxels.t_last,
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
    voxels = VoxelArrays(arrays["ijk"], arrays["s"], arrays["n"], arrays["t_last"])
    try:
        table = from_map_arrays(arrays)
        return Mapper.from_arrays(
            voxels, resolution=resolution, origin=origin, reflectivity=table, **settings
        )
    except ValueError as err:
        raise MapFileError(path, str(err)) from err


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
