"""``mfp-mapper``: the offline command line (bags, the built-in example, exports, pictures).

One module per subcommand (``cli.replay``, ``cli.merge``, ``cli.simulate``, ``cli.export``,
``cli.render``, ``cli.plot_convergence``, ``cli.query``, ``cli.evaluate``, ``cli.score``,
``cli.fit_prior``, ``cli.call``, ``cli.demo``), each
with ``add_parser(sub)`` and ``run(args)``; the work is in mapping/, sources/ and outputs/.
The modules import no numpy at the top, so ``mfp-mapper --help`` stays cheap.
Exit status: 0 success, 1 the job failed (bad bag, bad map file...), 2 bad usage,
130 interrupted.
"""

from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Sequence
from typing import Any

from mfp_mapper.cli import (
    call,
    demo,
    evaluate,
    export,
    fit_prior,
    localize,
    merge,
    plot_convergence,
    query,
    render,
    replay,
    score,
    simulate,
)
from mfp_mapper.cli.common import CliError, error
from mfp_mapper.config.names import VERSION

COMMANDS = (
    replay, localize, merge, simulate, export, render, plot_convergence, query, evaluate, score,
    fit_prior, call, demo,
)  # fmt: skip
"""The subcommand modules, in the order ``--help`` lists them."""

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


def build_parser() -> argparse.ArgumentParser:
    """The parser of every subcommand; each sets ``args.run``, its command."""
    parser = argparse.ArgumentParser(
        prog="mfp-mapper",
        description="Offline tools of mfp_mapper, the mean-free-path lidar mapper: replay "
        "bags into maps, simulate the built-in example, export and draw maps.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {VERSION}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS:
        command.add_parser(sub).set_defaults(run=command.run)
    return parser


class Terminated(BaseException):
    """Raised by the SIGTERM handler: ends the command as Ctrl-C does (cleanup runs, nothing
    half-written stays). Not a ``KeyboardInterrupt``: CPython 3.11 marks one that passes
    through ``exec`` of a string (dataclasses, rosbags' type store) as unhandled and then
    exits by SIGINT (status -2) even after ``main`` caught it and returned 130."""


def _terminated(signum: int, _frame: Any) -> None:
    raise Terminated


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
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
