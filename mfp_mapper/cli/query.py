"""``mfp-mapper query``: the statistics of the voxels at given points, and whether straight
segments are clear (the probability that a ray passes them unreflected)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import CliError, jsonable, load_map_arg


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``query`` subcommand's arguments."""
    p = sub.add_parser(
        "query",
        help="statistics of the voxels at points X Y Z ..., clear probability of segments",
        description="Points: the statistics of the voxel holding each point. Segments: the "
        "probability that a ray from the start reaches the end unreflected (the product over "
        "the voxels crossed, exact chords; never-observed voxels count with the prior) and "
        "the metres through never-observed voxels. With --json: a list of point rows, or "
        '{"points": [...], "segments": [...]} when segments are asked.',
    )
    p.add_argument(
        "map", help="map file (.npz) or tiled map (only the blocks or tiles needed are read)"
    )
    p.add_argument(
        "coords",
        nargs="*",
        type=float,
        metavar="X Y Z",
        help="points, three numbers each",
    )
    p.add_argument(
        "--segment",
        nargs=6,
        type=float,
        action="append",
        default=[],
        metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
        help="a straight segment from (X0, Y0, Z0) to (X1, Y1, Z1), map frame (repeatable)",
    )
    p.add_argument(
        "--segments",
        type=Path,
        metavar="FILE",
        help="a text file of segments, one per line: X0 Y0 Z0 X1 Y1 Z1 (spaces or commas; "
        "'#' starts a comment)",
    )
    p.add_argument(
        "--stamp",
        type=float,
        help="read the map decayed to this time (s; maps with a decay time only)",
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    return p


def read_segment_file(path: Path) -> list[list[float]]:
    """Segments of a text file: six numbers per line; CliError naming the bad line."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise CliError(f"{path}: cannot read the segments: {err}") from None
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].replace(",", " ").split()
        if not body:
            continue
        try:
            values = [float(v) for v in body]
        except ValueError:
            raise CliError(f"{path}:{number}: not numbers: {line.strip()!r}") from None
        if len(values) != 6:
            raise CliError(f"{path}:{number}: a segment is 6 numbers, got {len(values)}")
        rows.append(values)
    return rows


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from mfp_mapper.mapio.mapfile import MapFileError
    from mfp_mapper.outputs.report import query_lines, query_rows, segment_lines, segment_rows

    if len(args.coords) % 3:
        raise CliError(f"query needs X Y Z triples, got {len(args.coords)} numbers")
    segments = list(args.segment)
    if args.segments is not None:
        segments += read_segment_file(args.segments)
    if not args.coords and not segments:
        raise CliError("nothing to query: give points X Y Z, --segment or --segments")
    mapper = load_map_arg(args.map, lazy_tiles=True, queries=True)  # reads what it needs
    points = np.asarray(args.coords, dtype=np.float64).reshape(-1, 3)
    ends = np.asarray(segments, dtype=np.float64).reshape(-1, 6)
    try:
        rows = query_rows(mapper, points, args.stamp) if len(points) else []
        seg_rows = segment_rows(mapper, ends[:, :3], ends[:, 3:], args.stamp) if segments else []
    except MapFileError as err:  # a damaged tile
        raise CliError(str(err)) from None
    except ValueError as err:  # a segment the walk refuses (non-finite, too long, too far)
        raise CliError(str(err)) from None
    if args.json:
        out: Any = rows if not segments else {"points": rows, "segments": seg_rows}
        print(json.dumps(jsonable(out), indent=2))
        return 0
    print(f"map {args.map}: frame {mapper.frame_id}, {mapper.resolution:g} m voxels")
    for line in query_lines(rows) + segment_lines(seg_rows):
        print(line)
    return 0
