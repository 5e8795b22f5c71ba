"""``mfp-mapper merge``: the exact merge of map files and tiled maps into one.

Inputs are ``.npz`` map files or tiled map directories; the output is a map file when its
name ends in ``.npz``, else a tiled map. The merge goes tile by tile (map files are split
into tiles in a scratch folder first), so a tiled output never needs the whole map in
memory; a ``.npz`` output is assembled from the merged tiles at the end. Maps of other
resolutions, frames, decay times or origins are refused (``core.merge.MergeError``).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from mfp_mapper.core.merge import check_mergeable
from mfp_mapper.mapio.loading import is_map_file_name
from mfp_mapper.mapio.mapfile import read_map_arrays
from mfp_mapper.mapio.tiles import (
    DEFAULT_TILE_BLOCKS,
    TILE_DIR,
    TiledMap,
    check_tiled_output,
    concatenate,
    merge_tile,
    new_generation,
    write_index,
    write_map_file,
    write_tile,
    write_tiled,
)


@dataclass
class MergeResult:
    output: Path
    inputs: int
    voxels: int
    tiles: int


def as_tiled(path: Path, scratch: Path, tile_blocks: int) -> TiledMap:
    """``path`` as a tiled map of ``tile_blocks``: itself, or a copy split in ``scratch``."""
    if path.is_dir():
        tiled = TiledMap(path)
        if tiled.tile_blocks == tile_blocks:
            return tiled
        arrays = concatenate([tiled.read_tile(k) for k in sorted(tiled.tiles)], tiled.settings())
    else:
        arrays = read_map_arrays(path)
    target = Path(tempfile.mkdtemp(prefix="input-", dir=scratch))
    write_tiled(target, arrays, tile_blocks)
    return TiledMap(target)


def merge_maps(
    inputs: Sequence[str | Path], output: str | Path, tile_blocks: int = DEFAULT_TILE_BLOCKS
) -> MergeResult:
    """Merge ``inputs`` exactly into ``output``; MapFileError/MergeError name the input at
    fault, and nothing is written then."""
    out = Path(output)
    if not inputs:
        raise ValueError("nothing to merge: no input map")
    if not is_map_file_name(out):
        check_tiled_output(out)
    parent = out.parent if str(out.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=".mfp-merge-", dir=parent))
    generation = new_generation()
    tiled_out = scratch / "merged" if is_map_file_name(out) else out
    try:
        maps = [as_tiled(Path(p), scratch, tile_blocks) for p in inputs]
        check_mergeable([m.settings() for m in maps], [str(p) for p in inputs])
        (tiled_out / TILE_DIR).mkdir(parents=True, exist_ok=True)
        keys = sorted({k for m in maps for k in m.tiles})
        entries = [write_tile(tiled_out, k, merge_tile(maps, k), generation) for k in keys]
        write_index(tiled_out, maps[0].settings(), tile_blocks, entries)
        if is_map_file_name(out):
            write_map_file(TiledMap(tiled_out), out)
    except BaseException:
        if tiled_out == out:
            for stale in (out / TILE_DIR).glob(f"*.{generation}.npz"):
                stale.unlink(missing_ok=True)
        raise
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return MergeResult(out, len(inputs), sum(e.voxels for e in entries), len(entries))
