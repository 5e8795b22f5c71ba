"""The settings schema derived from the sections: SETTINGS, the YAML, ReplayOptions, NodeConfig,
the node's type and range checks as the CLI applies them, the former use_tf. No ROS."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import pytest

from mfp_mapper.config.param_file import load_node_parameters
from mfp_mapper.config.replay_options import ReplayOptions
from mfp_mapper.config.schema import (
    BY_NAME,
    NODE_SECTIONS,
    PARAMS,
    SETTINGS,
    SPECS,
    NodeConfig,
    check_parameters,
    check_value,
    defaults,
    defaults_yaml,
    python_type_name,
)

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "mfp_mapper.yaml"


def test_each_setting_is_defined_once_with_a_consistent_entry() -> None:
    assert len(BY_NAME) == len(SETTINGS)
    flags = [s.flag for s in SETTINGS if s.flag]
    assert len(flags) == len(set(flags))
    for s in SETTINGS:
        assert s.applies in ("node", "replay", "both"), s.name
        assert len(s.description) > 20 and s.description.endswith("."), s.name
        if s.default is not None:
            assert python_type_name(s.default) == s.ros_type, s.name
        if s.type is list:
            assert s.length is not None and (s.default is None or len(s.default) == s.length)
        if s.lo is not None:
            assert s.hi is not None and s.lo < s.hi, s.name
            if s.default is not None:
                assert s.check_range(s.default) is None, s.name
        if s.dynamic:
            # only the node changes settings at run time (a replay setting it shares may be one)
            assert s.is_parameter, f"{s.name}: only the node changes settings at run time"
    assert [p.name for p in PARAMS] == list(SPECS)
    assert all(not s.is_parameter for s in SETTINGS if s.name not in SPECS)


def test_config_yaml_is_generated_from_the_schema() -> None:
    assert CONFIG.read_text() == defaults_yaml(), (
        "config/mfp_mapper.yaml is stale: "
        "python -m mfp_mapper.config.schema > config/mfp_mapper.yaml"
    )
    # both ways, with the node's own reading of the file: every entry, no extra key, same types
    values = load_node_parameters(CONFIG)
    assert list(values) == list(defaults())
    for name, value in values.items():
        assert type(value) is type(SPECS[name].default) and value == SPECS[name].default, name
    assert check_parameters(values) == NodeConfig.from_values({})


def test_replay_options_derive_from_the_schema() -> None:
    opts = ReplayOptions()
    for s in SETTINGS:
        if not s.in_replay:
            continue
        section = getattr(opts, s.section)
        assert getattr(section, s.field) == s.held(s.default), s.name
    assert opts.config_extrinsic is None
    # fields are named without their section; a misspelt one is an error
    opts = ReplayOptions.of(resolution=0.3, odom_max_gap=0.2, use_tf_poses=True, every=2)
    assert (opts.map.resolution, opts.placement.odom_max_gap) == (0.3, 0.2)
    assert opts.replay.use_tf_poses and opts.but(every=3).replay.every == 3
    with pytest.raises(TypeError, match="max_gap"):
        ReplayOptions.of(max_gap=0.2)
    assert math.isinf(opts.map.core("decay_time")) and opts.map.core("max_voxels") is None
    assert opts.map.core("keep_radius") is None


def test_no_limit_rules_come_from_the_schema() -> None:
    assert math.isinf(BY_NAME["sensor_model.max_range"].core_value(-1.0))
    assert math.isinf(BY_NAME["decay_time"].core_value(0.0))
    assert BY_NAME["max_voxels"].core_value(0) is None
    assert BY_NAME["keep_radius"].core_value(0.0) is None
    assert BY_NAME["keep_radius"].core_value(2.5) == 2.5
    assert BY_NAME["resolution"].core_value(0.2) == 0.2


def test_node_config_holds_the_sections_and_gives_keep_radius() -> None:
    cfg = NodeConfig.from_values({"keep_radius": 30.0, "max_voxels": 1000})
    assert cfg.map.resolution == 0.1 and cfg.placement.deskew
    assert cfg.sensor_model.max_range == 100.0 and math.isinf(cfg.map.core("decay_time"))
    assert cfg.values()["keep_radius"] == 30.0
    assert cfg.core("keep_radius") == 30.0 and NodeConfig().core("keep_radius") is None
    from mfp_mapper.core.mapper import Mapper

    mapper = Mapper.of(cfg.map, cfg.sensor_model)
    assert (mapper.keep_radius, mapper.max_voxels, mapper.resolution) == (30.0, 1000, 0.1)
    assert Mapper.of(NodeConfig().map, NodeConfig().sensor_model).keep_radius is None


def test_the_replay_and_the_node_build_the_same_map() -> None:
    from mfp_mapper.core.mapper import mapper_kwargs

    node, replay = NodeConfig.from_values({}), ReplayOptions()
    assert (node.map, node.sensor_model) == (replay.map, replay.sensor_model)
    values = {"resolution": 0.2, "decay_time": 30.0, "sensor_model.max_range": -1.0}
    node = NodeConfig.from_values(values)
    replay = ReplayOptions.of(resolution=0.2, decay_time=30.0, max_range=-1.0)
    kwargs = mapper_kwargs(node.map, node.sensor_model)
    assert kwargs == mapper_kwargs(replay.map, replay.sensor_model)
    assert math.isinf(kwargs["max_range"]) and kwargs["decay_time"] == 30.0


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("resolution", 1, "Trying to set parameter 'resolution' to '1' of type 'INTEGER', "
         "expecting type 'DOUBLE': resolution"),
        ("threads", 2.0, "Trying to set parameter 'threads' to '2.0' of type 'DOUBLE', "
         "expecting type 'INTEGER': threads"),
        ("lidar.rpy", [0, 0, 0], "of type 'INTEGER_ARRAY', expecting type 'DOUBLE_ARRAY'"),
        ("resolution", 0.001, "Invalid parameter value (0.001) for parameter. Reason: Parameter "
         "resolution out of range Min: 0.01, Max: 10.0, value: 0.001: resolution"),
        ("threads", -1, "Reason: Parameter threads out of range. Min: 0, Max: 64, value: -1"),
    ],
)  # fmt: skip
def test_values_are_checked_with_rclpys_rules_and_words(
    name: str, value: object, message: str
) -> None:
    with pytest.raises(ValueError) as info:
        check_value(SPECS[name], value)
    assert message in str(info.value)


def test_range_edges_pass_as_in_rclpy() -> None:
    check_value(SPECS["resolution"], 10.0 * (1 + 1e-9))  # rclpy's relative tolerance
    check_value(SPECS["threads"], 64)


def test_unknown_names_are_an_error_and_rclpys_own_are_not() -> None:
    with pytest.raises(ValueError, match="unknown parameter.*resolutoin"):
        check_parameters({"resolutoin": 0.2})
    cfg = check_parameters({"use_sim_time": True, "qos_overrides./odom.subscription.depth": 5})
    assert cfg == NodeConfig.from_values({})
    with pytest.raises(ValueError, match="unknown parameter.*cloud_topic"):
        check_parameters({"cloud_topic": "/points"})  # a replay setting, not a node parameter


def test_node_config_has_one_typed_field_per_parameter() -> None:
    cfg = NodeConfig.from_values({})
    assert [f.name for f in fields(NodeConfig)] == [s.KEY for s in NODE_SECTIONS]
    assert list(cfg.values()) == [p.name for p in PARAMS]
    for p in PARAMS:
        value = getattr(getattr(cfg, p.section), p.field)
        assert isinstance(value, tuple if p.type is list else p.type), p.name


def test_octomap_server_names_pass_with_a_warning_and_typos_do_not() -> None:
    from mfp_mapper.config.schema import OCTOMAP_ONLY, octomap_only_parameters

    octomap = {"sensor_model.hit": 0.7, "filter_ground_plane": False, "resolution": 0.2}
    cfg = check_parameters(octomap)  # octomap-only names are no error
    assert cfg.map.resolution == 0.2
    assert octomap_only_parameters(list(octomap)) == ["filter_ground_plane", "sensor_model.hit"]
    # an octomap-only name never shadows one of ours
    assert not set(OCTOMAP_ONLY) & set(SPECS)
    with pytest.raises(ValueError, match="unknown parameter.*sensor_model.hitt"):
        check_parameters({"sensor_model.hitt": 0.7})


def test_the_point_cloud_box_and_its_run_time_changes_are_checked() -> None:
    for axis in "xyz":
        assert SPECS[f"point_cloud_min_{axis}"].dynamic
        with pytest.raises(ValueError, match=f"point_cloud_min_{axis} must be below"):
            NodeConfig.from_values({f"point_cloud_min_{axis}": 5.0, f"point_cloud_max_{axis}": 1.0})
    assert SPECS["sensor_model.max_range"].dynamic
    with pytest.raises(ValueError, match="min_range must be below"):
        NodeConfig.from_values({"sensor_model.min_range": 5.0, "sensor_model.max_range": 4.0})


def test_localization_needs_an_odometry_frame_name() -> None:
    """An empty ``localization.odom_frame`` would publish map -> '' on /tf (tf2 rejects it)."""
    from mfp_mapper.config.schema import NodeConfig

    for name in ("", "/", " "):
        with pytest.raises(ValueError, match="localization.odom_frame must name a frame"):
            NodeConfig.from_values({"localization.enabled": True, "localization.odom_frame": name})
    NodeConfig.from_values({"localization.odom_frame": ""})  # not localizing: unused


def test_the_former_use_tf_parameter_is_accepted_and_ignored() -> None:
    from mfp_mapper.config.schema import RETIRED, retired_parameters, unknown_parameters

    assert "use_tf" not in BY_NAME and "use_tf" in RETIRED
    assert check_parameters({"use_tf": True}) == NodeConfig()
    assert unknown_parameters(["use_tf"]) == [] and retired_parameters(["use_tf", "x"]) == [
        "use_tf"
    ]


def test_threads_zero_is_one_a_core_of_the_process_at_most_four() -> None:
    """``threads`` 0 (the default): one thread a core this process may run on, at most
    ``AUTOMATIC_THREADS_MAX``; a child pinned to one core gets one; a count set is kept;
    the core's ``Mapper`` itself defaults to one thread."""
    from mfp_mapper.config.sections import MapSection, SensorModelSection
    from mfp_mapper.config.setting import AUTOMATIC_THREADS_MAX, automatic_threads
    from mfp_mapper.core.mapper import Mapper, mapper_kwargs

    cores = len(os.sched_getaffinity(0))
    assert MapSection().threads == 0
    assert automatic_threads() == min(cores, AUTOMATIC_THREADS_MAX)
    assert MapSection().core("threads") == automatic_threads()
    assert MapSection(threads=3).core("threads") == 3
    assert mapper_kwargs(MapSection(), SensorModelSection())["threads"] == automatic_threads()
    assert Mapper(0.5).threads == 1
    pinned = subprocess.run(
        [sys.executable, "-c", PINNED_CHILD],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert pinned.stdout.split() == ["1", "1"]


PINNED_CHILD = """
import os
os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
from mfp_mapper.config.sections import MapSection
from mfp_mapper.config.setting import automatic_threads
print(automatic_threads(), MapSection().core("threads"))
"""
