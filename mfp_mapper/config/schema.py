"""The settings schema, derived from the sections (``mfp_mapper.config.sections``).

The sections are the one definition of every setting (their fields, made by ``setting``).
Derived here: ``SETTINGS`` (one ``Setting`` per field: name, type, default, description, lo,
hi, dynamic, applies, flag...), ``BY_NAME``, the node's parameters (``PARAMS``, declared by
``mfp_mapper.ros.params``), ``NodeConfig`` (the node's values, one instance per section:
``cfg.map.resolution``, ``cfg.localization.fit_drop``), the checks of a parameter file
(``check_parameters``: the node and ``--config`` use them) and ``config/mfp_mapper.yaml``
(``python -m mfp_mapper.config.schema > config/mfp_mapper.yaml``; a test checks it both ways).
``ReplayOptions`` and the ``replay`` CLI flags derive from them in
``mfp_mapper.config.replay_options``.

Adding a setting: one field in one section of ``mfp_mapper.config.sections``, then regenerate
the YAML. Reading one: ``cfg.<section>.<field>`` (the value as given), ``cfg.<section>.core(
"<field>")`` (the core's value, "<= 0 means no limit" applied); ``BY_NAME[name]`` is the
``Setting`` itself. This module is plain data and imports neither ROS nor numpy.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from mfp_mapper.config.sections import (
    SECTIONS,
    LocalizationSection,
    MapSection,
    NodeSection,
    OutputsSection,
    PlacementSection,
    QuerySection,
    Section,
    SensorModelSection,
)
from mfp_mapper.config.setting import (
    NO_LIMIT_Z,
    Applies,
    Setting,
    Unlimited,
    XyzRpy,
    xyz_rpy,
)

__all__ = [
    "BY_NAME", "NO_LIMIT_Z", "PARAMS", "SETTINGS", "SPECS", "Applies", "NodeConfig", "Setting",
    "Unlimited", "XyzRpy", "check_parameters", "check_value", "defaults", "defaults_yaml",
    "xyz_rpy",
]  # fmt: skip

SETTINGS: tuple[Setting, ...] = tuple(s for section in SECTIONS for s in section.settings())
"""Every setting, section by section, in field order."""

BY_NAME: dict[str, Setting] = {s.name: s for s in SETTINGS}
PARAMS: tuple[Setting, ...] = tuple(s for s in SETTINGS if s.is_parameter)
"""The node's ROS parameters, in declaration order."""
SPECS: dict[str, Setting] = {p.name: p for p in PARAMS}
"""ROS parameter name -> Setting."""

ROS_OWN_PARAMETERS = ("use_sim_time", "start_type_description_service")
"""Parameters rclpy declares on every node: accepted in a parameter file, not ours."""

RETIRED: dict[str, str] = {
    "use_tf": "it never had an effect: /tf and /tf_static are always read, and the lidar "
    "extrinsic comes from /tf_static unless lidar.translation / lidar.rpy are set",
}
"""Former parameters of the node, with why they are gone: a parameter file (or ``-p``) that
still sets one starts the node with one warning saying it is ignored (``retired_warning``)."""

OCTOMAP_ONLY = (
    "color.a", "color.b", "color.g", "color.r", "color_factor",
    "color_free.a", "color_free.b", "color_free.g", "color_free.r", "colored_map",
    "compress_map", "filter_ground_plane", "filter_speckles", "ground_filter.angle",
    "ground_filter.distance", "ground_filter.plane_distance",
    "incremental_2D_projection", "max_depth", "min_x_size", "min_y_size", "octomap_path",
    "publish_free_space", "sensor_model.hit", "sensor_model.max", "sensor_model.min",
    "sensor_model.miss", "use_height_map",
)  # fmt: skip
"""octomap_server (ROS 2) parameters with no meaning here (occupancy log-odds, colours,
ground filtering, octree depth, its .bt/.ot file): a parameter file naming them starts the
node with one warning listing them (``octomap_only_parameters``)."""


# --- checking parameter values with the node's rules ------------------------------------------


