"""Map queries while scans integrate: what ``~/query`` does per request, in one process.

A map of the real street (``../shared/data/ouster_street``, its three scans) or, without the
data, a simulated scene, at 0.1 m. One thread integrates the scans again and again as the
node's worker does (``Mapper.stage`` without the lock, ``commit`` under it); another asks
10,000 points (``Mapper.query``) and 1,000 segments of 20 m (``Mapper.query_segments``) under
the same lock. The same queries are timed with nothing integrating, in the same run: the
ratio busy / idle is the cost of answering during integration.

    python benchmarks/bench_query.py [--resolution 0.1] [--repeat 15]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
STREET = ROOT.parent / "shared" / "data" / "ouster_street"
sys.path[:0] = [str(ROOT), str(ROOT / "test"), str(ROOT / "benchmarks")]

from bench_likelihood import _simulated, _street  # noqa: E402

from mfp_mapper.core.mapper import Mapper  # noqa: E402


def _queries(mapper: Mapper, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """10,000 points and 1,000 segments of 20 m (random directions) around the map's data."""
    rng = np.random.default_rng(seed)
    stats = mapper.stored_voxels()
    centre = (stats.ijk.mean(axis=0) + 0.5) * mapper.resolution
    points = centre + rng.normal(scale=8.0, size=(10_000, 3))
    starts = centre + rng.normal(scale=5.0, size=(1_000, 3))
    d = rng.normal(size=(1_000, 3))
    ends = starts + 20.0 * d / np.linalg.norm(d, axis=1)[:, None]
    return points, starts, ends


def _time_queries(
    mapper: Mapper, lock: threading.Lock, queries: tuple[np.ndarray, ...], repeat: int
) -> tuple[list[float], list[float]]:
    points, starts, ends = queries
    t_points, t_segments = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        with lock:
            mapper.query(points)
        t1 = time.perf_counter()
        with lock:
            mapper.query_segments(starts, ends)
        t2 = time.perf_counter()
        t_points.append(t1 - t0)
        t_segments.append(t2 - t1)
    return t_points, t_segments


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=float, default=0.1)
    ap.add_argument("--repeat", type=int, default=15)
    args = ap.parse_args()
    scans, name = (_street(), "ouster_street") if STREET.is_dir() else (_simulated(), "simulated")
    mapper = Mapper(args.resolution, max_range=100.0)
    for k, (pts, origin) in enumerate(scans):
        mapper.integrate(pts, origin, float(k))
    lock = threading.Lock()
    queries = _queries(mapper)
    _time_queries(mapper, lock, queries, 2)  # compile outside the timing
    idle = _time_queries(mapper, lock, queries, args.repeat)

    stop = threading.Event()
    integrated = [0]

    def integrate() -> None:
        k = len(scans)
        while not stop.is_set():
            pts, origin = scans[k % len(scans)]
            staged = mapper.stage(pts, origin, float(k))
            with lock:
                mapper.commit(staged)
            integrated[0] += 1
            k += 1

    worker = threading.Thread(target=integrate)
    worker.start()
    try:
        while integrated[0] == 0:
            time.sleep(0.01)
        busy = _time_queries(mapper, lock, queries, args.repeat)
    finally:
        stop.set()
        worker.join()
    print(
        f"scene {name}, {mapper.resolution} m, {mapper.num_voxels:,} voxels; "
        f"{integrated[0]} scans integrated meanwhile; median of {args.repeat}"
    )
    for what, k in (("10,000 points", 0), ("1,000 segments of 20 m", 1)):
        i, b = statistics.median(idle[k]), statistics.median(busy[k])
        print(
            f"{what:24s} idle {i * 1e3:7.1f} ms  integrating {b * 1e3:7.1f} ms  ratio {b / i:.2f}"
        )


if __name__ == "__main__":
    main()
