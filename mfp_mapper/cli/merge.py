"""``mfp-mapper merge``: maps merged exactly into one (``mapio.merge_files``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import TILE_BLOCKS_HELP, CliError, check_writable, positive_int


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``merge`` subcommand's arguments."""
    p = sub.add_parser(
        "merge",
        help="merge maps exactly (.npz files or tiled maps) into one",
        description="Per-voxel sums, decay brought to a common time (docs/fleet.md). Maps of "
        "other resolutions, frames, decay times are refused. OUTPUT: NAME.npz, or a "
        "directory for a tiled map.",
    )
    p.add_argument("inputs", nargs="+", metavar="MAP", help="map files (.npz) or tiled maps")
    p.add_argument("-o", "--output", required=True, help="the merged map to write")
    p.add_argument("--tile-blocks", type=positive_int, default=32, help=TILE_BLOCKS_HELP)
    return p


def run(args: argparse.Namespace) -> int:
    from mfp_mapper.mapio.mapfile import MapFileError
    from mfp_mapper.mapio.merge_files import merge_maps

    out = Path(args.output)
    check_writable(out, tiled_ok=True)
    try:
        result = merge_maps(args.inputs, out, args.tile_blocks)
    except (MapFileError, ValueError) as err:  # MergeError is a ValueError
        raise CliError(f"{err} (nothing written)") from None
    print(f"merged {result.inputs} maps into {out}: {result.voxels:,} voxels")
    return 0