def python_type_name(value: Any) -> str:
    """The rclpy ``Parameter.Type`` name of a Python value (rclpy's own inference)."""
    if isinstance(value, bool):
        return "BOOL"
    if isinstance(value, int):
        return "INTEGER"
    if isinstance(value, float):
        return "DOUBLE"
    if isinstance(value, str):
        return "STRING"
    if isinstance(value, (list, tuple)):
        kinds = (
            (bytes, "BYTE"),
            (bool, "BOOL"),
            (int, "INTEGER"),
            (float, "DOUBLE"),
            (str, "STRING"),
        )
        for kind, name in kinds:  # rclpy's order: an empty list is a BYTE_ARRAY
            if all(isinstance(v, kind) for v in value):
                return f"{name}_ARRAY"
    raise ValueError(f"not a parameter value: {value!r}")


def unknown_parameters(names: list[str]) -> list[str]:
    """The names that are neither our parameters, rclpy's own nor octomap_server's, sorted."""
    return sorted(
        n
        for n in names
        if n not in SPECS
        and n not in ROS_OWN_PARAMETERS
        and n not in RETIRED
        and n not in OCTOMAP_ONLY
        and not n.startswith("qos_overrides.")
    )


def octomap_only_parameters(names: list[str]) -> list[str]:
    """The octomap_server parameters among ``names`` that mean nothing here, sorted."""
    return sorted(n for n in names if n in OCTOMAP_ONLY)


def retired_parameters(names: list[str]) -> list[str]:
    """The former parameters (``RETIRED``) among ``names``, sorted."""
    return sorted(n for n in names if n in RETIRED)


def retired_warning(names: list[str]) -> str:
    """The one warning for former parameters in a parameter file: they are ignored."""
    why = "; ".join(f"{n}: {RETIRED[n]}" for n in names)
    return f"ignoring former parameter(s) {', '.join(names)} ({why})"


def octomap_only_warning(names: list[str]) -> str:
    """The one warning for octomap_server-only names in a parameter file."""
    return (
        f"ignoring octomap_server parameter(s) with no meaning in mfp_mapper: {', '.join(names)} "
        "(docs/robot.md, 'Migrating from octomap_server')"
    )


def unknown_parameters_error(names: list[str]) -> str:
    """The one message for typos in a parameter file (node and --config)."""
    return f"unknown parameter(s) {', '.join(names)} (see config/mfp_mapper.yaml for the names)"


def check_value(setting: Setting, value: Any) -> None:
    """Reject a value the node rejects when declaring it, with the text of rclpy's exception
    (``InvalidParameterTypeException``, ``InvalidParameterValueException``): ValueError."""
    if value is None:
        return  # rclpy: "not set" (an empty list in a file) passes; NodeConfig rejects it
    got = python_type_name(value)
    if got != setting.ros_type:
        raise ValueError(
            f"Trying to set parameter '{setting.name}' to '{value}' of type '{got}', "
            f"expecting type '{setting.ros_type}': {setting.name}"
        )
    reason = setting.check_range(value)
    if reason is not None:
        raise ValueError(
            f"Invalid parameter value ({value}) for parameter. Reason: {reason}: {setting.name}"
        )


def check_parameters(values: dict[str, Any]) -> NodeConfig:
    """Parameter overrides -> NodeConfig with the node's rules: unknown names, then each value
    in declaration order (type, range), then the relations. Raises ValueError."""
    unknown = unknown_parameters(list(values))
    if unknown:
        raise ValueError(unknown_parameters_error(unknown))
    ours = {name: value for name, value in values.items() if name in SPECS}
    for spec in PARAMS:
        if spec.name in ours:
            check_value(spec, ours[spec.name])
    return NodeConfig.from_values(ours)


# --- the node's values -----------------------------------------------------------------------

NODE_SECTIONS: tuple[type[Section], ...] = tuple(
    section for section in SECTIONS if any(s.is_parameter for s in section.settings())
)
"""The sections that hold node parameters (every one but the replay's)."""


