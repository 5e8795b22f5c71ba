"""The `mfp-mapper` command line: every subcommand on a small simulated bag."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mfp_mapper.cli import build_parser, main
from mfp_mapper.mapio.loading import load_map
from mfp_mapper.outputs.export import read_ply


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cli")
    bag = root / "sim"
    assert (
        main(["simulate", str(bag), "--scene", "small", "--scans", "12", "--azimuths", "360"]) == 0
    )
    out = root / "map.npz"
    assert main(["replay", str(bag), "-o", str(out), "--resolution", "0.2", "-q"]) == 0
    return {"root": root, "bag": bag, "map": out, "truth": root / "sim.truth.json"}


def test_help_lists_subcommands_and_examples(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    for cmd in (
        "replay",
        "simulate",
        "export",
        "render",
        "plot-convergence",
        "query",
        "evaluate",
        "demo",
    ):
        assert cmd in text
    assert "examples:" in text
    for cmd in ("replay", "simulate", "export", "render", "plot-convergence", "query", "evaluate"):
        with pytest.raises(SystemExit) as info:
            build_parser().parse_args([cmd, "--help"])
        assert info.value.code == 0
    assert "--cloud-topic" in capsys.readouterr().out


def test_each_command_is_listed_with_its_modules_help() -> None:
    """``cli.main.COMMANDS`` (what ``--help`` lists without importing the modules) says what
    each module's own parser says, in the same order; a parser built for one command has
    that command's arguments and the others' names."""
    import argparse

    from mfp_mapper.cli.main import COMMANDS

    def listed(parser: argparse.ArgumentParser) -> list[tuple[str, str | None]]:
        (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        return [(a.dest, a.help) for a in sub._choices_actions]

    want = [(name, summary) for name, (_, summary) in COMMANDS.items()]
    assert listed(build_parser()) == want
    assert listed(build_parser("query")) == want
    args = build_parser("query").parse_args(["query", "m.npz", "1", "2", "3", "--json"])
    assert args.coords == [1.0, 2.0, 3.0] and args.json and callable(args.run)


@pytest.mark.parametrize(
    "argv", [["--help"], ["query", "--help"], ["query", "missing.npz", "1", "2", "3"]]
)
def test_a_command_imports_only_its_module(argv: list[str]) -> None:
    """``mfp-mapper --help`` imports no subcommand module; ``mfp-mapper query`` only its own
    (not the settings schema the bag commands' flags come from), in a fresh interpreter."""
    code = (
        "import sys\nfrom mfp_mapper.cli import main\ntry:\n    main(sys.argv[1:])\n"
        "except SystemExit:\n    pass\n"
        "print(sorted(m for m in sys.modules if m.startswith('mfp_mapper.c')))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120,
        cwd=Path(__file__).resolve().parents[2], check=True,
    )  # fmt: skip
    loaded = set(json.loads(proc.stdout.strip().splitlines()[-1].replace("'", '"')))
    cli = {m for m in loaded if m.startswith("mfp_mapper.cli.")}
    expected = {"mfp_mapper.cli.main", "mfp_mapper.cli.common"}
    assert cli == (expected if argv == ["--help"] else expected | {"mfp_mapper.cli.query"})
    assert "mfp_mapper.config.schema" not in loaded and "mfp_mapper.core.mapper" not in loaded


def test_replay_writes_a_loadable_map(run: dict[str, Path]) -> None:
    m = load_map(run["map"])
    assert m.resolution == 0.2 and m.frame_id == "odom" and m.num_voxels > 1000


def test_replay_prints_summary(
    run: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "m.npz"
    js = tmp_path / "s.json"
    code = main(["replay", str(run["bag"]), "-o", str(out), "--resolution", "0.5",
                 "--max-scans", "3", "--summary-json", str(js)])  # fmt: skip
    assert code == 0
    text = capsys.readouterr()
    assert "scans        3 used of 3" in text.out
    assert "replay [" in text.err  # the progress bar
    assert json.loads(js.read_text())["scans_used"] == 3


def test_replay_bad_bag_exits_nonzero_and_writes_no_map(
    run: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "m.npz"
    assert main(["replay", str(run["bag"]), "-o", str(out), "--cloud-topic", "/nope", "-q"]) == 1
    err = capsys.readouterr().err
    assert "/nope is not in the bag" in err and "no map written" in err
    assert not out.exists()
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag")
    assert main(["replay", str(junk), "-o", str(out), "-q"]) == 1
    assert not out.exists()
    assert main(["replay", str(run["bag"]), "-o", str(tmp_path / "no" / "m.npz"), "-q"]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_export_ply(run: dict[str, Path], tmp_path: Path) -> None:
    ply = tmp_path / "map.ply"
    assert main(["export", str(run["map"]), "-o", str(ply), "--min-doo", "0.1"]) == 0
    data = read_ply(ply)
    assert data["x"].size > 100 and np.all(data["degree_of_occupancy"] >= 0.1)


def test_render_pictures(run: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "pics"
    assert main(["render", str(run["map"]), "-o", str(out), "--slice-y", "0"]) == 0
    for name in ("doo_topdown.png", "std_topdown.png", "slice.png", "histogram.png"):
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_plot_convergence(tmp_path: Path) -> None:
    assert main(["plot-convergence", "-o", str(tmp_path / "fig9.png")]) == 0
    assert (tmp_path / "fig9.png").read_bytes()[:4] == b"\x89PNG"


def test_query(run: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["query", str(run["map"]), "0", "0", "1", "0", "0", "100", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 2
    assert rows[0]["observed"] and rows[0]["n"] > 0  # inside the cube of medium
    assert not rows[1]["observed"] and rows[1]["degree_of_occupancy"] is None
    assert rows[1]["mean_degree_of_occupancy"] is None  # unknown, not the prior's DoO
    assert main(["query", str(run["map"]), "0", "0", "1"]) == 0
    assert "DoO" in capsys.readouterr().out
    assert main(["query", str(run["map"]), "0", "0"]) == 1


LAUNCHER = Path(__file__).resolve().parents[2] / ".venv" / "bin" / "mfp-mapper"


@pytest.mark.parametrize("kind", ["plain", "histograms", "decaying_histograms"])
def test_query_of_points_as_a_user_types_it(
    run: dict[str, Path], kind: str, tmp_path: Path
) -> None:
    """``mfp-mapper query map.npz X Y Z ...`` (docs/cli.md), the console script in its own
    process: the numbers of the map loaded whole (``Mapper.query`` and ``reflectivity``,
    compiled), for points inside and outside the map, printed and ``--json``, with and
    without ``--stamp``, answered without numba, llvmlite or scipy imported (``python -X
    importtime``): a map without reflectivity histograms, one with them (replay's default
    here), and one with them under decay whose rows refer to other times (as merges write
    them)."""
    from mfp_mapper.mapio.mapfile import map_arrays, write_map_arrays
    from mfp_mapper.outputs.report import jsonable, query_lines, query_rows

    path = run["map"]
    arrays = map_arrays(load_map(run["map"]))
    if kind == "plain":
        path = tmp_path / "plain.npz"
        write_map_arrays(path, {k: v for k, v in arrays.items() if "reflectivity" not in k})
    elif kind == "decaying_histograms":
        path = tmp_path / "decaying.npz"
        t_rows = arrays["reflectivity_t_last"]
        shift = np.random.default_rng(6).uniform(0.0, 3.0, t_rows.shape)
        write_map_arrays(
            path, {**arrays, "decay_time": np.float64(2.0), "reflectivity_t_last": t_rows - shift}
        )
    whole = load_map(path)
    table = whole.stored_reflectivity()
    assert (table is None) == (kind == "plain")
    rng = np.random.default_rng(5)
    centres = whole.voxels().centers
    returns = np.zeros((0, 3)) if table is None else (table.ijk[::50] + 0.5) * whole.resolution
    points = np.concatenate([
        centres[rng.choice(len(centres), 40)], returns + np.asarray(whole.origin),
        rng.uniform(-6, 6, (20, 3)), [[0, 0, 500.0]],
    ])  # fmt: skip
    later = float(whole.stored_voxels().t_last.max()) + 1.5  # a stamp the decay can reach
    coords = [repr(float(v)) for v in points.ravel()]
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    door = [str(LAUNCHER)] if LAUNCHER.exists() else ["-m", "mfp_mapper.cli"]
    for extra, stamp in (([], None), (["--stamp", repr(later)], later)):
        for as_json in (False, True):
            argv = [sys.executable, "-X", "importtime", *door, "query", str(path), *coords]
            proc = subprocess.run(
                argv + extra + (["--json"] if as_json else []),
                capture_output=True, text=True, env=env, timeout=120, check=False,
            )  # fmt: skip
            assert proc.returncode == 0, proc.stderr
            rows = query_rows(whole, points, stamp)
            if as_json:
                assert json.loads(proc.stdout) == jsonable(rows)
            else:
                assert proc.stdout.splitlines()[1:] == query_lines(rows)
            imported = {
                line.split("|")[-1].strip().split(".")[0]
                for line in proc.stderr.splitlines()
                if line.startswith("import time:")
            }
            assert "numpy" in imported and "mfp_mapper" in imported
            assert not imported & {"numba", "llvmlite", "scipy"}


def test_evaluate(run: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    js = tmp_path / "ev.json"
    assert main(["evaluate", str(run["map"]), str(run["truth"]), "--json", str(js)]) == 0
    assert "cube: lambda 1.000" in capsys.readouterr().out
    (cube,) = json.loads(js.read_text())["media"]
    assert abs(cube["pooled"] - 1.0) < 0.1


def test_bad_map_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"nope")
    assert main(["export", str(bad), "-o", str(tmp_path / "x.ply")]) == 1
    assert main(["render", str(tmp_path / "missing.npz"), "-o", str(tmp_path)]) == 1
    assert "missing.npz: no such" in capsys.readouterr().err


def test_demo_runs_end_to_end(tmp_path: Path) -> None:
    """`python -m mfp_mapper.cli demo`, shrunk: prints its findings and where the pictures are."""
    out = tmp_path / "example_output"
    proc = subprocess.run(
        [sys.executable, "-m", "mfp_mapper.cli", "demo", "-o", str(out), "--scans", "30", "-q"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "what it found:" in proc.stdout
    assert "bush: estimated extinction" in proc.stdout
    assert f"pictures are in {(out / 'pictures').resolve()}" in proc.stdout
    for name in ("doo_topdown.png", "slice.png", "histogram.png", "convergence.png"):
        assert (out / "pictures" / name).is_file()
    assert (out / "map.npz").is_file() and (out / "map.ply").is_file()
    assert json.loads((out / "evaluation.json").read_text())["media"]


def test_replay_of_a_scan_folder_with_selection(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    from folder_helpers import write_pcd

    folder = tmp_path / "scans"
    folder.mkdir()
    angles = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    ring = {"x": (4 * np.cos(angles)).astype("<f4"), "y": (4 * np.sin(angles)).astype("<f4"),
            "z": np.zeros(360, "<f4")}  # fmt: skip
    for k in range(6):
        write_pcd(folder / f"{k:03d}.pcd", ring)
    out = tmp_path / "m.npz"
    argv = ["replay", str(folder), "-o", str(out), "--poses", "identity", "--resolution", "0.5",
            "--start", "#1", "--every", "2", "-q"]  # fmt: skip
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "scans        3 used of 6" in text and "identity" in text and out.exists()
    assert main(["replay", str(folder), "-o", str(out), "-q"]) == 1
    assert "--poses FILE" in capsys.readouterr().err
    assert main(["replay", str(tmp_path / "m.npz"), "-o", str(out), "--poses", "x"]) == 1


def test_version(capsys) -> None:  # type: ignore[no-untyped-def]
    import mfp_mapper

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"mfp-mapper {mfp_mapper.__version__}"


def test_query_segments_offline_agree_with_the_core(
    run: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Through the cube of medium (lambda 1 /m, 1.6 m wide) a segment is far less clear than
    the same length of free air beside it; the CLI's numbers are the Mapper's."""
    through = [-1.5, 0.1, 1.2, 1.5, 0.1, 1.2]
    beside = [2.0, 2.0, 1.0, 5.0, 2.0, 1.0]
    seg_file = tmp_path / "segments.txt"
    seg_file.write_text("# x0 y0 z0 x1 y1 z1\n" + ", ".join(map(str, beside)) + "\n")
    argv = ["query", str(run["map"]), "0", "0", "1", "--segment", *map(str, through)]
    assert main([*argv, "--segments", str(seg_file), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["points"]) == 1 and out["points"][0]["observed"]
    cube, air = out["segments"]
    assert cube["clear_probability"] < 0.5 * air["clear_probability"]
    assert cube["length"] == pytest.approx(3.0) and cube["unknown_length"] == 0.0
    want = load_map(run["map"]).query_segments([through[:3], beside[:3]], [through[3:], beside[3:]])
    assert [cube["clear_probability"], air["clear_probability"]] == pytest.approx(
        want.clear_probability.tolist(), rel=1e-12
    )
    assert main(["query", str(run["map"]), "--segment", *map(str, through)]) == 0
    assert "clear with probability" in capsys.readouterr().out
    seg_file.write_text("1 2 3 4 5\n")
    assert main(["query", str(run["map"]), "--segments", str(seg_file)]) == 1
    assert "segments.txt:1: a segment is 6 numbers, got 5" in capsys.readouterr().err
    assert main(["query", str(run["map"])]) == 1
    assert "nothing to query" in capsys.readouterr().err
    assert main(["query", str(run["map"]), "--segment", "0", "0", "0", "1e9", "0", "0"]) == 1
    assert "voxels" in capsys.readouterr().err
