"""``mfp-mapper score``: how well maps predict held-out lidar rays (``outputs.score``),
against classic occupancy."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import CliError, check_outputs, jsonable, load_map_arg, warn
from mfp_mapper.cli.input_args import add_input_arguments
from mfp_mapper.cli.replay import replay_options
from mfp_mapper.config.replay_options import add_replay_flags
from mfp_mapper.mapio.atomic import write_text_atomic


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``score`` subcommand's arguments."""
    p = sub.add_parser(
        "score",
        help="how well a map predicts held-out lidar rays, against classic occupancy",
        description="Score lidar scans with a map: log-likelihood per ray, log loss, Brier, "
        "calibration (ECE, table, reliability diagram). MAP INPUT...: every scan of the "
        "inputs against the map(s). --split even-odd INPUT: map the 1st, 3rd... scan, score "
        "the others, with classic occupancy (OctoMap log-odds) built from the same training "
        "rays (paper's a, b and fitted a, b). --split shots: within each scan, even rays map, "
        "odd rays are scored. Lists (--resolution 0.1,0.2) give one row each.",
    )
    p.add_argument(
        "paths", nargs="+", metavar="MAP|INPUT",
        help="maps (.npz, tiled map directories) then recordings (bags, scan folders); "
        "with --split: one recording, no map",
    )  # fmt: skip
    p.add_argument("--split", choices=("even-odd", "shots"), help="score held-out data")
    p.add_argument("--json", help="write the scores as JSON here (reliability PNG beside it)")
    p.add_argument("--plot", help="write the reliability diagram here (PNG)")
    p.add_argument("--no-classic", action="store_true", help="skip classic occupancy")
    p.add_argument("--config", help="a node parameter file (read as the node reads it)")
    add_replay_flags(p, lists=("resolution", "decay_time"))
    add_input_arguments(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")

    return p


def _is_map(path: str) -> bool:
    p = Path(path)
    return (p.suffix == ".npz" and p.is_file()) or (p / "index.json").is_file()


def _score_rows(args: argparse.Namespace) -> list[tuple[str, argparse.Namespace]]:
    """One (label, flags with single values) per combination of --resolution and
    --decay-time lists."""
    import itertools

    resolutions = args.resolution or [None]
    decays = args.decay_time or [None]
    rows = []
    for res, decay in itertools.product(resolutions, decays):
        label = []
        if args.resolution and len(args.resolution) > 1:
            label.append(f"resolution {res:g} m")
        if args.decay_time and len(args.decay_time) > 1:
            label.append(f"decay_time {decay:g} s")
        rows.append((", ".join(label), argparse.Namespace(**{
            **vars(args), "resolution": res, "decay_time": decay,
        })))  # fmt: skip
    return rows


def _priors(main: Any) -> dict[str, Any]:
    from mfp_mapper.core.model import UNIFORM

    return {"model": main} if main.is_uniform else {"model": main, "uniform_prior": UNIFORM}


def _map_prior(args: argparse.Namespace, opts: Any, mapper: Any) -> Any:
    """A map's own prior, or what the prior flags make of it: --prior-shape and --prior-rate
    replace that number, --prior-scale the family's (at the map's resolution) for the
    numbers not given."""
    from mfp_mapper.core.model import resolve_prior

    given = [getattr(args, k) is not None for k in ("prior_shape", "prior_rate", "prior_scale")]
    if not any(given):
        return mapper.prior
    # with --prior-scale, a number not given is 0: the family's
    shape = opts.map.prior_shape if given[0] else (0.0 if given[2] else mapper.prior.shape)
    rate = opts.map.prior_rate if given[1] else (0.0 if given[2] else mapper.prior.rate)
    return resolve_prior(mapper.resolution, shape, rate, opts.map.prior_scale)


def run(args: argparse.Namespace) -> int:
    from contextlib import ExitStack

    from mfp_mapper.core.model import resolve_prior
    from mfp_mapper.mapio.mapfile import MapFileError
    from mfp_mapper.mapping.replay import ReplayError
    from mfp_mapper.outputs import score
    from mfp_mapper.sources.opener import open_recording

    maps = [p for p in args.paths if _is_map(p)]
    inputs = [p for p in args.paths if not _is_map(p)]
    if not inputs:
        raise CliError("score needs a recording (bag or scan folder) to score")
    if args.split and maps:
        raise CliError("--split builds its own map from the recording: give no map")
    if args.split and len(inputs) != 1:
        raise CliError("--split takes one recording")
    if not args.split and not maps:
        raise CliError("give a map to score against, or --split even-odd on one recording")
    if maps and (args.resolution or args.decay_time):
        raise CliError("--resolution/--decay-time rows need --split (a map has its own)")
    plot = args.plot or (str(Path(args.json).with_suffix(".png")) if args.json else None)
    check_outputs(args.json, plot)
    log = None if args.quiet else warn
    results: list[tuple[str, dict[str, Any]]] = []
    rows = _score_rows(args)
    try:
        with ExitStack() as stack:
            opened = replay_options(rows[0][1])  # the rows differ in map settings only
            recordings = [
                stack.enter_context(open_recording(p, opened, args.poses, args.times, log))
                for p in inputs
            ]
            if args.split:
                for label, row_args in rows:
                    opts = replay_options(row_args)
                    m = opts.map
                    prior = resolve_prior(m.resolution, m.prior_shape, m.prior_rate, m.prior_scale)
                    scorer = score.score_split(
                        recordings[0], opts, args.split, _priors(prior),
                        classic=not args.no_classic, progress=not args.quiet, log=log,
                    )  # fmt: skip
                    results.append((label or f"resolution {opts.map.resolution:g} m", score.report(
                        scorer, "model"
                    )))  # fmt: skip
            else:
                opts = replay_options(args)
                for path in maps:
                    mapper = load_map_arg(path)
                    mapper.prior = _map_prior(args, opts, mapper)
                    scorer = score.score_map(
                        mapper, recordings, opts, _priors(mapper.prior), progress=not args.quiet,
                        log=log,
                    )  # fmt: skip
                    results.append((path, score.report(scorer, "model")))
    except (ReplayError, MapFileError, ValueError) as err:
        raise CliError(str(err)) from None
    if not any(rep["rays"] for _, rep in results):
        raise CliError("no ray was scored (every scan dropped, or no ray usable): no score")
    for label, rep in results:
        for line in score.summary_lines(rep, f"{label}: " if len(results) > 1 else ""):
            print(line)
    if len(results) > 1:
        refl = any("reflectivity" in rep for _, rep in results)  # the reflectivity field
        extra = f" {'refl/return':>11} {'refl gain':>9}" if refl else ""
        print(f"{'row':<28} {'loglik/ray':>11} {'density/ray':>11} {'ece':>8}{extra}")
        for label, rep in results:
            cells = ""
            if refl and "reflectivity" in rep:
                r = rep["reflectivity"]
                cells = f" {r['log_likelihood_per_return']:>11.4f} {r['gain_per_return']:>+9.4f}"
            print(
                f"{label:<28} {rep['log_likelihood_per_ray']:>11.4f} "
                f"{rep['log_density_per_ray']:>11.4f} {rep['ece']:>8.5f}{cells}"
            )
    single = results[0][1] if len(results) == 1 else None
    if args.json:
        doc = single if single is not None else {
            "rows": [{"label": label, **rep} for label, rep in results]
        }  # fmt: skip
        write_text_atomic(args.json, json.dumps(jsonable(doc), indent=2) + "\n")
        print(f"wrote {args.json}")
    if plot:
        for k, (label, rep) in enumerate(results):
            base = Path(plot)
            out = base if len(results) == 1 else base.with_stem(f"{base.stem}_{k}")
            print(f"wrote {score.plot_reliability(rep, out, label)}")
    return 0
