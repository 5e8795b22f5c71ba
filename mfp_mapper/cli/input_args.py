"""Command-line flags for what a replay reads (scan folders, poses, KISS-ICP) and which
clouds it maps (``--start``/``--end``; ``--every`` comes from the settings schema), for
``mfp-mapper replay``.

``--start`` and ``--end`` take one of:

- ``12.5``: seconds after the recording's first cloud (``ReplaySection.start_offset``);
- ``@1700000012.5``: an absolute cloud stamp in seconds (``ReplaySection.start``);
- ``#40``: a cloud's position in the recording, 0 = the first (``start_index``).

The window is half-open: ``[start, end)``. ``--every N`` then maps one cloud in N of it.
"""

from __future__ import annotations

import argparse
from typing import Any

WINDOW_HELP = "N s after the first cloud, @STAMP (absolute s) or #INDEX (0 = first cloud)"


def parse_bound(text: str) -> tuple[str, float]:
    """``("offset"|"stamp"|"index", value)`` of a ``--start``/``--end`` value."""
    try:
        if text.startswith("#"):
            index = int(text[1:])
            if index < 0:
                raise ValueError
            return "index", index
        if text.startswith("@"):
            return "stamp", float(text[1:])
        return "offset", float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected seconds (12.5), @STAMP (@1700000012.5) or #INDEX (#40)"
        ) from None


def add_input_arguments(p: argparse.ArgumentParser, per_input: bool = False) -> None:
    """The replay's flags for folders, poses, odometry and the cloud selection.
    ``per_input``: ``--poses`` may be given once per input (a list, see ``per_input_values``)."""
    p.add_argument(
        "--poses",
        metavar="FILE|identity",
        action="append" if per_input else "store",
        help="scan folder: poses file (KITTI 3x4 per scan, TUM 't x y z qx qy qz qw', "
        "odometry .csv) or 'identity' (every scan at the origin); a bag: TUM or odometry "
        ".csv, matched by stamp, instead of its own odometry or /tf"
        + ("; once for every input, or once per input in their order" if per_input else ""),
    )
    p.add_argument("--times", metavar="FILE", help="scan folder: one stamp (s) per scan")
    p.add_argument(
        "--odometry",
        choices=("kiss-icp",),
        help="estimate the poses from the clouds (bag or folder); needs the kiss-icp package",
    )
    p.add_argument("--start", type=parse_bound, help=f"first cloud mapped: {WINDOW_HELP}")
    p.add_argument("--end", type=parse_bound, help=f"end of the clouds mapped: {WINDOW_HELP}")


def input_options(args: argparse.Namespace) -> dict[str, Any]:
    """ReplayOptions fields from the flags of ``add_input_arguments``."""
    values: dict[str, Any] = {"odometry": args.odometry} if args.odometry else {}
    for bound, given in (("start", args.start), ("end", args.end)):
        if given is None:
            continue
        kind, value = given
        if kind == "index":
            values[f"{bound}_index"] = int(value)
        elif kind == "stamp":
            values[bound] = value
        else:
            values[f"{bound}_offset"] = value
    return values


def per_input_values(flag: str, given: list[Any] | None, inputs: int) -> list[Any]:
    """A flag given once per input (``action="append"``): not given -> None for each input,
    once -> the same for each, once per input -> in order; ValueError otherwise."""
    if not given:
        return [None] * inputs
    if len(given) == 1:
        return given * inputs
    if len(given) != inputs:
        raise ValueError(f"{flag} given {len(given)} times for {inputs} inputs: once, or once each")
    return list(given)
