"""The map file: a contract other programs read.

An ``.npz`` archive (never pickles) holding

=============  ==============  ===================================================
``ijk``        int32 (N, 3)    voxel index = floor(coordinate / resolution), map frame
``s``          float64 (N,)    metres travelled by rays inside the voxel
``n``          float64 (N,)    first returns inside the voxel (real after decay)
``t_last``     float64 (N,)    time (s) the statistics refer to (last update)
``resolution`` float64 ()      voxel edge, metres
``decay_time`` float64 ()      time constant, seconds (inf = static map)
``frame_id``   str ()          the map frame
``format``     str ()          ``"mfp_mapper.map"``
``version``    int64 ()        file format version (1)
=============  ==============  ===================================================

plus ``max_range`` and ``min_range`` (float64, metres). Files are written to a temporary
file in the same folder, flushed, and renamed over the target, so a reader never sees a
half-written map.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mfp_mapper.core.atomic import atomic_output
from mfp_mapper.core.store import VoxelArrays

if TYPE_CHECKING:
    from mfp_mapper.core.mapper import Mapper

FORMAT_NAME = "mfp_mapper.map"
FORMAT_VERSION = 1
REQUIRED_KEYS = ("ijk", "s", "n", "t_last", "resolution", "decay_time", "frame_id")


class MapFileError(ValueError):
    """A map file that cannot be read: names the file and what is wrong with it."""

    def __init__(self, path: str | Path, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem


def write_map(path: str | Path, mapper: Mapper) -> None:
    """Write ``mapper`` to ``path`` (.npz) atomically."""
    write_map_arrays(path, map_arrays(mapper))


def map_arrays(mapper: Mapper) -> dict[str, np.ndarray]:
    """The arrays of the map file: a snapshot, independent of the mapper afterwards (so a
    caller can take it under a lock and compress and write it outside)."""
    voxels = mapper.voxels()
    return {
        "ijk": voxels.ijk.astype(np.int32, copy=False),
        "s": voxels.s.astype(np.float64, copy=False),
        "n": voxels.n.astype(np.float64, copy=False),
        "t_last": voxels.t_last.astype(np.float64, copy=False),
        "resolution": np.float64(mapper.resolution),
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


def read_map(path: str | Path, **overrides: object) -> Mapper:
    """Read a map file into a new Mapper; ``overrides`` replace stored constructor settings."""
    return mapper_from_arrays(_read_arrays(Path(path)), path, **overrides)


def read_map_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """The checked arrays of a map file, as stored (float64 sums kept, no Mapper built)."""
    return _read_arrays(Path(path))


def mapper_from_arrays(
    arrays: dict[str, np.ndarray], path: str | Path = "<arrays>", **overrides: object
) -> Mapper:
    """A new Mapper holding map-file ``arrays`` (as ``read_map_arrays`` or ``map_arrays``
    give them; not checked again); ``path`` names them in errors; ``overrides`` replace
    stored constructor settings."""
    from mfp_mapper.core.mapper import Mapper

    settings: dict[str, object] = {
        "resolution": float(arrays["resolution"]),
        "decay_time": float(arrays["decay_time"]),
        "frame_id": str(arrays["frame_id"]),
    }
    for key in ("max_range", "min_range"):
        if key in arrays:
            settings[key] = float(arrays[key])
    settings.update(overrides)
    if settings["resolution"] != float(arrays["resolution"]):
        raise MapFileError(
            path, f"stored resolution {float(arrays['resolution'])} cannot be changed"
        )
    try:
        mapper = Mapper(**settings)  # type: ignore[arg-type]
    except ValueError as err:
        raise MapFileError(path, f"invalid settings: {err}") from err
    mapper._assign(VoxelArrays(arrays["ijk"], arrays["s"], arrays["n"], arrays["t_last"]))
    return mapper


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise MapFileError(path, "no such file")
    try:
        with np.load(path, allow_pickle=False) as archive:
            missing = [k for k in REQUIRED_KEYS if k not in archive.files]
            if missing:
                raise MapFileError(path, f"not an mfp_mapper map: missing {', '.join(missing)}")
            arrays = {k: archive[k] for k in archive.files}
    except MapFileError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as err:
        raise MapFileError(
            path, f"unreadable or truncated map file ({type(err).__name__}: {err})"
        ) from err
    _validate(path, arrays)
    return arrays


def _validate(path: Path, a: dict[str, np.ndarray]) -> None:
    if "format" in a and str(a["format"]) != FORMAT_NAME:
        raise MapFileError(path, f"format is {str(a['format'])!r}, expected {FORMAT_NAME!r}")
    if "version" in a and int(a["version"]) > FORMAT_VERSION:
        raise MapFileError(
            path, f"file format version {int(a['version'])} is newer than {FORMAT_VERSION}"
        )
    ijk = a["ijk"]
    if ijk.ndim != 2 or ijk.shape[1] != 3 or not np.issubdtype(ijk.dtype, np.integer):
        raise MapFileError(
            path, f"ijk must be an integer (N, 3) array, got {ijk.dtype} {ijk.shape}"
        )
    count = ijk.shape[0]
    for key in ("s", "n", "t_last"):
        arr = a[key]
        if arr.shape != (count,) or not np.issubdtype(arr.dtype, np.floating):
            raise MapFileError(
                path, f"{key} must be a float array of length {count}, got {arr.dtype} {arr.shape}"
            )
    for key in ("s", "n"):
        if not (np.isfinite(a[key]).all() and (a[key] >= 0).all()):
            raise MapFileError(path, f"{key} holds negative, NaN or infinite values")
    if not np.isfinite(a["t_last"]).all():
        raise MapFileError(path, "t_last holds NaN or infinite values (seconds expected)")
    for key in ("resolution", "decay_time"):
        if a[key].shape != () or not np.issubdtype(a[key].dtype, np.number):
            raise MapFileError(path, f"{key} must be a number")
    if not (np.isfinite(a["resolution"]) and a["resolution"] > 0):
        raise MapFileError(path, f"resolution must be positive, got {a['resolution']}")
    if a["frame_id"].shape != () or a["frame_id"].dtype.kind != "U":
        raise MapFileError(path, "frame_id must be a string")
    if count and _has_duplicates(ijk):
        raise MapFileError(path, "ijk lists a voxel more than once")


def _has_duplicates(ijk: np.ndarray) -> bool:
    """Whether a row of ``ijk`` appears twice: one sort of packed int64 keys when the index
    span allows (it always does for real maps), else numpy's row-wise unique (slow)."""
    rel = ijk.astype(np.int64) - ijk.min(axis=0)
    bits = [max(1, int(v).bit_length()) for v in rel.max(axis=0)]
    if sum(bits) > 63:
        return len(np.unique(ijk, axis=0)) != ijk.shape[0]
    packed = np.sort((rel[:, 0] << (bits[1] + bits[2])) | (rel[:, 1] << bits[2]) | rel[:, 2])
    return bool(np.any(packed[1:] == packed[:-1]))
