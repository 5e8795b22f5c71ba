"""Tiled maps: a map split by block ranges into map files, with a JSON index.

A tiled map is a directory (layout in docs/mapfiles.md)::

    index.json                       the contract: settings, tile edge, one entry per tile
    tiles/<tx>_<ty>_<tz>.<gen>.npz   each tile an ordinary map file (``mapfile``)

Tile ``(tx, ty, tz)`` holds the voxels of blocks ``[t * tile_blocks, (t + 1) * tile_blocks)``
on each axis (blocks of ``BLOCK_EDGE``\\ ^3 voxels). Tiles never split a block, so a tile
merges, decays and loads on its own: a reduction of many partial maps is a shuffle by tile,
and no worker holds the whole map. Tile files are written first, the index last (both
atomically), so a directory without its index, or with an older one, never lists a half
map; files of earlier versions are removed after the index is replaced. No pickles.
"""

from __future__ import annotations

import json
import math
import os
import secrets
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.core.mapper import Mapper, VoxelStats
from mfp_mapper.core.merge import check_mergeable, merge_map_arrays
from mfp_mapper.core.model import Prior
from mfp_mapper.core.packed import PackedBlocks
from mfp_mapper.core.reflectivity import (
    ARRAY_KEYS as REFLECTIVITY_KEYS,
)
from mfp_mapper.core.reflectivity import (
    ReflectivityBins,
    concatenate_tables,
    rows_within,
    select_rows,
)
from mfp_mapper.core.store import BLOCK_BITS
from mfp_mapper.core.voxel_stats import SegmentStats
from mfp_mapper.mapio.atomic import write_text_atomic
from mfp_mapper.mapio.blockfile import BLOCK_MEMBERS, concat_packed, take_blocks
from mfp_mapper.mapio.checks import (
    TILE_DIR,
    TILES_FORMAT,
    TILES_VERSION,
    future_problem,
    read_index,
)
from mfp_mapper.mapio.mapfile import (
    FORMAT_NAME,
    FORMAT_VERSION,
    MapFileError,
    contents_settings,
    mapper_from_arrays,
    mapper_settings,
    num_voxels,
    read_map_arrays,
    read_map_file,
    write_map_arrays,
)
from mfp_mapper.mapio.queries import MapFileQueries

INDEX_NAME = "index.json"
DEFAULT_TILE_BLOCKS = 32
"""Tile edge in blocks: 256 voxels, 25.6 m at 0.1 m."""
SETTINGS = (
    "resolution", "decay_time", "frame_id", "max_range", "min_range", "prior_shape", "prior_rate",
)  # fmt: skip
VOXEL_KEYS = ("ijk", "s", "n", "t_last")

TileKey = tuple[int, int, int]
MapArrays = dict[str, np.ndarray]


@dataclass(frozen=True)
class TileEntry:
    """One tile of the index: its key, file (relative to the map directory) and size."""

    key: TileKey
    file: str
    voxels: int
    t_max: float

    def to_json(self, tile_blocks: int) -> dict[str, Any]:
        lo = [k * tile_blocks for k in self.key]
        return {
            "tile": list(self.key),
            "blocks": [lo, [v + tile_blocks for v in lo]],
            "file": self.file,
            "voxels": self.voxels,
            "t_max": self.t_max,
        }


def tile_keys(ijk: NDArray[np.integer], tile_blocks: int) -> NDArray[np.int64]:
    """The tile (N, 3) of each voxel index."""
    return np.floor_divide(np.asarray(ijk, dtype=np.int64) >> BLOCK_BITS, tile_blocks)


