"""``mfp-mapper evaluate``: a map of a simulated bag against its truth."""

from __future__ import annotations

import argparse
import json
from typing import Any

from mfp_mapper.cli.common import CliError, check_outputs, jsonable, load_map_arg
from mfp_mapper.mapio.atomic import write_text_atomic


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``evaluate`` subcommand's arguments."""
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
    return p


def run(args: argparse.Namespace) -> int:
    from mfp_mapper.outputs.evaluate import evaluate_map
    from mfp_mapper.sources.simulate import SimulationError, load_truth

    if not 0 < args.level < 1:
        raise CliError(f"--level must lie in (0, 1), got {args.level}")
    check_outputs(args.json)
    mapper = load_map_arg(args.map)
    try:
        truth = load_truth(args.truth)
    except SimulationError as err:
        raise CliError(str(err)) from None
    ev = evaluate_map(mapper, truth, args.level, args.min_evidence)
    print(ev.format())
    if args.json:
        write_text_atomic(args.json, json.dumps(jsonable(ev.to_json()), indent=2) + "\n")
    return 0
