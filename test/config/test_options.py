"""The replay CLI's flags and ``--config``, derived from the settings schema."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from mfp_mapper.cli import build_parser
from mfp_mapper.config.replay_options import ConfigError, ReplayOptions, options_from_args
from mfp_mapper.config.schema import SETTINGS


def _opts(*argv: str) -> ReplayOptions:
    args = build_parser().parse_args(["replay", "bag", "-o", "m.npz", *argv])
    return options_from_args(args)


def test_every_flag_of_the_schema_is_a_replay_flag(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["replay", "--help"])
    text = capsys.readouterr().out
    for s in SETTINGS:
        if s.flag:
            assert s.flag in text, s.name
    assert _opts() == ReplayOptions()


def test_no_limit_flags_follow_the_schema() -> None:
    opts = _opts("--max-range", "0", "--decay-time", "0", "--max-voxels", "0")
    assert (opts.sensor_model.max_range, opts.map.decay_time, opts.map.max_voxels) == (0, 0, 0)
    assert math.isinf(opts.sensor_model.core("max_range")) and math.isinf(
        opts.map.core("decay_time")
    )
    assert opts.map.core("max_voxels") is None
    opts = _opts(
        "--max-range", "20", "--decay-time", "5", "--max-voxels", "7", "--keep-radius", "3"
    )
    assert (opts.sensor_model.max_range, opts.map.decay_time) == (20, 5)
    assert (opts.map.max_voxels, opts.map.keep_radius) == (7, 3)
    assert (opts.map.core("max_voxels"), opts.map.core("keep_radius")) == (7, 3)


def test_flags_map_to_their_fields() -> None:
    opts = _opts("--resolution", "0.3", "--min-range", "0.5", "--threads", "2", "--no-deskew",
                 "--max-gap", "0.2", "--cloud-topic", "/c", "--odom-topic", "/o", "--tf",
                 "--fixed-frame", "map", "--max-scans", "4", "--min-z", "-1", "--max-z", "3",
                 "--extrinsic", "1", "2", "3", "0", "0", "0")  # fmt: skip
    assert (opts.map.resolution, opts.map.threads) == (0.3, 2)
    assert (opts.sensor_model.min_range, opts.placement.deskew) == (0.5, False)
    assert (opts.placement.odom_max_gap, opts.replay.cloud_topic) == (0.2, "/c")
    assert (opts.replay.odom_topic, opts.replay.use_tf_poses) == ("/o", True)
    assert (opts.replay.fixed_frame, opts.replay.max_scans) == ("map", 4)
    assert (opts.placement.point_cloud_min_z, opts.placement.point_cloud_max_z) == (-1.0, 3.0)
    assert opts.replay.extrinsic is not None and list(opts.replay.extrinsic[0]) == [1, 2, 3]


@pytest.mark.parametrize(
    "argv",
    [["--resolution", "0"], ["--resolution", "nan"], ["--threads", "1.5"], ["--threads", "-1"],
     ["--max-range", "-5"], ["--max-scans", "-1"], ["--keep-radius", "-1"]],
)  # fmt: skip
def test_out_of_range_flags_are_usage_errors(argv: list[str]) -> None:
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["replay", "bag", "-o", "m.npz", *argv])
    assert info.value.code == 2


def test_flags_override_the_config_file(tmp_path: Path) -> None:
    cfg = tmp_path / "node.yaml"
    cfg.write_text(
        "mfp_mapper:\n  ros__parameters:\n    resolution: 0.25\n    keep_radius: 40.0\n"
        "    sensor_model.max_range: 30.0\n    deskew: false\n"
        "other_node:\n  ros__parameters:\n    resolution: 7.0\n    nonsense: 1\n"
    )
    opts = _opts("--config", str(cfg), "--max-range", "0")
    assert opts.map.resolution == 0.25 and opts.map.keep_radius == 40.0
    assert not opts.placement.deskew
    assert opts.sensor_model.max_range == 0.0  # the flag wins over the file


def test_config_errors_name_the_file(tmp_path: Path) -> None:
    cfg = tmp_path / "node.yaml"
    cfg.write_text("/**:\n  ros__parameters:\n    resolution: 1\n")
    with pytest.raises(ConfigError, match=r"node.yaml: Trying to set parameter 'resolution'"):
        _opts("--config", str(cfg))
    missing = tmp_path / "missing.yaml"
    with pytest.raises(ConfigError, match="missing.yaml: cannot read"):
        _opts("--config", str(missing))


def test_cli_reports_a_bad_config_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from mfp_mapper.cli import main

    cfg = tmp_path / "node.yaml"
    cfg.write_text("mfp_mapper:\n  ros__parameters:\n    resolutoin: 0.2\n")
    out = tmp_path / "m.npz"
    assert main(["replay", str(tmp_path), "-o", str(out), "--config", str(cfg), "-q"]) == 1
    err = capsys.readouterr().err
    assert "unknown parameter(s) resolutoin" in err and "no map written" in err
    assert not out.exists()


def test_an_octomap_server_file_configures_the_replay_with_one_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from mfp_mapper.config.replay_options import options_from_yaml

    path = tmp_path / "octomap_server.yaml"
    path.write_text(
        "/**:\n  ros__parameters:\n    resolution: 0.2\n    point_cloud_max_x: 12.0\n"
        "    sensor_model.hit: 0.7\n    filter_ground_plane: false\n"
    )
    opts = options_from_yaml(path)
    assert opts["resolution"] == 0.2 and opts["point_cloud_max_x"] == 12.0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "filter_ground_plane, sensor_model.hit" in err
    path.write_text("/**:\n  ros__parameters:\n    filter_grond_plane: false\n")
    with pytest.raises(ConfigError, match="filter_grond_plane"):
        options_from_yaml(path)


def test_a_file_setting_the_former_use_tf_warns_once_and_configures_the_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``use_tf`` never had an effect: an old parameter file that sets it still works."""
    from mfp_mapper.config.replay_options import options_from_yaml

    path = tmp_path / "old.yaml"
    path.write_text("/**:\n  ros__parameters:\n    use_tf: true\n    resolution: 0.2\n")
    assert options_from_yaml(path) == {"resolution": 0.2}
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "ignoring former parameter(s) use_tf" in err
