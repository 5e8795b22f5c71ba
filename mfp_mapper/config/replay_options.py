"""What a replay reads and how it maps: ``ReplayOptions``, derived from the settings schema.

``ReplayOptions`` holds the sections the replay reads (map, sensor model, placement, replay),
each value as given (``section.core(field)``: "<= 0 means no limit" applied).
``options_from_yaml`` reads a node parameter file with the node's rules
(``mfp_mapper.config.param_file``); ``add_replay_flags``/``options_from_args`` give the
``replay`` CLI its flags, one per setting with a ``flag``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Collection
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from mfp_mapper.config.param_file import load_node_parameters
from mfp_mapper.config.schema import (
    BY_NAME,
    SETTINGS,
    NodeConfig,
    Setting,
    check_parameters,
    octomap_only_parameters,
    octomap_only_warning,
    retired_parameters,
    retired_warning,
)
from mfp_mapper.config.sections import (
    MapSection,
    PlacementSection,
    ReplaySection,
    Section,
    SensorModelSection,
)
from mfp_mapper.config.setting import XyzRpy, xyz_rpy


@dataclass(frozen=True)
class ReplayOptions:
    """What to read and how to map it: the sections the replay uses (``opts.map.resolution``,
    ``opts.placement.odom_max_gap``, ``opts.replay.cloud_topic``; ``None`` topics are
    detected in the bag). ``ReplayOptions.of(resolution=0.2, max_scans=4)`` and
    ``opts.but(every=2)`` name fields without their section (field names are unique)."""

    map: MapSection = field(default_factory=MapSection)
    sensor_model: SensorModelSection = field(default_factory=SensorModelSection)
    placement: PlacementSection = field(default_factory=PlacementSection)
    replay: ReplaySection = field(default_factory=ReplaySection)
    config_extrinsic: XyzRpy | None = None
    """``placement``'s ``lidar.*`` when ``--config`` names them: used when /tf_static has no
    chain (the ``--extrinsic`` flag, ``replay.extrinsic``, overrides /tf_static)."""

    @classmethod
    def of(cls, **values: Any) -> ReplayOptions:
        """Options with these fields (named without their section) changed from the defaults."""
        return cls().but(**values)

    def but(self, **values: Any) -> ReplayOptions:
        """These options with some fields (named without their section) changed."""
        changes: dict[str, dict[str, Any]] = {}
        for name, value in values.items():
            if name == "config_extrinsic":
                continue
            key = _SECTION_OF.get(name)
            if key is None:
                raise TypeError(f"ReplayOptions has no field {name!r}")
            changes.setdefault(key, {})[name] = value
        sections = {key: replace(getattr(self, key), **kw) for key, kw in changes.items()}
        if "config_extrinsic" in values:
            sections["config_extrinsic"] = values["config_extrinsic"]
        return replace(self, **sections)


REPLAY_SECTIONS: tuple[type[Section], ...] = (
    MapSection,
    SensorModelSection,
    PlacementSection,
    ReplaySection,
)
"""The sections ``ReplayOptions`` holds."""

_SECTION_OF: dict[str, str] = {
    f.name: section.KEY
    for section in REPLAY_SECTIONS
    for f in fields(section)  # type: ignore[arg-type]
}

EXTRINSIC_PARAMETERS = ("lidar.translation", "lidar.rpy")
"""Node parameters that together give ``ReplayOptions.config_extrinsic``."""


class ReplayError(RuntimeError):
    """The bag cannot be replayed (unreadable, missing topic, no poses...): says why."""


class ConfigError(ReplayError, ValueError):
    """A parameter file the node would refuse: says which file and why."""


def options_from_config(cfg: NodeConfig, given: set[str]) -> dict[str, Any]:
    """ReplayOptions fields (named without their section) of the node parameters named in
    ``given``."""
    out: dict[str, Any] = {}
    for name in given:
        setting = BY_NAME[name]
        if not setting.in_replay:
            continue
        out[setting.field] = getattr(getattr(cfg, setting.section), setting.field)
    if given & set(EXTRINSIC_PARAMETERS):
        out["config_extrinsic"] = cfg.placement.lidar_xyz_rpy()
    return out


def options_from_yaml(path: str | Path) -> dict[str, Any]:
    """ReplayOptions fields (named without their section) from a node parameter file.

    The file is read as the node ``mfp_mapper`` reads it (its own section or ``/**``, rcl's
    typing of values, unknown names and values the node rejects are errors: ConfigError).
    Only the parameters the file sets are returned.
    """
    try:
        values = load_node_parameters(path)
        cfg = check_parameters(values)
    except ValueError as err:
        raise ConfigError(f"{path}: {err}") from None
    octomap_only = octomap_only_parameters(list(values))
    if octomap_only:
        print(f"mfp-mapper: {path}: {octomap_only_warning(octomap_only)}", file=sys.stderr)
    retired = retired_parameters(list(values))
    if retired:
        print(f"mfp-mapper: {path}: {retired_warning(retired)}", file=sys.stderr)
    return options_from_config(cfg, {n for n in values if n in BY_NAME})


# --- the replay CLI's flags ------------------------------------------------------------------


def _flag_type(setting: Setting) -> Any:
    """An argparse type: the setting's type and range."""
    base = float if setting.type is list else setting.type

    def parse(text: str) -> Any:
        try:
            value = base(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {base.__name__}, got {text!r}") from None
        if isinstance(value, float) and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text}")
        bounded = setting.lo is not None and setting.hi is not None and base is not str
        if bounded and not setting.lo <= value <= setting.hi:
            raise argparse.ArgumentTypeError(
                f"must lie in [{setting.lo:g}, {setting.hi:g}], got {text}"
            )
        return value

    parse.__name__ = base.__name__
    return parse


def _flag_help(setting: Setting) -> str:
    text = setting.description.rstrip(".")
    if setting.type is bool and setting.flag is not None and setting.flag.startswith("--no-"):
        text = f"turn off: {text[0].lower()}{text[1:]}"
    if setting.is_parameter:
        default = "" if setting.type is bool else f", default {setting.default}"
        text += f" (node parameter {setting.name}{default})"
    return text


def _comma_list(setting: Setting) -> Any:
    """An argparse type: comma-separated values, each of the setting's type and range."""
    one = _flag_type(setting)

    def parse(text: str) -> list[Any]:
        return [one(part) for part in text.split(",") if part.strip()]

    parse.__name__ = "list"
    return parse


def add_replay_flags(parser: argparse.ArgumentParser, lists: Collection[str] = ()) -> None:
    """One flag per schema entry that has one; every flag defaults to None (not given).
    Settings named in ``lists`` take comma-separated values (a list; ``score`` compares
    them)."""
    for setting in SETTINGS:
        if setting.flag is None:
            continue
        dest = setting.name.replace(".", "_")
        common: dict[str, Any] = {"dest": dest, "default": None, "help": _flag_help(setting)}
        if setting.name in lists:
            common["help"] += "; several, comma-separated: one row each"
            parser.add_argument(setting.flag, type=_comma_list(setting), **common)
            continue
        if setting.type is bool:
            on = not setting.flag.startswith("--no-")
            parser.add_argument(setting.flag, action="store_const", const=on, **common)
            continue
        metavar = setting.metavar or setting.flag.lstrip("-").replace("-", "_").upper()
        nargs = setting.length if setting.type is list else None
        parser.add_argument(
            setting.flag, type=_flag_type(setting), nargs=nargs, metavar=metavar, **common
        )


def options_from_args(args: argparse.Namespace) -> ReplayOptions:
    """ReplayOptions: schema defaults, then ``--config`` (if any), then the flags given."""
    values: dict[str, Any] = options_from_yaml(args.config) if args.config else {}
    for setting in SETTINGS:
        if setting.flag is None:
            continue
        given = getattr(args, setting.name.replace(".", "_"), None)
        if given is None:
            continue
        if setting.name == "extrinsic":
            values["extrinsic"] = xyz_rpy(given[:3], given[3:])
        else:
            values[setting.field] = setting.held(given)
    return ReplayOptions.of(**values)
