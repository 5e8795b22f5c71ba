"""Fleet mapping: several recordings, time windows, Dask workers, merges, bad bags.

The reference is the sequential replay: the same scans (the replay's own pipeline, seen
through ``on_scan``) integrated in time order into one Mapper.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mfp_mapper import Mapper
from mfp_mapper.mapio.loading import load_map, save_map
from mfp_mapper.mapio.mapfile import map_arrays
from mfp_mapper.mapio.merge_files import merge_maps
from mfp_mapper.mapio.tiles import TiledMap
from mfp_mapper.mapping.fleet import FleetError, FleetOptions, map_fleet, plan_tasks
from mfp_mapper.mapping.replay import ReplayOptions, replay
from mfp_mapper.sources.simulate import preset, simulate

SMALL = replace(preset("small"), scans=8, azimuths=180)
OPTS = ReplayOptions.of(resolution=0.25, decay_time=0.6, max_range=20.0)
CHUNK = 0.35  # seconds: each 0.8 s recording is split in three windows


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    root = tmp_path_factory.mktemp("fleet")
    # three robots on the same circle; the second starts while the first still drives
    starts = (1_700_000_000.0, 1_700_000_000.5, 1_700_000_003.0)
    return [
        simulate(root / f"robot{i}", replace(SMALL, start_time=t0, seed=i)).bag
        for i, t0 in enumerate(starts)
    ]


def _sequential(bags: list[Path], opts: ReplayOptions) -> dict[str, np.ndarray]:
    scans: list[tuple[float, np.ndarray, np.ndarray]] = []
    for bag in bags:
        replay(bag, opts, progress=False, on_scan=lambda t, p, o: scans.append((t, p, o)))
    mapper = Mapper(
        opts.map.resolution, max_range=opts.sensor_model.max_range, decay_time=opts.map.decay_time
    )
    for stamp, points, origins in sorted(scans, key=lambda s: s[0]):
        mapper.integrate(points, origins, stamp)
    arrays = map_arrays(mapper)
    arrays["frame_id"] = np.str_("odom")
    return arrays


@pytest.fixture(scope="module")
def reference(bags: list[Path]) -> dict[str, np.ndarray]:
    return _sequential(bags, OPTS)


def _assert_same_map(got: Mapper, want: dict[str, np.ndarray]) -> None:
    a = map_arrays(got)
    assert str(a["frame_id"]) == str(want["frame_id"])
    assert float(a["decay_time"]) == float(want["decay_time"])
    oa, ob = np.lexsort(a["ijk"].T), np.lexsort(want["ijk"].T)
    np.testing.assert_array_equal(a["ijk"][oa], want["ijk"][ob])
    for key in ("s", "n"):  # float32 sums in the store: rounding of the summation order
        np.testing.assert_allclose(a[key][oa], want[key][ob], rtol=3e-5, atol=1e-5)
    np.testing.assert_array_equal(a["t_last"][oa], want["t_last"][ob])


def test_windows_tile_the_time_axis(bags: list[Path]) -> None:
    tasks, failed = plan_tasks([str(b) for b in bags], CHUNK)
    assert not failed and len(tasks) >= 6
    for bag in bags:
        mine = [t for t in tasks if t.recording == str(bag)]
        assert mine[0].start is None and mine[-1].end is None
        for a, b in zip(mine[:-1], mine[1:], strict=True):
            assert a.end == b.start
    assert len(plan_tasks([str(bags[0])], None)[0]) == 1


def test_replay_windows_split_the_clouds_without_overlap(bags: list[Path]) -> None:
    from mfp_mapper.mapping.replay import NothingMapped

    stamps: list[float] = []
    replay(bags[0], OPTS, progress=False, on_scan=lambda t, p, o: stamps.append(t))
    cut = stamps[3]  # a cloud exactly on the bound goes to the later window
    seen: list[list[float]] = [[], []]
    for k, (lo, hi) in enumerate(((None, cut), (cut, None))):
        window = OPTS.but(start=lo, end=hi)
        replay(bags[0], window, progress=False, on_scan=lambda t, p, o, k=k: seen[k].append(t))
    assert seen == [stamps[:3], stamps[3:]]
    with pytest.raises(NothingMapped, match="no cloud stamp lies in the window"):
        replay(bags[0], OPTS.but(start=0.0, end=1.0), progress=False)


def test_sequential_fleet_with_windows_equals_the_sequential_replay(
    bags: list[Path], reference: dict[str, np.ndarray], tmp_path: Path
) -> None:
    out = tmp_path / "fleet.npz"
    result = map_fleet(bags, out, OPTS, FleetOptions(chunk_seconds=CHUNK, progress=False))
    assert len(result.tasks) >= 6 and not result.skipped
    assert sum(s.scans_used for s in result.summaries) == 3 * SMALL.scans
    assert "3 recordings" in result.format()
    _assert_same_map(load_map(out), reference)
    assert not list(tmp_path.glob(".mfp-fleet-*"))  # the work folder is gone


def test_two_dask_workers_equal_the_sequential_replay(
    bags: list[Path], reference: dict[str, np.ndarray], tmp_path: Path
) -> None:
    pytest.importorskip("distributed")
    out = tmp_path / "fleet_tiles"
    fleet = FleetOptions(workers=2, chunk_seconds=CHUNK, progress=False, tile_blocks=2)
    result = map_fleet(bags, out, OPTS, fleet)
    assert "LocalCluster, 2 worker" in result.executor
    assert result.tiles == len(TiledMap(out).tiles) > 1
    _assert_same_map(load_map(out), reference)


def test_an_existing_dask_cluster_by_its_scheduler_address(
    bags: list[Path], reference: dict[str, np.ndarray], tmp_path: Path
) -> None:
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, dashboard_address=None, processes=True
    ) as cluster:
        fleet = FleetOptions(scheduler=cluster.scheduler_address, progress=False)
        result = map_fleet(bags, tmp_path / "m.npz", OPTS, fleet)
        assert cluster.scheduler_address in result.executor
        assert len(cluster.scheduler_info["workers"]) == 1  # the cluster is left running
    _assert_same_map(load_map(tmp_path / "m.npz"), reference)


def test_merge_of_per_bag_maps_equals_the_sequential_replay(
    bags: list[Path], reference: dict[str, np.ndarray], tmp_path: Path
) -> None:
    paths = []
    for i, bag in enumerate(bags):
        paths.append(tmp_path / f"bag{i}.npz")
        save_map(replay(bag, OPTS, progress=False).mapper, paths[-1])
    merged = merge_maps(paths, tmp_path / "merged.npz")
    assert merged.inputs == 3
    _assert_same_map(load_map(tmp_path / "merged.npz"), reference)
    # tiled inputs and outputs, mixed with a map file
    merge_maps(paths[:2], tmp_path / "two_tiles", tile_blocks=2)
    merge_maps([tmp_path / "two_tiles", paths[2]], tmp_path / "all_tiles", tile_blocks=3)
    _assert_same_map(load_map(tmp_path / "all_tiles"), reference)


def test_merge_refuses_maps_of_other_settings(bags: list[Path], tmp_path: Path) -> None:
    from mfp_mapper.core.merge import MergeError

    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    save_map(replay(bags[0], OPTS, progress=False).mapper, a)
    save_map(replay(bags[1], OPTS.but(resolution=0.5), progress=False).mapper, b)
    with pytest.raises(MergeError, match=r"different resolution.*b\.npz"):
        merge_maps([a, b], tmp_path / "c.npz")
    assert not (tmp_path / "c.npz").exists() and not list(tmp_path.glob(".mfp-merge-*"))


@pytest.mark.parametrize("chunk", [None, CHUNK])
def test_a_bad_bag_fails_the_run_or_is_skipped(
    bags: list[Path], tmp_path: Path, chunk: float | None
) -> None:
    bad = tmp_path / "broken.bag"
    bad.write_bytes(b"#ROSBAG V2.0\n" + b"\x00garbage" * 50)
    out = tmp_path / "fleet.npz"
    quiet = FleetOptions(progress=False, chunk_seconds=chunk)
    with pytest.raises(FleetError, match=r"broken\.bag.*no map written"):
        map_fleet([bags[0], bad, bags[2]], out, OPTS, quiet)
    assert not out.exists()
    result = map_fleet([bags[0], bad, bags[2]], out, OPTS, replace(quiet, skip_bad=True))
    assert list(result.skipped) == [str(bad)] and "broken.bag" in result.format()
    _assert_same_map(load_map(out), _sequential([bags[0], bags[2]], OPTS))


def test_a_recording_with_nothing_mappable_in_any_window_fails(
    bags: list[Path], tmp_path: Path
) -> None:
    no_pose = OPTS.but(odom_max_gap=1e-4)  # odometry at 50 Hz: every cloud lacks a pose
    fleet = FleetOptions(progress=False, chunk_seconds=CHUNK)
    with pytest.raises(FleetError, match=r"robot1.*no cloud could be mapped"):
        map_fleet([bags[1]], tmp_path / "m.npz", no_pose, fleet)
    assert not (tmp_path / "m.npz").exists()


def test_progress_lines_name_the_stage_and_the_task(bags: list[Path], tmp_path: Path) -> None:
    import io

    from mfp_mapper.mapping.executors import StageProgress

    stream = io.StringIO()
    progress = StageProgress("replay", 3, stream=stream)
    progress.update(1, "robot0")
    progress.update(3, "robot2")
    last = stream.getvalue().replace("\r", "\n").strip().splitlines()[-1]
    assert last.startswith("replay 3/3 tasks") and "(robot2)" in last


def test_max_voxels_is_refused_for_several_tasks(bags: list[Path], tmp_path: Path) -> None:
    windows = FleetOptions(chunk_seconds=CHUNK, progress=False)
    with pytest.raises(FleetError, match="max_voxels"):
        map_fleet(bags, tmp_path / "m.npz", OPTS.but(max_voxels=1000), windows)
    with pytest.raises(FleetError, match="max_scans"):
        map_fleet(bags, tmp_path / "m.npz", OPTS.but(max_scans=3), FleetOptions())
    # one mapper in turn evicts as one long replay does
    bounded = OPTS.but(max_voxels=20_000)
    result = map_fleet(bags, tmp_path / "m.npz", bounded, FleetOptions(progress=False))
    assert 0 < result.voxels <= 20_000


# --- one mapper in turn, limits, cleanup ----------------------------------------------------


def test_in_turn_equals_the_fleet_path_and_the_sequential_replay(
    bags: list[Path], reference: dict[str, np.ndarray], tmp_path: Path
) -> None:
    in_turn = map_fleet(bags, tmp_path / "turn.npz", OPTS, FleetOptions(progress=False))
    assert in_turn.executor.startswith("in turn") and len(in_turn.tasks) == 3
    assert sum(s.scans_used for s in in_turn.summaries) == 3 * SMALL.scans
    windows = FleetOptions(chunk_seconds=CHUNK, progress=False)
    map_fleet(bags, tmp_path / "fleet.npz", OPTS, windows)
    fleet_map = map_arrays(load_map(tmp_path / "fleet.npz"))
    _assert_same_map(load_map(tmp_path / "turn.npz"), fleet_map)
    _assert_same_map(load_map(tmp_path / "turn.npz"), reference)
    tiles = map_fleet(bags, tmp_path / "tiles", OPTS, FleetOptions(progress=False, tile_blocks=2))
    assert tiles.tiles == len(TiledMap(tmp_path / "tiles").tiles) > 1
    _assert_same_map(load_map(tmp_path / "tiles"), reference)
    assert not list(tmp_path.glob(".mfp-fleet-*"))


def test_duplicate_inputs_are_refused_unless_allowed(bags: list[Path], tmp_path: Path) -> None:
    twice = [bags[0], Path(str(bags[0]) + "/"), bags[1]]
    with pytest.raises(FleetError, match="given twice.*--allow-duplicates"):
        map_fleet(twice, tmp_path / "m.npz", OPTS, FleetOptions(progress=False))
    link = tmp_path / "same"
    link.symlink_to(bags[1])
    with pytest.raises(FleetError, match="given twice"):
        map_fleet([bags[1], link], tmp_path / "m.npz", OPTS, FleetOptions(progress=False))
    assert not (tmp_path / "m.npz").exists()
    allowed = FleetOptions(progress=False, allow_duplicates=True)
    result = map_fleet([bags[0], bags[0]], tmp_path / "m.npz", OPTS, allowed)
    assert len(result.tasks) == 2


def test_tiny_chunks_and_many_workers_are_bounded(bags: list[Path]) -> None:
    lines: list[str] = []
    tasks, failed = plan_tasks([str(bags[0])], 1e-9, max_windows=16, log=lines.append)
    assert not failed and len(tasks) == SMALL.scans  # one window per cloud at most
    assert "1e-09" in lines[0] and f"{SMALL.scans} windows" in lines[0]
    tasks, _ = plan_tasks([str(bags[0])], 1e-3, max_windows=4, log=lines.append)
    assert len(tasks) == 4
    from mfp_mapper.mapping.fleet import _worker_count, default_workers

    cut = _worker_count(FleetOptions(workers=64), [], lines.append)
    assert cut == default_workers() and "--workers 64: using" in lines[-1]


def test_scratch_of_dead_runs_is_removed_and_live_ones_kept(tmp_path: Path) -> None:
    import os
    import socket
    import time

    from mfp_mapper.mapping.fleet import SCRATCH_STALE_SECONDS, remove_dead_scratch

    host = socket.gethostname()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip
    folders = {}
    for name, owner in [("dead", f"{host} {dead}"), ("alive", f"{host} {os.getpid()}"),
                        ("remote", f"elsewhere {dead}"), ("old", None), ("new", None)]:  # fmt: skip
        folders[name] = tmp_path / f".mfp-fleet-{name}"
        (folders[name] / "partials").mkdir(parents=True)
        if owner is not None:
            (folders[name] / "owner").write_text(owner + "\n")
    past = time.time() - SCRATCH_STALE_SECONDS - 10
    os.utime(folders["old"], (past, past))
    (tmp_path / ".mfp-fleet-file").write_text("not a folder")
    (tmp_path / "keep").mkdir()
    lines: list[str] = []
    removed = remove_dead_scratch(tmp_path, lines.append)
    assert sorted(p.name for p in removed) == [".mfp-fleet-dead", ".mfp-fleet-old"]
    assert all(folders[k].exists() for k in ("alive", "remote", "new"))
    assert (tmp_path / ".mfp-fleet-file").exists() and (tmp_path / "keep").exists()
    assert "removed 2 scratch folder(s)" in lines[0]


def test_a_killed_fleet_run_leaves_scratch_the_next_run_removes(
    bags: list[Path], tmp_path: Path
) -> None:
    import os
    import signal
    import time

    out = tmp_path / "m.npz"
    cmd = [sys.executable, "-m", "mfp_mapper.cli", "replay", *map(str, bags), "-o", str(out),
           "--chunk-seconds", str(CHUNK), *FLAGS]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(".mfp-fleet-*/partials/task*")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert list(tmp_path.glob(".mfp-fleet-*")) and not out.exists()
    run = subprocess.run([*cmd[:-1]], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "removed 1 scratch folder" in run.stderr
    assert not list(tmp_path.glob(".mfp-fleet-*")) and out.exists()


def test_sigterm_ends_a_fleet_run_cleanly(bags: list[Path], tmp_path: Path) -> None:
    import os
    import signal
    import time

    out = tmp_path / "m.npz"
    cmd = [sys.executable, "-m", "mfp_mapper.cli", "replay", *map(str, bags), "-o", str(out),
           "--chunk-seconds", str(CHUNK), *FLAGS]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(".mfp-fleet-*/partials/task*")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "Traceback" not in err and "interrupted" in err
    assert not list(tmp_path.glob(".mfp-fleet-*")) and not out.exists()


def test_bad_work_dir_and_read_only_output_are_one_line(
    bags: list[Path], tmp_path: Path, capsys
) -> None:  # type: ignore[no-untyped-def]
    import os

    from mfp_mapper.cli import main

    out = str(tmp_path / "m.npz")
    base = ["replay", str(bags[0]), str(bags[1]), "-o", out, "--chunk-seconds", "0.35", *FLAGS]
    assert main([*base, "--work-dir", str(tmp_path / "missing")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "missing: not an existing directory" in err
    (tmp_path / "afile").write_text("x")
    assert main([*base, "--work-dir", str(tmp_path / "afile")]) == 1
    assert "afile: not an existing directory" in capsys.readouterr().err
    if os.geteuid() != 0:  # root writes anywhere: the permission check cannot fail then
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        assert main([*base, "--work-dir", str(locked)]) == 1
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
        assert main(["replay", str(bags[0]), "-o", str(locked / "m.npz"), *FLAGS]) == 1
        assert "cannot write in" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()


def test_a_failing_recording_on_workers_is_one_line(bags: list[Path], tmp_path: Path) -> None:
    pytest.importorskip("distributed")
    bad = tmp_path / "broken.bag"
    bad.write_bytes(b"#ROSBAG V2.0\n" + b"\x00garbage" * 50)
    cmd = [sys.executable, "-m", "mfp_mapper.cli", "replay", str(bags[0]), str(bad),
           "-o", str(tmp_path / "m.npz"), "--workers", "2", *FLAGS]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert run.returncode == 1, run.stderr
    assert run.stderr.count("broken.bag") == 1, run.stderr
    assert len(run.stderr.strip().splitlines()) == 1, run.stderr  # no IOLoop traceback
    left = list(tmp_path.glob(".mfp-fleet-*"))
    assert not left and not (tmp_path / "m.npz").exists(), (left, run.stderr)


def test_scan_folders_among_several_inputs(bags: list[Path], tmp_path: Path) -> None:
    from folder_helpers import bag_contents, write_pcd

    from mfp_mapper.sources.opener import open_recording

    folders = []
    for i, bag in enumerate(bags[:2]):
        clouds, _ = bag_contents(bag)
        folder = tmp_path / f"frames{i}"
        folder.mkdir()
        for stamp, records in clouds[:2]:
            sec, nsec = int(stamp), round((stamp - int(stamp)) * 1e9)
            columns = {n: records[n] for n in ("x", "y", "z")}
            write_pcd(folder / f"cloud_{sec}_{nsec}.pcd", columns)
        folders.append(folder)
    fleet = FleetOptions(progress=False, poses="identity")
    result = map_fleet(folders, tmp_path / "m.npz", OPTS, fleet)
    assert len(result.tasks) == 2 and sum(s.scans_used for s in result.summaries) == 4
    mapper = replay(open_recording(folders[0], OPTS, "identity"), OPTS, progress=False).mapper
    replay(open_recording(folders[1], OPTS, "identity"), OPTS, progress=False, into=mapper)
    _assert_same_map(load_map(tmp_path / "m.npz"), map_arrays(mapper))
    with pytest.raises(FleetError, match="--poses FILE names the poses of one scan folder"):
        map_fleet(folders, tmp_path / "n.npz", OPTS, FleetOptions(poses=str(tmp_path / "p")))
    with pytest.raises(FleetError, match="--poses and --times are for folders"):
        map_fleet([folders[0], bags[0]], tmp_path / "n.npz", OPTS, fleet)


def test_the_live_node_never_imports_dask() -> None:
    code = (
        "import sys\n"
        "try:\n    import mfp_mapper.ros.node\nexcept ImportError as e:\n"
        "    print('skip', e); sys.exit(0)\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed'))\n"
        "print('dask modules:', bad); sys.exit(1 if bad else 0)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    if run.stdout.startswith("skip"):
        pytest.skip(f"rclpy not importable here: {run.stdout.strip()}")
    assert run.returncode == 0, run.stdout + run.stderr


# --- the command line ---------------------------------------------------------------------

FLAGS = ["--resolution", "0.25", "--decay-time", "0.6", "--max-range", "20", "-q"]


def test_cli_replay_of_several_bags_on_two_workers(
    bags: list[Path], reference: dict[str, np.ndarray], tmp_path: Path, capsys
) -> None:  # type: ignore[no-untyped-def]
    from mfp_mapper.cli import main

    pytest.importorskip("distributed")
    out = tmp_path / "fleet.npz"
    args = ["replay", *map(str, bags), "-o", str(out), "--workers", "2", "--chunk-seconds", "0.35"]
    assert main([*args, *FLAGS]) == 0
    assert "3 recordings in 12 tasks" in capsys.readouterr().out
    _assert_same_map(load_map(out), reference)


def test_the_launcher_runs_the_fleet_on_two_workers(
    bags: list[Path], reference: dict[str, np.ndarray], tmp_path: Path
) -> None:
    """The command docs/fleet.md gives (--workers), through the .venv/bin/mfp-mapper that
    ./run setup writes (Dask's spawned workers re-run that script: it must not start the CLI
    again)."""
    pytest.importorskip("distributed")
    launcher = Path(__file__).resolve().parents[2] / ".venv" / "bin" / "mfp-mapper"
    if not launcher.is_file():
        pytest.skip(f"{launcher} is made by ./run setup; not there")
    run = subprocess.run(
        [str(launcher), "replay", *map(str, bags), "--workers", "2", "-o", "m.npz", *FLAGS],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    assert "Traceback" not in run.stderr and "Nanny" not in run.stderr
    assert "3 recordings in 3 tasks" in run.stdout
    _assert_same_map(load_map(tmp_path / "m.npz"), reference)
    assert not list(tmp_path.glob(".mfp-fleet-*"))


def test_cli_sequential_replay_merge_and_tiled_outputs(
    bags: list[Path], reference: dict[str, np.ndarray], tmp_path: Path, capsys
) -> None:  # type: ignore[no-untyped-def]
    from mfp_mapper.cli import main

    tiles = tmp_path / "tiles"
    assert main(["replay", *map(str, bags), "-o", str(tiles), "--tile-blocks", "2", *FLAGS]) == 0
    _assert_same_map(load_map(tiles), reference)
    singles = []
    for i, bag in enumerate(bags):
        singles.append(str(tmp_path / f"bag{i}.npz"))
        assert main(["replay", str(bag), "-o", singles[-1], *FLAGS]) == 0
    assert main(["merge", *singles, "-o", str(tmp_path / "merged.npz")]) == 0
    _assert_same_map(load_map(tmp_path / "merged.npz"), reference)
    capsys.readouterr()
    # export, query and render read the tiled map
    assert main(["export", str(tiles), "-o", str(tmp_path / "t.ply")]) == 0
    assert main(["export", str(tmp_path / "merged.npz"), "-o", str(tmp_path / "m.ply")]) == 0
    assert f"{len(reference['s']):,} voxels" in capsys.readouterr().out
    assert main(["query", str(tiles), "0", "0", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["observed"] is True
    pictures = tmp_path / "pictures"
    bounds = ["--bounds", "-3", "-3", "-1", "3", "3", "3"]
    assert main(["render", str(tiles), "-o", str(pictures), *bounds]) == 0
    assert (pictures / "doo_topdown.png").is_file()


def test_cli_errors_name_the_input_and_write_nothing(
    bags: list[Path], tmp_path: Path, capsys
) -> None:  # type: ignore[no-untyped-def]
    from mfp_mapper.cli import main

    bad = tmp_path / "broken.bag"
    bad.write_bytes(b"#ROSBAG V2.0\n" + b"\x00garbage" * 50)
    out = tmp_path / "fleet.npz"
    assert main(["replay", str(bags[0]), str(bad), "-o", str(out), *FLAGS]) == 1
    err = capsys.readouterr().err
    assert "broken.bag" in err and "no map written" in err and not out.exists()
    assert main(["replay", str(bags[0]), str(bad), "-o", str(out), "--skip-bad", *FLAGS]) == 0
    captured = capsys.readouterr()
    assert "skipped" in captured.out and "broken.bag" in captured.out and out.exists()
    other = tmp_path / "other.npz"
    assert main(["replay", str(bags[1]), "-o", str(other), "--resolution", "0.5", "-q"]) == 0
    assert main(["merge", str(out), str(other), "-o", str(tmp_path / "m.npz")]) == 1
    assert "different resolution" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()
    (tmp_path / "stuff").mkdir()
    (tmp_path / "stuff" / "keep.txt").write_text("mine")
    assert main(["merge", str(out), "-o", str(tmp_path / "stuff")]) == 1
    assert "not replaced" in capsys.readouterr().err
    assert (tmp_path / "stuff" / "keep.txt").read_text() == "mine"
