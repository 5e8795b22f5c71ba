"""Fleet mapping: speed-up with Dask workers, per-task cost, and the cost of the reduction.

    python benchmarks/bench_fleet.py                    # 4 recordings x 30 scans, 0.1 m
    python benchmarks/bench_fleet.py --recordings 6 --scans 40 --workers 1 2
    python benchmarks/bench_fleet.py --merge-voxels 10000000   # merge and tile figures only
    python benchmarks/bench_fleet.py --json out.json

Part 1 (fleet): simulated VLP-16 recordings of the built-in scene (``sources.simulate``),
mapped in the same run: ``replay`` of each recording into its own map with nothing else
(the baseline: the work a fleet cannot avoid), the sequential fleet (``in_turn``: one
mapper takes the recordings in turn, what ``replay A B`` does without ``--workers``), the
partial maps as tiles + the exact reduction in this process (``partials``), and Dask
LocalClusters of each ``--workers`` count (the cluster start is timed apart). Ratios are
against the baseline and the in-process partials of this run. Per task: seconds, rays/s,
peak RSS of the worker process, partial voxels.

Part 2 (reduction): two synthetic maps that overlap by half, ``--merge-voxels`` voxels in
all: ``core.merge.merge_voxels`` (sort + segmented sums), ``np.sort`` of as many int64
keys (the floor of any sort-based merge, the ratio's baseline), writing and reading them as
tiles.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def make_recordings(root: Path, count: int, scans: int) -> list[Path]:
    from mfp_mapper.sources.simulate import preset, simulate

    cfg = replace(preset("demo"), scans=scans)
    return [
        simulate(root / f"robot{i}", replace(cfg, seed=i, start_time=1.7e9 + 60.0 * i)).bag
        for i in range(count)
    ]


def bench_fleet(args: argparse.Namespace, root: Path) -> dict[str, Any]:
    from mfp_mapper.mapping.fleet import FleetOptions, map_fleet
    from mfp_mapper.mapping.replay import ReplayOptions, replay

    bags = make_recordings(root / "bags", args.recordings, args.scans)
    opts = ReplayOptions.of(resolution=args.resolution, max_range=args.max_range)
    replay(bags[0], opts.but(max_scans=2), progress=False)  # compile/load the kernels
    out: dict[str, Any] = {"recordings": len(bags), "scans_each": args.scans}

    here = FleetOptions(progress=False)
    windows = FleetOptions(chunk_seconds=args.chunk_seconds or 1e9, progress=False)
    modes: list[tuple[str, FleetOptions]] = [
        ("in_turn", here),  # one mapper takes the recordings in turn (no --workers)
        ("partials", windows),  # partial maps + the exact reduction, in this process
    ] + [(f"dask_{w}", replace(windows, workers=w)) for w in args.workers]
    runs: dict[str, Any] = {}
    baseline = math.inf
    for _ in range(args.repeat):  # rounds interleave the modes; the best of each is kept
        t0 = time.perf_counter()
        rays = 0
        for bag in bags:
            result = replay(bag, opts, progress=False)
            rays += result.summary.rays_used
            result.mapper.close()
        baseline = min(baseline, time.perf_counter() - t0)
        for name, fleet in modes:
            t0 = time.perf_counter()
            res = map_fleet(bags, root / f"{name}.npz", opts, fleet)
            figures = _run_figures(res, time.perf_counter() - t0)
            if name not in runs or figures["seconds"] < runs[name]["seconds"]:
                runs[name] = figures
    out.update(baseline_s=baseline, rays=rays, runs=runs, repeat=args.repeat)
    base, seq_s = out["baseline_s"], runs["partials"]["seconds"]
    for name, r in runs.items():
        r["ratio_to_baseline"] = r["seconds"] / base
        r["speedup_vs_partials"] = seq_s / r["seconds"]
        print(
            f"{name:<12} {r['seconds']:7.2f} s (start {r['start_s']:.2f} s, replay "
            f"{r['replay_s']:.2f} s, reduce {r['reduce_s']:.2f} s, write "
            f"{r['write_s']:.2f} s)  {r['ratio_to_baseline']:.2f}x the baseline "
            f"{base:.2f} s, x{r['speedup_vs_partials']:.2f} vs partials here"
        )
    tasks = runs["partials"]["tasks"]
    print(
        f"per task (partials here): {np.median([t['seconds'] for t in tasks]):.2f} s median, "
        f"{np.median([t['rays_per_s'] for t in tasks]) / 1e6:.2f} M rays/s, partial "
        f"{np.median([t['voxels'] for t in tasks]) / 1e6:.2f} M voxels, peak RSS "
        f"{max(t['peak_rss_mb'] for t in tasks):.0f} MB"
    )
    return out


def _run_figures(result: Any, seconds: float) -> dict[str, Any]:
    return {
        "seconds": seconds,
        "start_s": result.seconds_start,
        "replay_s": result.seconds_replay,
        "reduce_s": result.seconds_reduce,
        "write_s": result.seconds_write,
        "voxels": result.voxels,
        "tiles": result.tiles,
        "tasks": [
            {
                "task": r.task.label,
                "seconds": r.seconds,
                "rays_per_s": (r.summary.rays_used / r.seconds) if r.summary else 0.0,
                "voxels": r.summary.voxels if r.summary else 0,
                "peak_rss_mb": r.peak_rss_bytes / 2**20,
            }
            for r in result.tasks
        ],
    }


def bench_merge(voxels: int, root: Path) -> dict[str, Any]:
    from mfp_mapper.core.merge import merge_voxels
    from mfp_mapper.core.store import VoxelArrays
    from mfp_mapper.mapio.mapfile import FORMAT_NAME, FORMAT_VERSION
    from mfp_mapper.mapio.tiles import TiledMap, write_tiled

    rng = np.random.default_rng(0)
    side = int(math.ceil((voxels / 2 / 0.3) ** (1 / 3) * 1.6))  # a third of a cube occupied
    cube = rng.choice(side**3, size=int(0.75 * voxels), replace=False)
    ijk = np.stack(np.unravel_index(cube, (side * 2, side, side // 2 + 1)), axis=1)
    ijk = (ijk - side // 2).astype(np.int32)
    half = voxels // 2
    parts = []
    for sel in (slice(0, half), slice(voxels - half - int(0.25 * voxels), None)):
        sub = ijk[sel][:half]
        rng.shuffle(sub)
        t = np.full(len(sub), 100.0)
        parts.append(VoxelArrays(sub, rng.random(len(sub)), rng.random(len(sub)), t))
    total = sum(len(p.s) for p in parts)
    times = []
    for _ in range(2):  # the first run also faults in fresh memory
        t0 = time.perf_counter()
        merged = merge_voxels(parts, 30.0)
        times.append(time.perf_counter() - t0)
    first_s, merge_s = times
    keys = rng.integers(0, 2**62, total)
    t0 = time.perf_counter()
    np.sort(keys)
    sort_s = time.perf_counter() - t0
    arrays = {
        "ijk": merged.ijk, "s": merged.s, "n": merged.n, "t_last": merged.t_last,
        "resolution": np.float64(0.1), "decay_time": np.float64(30.0),
        "max_range": np.float64(100.0), "min_range": np.float64(0.0),
        "frame_id": np.str_("map"), "format": np.str_(FORMAT_NAME),
        "version": np.int64(FORMAT_VERSION),
    }  # fmt: skip
    t0 = time.perf_counter()
    entries = write_tiled(root / "tiles", arrays)
    write_s = time.perf_counter() - t0
    disk = sum(p.stat().st_size for p in (root / "tiles").rglob("*.npz"))
    tiled = TiledMap(root / "tiles")
    t0 = time.perf_counter()
    for key in tiled.tiles:
        tiled.read_tile(key)
    read_s = time.perf_counter() - t0
    out = {
        "input_voxels": total,
        "merged_voxels": len(merged.s),
        "merge_s": merge_s,
        "merge_first_s": first_s,
        "sort_int64_s": sort_s,
        "tiles": len(entries),
        "tile_write_s": write_s,
        "tile_read_s": read_s,
        "bytes_on_disk": disk,
    }
    print(
        f"merge of {total / 1e6:.1f} M voxels (-> {len(merged.s) / 1e6:.1f} M): {merge_s:.2f} s"
        f" (first run {first_s:.2f} s)"
        f" ({merge_s / sort_s:.1f}x one np.sort of as many int64 keys, {sort_s:.2f} s); "
        f"as {len(entries)} tiles: write {write_s:.2f} s, read {read_s:.2f} s, "
        f"{disk / len(merged.s):.1f} bytes/voxel on disk"
    )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recordings", type=int, default=4)
    parser.add_argument("--scans", type=int, default=30, help="0.1 s rotations per recording")
    parser.add_argument("--resolution", type=float, default=0.1)
    parser.add_argument("--max-range", type=float, default=30.0)
    parser.add_argument("--chunk-seconds", type=float, default=None)
    parser.add_argument("--workers", type=int, nargs="*", default=[1, 2])
    parser.add_argument("--repeat", type=int, default=1, help="rounds; the best of each")
    parser.add_argument("--merge-voxels", type=int, default=10_000_000)
    parser.add_argument("--skip-fleet", action="store_true", help="part 2 only")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench_fleet_"))
    try:
        figures: dict[str, Any] = {}
        if not args.skip_fleet:
            figures["fleet"] = bench_fleet(args, root)
        if args.merge_voxels > 0:
            figures["merge"] = bench_merge(args.merge_voxels, root)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
