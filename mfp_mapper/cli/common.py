"""What the subcommands share: the error they report, map loading for a command, output
checks, argparse number types. Imports no numpy (``mfp-mapper --help`` stays cheap)."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import Any

TILE_BLOCKS_HELP = "tile edge of a tiled output, in 8x8x8-voxel blocks (default 32)"


class CliError(Exception):
    """A failure to report on stderr with exit status 1."""


def error(text: str) -> None:
    print(f"mfp-mapper: error: {text}", file=sys.stderr)


def warn(text: str) -> None:
    print(f"mfp-mapper: {text}", file=sys.stderr)


def jsonable(value: Any) -> Any:
    from mfp_mapper.outputs.report import jsonable

    return jsonable(value)


def load_map_arg(
    path: str, bounds: Any = None, lazy_tiles: bool = False, queries: bool = False
) -> Any:
    """A Mapper (only ``bounds`` when given); with ``lazy_tiles``, a tiled map is opened as a
    ``TiledMap`` that reads its tiles when asked; with ``queries`` too, a map file is opened
    as a ``MapFileQueries`` that reads the blocks each query needs."""
    from mfp_mapper.mapio.mapfile import MapFileError

    try:  # each import where needed: a query of points in a map file loads no numba
        if lazy_tiles and Path(path).is_dir():
            from mfp_mapper.mapio.tiles import TiledMap

            return TiledMap(path)
        if queries:
            from mfp_mapper.mapio.queries import MapFileQueries

            return MapFileQueries(path)
        from mfp_mapper.mapio.loading import load_map

        return load_map(path, bounds=bounds)
    except FileNotFoundError:
        raise CliError(f"{path}: no such map file") from None
    except (MapFileError, OSError, ValueError) as err:
        raise CliError(str(err)) from None
    except MemoryError:
        raise CliError(f"{path}: not enough memory to load this map") from None


def check_writable(path: Path, tiled_ok: bool = False) -> None:
    """CliError, before any work, when ``path`` cannot be written (no folder, read-only)."""
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise CliError(f"{path}: the folder {parent} does not exist")
    target = path if path.is_dir() else parent
    if not os.access(target, os.W_OK | os.X_OK):
        raise CliError(f"{path}: cannot write in {target} (read-only or not permitted)")
    from mfp_mapper.mapio.loading import is_map_file_name

    if tiled_ok and not is_map_file_name(path):
        from mfp_mapper.mapio.mapfile import MapFileError
        from mfp_mapper.mapio.tiles import check_tiled_output

        try:
            check_tiled_output(path)
        except MapFileError as err:
            raise CliError(str(err)) from None
    elif path.is_dir():
        raise CliError(f"{path} is a directory, expected a file name")


def check_outputs(*paths: str | Path | None) -> None:
    """``check_writable`` on every output path given (None: not asked for), before any work."""
    for path in paths:
        if path is not None:
            check_writable(Path(path))


def check_folder_writable(folder: Path) -> None:
    """CliError when ``folder`` (made if missing) could not be written in."""
    existing = folder.absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise CliError(f"{folder}: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise CliError(f"{folder}: cannot write in {existing} (read-only or not permitted)")


def one_line(err: BaseException) -> str:
    """The error's message on one line (a Dask or OS error may span several)."""
    text = " ".join(str(err).split()) or type(err).__name__
    if isinstance(err, OSError) and err.filename is not None and str(err.filename) not in text:
        text = f"{err.filename}: {text}"
    return text


def unit_interval(text: str) -> float:
    """An argparse type: a number in [0, 1]."""
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must lie in [0, 1], got {text}")
    return value


def positive(text: str) -> float:
    value = float(text)
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def nonneg_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text}")
    return value


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text}")
    return value
