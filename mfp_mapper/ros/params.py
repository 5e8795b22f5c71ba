"""The node's ROS parameters, declared from the settings sections (``mfp_mapper.config.schema``)."""

from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

from mfp_mapper.config.schema import (
    PARAMS,
    SPECS,
    NodeConfig,
    Setting,
    octomap_only_parameters,
    octomap_only_warning,
    retired_parameters,
    retired_warning,
    unknown_parameters,
    unknown_parameters_error,
)


def descriptor(spec: Setting) -> ParameterDescriptor:
    """The rcl_interfaces ParameterDescriptor of a parameter: description, range, read-only."""
    desc = ParameterDescriptor(
        name=spec.name, description=spec.description, read_only=not spec.dynamic
    )
    if spec.lo is not None and spec.hi is not None:
        if spec.type is int:
            desc.integer_range = [
                IntegerRange(from_value=int(spec.lo), to_value=int(spec.hi), step=1)
            ]
        elif spec.type is float:
            desc.floating_point_range = [
                FloatingPointRange(from_value=float(spec.lo), to_value=float(spec.hi), step=0.0)
            ]
    return desc


def parameter_overrides(node: Node) -> dict[str, Any]:
    """The values the node was started with (parameter files, ``-p``, ``parameter_overrides``)."""
    overrides = getattr(node, "_parameter_overrides", {})  # rclpy keeps them private
    return {name: param.value for name, param in overrides.items()}


def declare_parameters(node: Node) -> NodeConfig:
    """Declare every parameter on an rclpy node and return the validated values.

    An override naming no parameter (a typo) is an error, as in ``mfp-mapper --config``;
    octomap_server's names with no meaning here (``schema.OCTOMAP_ONLY``) get one warning,
    former parameters (``schema.RETIRED``: ignored) another; a value of the wrong type or out
    of range is rejected by rclpy (``ParameterException``), with the message
    ``mfp_mapper.config.schema.check_value`` gives the CLI.
    """
    given = list(parameter_overrides(node))
    unknown = [n for n in unknown_parameters(given) if not node.has_parameter(n)]
    if unknown:
        raise ValueError(unknown_parameters_error(unknown))
    octomap_only = octomap_only_parameters(given)
    if octomap_only:  # an octomap_server file: one line, the node starts
        node.get_logger().warning(octomap_only_warning(octomap_only))
    retired = retired_parameters(given)
    if retired:  # an old file of ours (use_tf): one line, the node starts
        node.get_logger().warning(retired_warning(retired))
    values: dict[str, Any] = {}
    for spec in PARAMS:
        param = node.declare_parameter(spec.name, spec.default, descriptor(spec))
        values[spec.name] = param.value
    return NodeConfig.from_values(values)


def usage() -> str:
    """What ``--help`` prints: how to start the node and its parameters with defaults."""
    lines = [
        "usage: ros2 run mfp_mapper mfp_mapper [--ros-args -p NAME:=VALUE ... "
        "--params-file config/mfp_mapper.yaml]",
        "",
        "Degree-of-occupancy mapping node (cloud_in: PointCloud2, odom: Odometry).",
        "Parameters:",
    ]
    for spec in SPECS.values():
        lines.append(f"  {spec.name} (default {spec.default!r}): {spec.description}")
    return "\n".join(lines)