@dataclass(frozen=True)
class NodeConfig:
    """The node's validated parameter values, one instance per section (``cfg.map.resolution``,
    ``cfg.localization.fit_drop``); replaced whole on a change at run time."""

    map: MapSection = dataclasses.field(default_factory=MapSection)
    sensor_model: SensorModelSection = dataclasses.field(default_factory=SensorModelSection)
    placement: PlacementSection = dataclasses.field(default_factory=PlacementSection)
    outputs: OutputsSection = dataclasses.field(default_factory=OutputsSection)
    localization: LocalizationSection = dataclasses.field(default_factory=LocalizationSection)
    node: NodeSection = dataclasses.field(default_factory=NodeSection)
    query: QuerySection = dataclasses.field(default_factory=QuerySection)

    def core(self, name: str) -> Any:
        """A parameter's value as the core takes it (``Setting.core_value``)."""
        spec = SPECS[name]
        return getattr(self, spec.section).core(spec.field)

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> NodeConfig:
        """Build from parameter values keyed by parameter name (the others take their
        defaults); raise ValueError if invalid."""
        unknown = [name for name in values if name not in SPECS]
        if unknown:
            raise ValueError(unknown_parameters_error(sorted(unknown)))
        unset = [name for name, value in values.items() if value is None]
        if unset:
            raise ValueError(f"parameter(s) {', '.join(unset)} not set (an empty list?)")
        for spec in PARAMS:
            vec = values.get(spec.name)
            if spec.type is not list or vec is None:
                continue
            if len(vec) != spec.length or not all(math.isfinite(float(v)) for v in vec):
                raise ValueError(
                    f"{spec.name} must be {spec.length} finite numbers, got {list(vec)}"
                )
        sections: dict[str, Any] = {
            section.KEY: section(
                **{
                    s.field: s.held(values[s.name]) if s.name in values else s.held(s.default)
                    for s in section.settings()
                }
            )
            for section in NODE_SECTIONS
        }
        cfg = cls(**sections)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Check the ranges and the relations between parameters; raise ValueError naming
        the culprit."""
        values = self.values()
        for spec in PARAMS:
            value = values[spec.name]
            if spec.lo is not None and not (spec.lo <= value <= spec.hi):
                raise ValueError(f"{spec.name}={value} outside [{spec.lo}, {spec.hi}]")
        sensor, box, out = self.sensor_model, self.placement, self.outputs
        if sensor.min_range >= sensor.core("max_range"):
            raise ValueError("sensor_model.min_range must be below sensor_model.max_range")
        for axis in "xyz":
            lo, hi = (getattr(box, f"point_cloud_{end}_{axis}") for end in ("min", "max"))
            if lo >= hi:
                raise ValueError(f"point_cloud_min_{axis} must be below point_cloud_max_{axis}")
        if out.occupancy_min_z >= out.occupancy_max_z:
            raise ValueError("occupancy_min_z must be below occupancy_max_z")
        loc = self.localization
        if loc.enabled and not loc.odom_frame.strip("/ "):
            raise ValueError(
                "localization.odom_frame must name a frame: the node publishes map -> it"
            )

    def values(self) -> dict[str, Any]:
        """Parameter name -> value, in declaration order."""
        return {s.name: getattr(getattr(self, s.section), s.field) for s in PARAMS}


def defaults() -> dict[str, Any]:
    """Parameter name -> default value."""
    return {p.name: p.default for p in PARAMS}


# --- the defaults YAML -----------------------------------------------------------------------

YAML_HEADER = """\
# Default parameters of the mfp_mapper node (ROS 2 parameter file), generated from the
# settings sections (mfp_mapper/config/sections.py) by
# `python -m mfp_mapper.config.schema > config/mfp_mapper.yaml`.
#   ros2 run mfp_mapper mfp_mapper --ros-args --params-file config/mfp_mapper.yaml
# Names follow octomap_server where a counterpart exists. Ranges and the full
# descriptions: `ros2 param describe /mfp_mapper <name>` or mfp_mapper/config/sections.py.
/**:
  ros__parameters:
"""


def _yaml_scalar(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return value or '""'
    if isinstance(value, float):
        return "-1.0e+6" if value == -1.0e6 else "1.0e+6" if value == 1.0e6 else repr(value)
    if isinstance(value, list):
        return "[" + ", ".join(_yaml_scalar(v) for v in value) + "]"
    return str(value)


def _wrap(text: str, indent: str, width: int = 96) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width, initial_indent=indent + "# ", subsequent_indent=indent + "# ")


def defaults_yaml() -> str:
    """The text of ``config/mfp_mapper.yaml``: every parameter with its default."""
    lines = [YAML_HEADER.rstrip("\n")]
    for spec in PARAMS:
        lines += _wrap(spec.description, "    ")
        lines.append(f"    {spec.name}: {_yaml_scalar(spec.default)}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    import sys

    sys.stdout.write(defaults_yaml())
