"""``mfp-mapper fit-prior``: the empirical-Bayes Gamma prior on the extinction
(``outputs.score.fit_prior``)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from mfp_mapper.cli.common import CliError, check_outputs, jsonable, warn
from mfp_mapper.cli.input_args import add_input_arguments
from mfp_mapper.cli.replay import replay_options
from mfp_mapper.config.replay_options import add_replay_flags
from mfp_mapper.mapio.atomic import write_text_atomic


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``fit-prior`` subcommand's arguments."""
    p = sub.add_parser(
        "fit-prior",
        help="empirical Bayes: the Gamma prior that best predicts held-out scans",
        description="Empirical Bayes (docs/scoring.md): within the TRAINING part of --split "
        "(what `score --split` maps), map one half and choose the Gamma(shape, rate) prior "
        "on the extinction that maximises the likelihood of the other half. even-odd: "
        "scans 0, 4, 8... map, 2, 6, 10... fit; shots: rays likewise. What `score --split` "
        "holds out (odd scans or rays) is never read.",
    )
    p.add_argument("input", metavar="INPUT", help="a recording (bag or scan folder)")
    p.add_argument("--split", choices=("even-odd", "shots"), default="even-odd")
    p.add_argument("--json", help="write shape, rate, gain as JSON here")
    p.add_argument("--config", help="a node parameter file (read as the node reads it)")
    add_replay_flags(p)
    add_input_arguments(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")

    return p


def run(args: argparse.Namespace) -> int:
    from mfp_mapper.core.model import UNIFORM
    from mfp_mapper.mapping.replay import ReplayError
    from mfp_mapper.outputs import score
    from mfp_mapper.sources.opener import open_recording

    check_outputs(args.json)
    log = None if args.quiet else warn
    try:
        opts = replay_options(args)
        sample = score.EventSample()
        with open_recording(args.input, opts, args.poses, args.times, log) as recording:
            score.score_split(
                recording, opts, args.split, {"uniform_prior": UNIFORM}, classic=False,
                sample=sample, within_training=True, progress=not args.quiet, log=log,
            )  # fmt: skip
        fitted = score.fit_prior(sample)
    except (ReplayError, ValueError) as err:
        raise CliError(str(err)) from None
    print(
        f"prior fitted on {fitted.rays:,} held-out rays of the training part of the "
        f"{args.split} split ("
        f"{fitted.events:,} events sampled): shape {fitted.shape:.6g}, rate {fitted.rate:.6g} m"
    )
    print(
        f"held-out log-likelihood per ray {fitted.log_likelihood_per_ray:.4f} "
        f"(uniform prior {fitted.uniform_log_likelihood_per_ray:.4f}): "
        f"{100 * fitted.gain:+.1f}%"
    )
    print("parameter file:\n" + fitted.parameter_snippet(), end="")
    print(f"flags: --prior-shape {fitted.shape:.6g} --prior-rate {fitted.rate:.6g}")
    if args.json:
        write_text_atomic(args.json, json.dumps(jsonable(fitted.json()), indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0
