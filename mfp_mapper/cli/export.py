"""``mfp-mapper export``: a map as PLY, a Nav2 map or an mcap bag."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import CliError, check_writable, load_map_arg, unit_interval


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``export`` subcommand's arguments."""
    p = sub.add_parser(
        "export",
        help="write a map as PLY (CloudCompare), a Nav2 map (PGM + YAML) or an mcap bag",
        description="ply: binary little endian, one vertex per observed voxel: "
        "x y z degree_of_occupancy std mean_free_path n s. nav2: a map_server map "
        "(OUT.yaml + OUT.pgm) of the height band: occupied where the hit probability >= "
        "--occupied-threshold, free below --free-threshold, else unknown. mcap: a ROS 2 bag "
        "(directory OUT) with the DoO and std clouds and the projected grid, for Foxglove "
        "or ros2 bag play. The format defaults from OUT: .ply, .yaml/.pgm, else mcap.",
    )
    p.add_argument("map", help="map file (.npz) or tiled map (ply: read tile by tile)")
    p.add_argument("-o", "--output", required=True, help="file (ply, nav2) or directory (mcap)")
    p.add_argument("--format", choices=("ply", "nav2", "mcap"), help="default: from OUT")
    p.add_argument(
        "--min-doo",
        type=unit_interval,
        default=0.0,
        help="ply, mcap: only voxels with most likely degree of occupancy >= this",
    )
    p.add_argument(
        "--min-evidence",
        type=float,
        default=0.0,
        help="ply, mcap: only voxels with s >= this (metres of rays)",
    )
    p.add_argument("--z-min", type=float, help="nav2, mcap: band bottom (default: floor+0.25)")
    p.add_argument("--z-max", type=float, help="nav2, mcap: band top (default: as render)")
    p.add_argument(
        "--occupied-threshold", type=unit_interval, default=None,
        help="nav2: occupied where the hit probability >= this (default: the node's "
        "projected_map.occupied_threshold, 0.25)",
    )  # fmt: skip
    p.add_argument(
        "--free-threshold", type=unit_interval, default=None,
        help="nav2: free where the hit probability < this (default: that of a never-observed "
        "voxel under the map's prior, as the node: 0.012 at 0.1 m with the default prior)",
    )  # fmt: skip
    return p


def run(args: argparse.Namespace) -> int:
    out = Path(args.output)
    fmt = args.format or _export_format(out)
    if fmt == "ply":
        from mfp_mapper.mapio.tiles import TiledMap
        from mfp_mapper.outputs.export import export_ply, export_ply_tiled

        check_writable(out)
        mapper = load_map_arg(args.map, lazy_tiles=True)  # a tiled map: one tile at a time
        export = export_ply_tiled if isinstance(mapper, TiledMap) else export_ply
        try:
            count = export(mapper, out, args.min_doo, args.min_evidence)
        except ValueError as err:  # a damaged tile (MapFileError), values beyond float32
            raise CliError(f"{err} (nothing written)") from None
        print(f"wrote {out}: {count:,} voxels (x y z degree_of_occupancy std mean_free_path n s)")
        return 0
    check_writable(out)
    mapper = load_map_arg(args.map)
    z_min, z_max = _export_band(mapper, args)
    try:
        if fmt == "nav2":
            from mfp_mapper.outputs.nav2_map import write_nav2_map

            check_writable(out)
            nav = write_nav2_map(
                mapper, out, z_min, z_max, args.occupied_threshold, args.free_threshold
            )
            cells = nav.occupancy
            print(
                f"wrote {nav.yaml} and {nav.image}: {cells.shape[1]} x {cells.shape[0]} cells "
                f"of {nav.resolution:g} m, band z in [{z_min:.2f}, {z_max:.2f}] m; "
                f"{int((cells == 100).sum()):,} occupied, {int((cells == 0).sum()):,} free, "
                f"{int((cells == -1).sum()):,} unknown"
            )
        else:
            from mfp_mapper.outputs.mcap_export import export_mcap

            counts = export_mcap(mapper, out, z_min, z_max, args.min_doo, args.min_evidence)
            listing = ", ".join(f"{topic} ({n:,})" for topic, n in counts.items())
            print(f"wrote {out} (mcap): {listing}")
    except (ValueError, FileExistsError) as err:
        raise CliError(str(err)) from None
    return 0


def _export_format(out: Path) -> str:
    suffix = out.suffix.lower()
    if suffix == ".ply":
        return "ply"
    return "nav2" if suffix in (".yaml", ".yml", ".pgm") else "mcap"


def _export_band(mapper: Any, args: argparse.Namespace) -> tuple[float, float]:
    """The height band of a 2D output: given, else the render's band from the data."""
    from mfp_mapper.outputs.render import BAND_HEIGHT, top_down_band

    needed = args.z_min is None or args.z_max is None
    # the band comes from the occupied voxels only (filtered in compiled code)
    lo, hi = top_down_band(mapper.voxels(min_doo=0.5)) if needed else (0.0, 0.0)
    z_min = args.z_min if args.z_min is not None else lo
    z_max = (
        args.z_max
        if args.z_max is not None
        else (hi if args.z_min is None else z_min + BAND_HEIGHT)
    )
    if not (math.isfinite(z_min) and math.isfinite(z_max)):
        raise CliError("no floor found in the map: give the band with --z-min and --z-max")
    return z_min, z_max
