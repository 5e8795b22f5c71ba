"""The ``mfp-mapper`` argument parser: every subcommand, its flags and their checks.

Imports no numpy: ``mfp-mapper --help`` stays cheap (the replay flags come from the settings
schema through ``config.replay_options``).
"""

from __future__ import annotations

import argparse
import math

EPILOG = """\
examples:
  mfp-mapper demo                     # simulate, map, draw, evaluate -> ./example_output
  mfp-mapper simulate sim_bag         # the built-in example as a ROS 2 mcap bag
  mfp-mapper replay sim_bag -o map.npz --resolution 0.2
  mfp-mapper replay run.bag --cloud-topic /velodyne_points --odom-topic /odom -o map.npz
  mfp-mapper replay ros2_bag --config config/mfp_mapper.yaml -o map.npz
  mfp-mapper replay day/*.bag -o fleet.npz --workers 4    # several recordings, on Dask
  mfp-mapper merge a.npz b.npz -o ab.npz              # exact merge of maps
  mfp-mapper replay day/*.bag -o fleet_tiles/ --chunk-seconds 60   # a tiled map
  mfp-mapper export map.npz -o map.ply --min-doo 0.1
  mfp-mapper render map.npz -o pictures/
  mfp-mapper plot-convergence -o pictures/
  mfp-mapper query map.npz 1.0 0.0 1.2  4.0 2.0 0.5
  mfp-mapper evaluate map.npz sim_bag.truth.json
"""


def _unit_interval(text: str) -> float:
    """An argparse type: a number in [0, 1]."""
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must lie in [0, 1], got {text}")
    return value


