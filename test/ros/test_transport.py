"""The large-data profile: the launch file's environment for the node, the node's loss line.

``launch`` and ``launch_ros`` are not on PyPI, so the launch file cannot be run here: its
logic lives in ``mfp_mapper.ros.transport.node_environment`` (tested below) and the launch
file is checked to call it with its ``large_data_profile`` argument (read as text).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from mfp_mapper.ros.transport import (
    PROFILE_ENV,
    node_environment,
    profile_path,
    transport_loss_text,
)

ROOT = Path(__file__).resolve().parents[2]
PROFILE = "/opt/ws/share/mfp_mapper/config/fastdds_large_data.xml"


def test_the_node_gets_the_profile_by_default() -> None:
    env, why = node_environment({}, PROFILE, True)
    assert env == {PROFILE_ENV: PROFILE} and PROFILE in why
    env, _ = node_environment({"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}, PROFILE, True)
    assert env == {PROFILE_ENV: PROFILE}


@pytest.mark.parametrize(
    ("environ", "enabled", "reason"),
    [
        ({}, False, "large_data_profile:=false"),
        ({PROFILE_ENV: "/home/me/mine.xml"}, True, "/home/me/mine.xml"),
        ({"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}, True, "not Fast DDS"),
    ],
)
def test_the_profile_is_left_out_when_off_or_meaningless(
    environ: dict[str, str], enabled: bool, reason: str
) -> None:
    env, why = node_environment(environ, PROFILE, enabled)
    assert env == {} and reason in why


def test_the_profile_file_is_found_in_this_checkout() -> None:
    path = Path(profile_path())
    assert path.is_file() and path.name == "fastdds_large_data.xml"


def test_the_loss_line_names_the_profile_and_the_backlog(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv(PROFILE_ENV, raising=False)
    text = transport_loss_text(3, (1, 5))
    assert text.startswith("3 cloud(s) lost in transport")
    assert "clouds_lost_transport" in text and "queue_full" in text and "1 of 5" in text
    assert "fastdds_large_data.xml" in text and "driver" in text
    assert f"no {PROFILE_ENV}" in text
    monkeypatch.setenv(PROFILE_ENV, "/x.xml")
    assert f"{PROFILE_ENV}=/x.xml" in transport_loss_text(1, (0, 5))


def test_the_launch_file_builds_the_node_environment_from_its_argument() -> None:
    source = (ROOT / "launch" / "mfp_mapper.launch.py").read_text()
    tree = ast.parse(source)
    declared = {
        node.args[0].value
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and getattr(node.func, "id", None) == "DeclareLaunchArgument"
        and isinstance(node.args[0], ast.Constant)
    }
    assert {"large_data_profile", "autostart", "octomap_topics", "node_name"} <= declared
    calls = [
        node
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "node_environment"
    ]
    assert len(calls) == 1 and "large_data_profile" in ast.unparse(calls[0])
    assert "additional_env=env" in source
