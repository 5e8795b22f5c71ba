"""What a replay reads and how it maps: ``ReplayOptions``, derived from the settings schema.

Field defaults are the schema's defaults as the core takes them (``Setting.core_value``:
"<= 0 means no limit" applied). ``options_from_yaml`` reads a node parameter file with the
node's rules (``mfp_mapper.config.param_file``); ``add_replay_flags``/``options_from_args``
give the ``replay`` CLI its flags, one per schema entry with a ``flag``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Collection
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from mfp_mapper.config.param_file import load_node_parameters
from mfp_mapper.config.schema import (
    BY_NAME,
    SETTINGS,
    MapSettings,
    NodeConfig,
    Setting,
    XyzRpy,
    check_parameters,
    octomap_only_parameters,
    octomap_only_warning,
    xyz_rpy,
)


def _default(name: str) -> Any:
    return BY_NAME[name].core_default


@dataclass
class ReplayOptions:
    """What to read and how to map it. ``None`` topics are detected in the bag."""

    resolution: float = _default("resolution")
    max_range: float = _default("sensor_model.max_range")
    min_range: float = _default("sensor_model.min_range")
    no_return_range: float = _default("sensor_model.no_return_range")
    """> 0: recover the firings with no return as rays this long (``sensing.no_return``)."""
    decay_time: float = _default("decay_time")
    threads: int = _default("threads")
    max_voxels: int | None = _default("max_voxels")
    keep_radius: float | None = _default("keep_radius")
    prior_shape: float = _default("prior.shape")
    prior_rate: float = _default("prior.rate")
    cloud_topic: str | None = _default("cloud_topic")
    odom_topic: str | None = _default("odom_topic")
    use_tf: bool = _default("use_tf_poses")
    """Poses from the /tf chain even when the bag has an Odometry topic."""
    fixed_frame: str | None = _default("fixed_frame")
    """TF mode: the frame the poses are in (default: ``odom`` if on the chain, else root)."""
    extrinsic: XyzRpy | None = None
    """Given explicitly (flag): overrides /tf_static."""
    config_extrinsic: XyzRpy | None = None
    """From the YAML (``lidar.*``): used when /tf_static has no chain."""
    deskew: bool = _default("deskew")
    max_gap: float = _default("odom_max_gap")
    point_cloud_min_x: float = _default("point_cloud_min_x")
    point_cloud_max_x: float = _default("point_cloud_max_x")
    point_cloud_min_y: float = _default("point_cloud_min_y")
    point_cloud_max_y: float = _default("point_cloud_max_y")
    point_cloud_min_z: float = _default("point_cloud_min_z")
    point_cloud_max_z: float = _default("point_cloud_max_z")
    max_scans: int | None = _default("max_scans")
    start: float | None = _default("start")
    """Map only clouds stamped at or after this absolute time (s): ``[start, end)``."""
    end: float | None = _default("end")
    """Map only clouds stamped before this absolute time (s)."""
    start_offset: float | None = _default("start_offset")
    """Like ``start``, in seconds after the recording's first cloud."""
    end_offset: float | None = _default("end_offset")
    """Like ``end``, in seconds after the recording's first cloud."""
    start_index: int = _default("start_index")
    """First cloud mapped, by its position in the recording (0 = the first)."""
    end_index: int | None = _default("end_index")
    """Clouds from this position on are not mapped: ``[start_index, end_index)``."""
    every: int = _default("every")
    """Map one cloud in ``every`` of those selected (the first, then every N-th)."""
    odometry: str | None = _default("odometry")
    """``"kiss-icp"``: poses estimated from the clouds (``sources.lidar_odometry``)."""

    def map_settings(self) -> MapSettings:
        """The map section of these options (what ``Mapper`` takes)."""
        return MapSettings.of(lambda name: getattr(self, BY_NAME[name].option))


EXTRINSIC_PARAMETERS = ("lidar.translation", "lidar.rpy")
"""Node parameters that together give ``ReplayOptions.config_extrinsic``."""

REPLAY_FIELDS = {f.name for f in fields(ReplayOptions)}


class ReplayError(RuntimeError):
    """The bag cannot be replayed (unreadable, missing topic, no poses...): says why."""


class ConfigError(ReplayError, ValueError):
    """A parameter file the node would refuse: says which file and why."""


def options_from_config(cfg: NodeConfig, given: set[str]) -> dict[str, Any]:
    """ReplayOptions fields of the node parameters named in ``given``."""
    out: dict[str, Any] = {}
    for name in given:
        setting = BY_NAME[name]
        if not setting.in_replay or name in EXTRINSIC_PARAMETERS:
            continue
        out[setting.option] = cfg.core(name)
    if given & set(EXTRINSIC_PARAMETERS):
        out["config_extrinsic"] = cfg.lidar_xyz_rpy()
    return out


def options_from_yaml(path: str | Path) -> dict[str, Any]:
    """ReplayOptions fields from a parameter file of the node (``config/*.yaml``).

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
            values[setting.option] = setting.core_value(given)
    return ReplayOptions(**values)
