"""``mfp-mapper localize``: each scan of a recording aligned against a fixed map by the forward
model's likelihood (``mapping.localize``); refined poses (TUM) and a per-scan confidence."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import CliError, check_writable, load_map_arg, warn
from mfp_mapper.cli.input_args import add_input_arguments, input_options
from mfp_mapper.config.replay_options import add_replay_flags

ALIGN_HELP = "scan-to-map alignment (docs/localization.md)"
MAX_LEVELS = 12
"""A coarsest voxel 2^11 times the map's (410 m at 0.2 m): more levels only cost time."""


def add_align_arguments(p: argparse.ArgumentParser) -> None:
    """The aligner's flags (``core.alignment.AlignOptions``)."""
    g = p.add_argument_group(ALIGN_HELP)
    g.add_argument(
        "--align-levels",
        type=int,
        default=3,
        help="pyramid levels: voxel edges resolution * 2^k (default 3)",
    )
    g.add_argument("--align-rays", type=int, default=3000, help="rays used per scan (default 3000)")
    g.add_argument("--align-max-sigma", type=float, default=0.05,
                   help="refuse when the weakest direction's std exceeds this, metres "
                   "(default 0.05)")  # fmt: skip


def align_options(args: argparse.Namespace) -> Any:
    import math

    from mfp_mapper.core.alignment import AlignOptions

    if (
        not 1 <= args.align_levels <= MAX_LEVELS
        or args.align_rays < 10
        or not 0 < args.align_max_sigma < math.inf
    ):
        raise CliError(
            f"--align-levels 1 to {MAX_LEVELS}, --align-rays >= 10, --align-max-sigma a finite "
            "number > 0 (metres)"
        )
    return AlignOptions(
        levels=args.align_levels, max_rays=args.align_rays, max_sigma_m=args.align_max_sigma
    )


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "localize",
        help="refine the poses of a recording's scans against a fixed map",
        description="Align each scan of INPUT (a bag or a folder of scan files) against MAP by "
        "the forward model's likelihood, starting from its pose in --poses (TUM matched by "
        "stamp; KITTI for a folder), the bag's own odometry or /tf, or --odometry kiss-icp; "
        "write the refined poses (TUM) and "
        "a per-scan confidence (FILE.confidence.jsonl). A correction the scan's geometry "
        "cannot support (a corridor, an open field) is refused: that scan keeps its pose.",
    )
    p.add_argument("map", help="the map (.npz or a tiled map directory)")
    p.add_argument("input", help="a bag (ROS 1 .bag, ROS 2 directory) or a folder of scan files")
    p.add_argument("--poses-out", required=True, metavar="FILE", help="refined poses (TUM)")
    p.add_argument("--config", help="a node parameter file (read as the node reads it)")
    add_replay_flags(p)  # the replay's settings flags (--extrinsic, topics, ...)
    add_input_arguments(p)
    add_align_arguments(p)
    return p


def run(args: argparse.Namespace) -> int:

    from mfp_mapper.config.replay_options import options_from_args
    from mfp_mapper.mapping.localize import localize
    from mfp_mapper.mapping.replay import ReplayError
    from mfp_mapper.sources.opener import open_recording

    out = Path(args.poses_out)
    check_pose_outputs(
        out,
        {"the map": args.map, "the input": args.input, "the --poses file": args.poses,
         "the --times file": args.times},
    )  # fmt: skip
    align = align_options(args)
    mapper = load_map_arg(args.map)
    if not mapper.num_voxels:
        raise CliError(f"{args.map}: the map is empty: nothing to localize against")
    try:
        opts = options_from_args(args).but(**input_options(args), resolution=mapper.resolution)
        with open_recording(args.input, opts, args.poses, args.times, warn) as recording:
            result = localize(mapper, recording, opts, align=align, log=warn)
    except ReplayError as err:
        raise CliError(f"{err} (no poses written)") from None
    except ValueError as err:  # invalid settings
        raise CliError(f"{err} (no poses written)") from None
    if not result.scans:
        raise CliError(f"{args.input}: no scan had an initial pose (no poses written)")
    write_results(result, out)
    print_summary(result, out)
    return 0


def check_pose_outputs(out: Path, inputs: dict[str, Any]) -> None:
    """CliError, before any work, when the poses or their confidence file (``out`` +
    ``.confidence.jsonl``) cannot be written, or would replace one of ``inputs`` (what the
    command reads or writes besides, by role: ``{"the map": path, ...}``; None: not given)."""
    import os

    from mfp_mapper.outputs.pose_output import confidence_path_for

    for path in (out, confidence_path_for(out)):
        check_writable(path)
        for role, other in inputs.items():
            if other is None or not str(other):
                continue
            same = os.path.realpath(path) == os.path.realpath(other)
            if not same and path.exists() and os.path.exists(other):
                same = os.path.samefile(path, other)
            if same:
                raise CliError(f"{path} is {role}: it would be replaced (nothing written)")


def write_results(result: Any, out: Path) -> None:
    """The poses (TUM) and their confidence file, each atomically; CliError when the disk
    refuses one."""
    try:
        _write_results(result, out)
    except OSError as err:
        raise CliError(f"{out}: cannot write the poses ({err.strerror or err})") from None


def _write_results(result: Any, out: Path) -> None:
    import numpy as np

    from mfp_mapper.outputs.pose_output import (
        confidence_path_for,
        write_confidence,
        write_tum_poses,
    )

    scans = result.scans
    write_tum_poses(
        out,
        [s.stamp for s in scans],
        np.array([s.position for s in scans]).reshape(-1, 3),
        np.array([s.quaternion for s in scans]).reshape(-1, 4),
    )
    write_confidence(confidence_path_for(out), [s.row() for s in scans])


def print_summary(result: Any, out: Path) -> None:
    import numpy as np

    aligned = [s for s in result.scans if s.alignment is not None]
    print(f"scans        {len(result.scans)} ({len(aligned)} aligned, {result.accepted} "
          "corrections accepted)")  # fmt: skip
    for s in result.scans:
        al = s.alignment
        if al is None:
            print(f"  {s.stamp:.6f}  not aligned: {s.note}")
        elif al.accepted:
            print(f"  {s.stamp:.6f}  moved {al.shift_m:.3f} m {al.angle_deg:.2f} deg, gain "
                  f"{s.exact_gain:.1f} nats, std {np.max(al.sigma[:3]):.3f} m "
                  f"{np.max(al.sigma[3:]):.2f} deg, {s.seconds:.2f} s")  # fmt: skip
        else:
            print(f"  {s.stamp:.6f}  kept its pose: {al.reason}")
    print(f"poses        {out}")
