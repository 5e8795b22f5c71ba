"""``mfp-mapper``: the offline command line (bags, the built-in example, exports, pictures).

A thin argparse layer: the work is in offline/ (replay, simulate, export, render, evaluate).
Exit status: 0 success, 1 the job failed (bad bag, bad map file...), 2 bad usage,
130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from mfp_mapper.core.atomic import write_text_atomic

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


class CliError(Exception):
    """A failure to report on stderr with exit status 1."""


def _unit_interval(text: str) -> float:
    """An argparse type: a number in [0, 1]."""
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must lie in [0, 1], got {text}")
    return value


def _err(text: str) -> None:
    print(f"mfp-mapper: error: {text}", file=sys.stderr)


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
    from mfp_mapper import __version__
    from mfp_mapper.offline.input_args import add_input_arguments
    from mfp_mapper.offline.names import BAG_FORMATS, SCENES
    from mfp_mapper.offline.options import add_replay_flags

    parser = argparse.ArgumentParser(
        prog="mfp-mapper",
        description="Offline tools of mfp_mapper, the mean-free-path lidar mapper: replay "
        "bags into maps, simulate the built-in example, export and draw maps.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
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
        help="run on a local Dask cluster of N worker processes (0: one per core)",
    )  # fmt: skip
    g.add_argument("--scheduler", metavar="ADDRESS", help="run on this existing Dask cluster")
    g.add_argument(
        "--chunk-seconds", type=_positive, metavar="S",
        help="also split each recording into windows of S seconds of cloud stamps",
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


# --- commands ---------------------------------------------------------------------------


def _load_map(path: str, bounds: Any = None, lazy_tiles: bool = False) -> Any:
    """A Mapper (only ``bounds`` when given); with ``lazy_tiles``, a tiled map is opened as a
    ``TiledMap`` that reads its tiles when asked."""
    from mfp_mapper.core.mapfile import MapFileError
    from mfp_mapper.core.mapper import Mapper
    from mfp_mapper.core.tiles import TiledMap

    try:
        if lazy_tiles and Path(path).is_dir():
            return TiledMap(path)
        return Mapper.load(path, bounds=bounds)
    except FileNotFoundError:
        raise CliError(f"{path}: no such map file") from None
    except (MapFileError, OSError, ValueError) as err:
        raise CliError(str(err)) from None


def _check_writable(path: Path, tiled_ok: bool = False) -> None:
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise CliError(f"{path}: the folder {parent} does not exist")
    if tiled_ok and path.suffix != ".npz":
        from mfp_mapper.core.mapfile import MapFileError
        from mfp_mapper.core.tiles import check_tiled_output

        try:
            check_tiled_output(path)
        except MapFileError as err:
            raise CliError(str(err)) from None
    elif path.is_dir():
        raise CliError(f"{path} is a directory, expected a file name")


def replay_options(args: argparse.Namespace) -> Any:
    """ReplayOptions from the schema defaults, ``--config``, the flags given and the
    input flags (``offline.input_args``)."""
    from dataclasses import replace

    from mfp_mapper.offline.input_args import input_options
    from mfp_mapper.offline.options import options_from_args

    return replace(options_from_args(args), **input_options(args))


def cmd_replay(args: argparse.Namespace) -> int:
    from mfp_mapper.offline.folder_replay import replay_folder
    from mfp_mapper.offline.replay import ReplayError, replay
    from mfp_mapper.offline.scan_folder import is_scan_folder

    out = Path(args.output)
    _check_writable(out, tiled_ok=True)
    fleet = any(
        getattr(args, k) is not None for k in ("workers", "scheduler", "chunk_seconds")
    ) or (len(args.inputs) > 1)
    if fleet:
        return cmd_replay_fleet(args, out)
    try:
        opts = replay_options(args)
        if is_scan_folder(args.inputs[0]):
            result = replay_folder(
                args.inputs[0], args.poses, opts, args.times, progress=not args.quiet, log=_warn
            )
        elif args.poses is not None or args.times is not None:
            raise ReplayError(
                f"{args.inputs[0]}: --poses and --times are for folders of scan files"
            )
        else:
            result = replay(args.inputs[0], opts, progress=not args.quiet, log=_warn)
    except ReplayError as err:
        raise CliError(f"{err} (no map written)") from None
    except ValueError as err:  # invalid mapper settings
        raise CliError(f"{err} (no map written)") from None
    if out.suffix == ".npz":
        result.mapper.save(out)
    else:
        from mfp_mapper.core.mapfile import map_arrays
        from mfp_mapper.core.tiles import write_tiled

        write_tiled(out, map_arrays(result.mapper), args.tile_blocks)
    summary = result.summary
    print(summary.format())
    print(f"map          {out} ({result.mapper.num_voxels:,} voxels, {opts.resolution:g} m)")
    if args.summary_json:
        write_text_atomic(args.summary_json, json.dumps(_jsonable(vars(summary)), indent=2) + "\n")
    return 0


def cmd_replay_fleet(args: argparse.Namespace, out: Path) -> int:
    """Several recordings (or windows, or Dask): ``offline.fleet``."""
    from mfp_mapper.offline.fleet import FleetOptions, default_workers, map_fleet
    from mfp_mapper.offline.replay import ReplayError

    workers = default_workers() if args.workers == 0 else args.workers
    fleet = FleetOptions(
        workers=workers,
        scheduler=args.scheduler,
        chunk_seconds=args.chunk_seconds,
        skip_bad=args.skip_bad,
        tile_blocks=args.tile_blocks,
        work_dir=args.work_dir,
        progress=not args.quiet,
    )
    try:
        opts = replay_options(args)
        result = map_fleet(args.inputs, out, opts, fleet, log=_warn)
    except (ReplayError, RuntimeError, ValueError) as err:  # FleetError, MergeError, Dask
        text = str(err)
        raise CliError(text if "no map written" in text else f"{text} (no map written)") from None
    print(result.format())
    if args.summary_json:
        tasks = [
            {"task": r.task.label, "seconds": r.seconds, **_jsonable(vars(r.summary))}
            for r in result.tasks
            if r.summary is not None
        ]
        summary = {"output": str(out), "voxels": result.voxels, "tasks": tasks}
        write_text_atomic(args.summary_json, json.dumps(_jsonable(summary), indent=2) + "\n")
    return 0


def cmd_merge(args: argparse.Namespace) -> int:
    from mfp_mapper.core.mapfile import MapFileError
    from mfp_mapper.offline.merge_maps import merge_maps

    out = Path(args.output)
    _check_writable(out, tiled_ok=True)
    try:
        result = merge_maps(args.inputs, out, args.tile_blocks)
    except (MapFileError, ValueError) as err:  # MergeError is a ValueError
        raise CliError(f"{err} (nothing written)") from None
    print(f"merged {result.inputs} maps into {out}: {result.voxels:,} voxels")
    return 0


def _warn(text: str) -> None:
    print(f"mfp-mapper: {text}", file=sys.stderr)


def _jsonable(value: Any) -> Any:
    from mfp_mapper.offline.report import jsonable

    return jsonable(value)


def _sim_config(args: argparse.Namespace) -> Any:
    from mfp_mapper.offline.simulate import preset

    cfg = preset(args.scene)
    changes: dict[str, Any] = {"seed": args.seed}
    if args.scans is not None:
        changes["scans"] = args.scans
    if args.azimuths is not None:
        changes["azimuths"] = max(args.azimuths, 1)
    if args.no_odom:
        changes["odom_topic"] = None
        changes["write_tf"] = True
    if args.tf:
        changes["write_tf"] = True
    if args.no_tf_static:
        changes["write_tf_static"] = False
    if args.cloud_in_base_frame:
        changes["cloud_in_base_frame"] = True
    if args.organized:
        changes["organized"] = True
    return replace(cfg, **changes)


def cmd_simulate(args: argparse.Namespace) -> int:
    from mfp_mapper.offline.simulate import SimulationError, simulate

    try:
        result = simulate(args.out_bag, _sim_config(args), args.format, overwrite=args.overwrite)
    except SimulationError as err:
        raise CliError(str(err)) from None
    from mfp_mapper.offline.report import simulation_lines

    for line in simulation_lines(result):
        print(line)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    out = Path(args.output)
    fmt = args.format or _export_format(out)
    if fmt == "ply":
        from mfp_mapper.core.mapfile import MapFileError
        from mfp_mapper.core.tiles import TiledMap
        from mfp_mapper.offline.export import export_ply, export_ply_tiled

        mapper = _load_map(args.map, lazy_tiles=True)  # a tiled map: one tile at a time
        _check_writable(out)
        export = export_ply_tiled if isinstance(mapper, TiledMap) else export_ply
        try:
            count = export(mapper, out, args.min_doo, args.min_evidence)
        except MapFileError as err:  # a damaged tile
            raise CliError(f"{err} (nothing written)") from None
        print(f"wrote {out}: {count:,} voxels (x y z degree_of_occupancy std mean_free_path n s)")
        return 0
    mapper = _load_map(args.map)
    z_min, z_max = _export_band(mapper, args)
    try:
        if fmt == "nav2":
            from mfp_mapper.offline.nav2_map import write_nav2_map

            _check_writable(out)
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
            from mfp_mapper.offline.mcap_export import export_mcap

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
    from mfp_mapper.offline.render import BAND_HEIGHT, top_down_band

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


def cmd_render(args: argparse.Namespace) -> int:
    from mfp_mapper.offline.render import render_map

    bounds = (args.bounds[:3], args.bounds[3:]) if args.bounds else None
    mapper = _load_map(args.map, bounds)
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


def cmd_plot_convergence(args: argparse.Namespace) -> int:
    from mfp_mapper.offline.render import plot_convergence

    print(f"wrote {plot_convergence(args.output, args.returns, args.passes)}")
    return 0


def cmd_query(args: argparse.Namespace) -> int:
    import numpy as np

    from mfp_mapper.offline.report import query_lines, query_rows

    if len(args.coords) % 3:
        raise CliError(f"query needs X Y Z triples, got {len(args.coords)} numbers")
    from mfp_mapper.core.mapfile import MapFileError

    mapper = _load_map(args.map, lazy_tiles=True)  # a tiled map reads the tiles it needs
    try:
        rows = query_rows(mapper, np.asarray(args.coords, dtype=np.float64).reshape(-1, 3))
    except MapFileError as err:  # a damaged tile
        raise CliError(str(err)) from None
    if args.json:
        print(json.dumps(_jsonable(rows), indent=2))
        return 0
    print(f"map {args.map}: frame {mapper.frame_id}, {mapper.resolution:g} m voxels")
    for line in query_lines(rows):
        print(line)
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from mfp_mapper.offline.evaluate import evaluate_map
    from mfp_mapper.offline.simulate import SimulationError, load_truth

    if not 0 < args.level < 1:
        raise CliError(f"--level must lie in (0, 1), got {args.level}")
    mapper = _load_map(args.map)
    try:
        truth = load_truth(args.truth)
    except SimulationError as err:
        raise CliError(str(err)) from None
    ev = evaluate_map(mapper, truth, args.level, args.min_evidence)
    print(ev.format())
    if args.json:
        write_text_atomic(args.json, json.dumps(_jsonable(ev.to_json()), indent=2) + "\n")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from mfp_mapper.offline.demo import run_demo
    from mfp_mapper.offline.replay import ReplayError

    try:
        run_demo(args.output, args.resolution, args.scans, args.format, args.seed,
                 progress=not args.quiet, warn=_warn)  # fmt: skip
    except ReplayError as err:
        raise CliError(str(err)) from None
    return 0


COMMANDS = {
    "replay": cmd_replay,
    "merge": cmd_merge,
    "simulate": cmd_simulate,
    "export": cmd_export,
    "render": cmd_render,
    "plot-convergence": cmd_plot_convergence,
    "query": cmd_query,
    "evaluate": cmd_evaluate,
    "demo": cmd_demo,
}


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except CliError as err:
        _err(str(err))
        return 1
    except KeyboardInterrupt:
        _err("interrupted (nothing written for the step in progress)")
        return 130
    except BrokenPipeError:
        return 1


if __name__ == "__main__":
    sys.exit(main())
