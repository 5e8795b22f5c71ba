"""``mfp-mapper render``: pictures of a map (top-down DoO and std, slice, histogram)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import CliError, check_folder_writable, load_map_arg


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``render`` subcommand's arguments."""
    p = sub.add_parser("render", help="draw a map: top-down DoO and std, slice, histogram")
    p.add_argument("map", help="map file (.npz)")
    p.add_argument("-o", "--output", required=True, help="directory for the PNG files")
    p.add_argument("--z-min", type=float, help="bottom of the top-down band (default: ground+0.25)")
    p.add_argument("--z-max", type=float, help="top of the top-down band (default: z-min+2.25)")
    p.add_argument("--slice-y", type=float, help="y of the vertical slice (default: median)")
    p.add_argument(
        "--bounds", nargs=6, type=float, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
        help="draw only this box (m; of a tiled map only its tiles are read)",
    )  # fmt: skip
    p.add_argument(
        "--value", choices=("most-likely", "mean"), default="most-likely",
        help="top-down DoO: the most likely (default) or the posterior mean (shows how "
        "little a voxel was seen)",
    )  # fmt: skip
    p.add_argument(
        "--min-evidence", type=float, default=0.0,
        help="draw only voxels with s >= this (metres of rays); others as unobserved",
    )  # fmt: skip
    return p


def run(args: argparse.Namespace) -> int:
    from mfp_mapper.outputs.render import render_map

    bounds = (args.bounds[:3], args.bounds[3:]) if args.bounds else None
    check_folder_writable(Path(args.output))
    mapper = load_map_arg(args.map, bounds)
    try:
        result = render_map(
            mapper,
            args.output,
            args.z_min,
            args.z_max,
            args.slice_y,
            value=args.value,
            min_evidence=args.min_evidence,
        )
    except ValueError as err:
        raise CliError(str(err)) from None
    for f in result.files:
        print(f"wrote {f}")
    return 0