def split_by_tile(arrays: MapArrays, tile_blocks: int) -> Iterator[tuple[TileKey, MapArrays]]:
    """The map-file arrays of each tile of a map (settings repeated in every tile): blocks
    (``map_blocks``) stay blocks, voxel lists (``map_arrays``) stay voxel lists."""
    blocks = "block_ijk" in arrays
    index = np.asarray(arrays["block_ijk"] if blocks else arrays["ijk"], dtype=np.int64)
    keys = np.floor_divide(index, tile_blocks) if blocks else tile_keys(index, tile_blocks)
    if keys.shape[0] == 0:
        return
    rel = keys - keys.min(axis=0)  # tiles span < 2^21 per axis: one int64 key per row
    packed = (rel[:, 0] << 42) | (rel[:, 1] << 21) | rel[:, 2]
    order = np.argsort(packed, kind="stable")
    starts = np.flatnonzero(np.diff(packed[order], prepend=-1))
    ends = np.append(starts[1:], order.shape[0])
    members = BLOCK_MEMBERS if blocks else VOXEL_KEYS
    settings = {k: v for k, v in arrays.items() if k not in members and k not in REFLECTIVITY_KEYS}
    table_keys = tile_keys(arrays.get("reflectivity_ijk", np.zeros((0, 3), np.int32)), tile_blocks)
    for lo, hi in zip(starts, ends, strict=True):
        pick = order[lo:hi]
        if blocks:
            tile = take_blocks(dict(arrays), np.sort(pick))
        else:
            tile = {k: np.asarray(arrays[k])[pick] for k in VOXEL_KEYS}
        x, y, z = (int(v) for v in keys[pick[0]])
        # the histograms of the tile's voxels (every one belongs to a voxel with returns)
        tile.update(select_rows(arrays, np.all(table_keys == (x, y, z), axis=1)))
        yield (x, y, z), {**settings, **tile}


def new_generation() -> str:
    """A token naming the files of one write of a tiled map."""
    return secrets.token_hex(4)


def tile_file(key: TileKey, generation: str) -> str:
    return f"{TILE_DIR}/{key[0]}_{key[1]}_{key[2]}.{generation}.npz"


def write_tile(
    directory: str | Path, key: TileKey, arrays: MapArrays, generation: str
) -> TileEntry:
    """Write one tile's map file (atomically); the index is written by ``write_index``."""
    name = tile_file(key, generation)
    write_map_arrays(Path(directory) / name, arrays)
    t = np.asarray(arrays["block_t"] if "block_t" in arrays else arrays["t_last"])
    return TileEntry(key, name, num_voxels(arrays), float(t.max()) if t.size else -math.inf)


def _json_number(value: float) -> float | None:
    return value if math.isfinite(value) else None  # null = infinite (JSON has no inf)


def write_index(
    directory: str | Path,
    settings: MapArrays,
    tile_blocks: int,
    entries: Iterable[TileEntry],
) -> None:
    """Write ``index.json`` (atomically), then remove tile files it does not list."""
    root = Path(directory)
    listed = sorted(entries, key=lambda e: e.key)
    index = {
        "format": TILES_FORMAT,
        "version": TILES_VERSION,
        "resolution": float(settings["resolution"]),
        "decay_time": _json_number(float(settings["decay_time"])),
        "frame_id": str(settings["frame_id"]),
        "max_range": _json_number(float(settings.get("max_range", math.inf))),
        "min_range": float(settings.get("min_range", 0.0)),
        "prior_shape": float(settings.get("prior_shape", 1.0)),
        "prior_rate": float(settings.get("prior_rate", 1.0)),
        "tile_blocks": tile_blocks,
        "voxels": sum(e.voxels for e in listed),
        "tiles": [e.to_json(tile_blocks) for e in listed],
    }
    if "origin" in settings:
        index["origin"] = np.asarray(settings["origin"], dtype=np.float64).ravel().tolist()
    write_text_atomic(root / INDEX_NAME, json.dumps(index, indent=1) + "\n")
    keep = {e.file for e in listed}
    for path in (root / TILE_DIR).glob("*.npz"):
        if f"{TILE_DIR}/{path.name}" not in keep:
            path.unlink(missing_ok=True)


