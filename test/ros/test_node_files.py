"""The node's parameter table, its default parameter file and its launch file (no DDS)."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import pytest
import yaml

from mfp_mapper.config.schema import PARAMS, SPECS, NodeConfig, defaults

ROOT = Path(__file__).resolve().parents[2]


def test_every_parameter_has_a_description_and_numeric_ones_a_range() -> None:
    for spec in PARAMS:
        assert len(spec.description) > 20, spec.name
        numeric = isinstance(spec.default, (int, float)) and not isinstance(spec.default, bool)
        if numeric:
            assert spec.lo is not None and spec.hi is not None, spec.name
            assert spec.lo <= spec.default <= spec.hi, spec.name
    for octomap_name in (
        "resolution",
        "frame_id",
        "base_frame_id",
        "sensor_model.max_range",
        "sensor_model.min_range",
        "point_cloud_min_z",
        "point_cloud_max_z",
        "occupancy_min_z",
        "occupancy_max_z",
        "latch",
    ):
        assert octomap_name in SPECS


def test_config_file_holds_exactly_the_defaults() -> None:
    doc = yaml.safe_load((ROOT / "config" / "mfp_mapper.yaml").read_text())
    params = doc["/**"]["ros__parameters"]
    assert params == defaults()
    NodeConfig.from_values(params)  # and they validate


def test_config_validation_names_the_culprit() -> None:
    cfg = NodeConfig.from_values(defaults())
    assert cfg.sensor_model.core("max_range") == 100.0 and math.isinf(cfg.map.core("decay_time"))
    unlimited = NodeConfig.from_values({"sensor_model.max_range": -1.0}).sensor_model
    assert math.isinf(unlimited.core("max_range"))
    for bad, culprit in (
        ({"occupancy_min_z": 3.0}, "occupancy_min_z"),
        ({"point_cloud_min_z": 2.0, "point_cloud_max_z": 1.0}, "point_cloud_min_z"),
        ({"sensor_model.min_range": 5.0, "sensor_model.max_range": 4.0}, "min_range"),
        ({"lidar.translation": [0.0, 1.0]}, "lidar.translation"),
        ({"resolution": 0.0}, "resolution"),
        ({"no_such_parameter": 1}, "no_such_parameter"),
    ):
        with pytest.raises(ValueError, match=culprit):
            NodeConfig.from_values(bad)


def test_launch_file_parses_and_uses_the_installed_names() -> None:
    path = ROOT / "launch" / "mfp_mapper.launch.py"
    source = path.read_text()
    tree = ast.parse(source, filename=str(path))
    compile(tree, str(path), "exec")
    functions = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in functions
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)}
    assert {"mfp_mapper", "mfp_mapper.yaml", "cloud_in", "odom"} <= strings


def test_node_start_removes_temporary_files_of_an_interrupted_save(tmp_path: Path) -> None:
    """A save killed midway leaves its temporary file beside map_path; the next start
    removes it (and only files of dead writers of that map)."""
    import logging

    from mfp_mapper.ros.map_files import initial_mapper

    dead_pid = 2**22 + 12345  # above pid_max: no such process
    stale = tmp_path / f".map.npz.{dead_pid}.abcdef.mfp-tmp"
    other = tmp_path / f".other.npz.{dead_pid}.abcdef.mfp-tmp"
    stale.write_bytes(b"half a map")
    other.write_bytes(b"someone else's")
    cfg = NodeConfig.from_values({"map_path": str(tmp_path / "map.npz")})
    mapper, failed = initial_mapper(cfg, logging.getLogger("test"))
    assert not failed and mapper.num_voxels == 0
    assert not stale.exists() and other.exists()
