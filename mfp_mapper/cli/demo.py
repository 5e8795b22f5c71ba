"""``mfp-mapper demo``: simulate -> replay -> render -> evaluate the built-in example."""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import CliError, check_folder_writable, nonneg_int, positive, warn
from mfp_mapper.config.names import BAG_FORMATS


def run_demo(
    output: str | Path,
    resolution: float = 0.2,
    scans: int = 120,
    fmt: str = "mcap",
    seed: int = 0,
    progress: bool = True,
    warn: Callable[[str], None] | None = None,
) -> None:
    """Run the whole chain into ``output`` and print what came out (ReplayError if the
    replay fails)."""
    from mfp_mapper.mapio.atomic import write_text_atomic
    from mfp_mapper.mapio.loading import save_map
    from mfp_mapper.mapping.replay import ReplayOptions, replay
    from mfp_mapper.outputs.evaluate import evaluate_map
    from mfp_mapper.outputs.export import export_ply
    from mfp_mapper.outputs.render import plot_convergence, render_map
    from mfp_mapper.outputs.report import jsonable, simulation_lines
    from mfp_mapper.sources.simulate import preset, simulate

    t0 = time.perf_counter()
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    bag = out / ("example.bag" if fmt == "ros1" else "example_bag")
    print(f"== 1/4 simulate the built-in example -> {bag}")
    cfg = replace(preset("demo"), scans=scans, seed=seed)
    sim = simulate(bag, cfg, fmt, overwrite=True)
    for line in simulation_lines(sim):
        print(line)
    print(f"== 2/4 replay it into a {resolution:g} m map")
    result = replay(bag, ReplayOptions.of(resolution=resolution), progress, warn)
    map_path = out / "map.npz"
    save_map(result.mapper, map_path)
    print(result.summary.format())
    print(f"map          {map_path}")
    print("== 3/4 pictures")
    pics = out / "pictures"
    rendered = render_map(result.mapper, pics, slice_y=0.0)
    files = [*rendered.files, plot_convergence(pics)]
    ply = out / "map.ply"
    count = export_ply(result.mapper, ply, min_doo=0.05)
    print(f"top-down band {rendered.band[0]:.2f}..{rendered.band[1]:.2f} m, slice at y = 0")
    for f in files:
        print(f"wrote {f}")
    print(f"wrote {ply} ({count:,} voxels with DoO >= 0.05, for CloudCompare/Open3D)")
    print("== 4/4 evaluate against the ground truth")
    ev = evaluate_map(result.mapper, sim.truth)
    write_text_atomic(out / "evaluation.json", json.dumps(jsonable(ev.to_json()), indent=2) + "\n")
    print(ev.format())
    print()
    print("what it found:")
    for m in ev.media:
        if m.voxels_observed:
            verdict = (
                "ok"
                if abs(m.pooled_relative_error) < 0.05 and 0.85 <= m.coverage <= 0.95
                else "CHECK"
            )
            print(
                f"  {m.name}: estimated extinction {m.pooled:.3f} /m vs true {m.extinction:g} /m; "
                f"90% intervals hold the truth in {100 * m.coverage:.0f}% of "
                f"{m.voxels_observed} voxels [{verdict}]"
            )
    print(
        f"  free air: {ev.free_air.voxels_with_returns} of {ev.free_air.voxels_observed:,} "
        "observed voxels hold a return"
    )
    print(f"pictures are in {pics.resolve()}/ (start with doo_topdown.png and slice.png)")
    print(f"done in {time.perf_counter() - t0:.1f} s")


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``demo`` subcommand's arguments."""
    p = sub.add_parser(
        "demo",
        help="simulate -> replay -> render -> evaluate the built-in example",
        description="Run the whole chain on the built-in example and say what came out.",
    )
    p.add_argument(
        "-o",
        "--output",
        default="example_output",
        help="directory for everything (default ./example_output)",
    )
    p.add_argument("--resolution", type=positive, default=0.2, help="voxel edge (default 0.2)")
    p.add_argument("--scans", type=nonneg_int, default=120, help="rotations (default 120)")
    p.add_argument("--format", choices=BAG_FORMATS, default="mcap")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def run(args: argparse.Namespace) -> int:
    from mfp_mapper.mapping.replay import ReplayError

    check_folder_writable(Path(args.output))
    try:
        run_demo(args.output, args.resolution, args.scans, args.format, args.seed,
                 progress=not args.quiet, warn=warn)  # fmt: skip
    except ReplayError as err:
        raise CliError(str(err)) from None
    return 0
