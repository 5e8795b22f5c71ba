"""The node's parameters declared from the settings sections (``mfp_mapper.ros.params``), in a
node of this process (rclpy, no DDS traffic)."""

from __future__ import annotations

from typing import Any

import pytest

from mfp_mapper.config.schema import PARAMS, NodeConfig

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip("rclpy")


class _Logger:
    def __init__(self) -> None:
        self.warnings: list[str] = []

    def warning(self, text: str) -> None:
        self.warnings.append(text)


def _declared(overrides: dict[str, Any]) -> tuple[NodeConfig, list[str], Any]:
    """Declare the parameters on a node started with ``overrides``: (config, warnings, the
    descriptors of the declared parameters)."""
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from mfp_mapper.ros.params import declare_parameters

    ctx = rclpy.context.Context()
    rclpy.init(args=[], context=ctx)
    try:
        node = Node(
            "mfp_mapper",
            context=ctx,
            parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
        )
        logger = _Logger()
        node.get_logger = lambda: logger  # type: ignore[method-assign]
        try:
            cfg = declare_parameters(node)
            described = node.describe_parameters([p.name for p in PARAMS])
        finally:
            node.destroy_node()
        return cfg, logger.warnings, described
    finally:
        rclpy.shutdown(context=ctx)


def test_every_setting_of_the_sections_is_declared_with_its_range_and_mutability() -> None:
    cfg, warnings, described = _declared({"resolution": 0.2})
    assert cfg.map.resolution == 0.2 and not warnings
    for spec, desc in zip(PARAMS, described, strict=True):
        assert desc.name == spec.name and desc.read_only == (not spec.dynamic)
        ranges = list(desc.floating_point_range) + list(desc.integer_range)
        assert bool(ranges) == (spec.lo is not None and spec.type in (int, float)), spec.name


def test_the_former_use_tf_is_ignored_with_one_warning() -> None:
    """``use_tf`` never had an effect: a parameter file that still sets it starts the node."""
    cfg, warnings, _ = _declared({"use_tf": True, "resolution": 0.2})
    assert cfg == NodeConfig.from_values({"resolution": 0.2})
    assert len(warnings) == 1 and "ignoring former parameter(s) use_tf" in warnings[0]
