"""``mfp-mapper --config`` reads a parameter file exactly as the node does: the same files
through real rcl/rclpy (and the real node) and through ``mfp_mapper.config.param_file``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from mfp_mapper.config.param_file import ParamFileError, load_node_parameters
from mfp_mapper.config.replay_options import options_from_yaml
from mfp_mapper.config.schema import check_parameters

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip("rclpy")

# Scalars, sections, wildcards and precedence: what rcl makes of them for node /mfp_mapper.
TYPING = """\
/**:
  ros__parameters:
    a: 1
    b: 1e3
    c: 010
    d: 0x10
    e: yes
    f: "1"
    g: .inf
    h: [1, 2]
    i: [0.5, 1.5e2]
    j: ['x', zz]
    k: 1.
    l: Y
    m: ~
    o: 1_000
    p: +5
    q: -inf
    r: !!str 1
    s: off
    t: tRue
    u: 08
    v: 99999999999999999999
    w: 0x1p3
    x: "  "
    z: 1e
    prec: wild
    empty: []
/*:
  ros__parameters:
    star: 1
    prec: star
mfp_mapper:
  ros__parameters:
    prec: exact
    nested:
      deeper:
        x: 2.5
/mfp_mapper:
  ros__parameters:
    prec2: slash
/**:
  ros__parameters:
    prec2: wild again
/**/mfp_mapper:
  ros__parameters:
    ww: 1
ns:
  mfp_mapper:
    ros__parameters:
      other_namespace: 1
other_node:
  ros__parameters:
    other: 1
"""

NODE_CASES = {
    "defaults": None,  # config/mfp_mapper.yaml
    "own section": "mfp_mapper:\n  ros__parameters:\n    resolution: 0.25\n    deskew: false\n",
    "other node ignored": "other:\n  ros__parameters:\n    resolution: 5\n",
    "typo": "/**:\n  ros__parameters:\n    resolutoin: 0.2\n",
    "typo in own section": (
        "mfp_mapper:\n  ros__parameters:\n    sensor_model:\n      max_rang: 1.0\n"
    ),
    "int for double": "/**:\n  ros__parameters:\n    resolution: 1\n",
    "int array for doubles": "/**:\n  ros__parameters:\n    lidar.translation: [0, 0, 1]\n",
    "double for int": "/**:\n  ros__parameters:\n    threads: 2.0\n",
    "string for bool": "/**:\n  ros__parameters:\n    deskew: 'no'\n",
    "yes for bool": "/**:\n  ros__parameters:\n    deskew: no\n    latch: On\n",
    "out of range": "/**:\n  ros__parameters:\n    resolution: 0.001\n",
    "int out of range": "/**:\n  ros__parameters:\n    threads: -1\n",
    "relation": "/**:\n  ros__parameters:\n    occupancy_min_z: 3.0\n",
    "short vector": "/**:\n  ros__parameters:\n    lidar.rpy: [0.0, 1.0]\n",
    "empty vector": "/**:\n  ros__parameters:\n    lidar.rpy: []\n",
    "exponent double": "/**:\n  ros__parameters:\n    decay_time: 1e2\n    keep_radius: 50.\n",
    "mixed sequence": "/**:\n  ros__parameters:\n    lidar.rpy: [0, 0.5, 1.0]\n",
    "no ros__parameters": "resolution: 0.2\n",
    "rclpy's own": "/**:\n  ros__parameters:\n    use_sim_time: true\n",
    "former use_tf": "/**:\n  ros__parameters:\n    use_tf: true\n    resolution: 0.2\n",
}


def _write(tmp_path: Path, name: str, text: str | None) -> Path:
    if text is None:
        return Path(__file__).resolve().parents[2] / "config" / "mfp_mapper.yaml"
    path = tmp_path / (name.replace(" ", "_").replace("'", "") + ".yaml")
    path.write_text(text)
    return path


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


def _rcl_overrides(path: Path) -> dict[str, Any]:
    """What rclpy hands a node named mfp_mapper started with ``--params-file path``."""
    from rclpy.node import Node

    ctx = rclpy.context.Context()
    rclpy.init(args=["x", "--ros-args", "--params-file", str(path)], context=ctx)
    try:
        node = Node("mfp_mapper", context=ctx)
        values = {k: p.value for k, p in node._parameter_overrides.items()}
        node.destroy_node()
        return values
    finally:
        rclpy.shutdown(context=ctx)


def test_values_sections_and_precedence_are_rcls(tmp_path: Path) -> None:
    path = _write(tmp_path, "typing", TYPING)
    ours = load_node_parameters(path)
    theirs = _rcl_overrides(path)
    assert sorted(ours) == sorted(theirs)
    for name, value in theirs.items():
        assert _same(ours[name], value), (name, ours[name], value)
    # later sections win, and a repeated section merges into its first appearance
    assert ours["prec"] == "exact" and ours["prec2"] == "slash"


def _node_outcome(path: Path) -> tuple[str, Any]:
    """("ok", parameter values) or ("error", message) or ("unreadable", message)."""
    from rclpy.exceptions import ParameterException

    from mfp_mapper.ros.node import MfpMapperNode

    ctx = rclpy.context.Context()
    try:
        rclpy.init(args=["x", "--ros-args", "--params-file", str(path)], context=ctx)
    except Exception as err:  # rcl could not parse the file: rclpy raises RCLError
        return "unreadable", str(err)
    try:
        node = MfpMapperNode(context=ctx)
    except (ValueError, ParameterException) as err:  # what main() reports, exit status 2
        return "error", str(err)
    else:
        values = node.cfg.values()
        node.close()
        node.destroy_node()
        return "ok", values
    finally:
        rclpy.shutdown(context=ctx)


def _cli_outcome(path: Path) -> tuple[str, Any]:
    try:
        values = load_node_parameters(path)
    except ParamFileError as err:
        return "unreadable", str(err)
    try:
        return "ok", check_parameters(values).values()
    except ValueError as err:
        return "error", str(err)


@pytest.mark.parametrize("case", sorted(NODE_CASES))
def test_cli_reads_a_file_as_the_node_does(case: str, tmp_path: Path) -> None:
    path = _write(tmp_path, case, NODE_CASES[case])
    node_kind, node_result = _node_outcome(path)
    cli_kind, cli_result = _cli_outcome(path)
    assert cli_kind == node_kind, (node_result, cli_result)
    if node_kind == "unreadable":
        return  # rcl's parser message differs in wording; both refuse the file
    assert cli_result == node_result
    if node_kind == "error":  # and options_from_yaml (replay --config) says the same
        with pytest.raises(ValueError) as info:
            options_from_yaml(path)
        assert str(info.value) == f"{path}: {node_result}"


def test_the_cases_cover_each_outcome(tmp_path: Path) -> None:
    kinds = {_cli_outcome(_write(tmp_path, c, t))[0] for c, t in NODE_CASES.items()}
    assert kinds == {"ok", "error", "unreadable"}


def test_keep_radius_reaches_the_nodes_mapper(tmp_path: Path) -> None:
    from mfp_mapper.ros.node import MfpMapperNode

    path = _write(tmp_path, "keep", "mfp_mapper:\n  ros__parameters:\n    keep_radius: 25.0\n")
    ctx = rclpy.context.Context()
    rclpy.init(args=["x", "--ros-args", "--params-file", str(path)], context=ctx)
    try:
        node = MfpMapperNode(context=ctx)
        try:
            assert node.cfg.map.keep_radius == 25.0
            assert node.mapper.keep_radius == 25.0
        finally:
            node.close()
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
