"""``mfp-mapper simulate``: the built-in example bag with its ground truth."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import CliError, check_folder_writable, nonneg_int
from mfp_mapper.config.names import BAG_FORMATS, SCENES


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``simulate`` subcommand's arguments."""
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
    p.add_argument("--scans", type=nonneg_int, help="number of 0.1 s rotations")
    p.add_argument("--azimuths", type=nonneg_int, help="azimuth steps per rotation")
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
    return p


def _sim_config(args: argparse.Namespace) -> Any:
    from mfp_mapper.sources.simulate import preset

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


def run(args: argparse.Namespace) -> int:
    from mfp_mapper.sources.simulate import SimulationError, simulate

    check_folder_writable(Path(args.out_bag).absolute().parent)
    try:
        result = simulate(args.out_bag, _sim_config(args), args.format, overwrite=args.overwrite)
    except SimulationError as err:
        raise CliError(str(err)) from None
    from mfp_mapper.outputs.report import simulation_lines

    for line in simulation_lines(result):
        print(line)
    return 0
