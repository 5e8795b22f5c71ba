"""``mfp-mapper``: the offline command line (bags, the built-in example, exports, pictures).

A thin argparse layer: the work is in mapping/, sources/ and outputs/ (replay, simulate,
export, render, evaluate).
Exit status: 0 success, 1 the job failed (bad bag, bad map file...), 2 bad usage,
130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from mfp_mapper.cli.args import build_parser as build_parser  # re-exported
from mfp_mapper.mapio.atomic import write_text_atomic


class CliError(Exception):
    """A failure to report on stderr with exit status 1."""


def _err(text: str) -> None:
    print(f"mfp-mapper: error: {text}", file=sys.stderr)


# --- commands ---------------------------------------------------------------------------


def _load_map(path: str, bounds: Any = None, lazy_tiles: bool = False) -> Any:
    """A Mapper (only ``bounds`` when given); with ``lazy_tiles``, a tiled map is opened as a
    ``TiledMap`` that reads its tiles when asked."""
    from mfp_mapper.mapio.loading import load_map
    from mfp_mapper.mapio.mapfile import MapFileError
    from mfp_mapper.mapio.tiles import TiledMap

    try:
        if lazy_tiles and Path(path).is_dir():
            return TiledMap(path)
        return load_map(path, bounds=bounds)
    except FileNotFoundError:
        raise CliError(f"{path}: no such map file") from None
    except (MapFileError, OSError, ValueError) as err:
        raise CliError(str(err)) from None


def _check_writable(path: Path, tiled_ok: bool = False) -> None:
    """CliError, before any work, when ``path`` cannot be written (no folder, read-only)."""
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise CliError(f"{path}: the folder {parent} does not exist")
    target = path if path.is_dir() else parent
    if not os.access(target, os.W_OK | os.X_OK):
        raise CliError(f"{path}: cannot write in {target} (read-only or not permitted)")
    if tiled_ok and path.suffix != ".npz":
        from mfp_mapper.mapio.mapfile import MapFileError
        from mfp_mapper.mapio.tiles import check_tiled_output

        try:
            check_tiled_output(path)
        except MapFileError as err:
            raise CliError(str(err)) from None
    elif path.is_dir():
        raise CliError(f"{path} is a directory, expected a file name")


def _check_folder_writable(folder: Path) -> None:
    """CliError when ``folder`` (made if missing) could not be written in."""
    existing = folder.absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise CliError(f"{folder}: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise CliError(f"{folder}: cannot write in {existing} (read-only or not permitted)")


def replay_options(args: argparse.Namespace) -> Any:
    """ReplayOptions from the schema defaults, ``--config``, the flags given and the
    input flags (``cli.input_args``)."""
    from dataclasses import replace

    from mfp_mapper.cli.input_args import input_options
    from mfp_mapper.config.replay_options import options_from_args

    return replace(options_from_args(args), **input_options(args))


def cmd_replay(args: argparse.Namespace) -> int:
    from mfp_mapper.mapping.folder_replay import replay_folder
    from mfp_mapper.mapping.replay import ReplayError, replay
    from mfp_mapper.sources.scan_folder import is_scan_folder

    out = Path(args.output)
    _check_writable(out, tiled_ok=True)
    fleet = any(
        getattr(args, k) is not None for k in ("workers", "scheduler", "chunk_seconds")
    ) or (len(args.inputs) > 1)
    if fleet:
        return cmd_replay_fleet(args, out)
    try:
        opts = replay_options(args)
        if is_scan_folder(args.inputs[0]):
            result = replay_folder(
                args.inputs[0], args.poses, opts, args.times, progress=not args.quiet, log=_warn
            )
        elif args.poses is not None or args.times is not None:
            raise ReplayError(
                f"{args.inputs[0]}: --poses and --times are for folders of scan files"
            )
        else:
            result = replay(args.inputs[0], opts, progress=not args.quiet, log=_warn)
    except ReplayError as err:
        raise CliError(f"{err} (no map written)") from None
    except ValueError as err:  # invalid mapper settings
        raise CliError(f"{err} (no map written)") from None
    if out.suffix == ".npz":
        from mfp_mapper.mapio.loading import save_map

        save_map(result.mapper, out)
    else:
        from mfp_mapper.mapio.mapfile import map_arrays
        from mfp_mapper.mapio.tiles import write_tiled

        write_tiled(out, map_arrays(result.mapper), args.tile_blocks)
    summary = result.summary
    print(summary.format())
    print(f"map          {out} ({result.mapper.num_voxels:,} voxels, {opts.resolution:g} m)")
    if args.summary_json:
        write_text_atomic(args.summary_json, json.dumps(_jsonable(vars(summary)), indent=2) + "\n")
    return 0


def cmd_replay_fleet(args: argparse.Namespace, out: Path) -> int:
    """Several inputs (or windows, or Dask): ``mapping.fleet``."""
    from mfp_mapper.mapping.fleet import FleetOptions, default_workers, map_fleet
    from mfp_mapper.mapping.replay import ReplayError

    workers = default_workers() if args.workers == 0 else args.workers
    fleet = FleetOptions(
        workers=workers,
        scheduler=args.scheduler,
        chunk_seconds=args.chunk_seconds,
        skip_bad=args.skip_bad,
        tile_blocks=args.tile_blocks,
        work_dir=args.work_dir,
        progress=not args.quiet,
        allow_duplicates=args.allow_duplicates,
        poses=None if args.poses is None else str(args.poses),
        times=None if args.times is None else str(args.times),
    )
    try:
        opts = replay_options(args)
        result = map_fleet(args.inputs, out, opts, fleet, log=_warn)
    except (ReplayError, RuntimeError, ValueError, OSError) as err:  # FleetError, Dask...
        text = _one_line(err)
        raise CliError(text if "no map written" in text else f"{text} (no map written)") from None
    print(result.format())
    if args.summary_json:
        tasks = [
            {"task": r.task.label, "seconds": r.seconds, **_jsonable(vars(r.summary))}
            for r in result.tasks
            if r.summary is not None
        ]
        summary = {"output": str(out), "voxels": result.voxels, "tasks": tasks}
        write_text_atomic(args.summary_json, json.dumps(_jsonable(summary), indent=2) + "\n")
    return 0


def _one_line(err: BaseException) -> str:
    """The error's message on one line (a Dask or OS error may span several)."""
    text = " ".join(str(err).split()) or type(err).__name__
    if isinstance(err, OSError) and err.filename is not None and str(err.filename) not in text:
        text = f"{err.filename}: {text}"
    return text