def write_tiled(
    directory: str | Path, arrays: MapArrays, tile_blocks: int = DEFAULT_TILE_BLOCKS
) -> list[TileEntry]:
    """Write map-file ``arrays`` (blocks or voxel lists) as a tiled map in ``directory``."""
    if tile_blocks < 1:
        raise ValueError(f"tile_blocks must be >= 1, got {tile_blocks}")
    root = Path(directory)
    check_tiled_output(root)
    (root / TILE_DIR).mkdir(parents=True, exist_ok=True)
    generation = new_generation()
    entries = [write_tile(root, k, a, generation) for k, a in split_by_tile(arrays, tile_blocks)]
    write_index(root, arrays, tile_blocks, entries)
    return entries


def is_tiled(path: str | Path) -> bool:
    return (Path(path) / INDEX_NAME).is_file()


def check_tiled_output(path: str | Path) -> None:
    """MapFileError unless a tiled map may be written at ``path``: a new or empty directory,
    or a tiled map (replaced); never another non-empty directory or a file."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise MapFileError(p, "exists and is not a directory (a tiled map is a directory)")
    if p.is_dir() and any(p.iterdir()) and not is_tiled(p):
        raise MapFileError(p, f"is a non-empty directory without {INDEX_NAME}: not replaced")


class TiledMap:
    """A tiled map opened for reading: only the tiles a call needs are read."""

    def __init__(self, directory: str | Path, decay_time: float | None = None) -> None:
        """``decay_time``: the decay time (s, inf: none) the tiles' voxels will decay under
        when not the index's own: their stamps are checked against that one."""
        self.root = Path(directory)
        index_path = self.root / INDEX_NAME
        if not self.root.is_dir():
            raise MapFileError(self.root, "not a tiled map: not a directory")
        if not os.path.lexists(index_path):
            raise MapFileError(self.root, f"not a tiled map: no {INDEX_NAME}")
        try:
            index = read_index(index_path)
            written_at = index_path.stat().st_mtime
        except (OSError, ValueError) as err:  # UnicodeDecodeError is a ValueError
            raise MapFileError(index_path, f"unreadable tile index: {err}") from None
        self.tile_blocks: int = index["tile_blocks"]
        self.resolution: float = index["resolution"]
        self.decay_time: float = index["decay_time"]
        self.frame_id: str = index["frame_id"]
        self.max_range: float = index["max_range"]
        self.min_range: float = index["min_range"]
        self.prior = Prior(index["prior_shape"], index["prior_rate"])
        self.origin: list[float] | None = index["origin"]
        self.tiles = {key: TileEntry(key, *rest) for key, *rest in index["tiles"]}
        t_max = max((e.t_max for e in self.tiles.values()), default=-math.inf)
        decay = self.decay_time if decay_time is None else decay_time
        problem = future_problem(t_max, decay, written_at, "t_max")
        if problem:
            raise MapFileError(index_path, problem)

    @property
    def num_voxels(self) -> int:
        return sum(e.voxels for e in self.tiles.values())

    def settings(self) -> MapArrays:
        """The settings as map-file arrays (what every tile file repeats)."""
        out: MapArrays = {
            "resolution": np.float64(self.resolution),
            "decay_time": np.float64(self.decay_time),
            "frame_id": np.str_(self.frame_id),
            "max_range": np.float64(self.max_range),
            "min_range": np.float64(self.min_range),
            "prior_shape": np.float64(self.prior.shape),
            "prior_rate": np.float64(self.prior.rate),
            "format": np.str_(FORMAT_NAME),
            "version": np.int64(FORMAT_VERSION),
        }
        out["origin"] = np.asarray(self.origin or (0.0, 0.0, 0.0), dtype=np.float64)
        return out

    def read_tile(self, key: TileKey) -> MapArrays:
        """The map-file arrays of one tile; MapFileError when the tile is damaged or does not
        belong here (other settings, voxels outside its block range)."""
        entry = self.tiles[key]
        path = self.root / entry.file
        arrays = read_map_arrays(path)
        try:
            check_mergeable([self.settings(), arrays], [str(self.root / INDEX_NAME), str(path)])
        except ValueError as err:
            raise MapFileError(path, str(err)) from None
        inside = np.all(tile_keys(arrays["ijk"], self.tile_blocks) == key, axis=1)
        table_ijk = arrays.get("reflectivity_ijk", np.zeros((0, 3), np.int32))
        inside = np.append(inside, np.all(tile_keys(table_ijk, self.tile_blocks) == key, axis=1))
        if arrays["s"].shape[0] != entry.voxels or not inside.all():
            raise MapFileError(path, f"does not hold the {entry.voxels} voxels of tile {key}")
        t_last = arrays["t_last"]
        if t_last.size and float(t_last.max()) > entry.t_max:
            raise MapFileError(
                path, f"t_last reaches {float(t_last.max())} s, after the index's t_max "
                f"{entry.t_max} s for tile {key}"
            )  # fmt: skip
        return arrays

    def read_tile_blocks(self, key: TileKey) -> PackedBlocks | None:
        """The packed blocks of one tile (None when it is a version 1 or 2 file, or holds
        reflectivity histograms: read it with ``read_tile``), checked as ``read_tile``
        checks its voxels."""
        entry = self.tiles[key]
        path = self.root / entry.file
        contents = read_map_file(path)
        packed = contents.packed
        if packed is None or contents.reflectivity is not None:
            return None
        try:
            names = [str(self.root / INDEX_NAME), str(path)]
            check_mergeable([self.settings(), contents_settings(contents)], names)
        except ValueError as err:
            raise MapFileError(path, str(err)) from None
        inside = np.all(np.floor_divide(packed.block_ijk, self.tile_blocks) == key, axis=1)
        if packed.num_voxels != entry.voxels or not inside.all():
            raise MapFileError(path, f"does not hold the {entry.voxels} voxels of tile {key}")
        t_max = float(packed.block_t.max(initial=-math.inf))
        if t_max > entry.t_max:
            raise MapFileError(
                path, f"t_last reaches {t_max} s, after the index's t_max {entry.t_max} s "
                f"for tile {key}"
            )  # fmt: skip
        return packed

    def keys_in(self, bounds: tuple[ArrayLike, ArrayLike] | None = None) -> list[TileKey]:
        """Tiles that may hold voxel centres inside ``bounds`` (metres; None: all)."""
        keys = sorted(self.tiles)
        if bounds is None:
            return keys
        lo_i, hi_i = index_bounds(bounds, self.resolution, self.origin)
        edge = self.tile_blocks << BLOCK_BITS
        lo_t = np.floor_divide(lo_i, edge)
        hi_t = np.floor_divide(hi_i, edge)
        return [k for k in keys if np.all(lo_t <= k) and np.all(np.asarray(k) <= hi_t)]

    def load(
        self, bounds: tuple[ArrayLike, ArrayLike] | None = None, **overrides: object
    ) -> Mapper:
        """A Mapper with the voxels whose centres lie in ``bounds`` (metres, inclusive;
        None: the whole map), read from the tiles that reach into them (the whole map of
        block tiles, version 3 or 4: block by block, as a map file loads)."""
        if bounds is None:
            blocks = [self.read_tile_blocks(k) for k in self.keys_in()]
            if all(b is not None for b in blocks):
                settings = mapper_settings(self.settings(), self.root, dict(overrides))
                try:
                    # each tile was checked whole (read_tile_blocks) and holds blocks
                    # of its own tile only: together they are distinct, and the store
                    # takes them in tile order (sorting them moved every value: 0.27 of
                    # the 0.4 s CPU of a norlab load, docs/performance.md)
                    return Mapper.from_blocks(
                        concat_packed([b for b in blocks if b is not None], sort=False),
                        resolution=self.resolution,
                        origin=np.asarray(self.origin or (0.0, 0.0, 0.0)),
                        reflectivity=None,
                        checked=True,
                        **settings,
                    )
                except ValueError as err:
                    raise MapFileError(self.root, str(err)) from err
        parts = [self.read_tile(k) for k in self.keys_in(bounds)]
        arrays = concatenate(parts, self.settings())
        if bounds is not None:
            lo_i, hi_i = index_bounds(bounds, self.resolution, self.origin)
            keep = np.all((arrays["ijk"] >= lo_i) & (arrays["ijk"] <= hi_i), axis=1)
            arrays = {**arrays, **{k: arrays[k][keep] for k in VOXEL_KEYS}}
            arrays.update(select_rows(arrays, rows_within(arrays, lo_i, hi_i)))
        return mapper_from_arrays(arrays, self.root, **overrides)

    def tile_queries(self, key: TileKey) -> MapFileQueries:
        """One tile opened for queries (reading the blocks they need), its settings checked
        against the index."""
        entry = self.tiles[key]
        path = self.root / entry.file
        q = MapFileQueries(path, self.decay_time)
        try:
            names = [str(self.root / INDEX_NAME), str(path)]
            check_mergeable([self.settings(), q.settings()], names)
        except ValueError as err:
            raise MapFileError(path, str(err)) from None
        inside = np.all(np.floor_divide(q.block_ijk, self.tile_blocks) == key, axis=1)
        if q.num_voxels != entry.voxels or not inside.all():
            raise MapFileError(path, f"does not hold the {entry.voxels} voxels of tile {key}")
        if q.t_max > entry.t_max:
            raise MapFileError(
                path, f"t_last reaches {q.t_max} s, after the index's t_max "
                f"{entry.t_max} s for tile {key}"
            )  # fmt: skip
        return q

    def tile_mapper(self, key: TileKey) -> Mapper:
        """One tile as a Mapper of its own."""
        return mapper_from_arrays(self.read_tile(key), self.root / self.tiles[key].file)

    def iter_tiles(
        self, bounds: tuple[ArrayLike, ArrayLike] | None = None
    ) -> Iterator[tuple[TileKey, Mapper]]:
        """Each tile reaching into ``bounds`` as a Mapper, one at a time."""
        for key in self.keys_in(bounds):
            yield key, self.tile_mapper(key)

    def query(self, points: ArrayLike, stamp: float | None = None) -> VoxelStats:
        """``Mapper.query`` over the tiles: of each tile holding a point, the blocks holding
        points are read."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = self._empty_mapper().query(
            pts, stamp
        )  # the answer for unobserved voxels, and every ijk
        keys = tile_keys(out.ijk, self.tile_blocks)
        for key in {(int(a), int(b), int(c)) for a, b, c in keys}:
            if key in self.tiles:
                rows = np.flatnonzero(np.all(keys == key, axis=1))
                part = self.tile_queries(key).query(pts[rows], stamp)
                for name in ("s", "n", "t_last", "observed"):
                    getattr(out, name)[rows] = getattr(part, name)
        return out

    def reflectivity(
        self, points: ArrayLike, stamp: float | None = None
    ) -> tuple[ReflectivityBins, NDArray[np.float64]] | None:
        """``Mapper.reflectivity`` over the tiles: of each tile holding a point, the blocks
        holding them (``MapFileQueries``); None when no tile read holds histograms."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        keys = tile_keys(self._empty_mapper().query(pts).ijk, self.tile_blocks)
        bins, counts = None, None
        for key in {(int(a), int(b), int(c)) for a, b, c in keys}:
            if key not in self.tiles:
                continue
            part = self.tile_queries(key).reflectivity(pts[np.all(keys == key, axis=1)], stamp)
            if part is None:
                continue
            if counts is None:
                bins, counts = part[0], np.zeros((len(pts), part[0].count))
            if part[0] == bins:
                counts[np.all(keys == key, axis=1)] = part[1]
        return None if bins is None or counts is None else (bins, counts)

    def _empty_mapper(self) -> Mapper:
        """A Mapper with this map's settings and no voxel."""
        return Mapper(
            self.resolution,
            decay_time=self.decay_time,
            frame_id=self.frame_id,
            origin=self.origin or (0.0, 0.0, 0.0),
            prior_shape=self.prior.shape,
            prior_rate=self.prior.rate,
        )

    def query_segments(
        self, starts: ArrayLike, ends: ArrayLike, stamp: float | None = None
    ) -> SegmentStats:
        """``Mapper.query_segments`` over the tiles: reads the tiles that reach into the
        segments' bounding box (padded by a voxel)."""
        a = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
        b = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
        if a.shape != b.shape or not len(a) or not (np.isfinite(a).all() and np.isfinite(b).all()):
            # nothing to read: the core answers (or refuses) as for an empty map
            return self._empty_mapper().query_segments(a, b, stamp)
        pad = self.resolution
        lo = np.minimum(a.min(axis=0), b.min(axis=0)) - pad
        hi = np.maximum(a.max(axis=0), b.max(axis=0)) + pad
        return self.load(bounds=(lo, hi)).query_segments(a, b, stamp)


