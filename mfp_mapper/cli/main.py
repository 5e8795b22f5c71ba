"""``mfp-mapper``: the offline command line (bags, the built-in example, exports, pictures).

One module per subcommand (``COMMANDS``: ``cli.replay``, ``cli.merge``, ``cli.simulate``,
``cli.export``, ``cli.render``, ``cli.plot_convergence``, ``cli.query``, ``cli.evaluate``,
``cli.score``, ``cli.fit_prior``, ``cli.call``, ``cli.demo``), each with ``add_parser(sub)``
and ``run(args)``; the work is in mapping/, sources/ and outputs/. The modules import no
numpy at the top, and a command imports only its own module, so ``mfp-mapper --help`` and
``mfp-mapper query`` stay cheap.
Exit status: 0 success, 1 the job failed (bad bag, bad map file...), 2 bad usage,
130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
from collections.abc import Sequence
from typing import Any

from mfp_mapper.cli.common import CliError, error
from mfp_mapper.config.names import VERSION

COMMANDS = {
    "replay": ("replay", "map ROS 1 .bag or ROS 2 (sqlite3/mcap) bags into one map"),
    "localize": ("localize", "refine the poses of a recording's scans against a fixed map"),
    "merge": ("merge", "merge maps exactly (.npz files or tiled maps) into one"),
    "simulate": ("simulate", "write the built-in example bag with its ground truth"),
    "export": (
        "export",
        "write a map as PLY (CloudCompare), a Nav2 map (PGM + YAML) or an mcap bag",
    ),
    "render": ("render", "draw a map: top-down DoO and std, slice, histogram"),
    "plot-convergence": (
        "plot_convergence",
        "one cell probed repeatedly: DoO vs classic occupancy (Fig. 9)",
    ),
    "query": (
        "query",
        "statistics of the voxels at points X Y Z ..., clear probability of segments",
    ),
    "evaluate": ("evaluate", "compare a map of a simulated bag with its truth"),
    "score": ("score", "how well a map predicts held-out lidar rays, against classic occupancy"),
    "fit-prior": (
        "fit_prior",
        "empirical Bayes: the Gamma prior that best predicts held-out scans",
    ),
    "call": (
        "call",
        "call a running node's services: status, query, segment, getmap, save, reset, "
        "clear-bbox, lifecycle",
    ),
    "demo": ("demo", "simulate -> replay -> render -> evaluate the built-in example"),
}
"""Each subcommand: its module in ``mfp_mapper.cli`` and the line ``--help`` lists (the
module's own ``help``; ``test_cli.py`` checks they agree), in the order listed. Only the
module of the command run is imported (``build_parser``): ``mfp-mapper query`` loads
neither the settings schema nor the bag readers the others need."""

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
  mfp-mapper query map.npz --segment 0 0 1  20 0 1     # is this line of sight clear?
  mfp-mapper call status                              # a running node's counters
  mfp-mapper call segment 0 0 1  20 0 1               # ask a running node
  mfp-mapper evaluate map.npz sim_bag.truth.json
  mfp-mapper score --split even-odd run.bag --json score.json   # held-out likelihood
  mfp-mapper fit-prior run.bag                        # the prior that predicts best
  mfp-mapper localize map.npz scans/ --poses guess.tum --poses-out refined.tum
"""


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every subcommand; each sets ``args.run``, its command. With
    ``command``, only that subcommand's module is imported and its arguments built (with
    "", none): the others are listed by name and help line alone (what ``--help`` shows
    of them)."""
    parser = argparse.ArgumentParser(
        prog="mfp-mapper",
        description="Offline tools of mfp_mapper, the mean-free-path lidar mapper: replay "
        "bags into maps, simulate the built-in example, export and draw maps.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {VERSION}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module_name, summary) in COMMANDS.items():
        if command is None or name == command:
            module = importlib.import_module(f"mfp_mapper.cli.{module_name}")
            module.add_parser(sub).set_defaults(run=module.run)
        else:
            sub.add_parser(name, help=summary)
    return parser


def command_of(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names: its first word not an option (``mfp-mapper`` takes
    no option with a value before it); None when there is none."""
    return next((word for word in argv if not word.startswith("-")), None)


class Terminated(BaseException):
    """Raised by the SIGTERM handler: ends the command as Ctrl-C does (cleanup runs, nothing
    half-written stays). Not a ``KeyboardInterrupt``: CPython 3.11 marks one that passes
    through ``exec`` of a string (dataclasses, rosbags' type store) as unhandled and then
    exits by SIGINT (status -2) even after ``main`` caught it and returned 130."""


def _terminated(signum: int, _frame: Any) -> None:
    raise Terminated


def main(argv: Sequence[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(command_of(words) or "").parse_args(words)
    try:
        previous = signal.signal(signal.SIGTERM, _terminated)
    except ValueError:  # not the main thread: leave signals alone
        previous = None
    try:
        return int(args.run(args))
    except CliError as err:
        error(str(err))
        return 1
    except ValueError as err:  # a damaged tile found while a command runs
        from mfp_mapper.mapio.mapfile import MapFileError

        if not isinstance(err, MapFileError):
            raise
        error(f"{err} (nothing written)")
        return 1
    except (KeyboardInterrupt, Terminated):
        error("interrupted (nothing written for the step in progress)")
        return 130
    except BrokenPipeError:
        return 1
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
