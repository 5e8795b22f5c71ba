"""What two threads cost in CPU against one, on the same scans in one process.

Three runs a round, of every scan of a scene into a fresh store (``integrate_rays`` as
``Mapper.integrate`` calls it; the first scan not counted):

- one thread, whole rays (a store of one shard);
- two threads' tasks one after another on one thread (the same count, split and shards'
  walks, nothing at once): what the split and the stretches cost;
- two threads at once (the thread pool): what running them together costs on top.

Each task's thread CPU time is summed by phase (the pool's tasks wrapped); the scans' wall
times too. It prints each phase and the CPU of two threads against one thread's: two
cores give at most 2 / that ratio in wall time. Then, for the two threads at once, the
walks' round against the best split of its measured shard walks between the threads and
against half their CPU time: what a better deal of the shards could still give.

    python benchmarks/bench_thread_cpu.py                           # box world, 0.2 m
    python benchmarks/bench_thread_cpu.py --scene ouster_street --rounds 3
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parent)]
from bench_core import _scene  # noqa: E402

from mfp_mapper import Mapper  # noqa: E402
from mfp_mapper.core import mapper as mapper_module  # noqa: E402
from mfp_mapper.core.memory_bound import scan_new_blocks  # noqa: E402
from mfp_mapper.core.store import BlockStore  # noqa: E402
from mfp_mapper.core.traversal import integrate_rays  # noqa: E402

Scans = list[tuple[np.ndarray, np.ndarray]]


def run(scans: Scans, resolution: float, threads: int, one_after_another: bool) -> dict:
    """Every scan into a fresh store of ``threads``' shards (``integrate_rays``, as
    ``Mapper.integrate`` calls it): wall (ms) of the later scans, CPU (ms) by phase, and
    each walks' round (its wall time and each task's, ms)."""
    placer = Mapper(resolution, max_range=100.0)  # places the rays (no origin: raw frame)
    store = BlockStore(shards=mapper_module.shard_count(threads))
    pool = ThreadPoolExecutor(threads) if threads > 1 else None
    cpu: dict[str, float] = defaultdict(float)
    walk_rounds: list[tuple[float, list[float]]] = []
    lock = threading.Lock()
    counting = [False]
    inline = [0.0]  # CPU of the tasks run on the calling thread (one after another)

    def run_parallel(fn: Callable[[int], None], items: Sequence[int]) -> None:
        name = getattr(fn, "__name__", "task")
        spans: list[float] = []

        def task(item: int) -> None:
            c0, t0 = time.thread_time(), time.perf_counter()
            fn(item)
            with lock:
                if counting[0]:
                    cpu[name] += 1e3 * (time.thread_time() - c0)
                spans.append(1e3 * (time.perf_counter() - t0))

        t0 = time.perf_counter()
        if pool is None or one_after_another:
            c0 = time.thread_time()
            for item in items:
                task(item)
            inline[0] += 1e3 * (time.thread_time() - c0)
        else:
            list(pool.map(task, items))
        if counting[0] and name.startswith("walk") and len(spans) > 1:
            walk_rounds.append((1e3 * (time.perf_counter() - t0), spans))

    wall = 0.0
    try:
        for k, (points, origin) in enumerate(scans):
            rays, _ = placer.place_rays(points, origin)
            counting[0] = k > 0
            inline[0] = 0.0
            c0, t0 = time.thread_time(), time.perf_counter()
            integrate_rays(
                store, rays, store.begin_scan(), float(k), math.inf, run_parallel,
                scan_new_blocks(None),
            )  # fmt: skip
            store.finish_scan()
            if k:
                wall += 1e3 * (time.perf_counter() - t0)
                cpu["calling thread"] += 1e3 * (time.thread_time() - c0) - inline[0]
    finally:
        placer.close()
        if pool is not None:
            pool.shutdown()
    return {"wall": wall, "cpu": dict(cpu), "walk_rounds": walk_rounds}


def best_deal(spans: Sequence[float]) -> float:
    """The shortest longest thread of the walks ``spans`` dealt between two threads."""
    total = sum(spans)
    best = total
    for sides in itertools.product((0, 1), repeat=len(spans) - 1):
        one = sum(s for s, side in zip(spans[1:], sides, strict=True) if side) + spans[0]
        best = min(best, max(one, total - one))
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="anchors", help="anchors (box world) or ouster_street")
    parser.add_argument("--resolution", type=float, default=0.2)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    scans = _scene(args.scene)
    print(f"{args.scene} at {args.resolution} m, {len(scans) - 1} later scans a run (ms)")
    for round_ in range(args.rounds):
        one = run(scans, args.resolution, 1, False)
        apart = run(scans, args.resolution, 2, True)
        together = run(scans, args.resolution, 2, False)
        base = sum(one["cpu"].values())  # one thread: the calling thread's CPU
        print(f"round {round_ + 1}: one thread {base:.0f}")
        for label, result in (("two threads, one after another", apart), ("at once", together)):
            cpu = result["cpu"]
            work = sum(cpu.values())
            phases = ", ".join(f"{name} {ms:.0f}" for name, ms in sorted(cpu.items()))
            print(
                f"  {label}: wall {result['wall']:.0f}, CPU {work:.0f} ({phases}); CPU / one "
                f"thread's {work / base:.2f}, one thread's wall / this "
                f"{one['wall'] / result['wall']:.2f}"
            )
        rounds = together["walk_rounds"]
        if rounds:
            achieved = sum(wall for wall, _ in rounds)
            print(
                f"  walks at once: their rounds {achieved:.0f}, the best deal of "
                f"the measured walks {sum(best_deal(s) for _, s in rounds):.0f}, half their "
                f"time {sum(sum(s) / 2 for _, s in rounds):.0f}"
            )


if __name__ == "__main__":
    main()
