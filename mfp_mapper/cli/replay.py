"""``mfp-mapper replay``: recordings (bags, scan folders) into a map; several of them or
``--workers``: the fleet (``mapping.fleet``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import (
    TILE_BLOCKS_HELP,
    CliError,
    check_outputs,
    check_writable,
    jsonable,
    nonneg_int,
    one_line,
    positive,
    positive_int,
    warn,
)
from mfp_mapper.cli.input_args import add_input_arguments, input_options
from mfp_mapper.cli.localize import add_align_arguments
from mfp_mapper.config.replay_options import ReplayOptions, add_replay_flags, options_from_args
from mfp_mapper.mapio.atomic import write_text_atomic


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``replay`` subcommand's arguments."""
    p = sub.add_parser(
        "replay",
        help="map ROS 1 .bag or ROS 2 (sqlite3/mcap) bags into one map",
        description="Replay a bag into a map. Topics are found automatically when the bag has "
        "one PointCloud2 and one Odometry topic; without Odometry, poses come from /tf. The "
        "lidar extrinsic comes from /tf_static (identity when the cloud frame is the odometry "
        "child frame), else from --extrinsic or the config. The map is written only when the "
        "whole bag was replayed. Several bags (or --workers, --scheduler, --chunk-seconds): "
        "partial maps merged exactly into one (docs/fleet.md).",
    )
    p.add_argument(
        "inputs", nargs="+", metavar="INPUT",
        help="ROS 1 .bag files, ROS 2 bag directories, or a folder of scan files (several "
        "bags: mapped into one map)",
    )  # fmt: skip
    p.add_argument(
        "-o", "--output", required=True,
        help="the map to write: NAME.npz, or a directory for a tiled map (docs/mapfiles.md)",
    )  # fmt: skip
    p.add_argument("--config", help="a node parameter file (read as the node reads it)")
    add_replay_flags(p)  # one flag per setting of the schema that has one
    add_input_arguments(p)  # folders, poses, odometry, --start/--end
    p.add_argument(
        "--refine-poses", action="store_true",
        help="align each scan against the map built so far (by the forward model's "
        "likelihood) before integrating it; initial guess from the pose source (the bag's "
        "odometry or /tf, --poses, --odometry kiss-icp)",
    )  # fmt: skip
    p.add_argument(
        "--poses-out", metavar="FILE",
        help="write the poses used (refined or not) as TUM, and a per-scan "
        "confidence file FILE.confidence.jsonl",
    )  # fmt: skip
    add_align_arguments(p)
    p.add_argument("--summary-json", help="also write the summary as JSON here")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _fleet_arguments(p)
    return p


def replay_options(args: argparse.Namespace) -> ReplayOptions:
    """ReplayOptions from the schema defaults, ``--config``, the flags given and the
    input flags (``cli.input_args``)."""
    return options_from_args(args).but(**input_options(args))


def run(args: argparse.Namespace) -> int:
    from mfp_mapper.mapio.loading import save_map
    from mfp_mapper.mapping.replay import ReplayError, replay
    from mfp_mapper.sources.opener import open_recording

    out = Path(args.output)
    check_writable(out, tiled_ok=True)
    check_outputs(args.summary_json)
    fleet = any(
        getattr(args, k) is not None for k in ("workers", "scheduler", "chunk_seconds")
    ) or (len(args.inputs) > 1)
    if fleet:
        if args.refine_poses or args.poses_out:
            raise CliError(
                "--refine-poses and --poses-out take one input, a scan folder or a bag (not "
                "several inputs, --workers, --scheduler or --chunk-seconds)"
            )
        return run_fleet(args, out)
    if args.refine_poses or args.poses_out:
        return run_refined(args, out)
    try:
        opts = replay_options(args)
        with open_recording(args.inputs[0], opts, args.poses, args.times, warn) as recording:
            result = replay(recording, opts, progress=not args.quiet, log=warn)
    except ReplayError as err:
        raise CliError(f"{err} (no map written)") from None
    except ValueError as err:  # invalid mapper settings
        raise CliError(f"{err} (no map written)") from None
    save_map(result.mapper, out, args.tile_blocks)
    summary = result.summary
    print(summary.format())
    print(f"map          {out} ({result.mapper.num_voxels:,} voxels, {opts.map.resolution:g} m)")
    if args.summary_json:
        write_text_atomic(args.summary_json, json.dumps(jsonable(vars(summary)), indent=2) + "\n")
    return 0