def index_bounds(
    bounds: tuple[ArrayLike, ArrayLike], resolution: float, origin: ArrayLike | None = None
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The voxel index range whose centres lie in ``bounds`` (metres, +-inf allowed), as
    ``Mapper.voxels(bounds=...)`` reads it; indices relative to ``origin`` (the map file's
    corner of voxel 0, where the format stores one)."""
    big = float(2**40)
    corner = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).ravel()
    with np.errstate(invalid="ignore", over="ignore"):
        lo_m, hi_m = ((np.asarray(b, dtype=np.float64) - corner) / resolution - 0.5 for b in bounds)
        lo = np.ceil(np.clip(lo_m, -big, big))
        hi = np.floor(np.clip(hi_m, -big, big))
    return lo.astype(np.int64), hi.astype(np.int64)


def concatenate(parts: Sequence[MapArrays], settings: MapArrays) -> MapArrays:
    """Disjoint map-file arrays (e.g. tiles) as one: no voxel may appear twice (their
    reflectivity histograms too; MapFileError when their bins differ)."""
    voxels: MapArrays = {
        "ijk": np.zeros((0, 3), np.int32),
        "s": np.zeros(0),
        "n": np.zeros(0),
        "t_last": np.zeros(0),
    }
    if parts:
        voxels = {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in VOXEL_KEYS}
    try:
        table = concatenate_tables(parts)
    except ValueError as err:
        raise MapFileError("<tiles>", str(err)) from None
    return {**settings, **voxels, **table}


def write_map_file(tiled: TiledMap, path: str | Path) -> int:
    """Write a tiled map as one map file (atomically); returns the voxel count."""
    tiles = [tiled.read_tile(k) for k in sorted(tiled.tiles)]
    arrays = concatenate(tiles, tiled.settings())
    write_map_arrays(path, arrays)
    return int(arrays["s"].shape[0])


def merge_tile(tiled: Sequence[TiledMap], key: TileKey) -> MapArrays:
    """The exact merge of tile ``key`` of several tiled maps (those that have it)."""
    have = [t for t in tiled if key in t.tiles]
    return merge_map_arrays(
        [t.read_tile(key) for t in have], [str(t.root / t.tiles[key].file) for t in have]
    )


def write_map_path(path: str | Path, arrays: MapArrays) -> int:
    """Write map-file ``arrays`` (blocks or voxel lists) where ``path`` says: a tiled map
    when ``path`` is a directory (or ends with a slash; an existing tiled map keeps its tile
    edge), else one map file; both atomically. Returns the number of voxels written."""
    if str(path).endswith(("/", "\\")) or Path(path).is_dir():
        tile_blocks = TiledMap(path).tile_blocks if is_tiled(path) else DEFAULT_TILE_BLOCKS
        write_tiled(path, arrays, tile_blocks)
    else:
        write_map_arrays(path, arrays)
    return num_voxels(arrays)
