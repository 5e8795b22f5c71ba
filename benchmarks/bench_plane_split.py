"""Two threads on one scan: the tile split the mapper uses against a split-free ceiling.

``integrate_rays`` with two threads cuts every ray into its stretches in the tiles of the
store's shards (a 3-D checkerboard, ``blocks.SHARD_TILE_BITS``): a split pass over the rays,
then each shard's stretches walked by one thread. Both cost work one thread walking whole
rays does not do. This benchmark measures, in one run and in wall time, against one thread
walking the scan's whole rays into a store of one shard:

- ``tile split``: ``integrate_rays`` into a store of ``mapper.shard_count(2)`` shards, two
  threads from a pool, as ``Mapper(threads=2)`` runs it (without placing the rays);
- ``plane ceiling``: the scan's rays divided by a vertical plane through the sensor (its
  direction chosen so that both sides visit as many voxels), each side's whole rays walked
  by a thread of its own into a store of its own. No ray is cut and nothing is split, so no
  partition of the space can do better: it is not a map (the two stores would need merging,
  and the voxels on the plane hold rays of both sides); it is what two threads give on this
  machine to a design that writes both sides into one store, with the voxels the two sides
  share added apart, in ray order.

Rounds are interleaved (one thread, tile split, plane ceiling), later scans only (every scan
integrated once before the timed rounds, as a running mapper has seen the place), with the
cores the rest of the machine used meanwhile; the ratio is one thread's wall time over the
row's, per scan, median and range.

    python benchmarks/bench_plane_split.py                      # box world and OS1-128, 0.2 m
    python benchmarks/bench_plane_split.py --resolutions 0.2 0.1 --rounds 5
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_core import OUSTER, _scene  # noqa: E402
from bench_parallel_ceiling import _busy_seconds  # noqa: E402

from mfp_mapper import Mapper  # noqa: E402
from mfp_mapper.core import mapper as mapper_module  # noqa: E402
from mfp_mapper.core.store import BlockStore  # noqa: E402
from mfp_mapper.core.traversal import Rays, integrate_rays  # noqa: E402

PLANE_DIRECTIONS = 64
"""Directions of the vertical plane tried for the ceiling's balance (half a turn)."""


def one_after_another(fn, items) -> None:  # type: ignore[no-untyped-def]
    for item in items:
        fn(item)


def plane_sides(rays: Rays) -> tuple[Rays, Rays, float]:
    """The rays on each side of the vertical plane through the sensor that best balances
    the voxels they visit, and the imbalance left (|a - b| / (a + b))."""
    direction = rays.ends_vox - rays.origins_vox
    visits = np.abs(np.floor(rays.ends_vox) - np.floor(rays.origins_vox)).sum(axis=1) + 1
    best_gap, best = math.inf, np.zeros(len(rays), dtype=bool)
    for phi in np.linspace(0.0, np.pi, PLANE_DIRECTIONS, endpoint=False):
        side = math.cos(phi) * direction[:, 0] + math.sin(phi) * direction[:, 1] > 0.0
        gap = abs(float(visits[side].sum() - visits[~side].sum())) / float(visits.sum())
        if gap < best_gap:
            best_gap, best = gap, side

    def part(mask: np.ndarray) -> Rays:
        return Rays(rays.origins_vox[mask], rays.ends_vox[mask], rays.lengths[mask],
                    rays.has_return[mask])  # fmt: skip

    return part(best), part(~best), best_gap


def integrate(store: BlockStore, rays: Rays, stamp: float, run_parallel) -> None:  # type: ignore[no-untyped-def]
    integrate_rays(store, rays, store.begin_scan(), stamp, math.inf, run_parallel)
    store.finish_scan()


def measure(scene: str, resolution: float, rounds: int) -> None:
    scans = _scene(scene)
    placer = Mapper(resolution, max_range=100.0)
    placer.integrate(scans[0][0][:64], scans[0][1], 0.0)  # the map's origin: the first sensor
    placed = [placer.place_rays(points, origin)[0] for points, origin in scans]
    sides = [plane_sides(rays) for rays in placed]
    placer.close()
    pool = ThreadPoolExecutor(2)

    def pooled(fn, items) -> None:  # type: ignore[no-untyped-def]
        list(pool.map(fn, items))

    whole = BlockStore(shards=1)
    tiles = BlockStore(shards=mapper_module.shard_count(2))
    side_a, side_b = BlockStore(shards=1), BlockStore(shards=1)

    def plane(k: int, stamp: float) -> None:
        a, b, _ = sides[k]
        other = threading.Thread(target=integrate, args=(side_b, b, stamp, one_after_another))
        other.start()
        integrate(side_a, a, stamp, one_after_another)
        other.join()

    runs = {
        "one thread": lambda k, stamp: integrate(whole, placed[k], stamp, one_after_another),
        "tile split": lambda k, stamp: integrate(tiles, placed[k], stamp, pooled),
        "plane ceiling": plane,
    }
    stamp = 0.0
    for k in range(len(placed)):  # every place seen once: the timed scans are later scans
        stamp += 1.0
        for run in runs.values():
            run(k, stamp)
    times: dict[str, list[float]] = {name: [] for name in runs}
    others: list[float] = []
    for _ in range(rounds):
        for k in range(len(placed)):
            stamp += 1.0
            for name, run in runs.items():
                busy0, own0, t0 = _busy_seconds(), time.process_time(), time.perf_counter()
                run(k, stamp)
                wall = time.perf_counter() - t0
                times[name].append(wall)
                others.append(max(0.0, _busy_seconds() - busy0 - time.process_time() + own0) / wall)
    pool.shutdown()
    gaps = [gap for _, _, gap in sides]
    one = np.array(times["one thread"])
    print(
        f"{scene} {resolution} m, {len(placed)} scans x {rounds} rounds; one thread "
        f"{1e3 * np.median(one):.1f} ms a scan; others used {min(others):.2f}-"
        f"{max(others):.2f} cores; plane imbalance {max(gaps):.3f}"
    )
    for name in ("tile split", "plane ceiling"):
        ratio = one / np.array(times[name])
        print(
            f"  {name}: {1e3 * np.median(times[name]):.1f} ms, one thread / two "
            f"{np.median(ratio):.2f}x ({ratio.min():.2f}-{ratio.max():.2f})",
            flush=True,
        )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--resolutions", type=float, nargs="+", default=[0.2])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    scenes = ["anchors"] + (["ouster_street"] if OUSTER.is_dir() else [])
    for scene in scenes:
        for resolution in args.resolutions:
            measure(scene, resolution, args.rounds)


if __name__ == "__main__":
    main()