def cmd_merge(args: argparse.Namespace) -> int:
    from mfp_mapper.mapio.mapfile import MapFileError
    from mfp_mapper.mapio.merge_files import merge_maps

    out = Path(args.output)
    _check_writable(out, tiled_ok=True)
    try:
        result = merge_maps(args.inputs, out, args.tile_blocks)
    except (MapFileError, ValueError) as err:  # MergeError is a ValueError
        raise CliError(f"{err} (nothing written)") from None
    print(f"merged {result.inputs} maps into {out}: {result.voxels:,} voxels")
    return 0


def _warn(text: str) -> None:
    print(f"mfp-mapper: {text}", file=sys.stderr)


def _jsonable(value: Any) -> Any:
    from mfp_mapper.outputs.report import jsonable

    return jsonable(value)


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


def cmd_simulate(args: argparse.Namespace) -> int:
    from mfp_mapper.sources.simulate import SimulationError, simulate

    try:
        result = simulate(args.out_bag, _sim_config(args), args.format, overwrite=args.overwrite)
    except SimulationError as err:
        raise CliError(str(err)) from None
    from mfp_mapper.outputs.report import simulation_lines

    for line in simulation_lines(result):
        print(line)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    out = Path(args.output)
    fmt = args.format or _export_format(out)
    if fmt == "ply":
        from mfp_mapper.mapio.mapfile import MapFileError
        from mfp_mapper.mapio.tiles import TiledMap
        from mfp_mapper.outputs.export import export_ply, export_ply_tiled

        _check_writable(out)
        mapper = _load_map(args.map, lazy_tiles=True)  # a tiled map: one tile at a time
        export = export_ply_tiled if isinstance(mapper, TiledMap) else export_ply
        try:
            count = export(mapper, out, args.min_doo, args.min_evidence)
        except MapFileError as err:  # a damaged tile
            raise CliError(f"{err} (nothing written)") from None
        print(f"wrote {out}: {count:,} voxels (x y z degree_of_occupancy std mean_free_path n s)")
        return 0
    _check_writable(out)
    mapper = _load_map(args.map)
    z_min, z_max = _export_band(mapper, args)
    try:
        if fmt == "nav2":
            from mfp_mapper.outputs.nav2_map import write_nav2_map

            _check_writable(out)
            nav = write_nav2_map(
                mapper, out, z_min, z_max, args.occupied_threshold, args.free_threshold
            )
            cells = nav.occupancy
            print(
                f"wrote {nav.yaml} and {nav.image}: {cells.shape[1]} x {cells.shape[0]} cells "
                f"of {nav.resolution:g} m, band z in [{z_min:.2f}, {z_max:.2f}] m; "
                f"{int((cells == 100).sum()):,} occupied, {int((cells == 0).sum()):,} free, "
                f"{int((cells == -1).sum()):,} unknown"
            )
        else:
            from mfp_mapper.outputs.mcap_export import export_mcap

            counts = export_mcap(mapper, out, z_min, z_max, args.min_doo, args.min_evidence)
            listing = ", ".join(f"{topic} ({n:,})" for topic, n in counts.items())
            print(f"wrote {out} (mcap): {listing}")
    except (ValueError, FileExistsError) as err:
        raise CliError(str(err)) from None
    return 0


