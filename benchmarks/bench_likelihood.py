"""Scoring a scan against integrating it: the cost of ``core.likelihood`` in one run.

A real street (``../shared/data/ouster_street``: two Ouster scans mapped, the third scored)
or, without the data, a simulated scene. Each repetition integrates the scan into the map
(the map grows a little, its voxels barely change) and scores it, interleaved; prints the
median seconds of each and the ratio score / integrate.

    python benchmarks/bench_likelihood.py [--resolution 0.2] [--repeat 7]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
STREET = ROOT.parent / "shared" / "data" / "ouster_street"
sys.path[:0] = [str(ROOT), str(ROOT / "test")]

from mfp_mapper.core.likelihood import scan_log_likelihood  # noqa: E402
from mfp_mapper.core.mapper import Mapper  # noqa: E402


def _street() -> list[tuple[np.ndarray, np.ndarray]]:
    """The three street scans in the world frame, with their sensor origins."""
    poses = np.loadtxt(STREET / "poses.txt").reshape(-1, 3, 4)
    scans = []
    for k, pose in enumerate(poses):
        xyz = np.fromfile(STREET / "scans" / f"{k:06d}.bin", dtype=np.float32).reshape(-1, 4)
        pts = xyz[:, :3].astype(np.float64) @ pose[:, :3].T + pose[:, 3]
        scans.append((pts, pose[:, 3].copy()))
    return scans


def _simulated() -> list[tuple[np.ndarray, np.ndarray]]:
    from box_world import anchors_scene

    return anchors_scene()[:3]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=float, default=0.2)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    scans, name = (_street(), "ouster_street") if STREET.is_dir() else (_simulated(), "simulated")
    mapper = Mapper(args.resolution, max_range=100.0)
    for k, (pts, origin) in enumerate(scans[:-1]):
        mapper.integrate(pts, origin, float(k))
    pts, origin = scans[-1]
    stamp = float(len(scans) - 1)
    scan_log_likelihood(mapper, pts, origin, stamp)  # compile outside the timing
    t_int, t_score = [], []
    events = 0
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        result = scan_log_likelihood(mapper, pts, origin, stamp)
        t_score.append(time.perf_counter() - t0)
        events = result.events
        t0 = time.perf_counter()
        mapper.integrate(pts, origin, stamp)
        t_int.append(time.perf_counter() - t0)
    score, integrate = statistics.median(t_score), statistics.median(t_int)
    print(f"scene {name}: {len(pts)} rays, {events} events, resolution {args.resolution} m")
    print(
        f"integrate {integrate * 1e3:.1f} ms  score {score * 1e3:.1f} ms (median of {args.repeat})"
    )
    print(f"ratio score/integrate {score / integrate:.2f}")


if __name__ == "__main__":
    main()
