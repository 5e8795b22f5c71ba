"""Staged integration (``Mapper.stage`` + ``commit``, what the live node does) against the
direct ``Mapper.integrate``, on the same scans, interleaved in one run.

Each round integrates one large scan (``--points``, 2 M by default: a lidar in a 30 x 30 m
room, moving 0.7 m a scan, so the scan overlaps the map already built) into two maps
that hold the same earlier scans: one directly, one staged. Reported: the wall time of
both (the throughput cost of staging), the time ``commit`` holds the map (what a service
may wait for during an integration, against the whole integration that held it before),
and the memory of the staged store (freed after the commit).

    .venv/bin/python benchmarks/bench_staging.py
    .venv/bin/python benchmarks/bench_staging.py --points 2e5 --rounds 5
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]


def _scan(rng: np.random.Generator, count: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """About ``count`` returns of a lidar (-30..30 deg, 2048 azimuths) in a 30 x 30 m room
    (floor 2 m below the sensor, ceiling 6 m above), the sensor 0.7 m further each scan."""
    rows = max(1, count // 2048)
    el = np.radians(np.linspace(-30.0, 30.0, rows))
    az = np.linspace(-np.pi, np.pi, 2048, endpoint=False) + rng.uniform(0, 1e-3)
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    origin = np.array([0.7 * k - 5.0, 0.3 * k - 2.0, 0.0])
    with np.errstate(divide="ignore"):
        up = np.where(d[:, 2] > 0, 6.0 / d[:, 2], 2.0 / np.abs(d[:, 2]))
        wx = np.where(d[:, 0] > 0, 15.0 - origin[0], 15.0 + origin[0]) / np.abs(d[:, 0])
        wy = np.where(d[:, 1] > 0, 15.0 - origin[1], 15.0 + origin[1]) / np.abs(d[:, 1])
    t = np.minimum(np.minimum(wx, wy), up)
    return origin + d * t[:, None], origin


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=float, default=2e6)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--resolution", type=float, default=0.1)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    from mfp_mapper import Mapper

    rng = np.random.default_rng(0)
    count = int(args.points)
    maps = [Mapper(args.resolution, threads=args.threads, max_range=60.0) for _ in range(2)]
    warm = _scan(rng, 2000, 0)
    for m in maps:  # compile and give both the same first scan
        m.commit(m.stage(*warm, 0.0))
        m.integrate(*warm, 0.5)
    direct, staged, commit, staged_mb, scan_rays = [], [], [], [], 0
    for k in range(1, args.rounds + 1):
        points, origin = _scan(rng, count, k)
        order = (0, 1) if k % 2 else (1, 0)  # interleaved: neither always runs first
        for which in order:
            t0 = time.perf_counter()
            if which == 0:
                summary = maps[0].integrate(points, origin, float(k))
                direct.append(time.perf_counter() - t0)
                scan_rays = summary.rays_used
            else:
                scan = maps[1].stage(points, origin, float(k))
                staged_mb.append(scan.store.nbytes / 1e6)
                summary = maps[1].commit(scan)
                staged.append(time.perf_counter() - t0)
                commit.append(summary.commit_seconds)
                del scan
    assert maps[0].num_voxels == maps[1].num_voxels
    d, s, c = (statistics.median(x) for x in (direct, staged, commit))
    print(
        f"{args.rounds} scans of {scan_rays / 1e6:.2f} M rays, {args.resolution} m, "
        f"threads {args.threads}; map {maps[0].num_voxels / 1e6:.1f} M voxels, "
        f"{maps[0].memory_bytes / 1e6:.0f} MB (median of rounds)"
    )
    print(f"  integrate (map locked throughout)  {d:7.3f} s   1.00x")
    print(f"  stage + commit                     {s:7.3f} s   {s / d:.2f}x")
    print(f"    of which commit (map locked)     {c:7.3f} s   {c / d:.3f}x")
    print(
        f"  staged store (freed after commit)  {statistics.median(staged_mb):7.0f} MB  "
        f"{statistics.median(staged_mb) * 1e6 / maps[0].memory_bytes:.2f}x the map"
    )


if __name__ == "__main__":
    main()