def _export_format(out: Path) -> str:
    suffix = out.suffix.lower()
    if suffix == ".ply":
        return "ply"
    return "nav2" if suffix in (".yaml", ".yml", ".pgm") else "mcap"


def _export_band(mapper: Any, args: argparse.Namespace) -> tuple[float, float]:
    """The height band of a 2D output: given, else the render's band from the data."""
    from mfp_mapper.outputs.render import BAND_HEIGHT, top_down_band

    needed = args.z_min is None or args.z_max is None
    # the band comes from the occupied voxels only (filtered in compiled code)
    lo, hi = top_down_band(mapper.voxels(min_doo=0.5)) if needed else (0.0, 0.0)
    z_min = args.z_min if args.z_min is not None else lo
    z_max = (
        args.z_max
        if args.z_max is not None
        else (hi if args.z_min is None else z_min + BAND_HEIGHT)
    )
    if not (math.isfinite(z_min) and math.isfinite(z_max)):
        raise CliError("no floor found in the map: give the band with --z-min and --z-max")
    return z_min, z_max


def cmd_render(args: argparse.Namespace) -> int:
    from mfp_mapper.outputs.render import render_map

    bounds = (args.bounds[:3], args.bounds[3:]) if args.bounds else None
    _check_folder_writable(Path(args.output))
    mapper = _load_map(args.map, bounds)
    try:
        result = render_map(
            mapper,
            args.output,
            args.z_min,
            args.z_max,
            args.slice_y,
            value=args.value,
            min_evidence=args.min_evidence,
        )
    except ValueError as err:
        raise CliError(str(err)) from None
    for f in result.files:
        print(f"wrote {f}")
    return 0


def cmd_plot_convergence(args: argparse.Namespace) -> int:
    from mfp_mapper.outputs.render import plot_convergence

    print(f"wrote {plot_convergence(args.output, args.returns, args.passes)}")
    return 0


def cmd_query(args: argparse.Namespace) -> int:
    import numpy as np

    from mfp_mapper.outputs.report import query_lines, query_rows

    if len(args.coords) % 3:
        raise CliError(f"query needs X Y Z triples, got {len(args.coords)} numbers")
    from mfp_mapper.mapio.mapfile import MapFileError

    mapper = _load_map(args.map, lazy_tiles=True)  # a tiled map reads the tiles it needs
    try:
        rows = query_rows(mapper, np.asarray(args.coords, dtype=np.float64).reshape(-1, 3))
    except MapFileError as err:  # a damaged tile
        raise CliError(str(err)) from None
    if args.json:
        print(json.dumps(_jsonable(rows), indent=2))
        return 0
    print(f"map {args.map}: frame {mapper.frame_id}, {mapper.resolution:g} m voxels")
    for line in query_lines(rows):
        print(line)
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from mfp_mapper.outputs.evaluate import evaluate_map
    from mfp_mapper.sources.simulate import SimulationError, load_truth

    if not 0 < args.level < 1:
        raise CliError(f"--level must lie in (0, 1), got {args.level}")
    mapper = _load_map(args.map)
    try:
        truth = load_truth(args.truth)
    except SimulationError as err:
        raise CliError(str(err)) from None
    ev = evaluate_map(mapper, truth, args.level, args.min_evidence)
    print(ev.format())
    if args.json:
        write_text_atomic(args.json, json.dumps(_jsonable(ev.to_json()), indent=2) + "\n")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from mfp_mapper.cli.demo import run_demo
    from mfp_mapper.mapping.replay import ReplayError

    try:
        run_demo(args.output, args.resolution, args.scans, args.format, args.seed,
                 progress=not args.quiet, warn=_warn)  # fmt: skip
    except ReplayError as err:
        raise CliError(str(err)) from None
    return 0


COMMANDS = {
    "replay": cmd_replay,
    "merge": cmd_merge,
    "simulate": cmd_simulate,
    "export": cmd_export,
    "render": cmd_render,
    "plot-convergence": cmd_plot_convergence,
    "query": cmd_query,
    "evaluate": cmd_evaluate,
    "demo": cmd_demo,
}


def _terminated(signum: int, _frame: Any) -> None:
    """SIGTERM ends the command as Ctrl-C does: cleanup runs, nothing half-written stays."""
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        previous = signal.signal(signal.SIGTERM, _terminated)
    except ValueError:  # not the main thread: leave signals alone
        previous = None
    try:
        return COMMANDS[args.command](args)
    except CliError as err:
        _err(str(err))
        return 1
    except KeyboardInterrupt:
        _err("interrupted (nothing written for the step in progress)")
        return 130
    except BrokenPipeError:
        return 1
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
