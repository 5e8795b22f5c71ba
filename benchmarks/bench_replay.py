"""Bag replay throughput on the built-in example, and where the time goes.

    python benchmarks/bench_replay.py                 # demo scene, 120 scans, 0.2 m, mcap
    python benchmarks/bench_replay.py --octomap       # + OctoMap fed the same clouds and poses
    python benchmarks/bench_replay.py --resolution 0.1 --scans 60 --format sqlite3

Reports for ``mfp-mapper replay``: rays/s end to end, and the share of the time spent
outside the core (bag reading, deserialisation, PointCloud2 parsing, pose interpolation and
de-skew) against ``Mapper.integrate``. With ``--octomap``, the same de-skewed points are
first extracted from the bag; then OctoMap (octomap-python, ``insertPointCloud``) and the
mfp core insert them, each cloud with one origin (the sensor position at mid-scan, since
OctoMap takes one origin per cloud), timed alone, in fresh subprocesses.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def extract(bag: Path, out: Path) -> int:
    """De-skewed map-frame points and one origin per cloud, placed by the replay itself."""
    from mfp_mapper.mapping.replay import ReplayOptions, replay

    arrays: dict[str, np.ndarray] = {}

    def keep(_stamp: float, points: np.ndarray, origins: np.ndarray) -> None:
        k = len(arrays) // 2
        arrays[f"p{k}"] = points
        arrays[f"o{k}"] = np.asarray(origins).reshape(-1, 3).mean(axis=0)

    replay(bag, ReplayOptions(), progress=False, on_scan=keep)
    np.savez(out, **arrays)
    return len(arrays) // 2


def child(kind: str, data: Path, resolution: float, max_range: float) -> dict:
    """In a subprocess: insert the extracted clouds with one mapper, time it."""
    arrays = np.load(data)
    scans = [(arrays[f"p{k}"], arrays[f"o{k}"]) for k in range(len(arrays.files) // 2)]
    rays = sum(len(p) for p, _ in scans)
    if kind == "octomap":
        import octomap

        tree = octomap.OcTree(resolution)
        t0 = time.perf_counter()
        for points, origin in scans:
            tree.insertPointCloud(points, origin, maxrange=max_range)
        seconds = time.perf_counter() - t0
        return {"kind": kind, "rays": rays, "seconds": seconds, "nodes": int(tree.size())}
    from mfp_mapper.core.mapper import Mapper

    warm = Mapper(resolution, max_range=max_range)
    warm.integrate(scans[0][0][:1000], scans[0][1], 0.0)  # compile / load the numba cache
    mapper = Mapper(resolution, max_range=max_range)
    t0 = time.perf_counter()
    for k, (points, origin) in enumerate(scans):
        mapper.integrate(points, origin, float(k))
    seconds = time.perf_counter() - t0
    return {"kind": kind, "rays": rays, "seconds": seconds, "voxels": mapper.num_voxels}


def run_child(kind: str, data: Path, resolution: float, max_range: float) -> dict:
    cmd = [sys.executable, __file__, "--child", kind, "--data", str(data),
           "--resolution", str(resolution), "--max-range", str(max_range)]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    from mfp_mapper.sources.simulate import BAG_FORMATS

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scans", type=int, default=120)
    ap.add_argument("--resolution", type=float, default=0.2)
    ap.add_argument("--format", choices=BAG_FORMATS, default="mcap")
    ap.add_argument("--octomap", action="store_true", help="also OctoMap on the same clouds")
    ap.add_argument("--max-range", type=float, default=100.0)
    ap.add_argument("--bag", help="replay this bag instead of simulating the example")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--data", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, Path(args.data), args.resolution, args.max_range)))
        return 0

    from mfp_mapper.core.mapper import Mapper
    from mfp_mapper.mapping.replay import ReplayOptions, replay
    from mfp_mapper.sources.simulate import preset, simulate

    with tempfile.TemporaryDirectory() as tmp:
        if args.bag:
            bag = Path(args.bag)
        else:
            bag = Path(tmp) / ("example.bag" if args.format == "ros1" else "example")
            t0 = time.perf_counter()
            simulate(bag, replace(preset("demo"), scans=args.scans), args.format)
            print(f"simulated {bag.name} ({args.format}, {args.scans} scans) in "
                  f"{time.perf_counter() - t0:.1f} s")  # fmt: skip
        Mapper(args.resolution).integrate(np.ones((2, 3)), np.zeros(3), 0.0)  # warm numba
        opts = ReplayOptions.of(resolution=args.resolution, max_range=args.max_range)
        t0 = time.perf_counter()
        result = replay(bag, opts, progress=False)
        wall = time.perf_counter() - t0
        s = result.summary
        print(f"\nreplay at {args.resolution} m: {s.rays_used:,} rays, {s.scans_used} scans")
        print(f"  wall (open bag, poses, clouds): {wall:.2f} s = {s.rays_used / wall:,.0f} rays/s")
        print(f"  cloud loop: {s.seconds:.2f} s, core (Mapper.integrate) {s.seconds_core:.2f} s")
        outside = wall - s.seconds_core
        print(f"  outside the core (reading, parsing, poses, de-skew): {outside:.2f} s = "
              f"{100 * outside / wall:.0f}% of the wall time")  # fmt: skip
        print(f"  voxels {s.voxels:,}, {s.memory_bytes / 2**20:.0f} MiB")
        if args.octomap:
            data = Path(tmp) / "clouds.npz"
            n = extract(bag, data)
            print(f"\nsame {n} clouds, one origin each (mid-scan), insertion only:")
            mfp = run_child("mfp", data, args.resolution, args.max_range)
            octo = run_child("octomap", data, args.resolution, args.max_range)
            for r in (mfp, octo):
                name = "mfp_mapper core" if r["kind"] == "mfp" else "OctoMap insertPointCloud"
                print(
                    f"  {name:26s} {r['seconds']:7.2f} s  {r['rays'] / r['seconds']:>12,.0f} rays/s"
                )
            print(f"  speed-up over OctoMap: {octo['seconds'] / mfp['seconds']:.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
