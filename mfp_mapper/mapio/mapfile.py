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

plus ``max_range`` and ``min_range`` (float64, metres). The centre of voxel ``ijk`` is
``origin + (ijk + 0.5) * resolution`` (map frame, metres). Every voxel is listed once, in no
particular order. Files are written atomically (``mapio.atomic``).

Reading checks the archive before allocating: the arrays' shapes and dtypes from their
``.npy`` headers, sizes against the archive's own sizes; then the values: resolution in
[``MIN_RESOLUTION``, ``MAX_RESOLUTION``], indices within the store's range, no voxel twice
(checked while the voxels are stored, in compiled code).
"""

from __future__ import annotations

import math
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.errors import CoreError
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.store import (
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    VoxelArrays,
    voxel_problem,
)
from mfp_mapper.mapio.atomic import atomic_output

FORMAT_NAME = "mfp_mapper.map"
FORMAT_VERSION = 2
REQUIRED_KEYS = ("ijk", "s", "n", "t_last", "resolution", "decay_time", "frame_id")
_MAX_DEFLATE_RATIO = 1100  # deflate cannot expand data more than ~1032 times
_SCALARS = {"resolution": "f", "decay_time": "f", "max_range": "f", "min_range": "f"}


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
    def origin(self) -> tuple[float, float, float] | None: ...

    def stored_voxels(self) -> VoxelArrays: ...


@dataclass
class MapContents:
    """A map file's contents, checked: settings and voxels."""

    resolution: float
    origin: tuple[float, float, float]
    decay_time: float
    frame_id: str
    ranges: dict[str, float]
    """``max_range`` and ``min_range`` where the file has them."""
    voxels: VoxelArrays


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
        "frame_id": np.str_(mapper.frame_id),
        "format": np.str_(FORMAT_NAME),
        "version": np.int64(FORMAT_VERSION),
    }


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


def read_map_file(path: str | Path) -> MapContents:
    """Read and check a map file; raises ``MapFileError`` naming the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise MapFileError(path, "no such file")
    try:
        with zipfile.ZipFile(path) as archive:
            headers = _check_headers(path, archive)
            arrays = {}
            for name in headers:
                with archive.open(f"{name}.npy") as member:
                    arrays[name] = np.lib.format.read_array(member, allow_pickle=False)
    except MapFileError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as err:
        raise MapFileError(
            path, f"unreadable or truncated map file ({type(err).__name__}: {err})"
        ) from err
    return _contents(path, arrays)


def _check_headers(
    path: Path, archive: zipfile.ZipFile
) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shapes and dtypes of the members, checked before any array is read."""
    headers: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
    for info in archive.infolist():
        if not info.filename.endswith(".npy"):
            continue
        with archive.open(info) as member:
            version = np.lib.format.read_magic(member)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(member)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(member)
        name = info.filename[: -len(".npy")]
        if dtype.hasobject:
            raise MapFileError(path, f"unreadable or truncated map file ({name} holds objects)")
        nbytes = math.prod(shape) * dtype.itemsize
        limit = min(info.file_size, _MAX_DEFLATE_RATIO * info.compress_size + (1 << 20))
        if nbytes > limit:
            raise MapFileError(
                path, f"{name} claims {nbytes} bytes ({shape} {dtype}) but holds at most {limit}"
            )
        headers[name] = (shape, dtype)
    missing = [k for k in REQUIRED_KEYS if k not in headers]
    if missing:
        raise MapFileError(path, f"not an mfp_mapper map: missing {', '.join(missing)}")
    shape, dtype = headers["ijk"]
    if len(shape) != 2 or shape[1] != 3 or dtype.kind not in "iu":
        raise MapFileError(path, f"ijk must be an integer (N, 3) array, got {dtype} {shape}")
    for key in ("s", "n", "t_last"):
        if headers[key] != ((shape[0],), headers[key][1]) or headers[key][1].kind != "f":
            raise MapFileError(
                path,
                f"{key} must be a float array of length {shape[0]}, got "
                f"{headers[key][1]} {headers[key][0]}",
            )
    for key in ("resolution", "decay_time"):
        if headers[key][0] != () or headers[key][1].kind not in "iuf":
            raise MapFileError(path, f"{key} must be a number")
    if headers["frame_id"][0] != () or headers["frame_id"][1].kind != "U":
        raise MapFileError(path, "frame_id must be a string")
    if "origin" in headers and (headers["origin"][0] != (3,) or headers["origin"][1].kind != "f"):
        raise MapFileError(path, "origin must be a float array of 3 metres")
    return headers


def _contents(path: Path, a: dict[str, np.ndarray]) -> MapContents:
    if "format" in a and str(a["format"]) != FORMAT_NAME:
        raise MapFileError(path, f"format is {str(a['format'])!r}, expected {FORMAT_NAME!r}")
    version = int(a["version"]) if "version" in a else 1
    if version > FORMAT_VERSION:
        raise MapFileError(path, f"file format version {version} is newer than {FORMAT_VERSION}")
    if version >= 2 and "origin" not in a:
        raise MapFileError(path, f"version {version} needs origin")
    resolution = float(a["resolution"])
    if not MIN_RESOLUTION <= resolution <= MAX_RESOLUTION:
        raise MapFileError(
            path,
            f"resolution must be positive, within [{MIN_RESOLUTION}, {MAX_RESOLUTION}] m, "
            f"got {resolution}",
        )
    origin = a.get("origin", np.zeros(3))
    if not np.isfinite(origin).all():
        raise MapFileError(path, f"origin must be finite metres, got {origin.tolist()}")
    problem = voxel_problem(a["ijk"], a["s"], a["n"], a["t_last"])
    if problem:
        raise MapFileError(path, problem)
    ranges: dict[str, float] = {k: float(a[k]) for k in ("max_range", "min_range") if k in a}
    voxels = VoxelArrays(a["ijk"], a["s"], a["n"], a["t_last"])
    ox, oy, oz = (float(v) for v in origin)
    return MapContents(
        resolution, (ox, oy, oz), float(a["decay_time"]), str(a["frame_id"]), ranges, voxels
    )


def read_map_arrays(path: str | Path, check_duplicates: bool = True) -> dict[str, np.ndarray]:
    """The arrays of a map file as stored (float64 sums kept, no Mapper built), checked as
    ``read_map_file`` checks them, and for voxels listed twice (one sort of packed keys;
    ``check_duplicates=False`` when a Mapper is built from them: its store finds them and
    names the voxel)."""
    c = read_map_file(path)
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
        **{k: float(arrays[k]) for k in ("max_range", "min_range") if k in arrays},
        **overrides,
    }
    for fixed, stored in (("resolution", resolution), ("origin", origin)):
        if fixed in settings and np.any(np.asarray(settings.pop(fixed)) != stored):
            raise MapFileError(path, f"stored {fixed} {stored} cannot be changed")
    voxels = VoxelArrays(arrays["ijk"], arrays["s"], arrays["n"], arrays["t_last"])
    try:
        return Mapper.from_arrays(voxels, resolution=resolution, origin=origin, **settings)
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
