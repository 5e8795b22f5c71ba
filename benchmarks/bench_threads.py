"""How the threads of one scan would scale with free cores: CPU time of each part.

Wall time of two threads means little on a machine whose cores other work keeps busy.
This benchmark runs the parts of a threaded integration one after another in one thread
and reads each part's thread CPU time: the split of the rays into the shards' stretches
(``traversal.split_rays``, a part of the rays a task) and each shard's walk (a task), in
the order ``integrate_rays`` hands them to the threads. The critical path with T threads
is the serial rest plus each phase's tasks dealt to T threads as a pool does (the next
task to the first thread free); against one thread's walk of whole rays that is the
speed-up the threads can give (memory bandwidth aside). It prints each thread's CPU time
on that path (its idle time is the path less it) and the work of all threads against
one thread's. The store has the shards
a Mapper of T threads has (``mapper.shard_count``), or ``--shards-per-thread``.

    python benchmarks/bench_threads.py                      # hall and OS1-128, 0.2 and 0.1 m
    python benchmarks/bench_threads.py --threads 2 4 8 16 --resolutions 0.1
"""

from __future__ import annotations

import argparse
import heapq
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parent)]
from bench_core import OUSTER, _scene  # noqa: E402

from mfp_mapper import Mapper  # noqa: E402
from mfp_mapper.core import mapper as mapper_module  # noqa: E402
from mfp_mapper.core import traversal  # noqa: E402
from mfp_mapper.core.store import BlockStore  # noqa: E402
from mfp_mapper.core.traversal import integrate_rays  # noqa: E402


def deal(times: Sequence[float], threads: int) -> list[float]:
    """Each thread's busy time when ``times`` are dealt in order to ``threads`` threads,
    each task to the first thread free (as a thread pool's ``map``)."""
    free = [(0.0, t) for t in range(threads)]
    for task in times:
        busy, thread = heapq.heappop(free)
        heapq.heappush(free, (busy + task, thread))
    return [busy for busy, _ in sorted(free, key=lambda x: x[1])]


def makespan(times: Sequence[float], threads: int) -> float:
    """When the last of ``times`` ends, dealt as ``deal`` deals them."""
    return max(deal(times, threads))


def scan_parts(
    scene: str, resolution: float, threads: int
) -> tuple[float, float, float, float, float, list[float]]:
    """Medians over the later scans (ms): the split (counting the stretches, then
    splitting), the sum and the slowest of the shards' walks, the serial rest of
    ``integrate_rays`` (the shares, the order of the shards), the critical path with
    ``threads`` threads (serial rest + each phase's tasks dealt to the threads), and each
    thread's CPU time on that path (every phase; the gap to the path is its idle time)."""
    scans = _scene(scene)
    placer = Mapper(resolution, max_range=100.0)  # places the rays (no origin: raw frame)
    store = BlockStore(shards=mapper_module.shard_count(threads))
    calls: list[list[float]] = []

    def one_after_another(fn: Callable[[int], None], items: Sequence[int]) -> None:
        times = []
        for item in items:
            cpu0 = time.thread_time()
            fn(item)
            times.append(time.thread_time() - cpu0)
        calls.append(times)

    rows = []
    for k, (points, origin) in enumerate(scans):
        rays, _ = placer.place_rays(points, origin)
        calls.clear()
        cpu0 = time.thread_time()
        integrate_rays(store, rays, store.begin_scan(), float(k), math.inf, one_after_another)
        whole = time.thread_time() - cpu0
        store.finish_scan()
        phases = calls[:-1]  # counting the stretches, splitting the rays
        split = [t for phase in phases for t in phase] or [0.0]
        walks = calls[-1] if calls else [whole]
        serial = whole - sum(split) - (sum(walks) if calls else whole)
        path = serial + sum(makespan(p, threads) for p in phases) + makespan(walks, threads)
        busy = list(deal(walks, threads))
        for phase in phases:
            busy = [a + b for a, b in zip(busy, deal(phase, threads), strict=True)]
        rows.append((sum(split), sum(walks), max(walks), serial, path, *sorted(busy)))
    medians = [1e3 * float(np.median(column)) for column in zip(*rows[1:], strict=True)]
    return (*medians[:5], medians[5:])  # type: ignore[return-value]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--resolutions", type=float, nargs="+", default=[0.2, 0.1])
    parser.add_argument("--threads", type=int, nargs="+", default=[2, 4, 8])
    parser.add_argument(
        "--shards-per-thread", type=int, default=traversal.SHARDS_PER_THREAD,
        help="shards of the store per thread (1: a shard a thread, as before)",
    )  # fmt: skip
    args = parser.parse_args()
    traversal.SHARDS_PER_THREAD = args.shards_per_thread
    scenes = ["anchors"] + (["ouster_street"] if OUSTER.is_dir() else [])
    print(
        f"scene, resolution, threads ({args.shards_per_thread} shards a thread), CPU ms a "
        "later scan: split / walks (sum; slowest shard) / serial rest / critical path "
        "(speed-up); each thread's CPU on the path"
    )
    for scene in scenes:
        for resolution in args.resolutions:
            one = scan_parts(scene, resolution, 1)[1]
            print(f"{scene} {resolution} m, 1 thread: {one:.1f} ms")
            for threads in args.threads:
                split, walks, slowest, serial, path, busy = scan_parts(scene, resolution, threads)
                print(
                    f"{scene} {resolution} m, {threads}: {split:.1f} / {walks:.1f}; "
                    f"{slowest:.1f} / {serial:.1f} / {path:.1f} ({one / path:.2f}x); "
                    f"threads {' '.join(f'{b:.1f}' for b in busy)} "
                    f"(work {(split + walks + serial) / one:.2f}x one thread's)"
                )


if __name__ == "__main__":
    main()
