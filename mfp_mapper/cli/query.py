"""``mfp-mapper query``: the statistics of the voxels at given points."""

from __future__ import annotations

import argparse
import json
from typing import Any

from mfp_mapper.cli.common import CliError, jsonable, load_map_arg


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``query`` subcommand's arguments."""
    p = sub.add_parser("query", help="statistics of the voxels at points X Y Z ...")
    p.add_argument("map", help="map file (.npz) or tiled map (only the tiles needed are read)")
    p.add_argument(
        "coords",
        nargs="+",
        type=float,
        metavar="X Y Z",
        help="one or more points, three numbers each",
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    return p


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from mfp_mapper.outputs.report import query_lines, query_rows

    if len(args.coords) % 3:
        raise CliError(f"query needs X Y Z triples, got {len(args.coords)} numbers")
    from mfp_mapper.mapio.mapfile import MapFileError

    mapper = load_map_arg(args.map, lazy_tiles=True)  # a tiled map reads the tiles it needs
    try:
        rows = query_rows(mapper, np.asarray(args.coords, dtype=np.float64).reshape(-1, 3))
    except MapFileError as err:  # a damaged tile
        raise CliError(str(err)) from None
    if args.json:
        print(json.dumps(jsonable(rows), indent=2))
        return 0
    print(f"map {args.map}: frame {mapper.frame_id}, {mapper.resolution:g} m voxels")
    for line in query_lines(rows, mapper.prior):
        print(line)
    return 0