def run_refined(args: argparse.Namespace, out: Path) -> int:
    """One recording, scan by scan, with ``--refine-poses`` and/or ``--poses-out``
    (``mapping.localize.replay_refined``)."""
    from mfp_mapper.cli.localize import (
        align_options,
        check_pose_outputs,
        print_summary,
        write_results,
    )
    from mfp_mapper.mapio.loading import save_map
    from mfp_mapper.mapping.localize import replay_refined
    from mfp_mapper.mapping.replay import ReplayError
    from mfp_mapper.sources.opener import open_recording

    poses_out = Path(args.poses_out) if args.poses_out else None
    if poses_out is not None:
        check_pose_outputs(
            poses_out,
            {"the map (-o)": out, "the input": args.inputs[0], "the --poses file": args.poses,
             "the --times file": args.times},
        )  # fmt: skip
    try:
        opts = replay_options(args)
        with open_recording(args.inputs[0], opts, args.poses, args.times, warn) as recording:
            result = replay_refined(
                recording, opts, align=align_options(args), log=warn, refine=args.refine_poses
            )
    except ReplayError as err:
        raise CliError(f"{err} (no map written)") from None
    except ValueError as err:
        raise CliError(f"{err} (no map written)") from None
    if result.mapper is None or not result.scans:
        raise CliError(f"{args.inputs[0]}: no scan had a pose (no map written)")
    save_map(result.mapper, out, args.tile_blocks)
    if poses_out is not None:
        write_results(result, poses_out)
    if args.refine_poses:
        print_summary(result, poses_out or Path("(not written)"))
    print(f"map          {out} ({result.mapper.num_voxels:,} voxels)")
    return 0


def run_fleet(args: argparse.Namespace, out: Path) -> int:
    """Several inputs (or windows, or Dask): ``mapping.fleet``."""
    from mfp_mapper.mapping.fleet import FleetOptions, default_workers, map_fleet
    from mfp_mapper.mapping.replay import ReplayError

    workers = default_workers() if args.workers == 0 else args.workers
    fleet = FleetOptions(
        workers=workers,
        scheduler=args.scheduler,
        chunk_seconds=args.chunk_seconds,
        skip_bad=args.skip_bad,
        tile_blocks=args.tile_blocks,
        work_dir=args.work_dir,
        progress=not args.quiet,
        allow_duplicates=args.allow_duplicates,
        poses=None if args.poses is None else str(args.poses),
        times=None if args.times is None else str(args.times),
    )
    try:
        opts = replay_options(args)
        result = map_fleet(args.inputs, out, opts, fleet, log=warn)
    except (ReplayError, RuntimeError, ValueError, OSError) as err:  # FleetError, Dask...
        text = one_line(err)
        raise CliError(text if "no map written" in text else f"{text} (no map written)") from None
    print(result.format())
    if args.summary_json:
        tasks = [
            {"task": r.task.label, "seconds": r.seconds, **jsonable(vars(r.summary))}
            for r in result.tasks
            if r.summary is not None
        ]
        summary = {"output": str(out), "voxels": result.voxels, "tasks": tasks}
        write_text_atomic(args.summary_json, json.dumps(jsonable(summary), indent=2) + "\n")
    return 0


def _fleet_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("several recordings, Dask (docs/fleet.md)")
    g.add_argument(
        "--workers", type=nonneg_int, metavar="N",
        help="run on a local Dask cluster of N worker processes (0: one per core; at most "
        "one per core and per task)",
    )  # fmt: skip
    g.add_argument("--scheduler", metavar="ADDRESS", help="run on this existing Dask cluster")
    g.add_argument(
        "--chunk-seconds", type=positive, metavar="S",
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
    g.add_argument("--tile-blocks", type=positive_int, default=32, help=TILE_BLOCKS_HELP)