def _positive(text: str) -> float:
    value = float(text)
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def _nonneg_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    from mfp_mapper.cli.input_args import add_input_arguments
    from mfp_mapper.config.names import BAG_FORMATS, SCENES, VERSION
    from mfp_mapper.config.replay_options import add_replay_flags

    parser = argparse.ArgumentParser(
        prog="mfp-mapper",
        description="Offline tools of mfp_mapper, the mean-free-path lidar mapper: replay "
        "bags into maps, simulate the built-in example, export and draw maps.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {VERSION}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser(
        "replay",
        help="map ROS 1 .bag or ROS 2 (sqlite3/mcap) bags into one map",
        description="Replay a bag into a map. Topics are found automatically when the bag has "
        "one PointCloud2 and one Odometry topic; without Odometry, poses come from /tf. The "
        "lidar extrinsic comes from /tf_static (identity when the cloud frame is the odometry "
        "child frame), else from --extrinsic or the config. The map is written only when the "
        "whole bag was replayed. Several bags (or --workers, --scheduler, --chunk-seconds): "
        "partial maps merged exactly into one (docs/FLEET.md).",
    )
    p.add_argument(
        "inputs", nargs="+", metavar="INPUT",
        help="ROS 1 .bag files, ROS 2 bag directories, or a folder of scan files (several "
        "bags: mapped into one map)",
    )  # fmt: skip
    p.add_argument(
        "-o", "--output", required=True,
        help="the map to write: NAME.npz, or a directory for a tiled map (docs/TILES.md)",
    )  # fmt: skip
    p.add_argument("--config", help="a node parameter file (read as the node reads it)")
    add_replay_flags(p)  # one flag per setting of the schema that has one
    add_input_arguments(p)  # folders, poses, odometry, --start/--end
    p.add_argument("--summary-json", help="also write the summary as JSON here")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _fleet_arguments(p)

    p = sub.add_parser(
        "merge",
        help="merge maps exactly (.npz files or tiled maps) into one",
        description="Per-voxel sums, decay brought to a common time (docs/FLEET.md). Maps of "
        "other resolutions, frames, decay times are refused. OUTPUT: NAME.npz, or a "
        "directory for a tiled map.",
    )
    p.add_argument("inputs", nargs="+", metavar="MAP", help="map files (.npz) or tiled maps")
    p.add_argument("-o", "--output", required=True, help="the merged map to write")
    p.add_argument("--tile-blocks", type=_positive_int, default=32, help=TILE_BLOCKS_HELP)

    p = sub.add_parser(
        "simulate",
        help="write the built-in example bag with its ground truth",
        description="Simulate a lidar on a robot driving a circle in a closed room with solid "
        "boxes and volumes of medium of known extinction. Writes OUT_BAG and "
        "OUT_BAG.truth.json beside it.",
    )
    p.add_argument("out_bag", help="bag to write: a directory (ROS 2) or NAME.bag (ROS 1)")
    p.add_argument(
        "--format",
        choices=BAG_FORMATS,
        help="storage (default: ros1 for *.bag, else mcap)",
    )
    p.add_argument(
        "--scene",
        choices=SCENES,
        default="demo",
        help="demo: the example hall; small: one cube of medium (tests); open: "
        "small without ceiling (rays escape: shows the bias)",
    )
    p.add_argument("--scans", type=_nonneg_int, help="number of 0.1 s rotations")
    p.add_argument("--azimuths", type=_nonneg_int, help="azimuth steps per rotation")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--no-odom", action="store_true", help="no Odometry topic (poses on /tf)")
    p.add_argument("--tf", action="store_true", help="also write odom -> base_link on /tf")
    p.add_argument("--no-tf-static", action="store_true", help="no /tf_static")
    p.add_argument(
        "--organized",
        action="store_true",
        help="organized clouds (rows = beams) with NaN for no-returns, as velodyne's "
        "organize_cloud (replay --no-return-range recovers them)",
    )
    p.add_argument(
        "--cloud-in-base-frame",
        action="store_true",
        help="publish the points in base_link (no extrinsic needed)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace OUT_BAG if it exists")

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
        type=_unit_interval,
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
        "--occupied-threshold", type=_unit_interval, default=None,
        help="nav2: occupied where the hit probability >= this (default: the node's "
        "projected_map.occupied_threshold, 0.25)",
    )  # fmt: skip
    p.add_argument(
        "--free-threshold", type=_unit_interval, default=None,
        help="nav2: free where the hit probability < this (default: that of a never-observed "
        "voxel, resolution / (1 + resolution), as the node)",
    )  # fmt: skip

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

    p = sub.add_parser(
        "plot-convergence", help="one cell probed repeatedly: DoO vs classic occupancy (Fig. 9)"
    )
    p.add_argument("-o", "--output", required=True, help="PNG file or directory")
    p.add_argument("--returns", type=_nonneg_int, default=10, help="reflected rays first")
    p.add_argument("--passes", type=_nonneg_int, default=40, help="then rays passing through")

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

    p = sub.add_parser("evaluate", help="compare a map of a simulated bag with its truth")
    p.add_argument("map", help="map file (.npz)")
    p.add_argument("truth", help="the .truth.json written by simulate")
    p.add_argument("--level", type=float, default=0.9, help="credible level (default 0.9)")
    p.add_argument(
        "--min-evidence",
        type=float,
        default=0.0,
        help="only voxels with s >= this (metres of rays)",
    )
    p.add_argument("--json", help="also write the results as JSON here")

    p = sub.add_parser(
        "demo",
        help="simulate -> replay -> render -> evaluate the built-in example",
        description="Run the whole chain on the built-in example and say what came out.",
    )
    p.add_argument(
        "-o",
        "--output",
        default="example_output",
        help="directory for everything (default ./example_output)",
    )
    p.add_argument("--resolution", type=_positive, default=0.2, help="voxel edge (default 0.2)")
    p.add_argument("--scans", type=_nonneg_int, default=120, help="rotations (default 120)")
    p.add_argument("--format", choices=BAG_FORMATS, default="mcap")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return parser


TILE_BLOCKS_HELP = "tile edge of a tiled output, in 8x8x8-voxel blocks (default 32)"


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text}")
    return value


def _fleet_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("several recordings, Dask (docs/FLEET.md)")
    g.add_argument(
        "--workers", type=_nonneg_int, metavar="N",
        help="run on a local Dask cluster of N worker processes (0: one per core; at most "
        "one per core and per task)",
    )  # fmt: skip
    g.add_argument("--scheduler", metavar="ADDRESS", help="run on this existing Dask cluster")
    g.add_argument(
        "--chunk-seconds", type=_positive, metavar="S",
        help="also split each recording into windows of S seconds of cloud stamps (widened "
        "to at most one window per cloud and 16 per worker)",
    )  # fmt: skip
    g.add_argument(
        "--allow-duplicates", action="store_true",
        help="map an input given twice twice (refused by default: its evidence would count "
        "twice)",
    )  # fmt: skip
    g.add_argument(
        "--skip-bad", action="store_true",
        help="leave out recordings that fail (listed at the end) instead of stopping",
    )  # fmt: skip
    g.add_argument(
        "--work-dir", help="folder for the partial maps (default: beside the output; every "
        "worker must see it)",
    )  # fmt: skip
    g.add_argument("--tile-blocks", type=_positive_int, default=32, help=TILE_BLOCKS_HELP)
