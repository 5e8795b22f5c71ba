"""``mfp-mapper fit-prior``: the empirical-Bayes Gamma prior on the extinction
(``outputs.score.fit_prior``), and over several recordings the scale of the family of priors
that follows the voxel size (``outputs.score.fit_scale``, ``leave_one_out``)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from mfp_mapper.cli.common import CliError, check_outputs, jsonable, warn
from mfp_mapper.cli.input_args import add_input_arguments, per_input_values
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
        "holds out (odd scans or rays) is never read. Several inputs (and --resolution "
        "0.1,0.2): also the scale a of the family shape = a * resolution, rate = a * "
        "resolution / 2 fitted on all of them (prior.scale), and a leave-one-recording-out "
        "table. --poses and --split: once for all inputs, or once per input in order "
        "(--poses '': a bag's own poses).",
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="recordings (bags, scan folders)")
    p.add_argument(
        "--split", choices=("even-odd", "shots"), action="append",
        help="even-odd (default) or shots; once for all inputs or once per input",
    )  # fmt: skip
    p.add_argument("--json", help="write the fit (shape, rate, gain; scale, table) as JSON here")
    p.add_argument("--config", help="a node parameter file (read as the node reads it)")
    add_replay_flags(p, lists=("resolution",))
    add_input_arguments(p, per_input=True)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")

    return p


def run(args: argparse.Namespace) -> int:
    from mfp_mapper.core.model import UNIFORM, family_prior
    from mfp_mapper.mapping.replay import ReplayError
    from mfp_mapper.outputs import score
    from mfp_mapper.sources.opener import open_recording

    check_outputs(args.json)
    log = None if args.quiet else warn
    try:
        poses = [
            p or None  # --poses '': this input brings its own (a bag)
            for p in per_input_values("--poses", args.poses, len(args.inputs))
        ]
        splits = per_input_values("--split", args.split, len(args.inputs))
    except ValueError as err:
        raise CliError(str(err)) from None
    splits = [split or "even-odd" for split in splits]
    resolutions = args.resolution or [None]
    samples: list[score.RecordingSample] = []
    fits: list[score.FittedPrior] = []
    try:
        for path, pose_file, split in zip(args.inputs, poses, splits, strict=True):
            for resolution in resolutions:
                flags = argparse.Namespace(**{**vars(args), "resolution": resolution})
                opts = replay_options(flags)
                sample = score.EventSample()
                with open_recording(path, opts, pose_file, args.times, log) as recording:
                    score.score_split(
                        recording, opts, split, {"uniform_prior": UNIFORM}, classic=False,
                        sample=sample, within_training=True, progress=not args.quiet, log=log,
                    )  # fmt: skip
                try:
                    fits.append(score.fit_prior(sample))
                except ValueError as err:
                    raise ValueError(f"{path} at {opts.map.resolution:g} m: {err}") from None
                samples.append(score.RecordingSample(path, opts.map.resolution, sample))
        scale = score.fit_scale(samples)
        several = len(args.inputs) > 1
        table = (
            score.leave_one_out(samples, {k: f.prior for k, f in enumerate(fits)})
            if several
            else []
        )
    except (ReplayError, ValueError) as err:
        raise CliError(str(err)) from None
    for r, fitted in zip(samples, fits, strict=True):
        label = f"{r.recording} at {r.resolution:g} m: " if len(samples) > 1 else ""
        _print_fit(label, fitted, splits[args.inputs.index(r.recording)])
    family = [r.per_ray(family_prior(scale, r.resolution)) for r in samples]
    print(
        f"family shape = a * resolution, rate = a * resolution / 2: a = {scale:.5g} per metre "
        f"fitted on {len(samples)} sample(s)"
    )
    for r, fitted, value in zip(samples, fits, family, strict=True):
        prior = family_prior(scale, r.resolution)
        own = fitted.log_likelihood_per_ray
        print(
            f"  {r.recording} at {r.resolution:g} m: shape {prior.shape:.4g}, rate "
            f"{prior.rate:.4g} m, log-likelihood per ray {value:.4f} (own fit {own:.4f}, "
            f"{100 * (own - value) / abs(own):.1f}% better)"
        )
    if table:
        print("leave one recording out (a fitted on the others, scored on it):")
        print(f"  {'recording':<32} {'res':>5} {'a':>8} {'family':>9} {'own':>9} {'gap':>6} "
              f"{'uniform':>9}")  # fmt: skip
        for row in table:
            print(
                f"  {row.recording:<32} {row.resolution:>5g} {row.scale:>8.4g} "
                f"{row.family:>9.4f} {row.own:>9.4f} {100 * row.gap:>5.1f}% {row.uniform:>9.4f}"
            )
    print(f"parameter file (the family):\n/**:\n  ros__parameters:\n    prior.scale: {scale:.4g}")
    if args.json:
        doc: dict[str, Any] = fits[0].json() if len(samples) == 1 else {}
        doc["scale"] = scale
        doc["samples"] = [
            {"recording": r.recording, "resolution": r.resolution, **f.json(),
             "family_log_likelihood_per_ray": v}
            for r, f, v in zip(samples, fits, family, strict=True)
        ]  # fmt: skip
        if table:
            doc["leave_one_out"] = [row.json() for row in table]
        write_text_atomic(args.json, json.dumps(jsonable(doc), indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


def _print_fit(label: str, fitted: Any, split: str) -> None:
    print(
        f"{label}prior fitted on {fitted.rays:,} held-out rays of the training part of the "
        f"{split} split ("
        f"{fitted.events:,} events sampled): shape {fitted.shape:.6g}, rate {fitted.rate:.6g} m"
    )
    print(
        f"{label}held-out log-likelihood per ray {fitted.log_likelihood_per_ray:.4f} "
        f"(uniform prior {fitted.uniform_log_likelihood_per_ray:.4f}): "
        f"{100 * fitted.gain:+.1f}%"
    )
    if not label:
        print("parameter file:\n" + fitted.parameter_snippet(), end="")
        print(f"flags: --prior-shape {fitted.shape:.6g} --prior-rate {fitted.rate:.6g}")
