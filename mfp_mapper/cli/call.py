"""``mfp-mapper call``: talk to a running node, for machines without the ROS 2 command line
and for scripts (``mfp_mapper.ros.client``). Needs rclpy and the node's messages (the .venv
that ``./run setup`` makes, or a sourced ROS 2 workspace)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import CliError, check_writable, jsonable

ACTIONS = ("status", "query", "segment", "getmap", "save", "reset", "clear-bbox", "lifecycle")


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``call`` subcommand's arguments."""
    p = sub.add_parser(
        "call",
        help="call a running node's services: " + ", ".join(ACTIONS),
        description="Call a running mfp_mapper node (same ROS_DOMAIN_ID and discovery range "
        "as the node). status: its ~/status counters; query X Y Z ...: the voxels at points; "
        "segment X0 Y0 Z0 X1 Y1 Z1 ...: the probability that each straight segment is clear; "
        "getmap -o NAME: the ~/hit_probability_map grid as NAME.pgm + NAME.yaml (Nav2 "
        "map_server format); save; reset; clear-bbox X0 Y0 Z0 X1 Y1 Z1; lifecycle [TRANSITION]: "
        "the state, or a transition (configure, activate, deactivate, cleanup, shutdown).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
        "  mfp-mapper call status\n"
        "  mfp-mapper call query 1.0 0.0 1.2  4.0 2.0 0.5 --json\n"
        "  mfp-mapper call segment 0 0 1  20 0 1 --frame base_link\n"
        "  mfp-mapper call getmap -o office\n"
        "  mfp-mapper call lifecycle deactivate --node octomap_server --namespace robot1",
    )
    p.add_argument("action", choices=ACTIONS, metavar="ACTION", help=", ".join(ACTIONS))
    p.add_argument("values", nargs="*", help="the action's numbers, or its lifecycle transition")
    p.add_argument("--node", default="mfp_mapper", help="node name (default mfp_mapper)")
    p.add_argument("--namespace", default="", help="node namespace (default none)")
    p.add_argument(
        "--frame",
        default="",
        help="query/segment: the frame of the points (default: the map frame)",
    )
    p.add_argument(
        "--stamp", type=float, default=0.0, help="query/segment: read the map at this time (s)"
    )
    p.add_argument("-o", "--output", type=Path, help="getmap: where to write NAME.pgm + .yaml")
    p.add_argument(
        "--timeout", type=float, default=10.0, help="seconds to wait for the node (default 10)"
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    return p


def _numbers(values: list[str], per: int, what: str) -> list[list[float]]:
    try:
        numbers = [float(v) for v in values]
    except ValueError:
        raise CliError(f"{what} takes numbers, got {' '.join(values)!r}") from None
    if not numbers or len(numbers) % per or not all(math.isfinite(v) for v in numbers):
        raise CliError(f"{what} takes groups of {per} finite numbers, got {len(numbers)}")
    return [numbers[i : i + per] for i in range(0, len(numbers), per)]


def _print(args: argparse.Namespace, value: Any, lines: list[str]) -> None:
    if args.json:
        print(json.dumps(jsonable(value), indent=2))
    else:
        for line in lines:
            print(line)


def _query(args: argparse.Namespace, client: Any, segments: bool) -> int:
    groups = _numbers(args.values, 6 if segments else 3, args.action)
    kind = {"segments": groups} if segments else {"points": groups}
    answer = client.query(frame_id=args.frame, stamp=args.stamp, **kind)
    if not answer.success:
        raise CliError(f"{client.target}/query refused: {answer.message}")
    rows = answer.segments if segments else answer.points
    lines = [f"{answer.message} (map frame {answer.map_frame_id})"]
    for row in rows:
        if segments:
            lines.append(
                f"{tuple(row['start'])} -> {tuple(row['end'])}: clear with probability "
                f"{row['clear_probability']:.4g}, {row['unknown_length']:.2f} m never observed"
            )
        elif not row["observed"]:
            lines.append(f"{tuple(row['point'])}: unknown (never observed)")
        else:
            lines.append(
                f"{tuple(row['point'])}: DoO {row['degree_of_occupancy']:.3f} "
                f"(std {row['std']:.3f}), p_hit {row['hit_probability']:.3f}"
            )
    _print(args, {"map_frame_id": answer.map_frame_id, "results": rows}, lines)
    return 0


def _getmap(args: argparse.Namespace, client: Any) -> int:
    from mfp_mapper.outputs.nav2_map import write_occupancy_grid

    if args.output is None:
        raise CliError("getmap needs -o NAME (writes NAME.pgm and NAME.yaml)")
    yaml_path = args.output.with_suffix(".yaml")
    check_writable(yaml_path)
    grid = client.get_map()
    info = grid.info
    if info.width == 0 or info.height == 0:
        raise CliError(f"{client.target}/hit_probability_map answered an empty grid: no map yet")
    written = write_occupancy_grid(
        grid.data,
        (int(info.height), int(info.width)),
        (float(info.origin.position.x), float(info.origin.position.y)),
        float(info.resolution),
        yaml_path,
        grid.header.frame_id,
    )
    summary = {"yaml": str(written.yaml), "image": str(written.image),
               "width": int(info.width), "height": int(info.height),
               "resolution": float(info.resolution), "frame_id": grid.header.frame_id}  # fmt: skip
    _print(args, summary, [
        f"wrote {written.image} and {written.yaml}: {info.width} x {info.height} cells of "
        f"{info.resolution:g} m, frame {grid.header.frame_id}"
    ])  # fmt: skip
    return 0


def _lifecycle(args: argparse.Namespace, client: Any) -> int:
    from mfp_mapper.ros.client import CallError

    if len(args.values) > 1:
        raise CliError("lifecycle takes at most one transition")
    if not args.values:
        state = client.lifecycle_state()
        allowed = client.lifecycle_transitions()
        _print(args, {"state": state, "transitions": allowed},
               [f"{client.target}: {state} (transitions: {', '.join(allowed)})"])  # fmt: skip
        return 0
    try:
        ok = client.lifecycle_change(args.values[0])
    except CallError as err:
        raise CliError(str(err)) from None
    state = client.lifecycle_state() if args.values[0] != "shutdown" or ok else "unknown"
    outcome = "done" if ok else "refused by the node"
    _print(args, {"success": ok, "state": state}, [f"{args.values[0]}: {outcome}; now {state}"])
    return 0 if ok else 1


def run(args: argparse.Namespace) -> int:
    try:
        from mfp_mapper.ros.client import CallError, NodeClient
    except ImportError as err:
        raise CliError(
            f"calling a node needs rclpy and mfp_mapper_msgs ({err}): use the .venv of "
            "./run setup, or source your ROS 2 workspace"
        ) from None
    if args.action in ("getmap", "save", "reset", "status") and args.values:
        raise CliError(f"{args.action} takes no values")
    try:
        with NodeClient(args.node, args.namespace, timeout=args.timeout) as client:
            if args.action == "status":
                status = client.status()
                _print(args, status, [json.dumps(status, indent=2)])
                return 0
            if args.action in ("query", "segment"):
                return _query(args, client, segments=args.action == "segment")
            if args.action == "getmap":
                return _getmap(args, client)
            if args.action == "save":
                ok, message = client.save()
                _print(args, {"success": ok, "message": message}, [message])
                return 0 if ok else 1
            if args.action == "reset":
                client.reset()
                _print(args, {"success": True}, [f"{client.target}: map reset"])
                return 0
            if args.action == "clear-bbox":
                corners = _numbers(args.values, 6, "clear-bbox")
                if len(corners) != 1:
                    raise CliError("clear-bbox takes one box: X0 Y0 Z0 X1 Y1 Z1")
                ok, message, cleared = client.clear_bbox(corners[0][:3], corners[0][3:])
                _print(args, {"success": ok, "message": message, "cleared": cleared}, [message])
                return 0 if ok else 1
            return _lifecycle(args, client)
    except CallError as err:
        raise CliError(str(err)) from None
    except ValueError as err:
        raise CliError(str(err)) from None
