"""What two threads can give at all on this machine: small kernels, 1 against 2 threads.

The threaded walk splits space: each thread adds chords into its own blocks of a large
array. The ceiling for that on a given machine is what the same access pattern gives with
nothing else in the way. Three ``nogil`` numba kernels, each run by one thread over all
the work or by two ``threading.Thread`` over half the work each (each thread on its own
half of the array, as the shards own their blocks):

- ``gather-add``: random float32 read-modify-writes into a large array (every add a
  cache miss, like entering a new block);
- ``line-add``: a random 64-byte line, then 16 adds into it (the walk's pattern: a block
  entered, then several voxels of it);
- ``compute``: the same random-number and float arithmetic in registers only (the control:
  what two cores give without memory).

Rounds are interleaved (1 thread, 2 threads, 1 thread, ...), wall time of each, with the
load average read before each round, and the cores the rest of the machine used during each
run (``/proc/stat``). The ratio is one thread's wall time / two threads'; the quiet rounds'
(nothing else ran) is printed apart.

    python benchmarks/bench_parallel_ceiling.py                  # 100 MB, 5 rounds
    python benchmarks/bench_parallel_ceiling.py --mbytes 20 150 --rounds 7
"""

from __future__ import annotations

import argparse
import os
import threading
import time
from collections.abc import Callable

import numba
import numpy as np


@numba.njit(nogil=True, cache=True)
def _gather_add(table: np.ndarray, lo: int, hi: int, count: int, seed: int) -> float:
    """``count`` random adds into ``table[lo:hi]``; returns a checksum of the draws."""
    state = np.uint64(seed) | np.uint64(1)
    span = np.uint64(hi - lo)
    total = 0.0
    for _ in range(count):
        state ^= state << np.uint64(13)
        state ^= state >> np.uint64(7)
        state ^= state << np.uint64(17)
        index = lo + np.int64(state % span)
        value = np.float32(state & np.uint64(1023)) * np.float32(1e-3)
        table[index] += value
        total += value
    return total


@numba.njit(nogil=True, cache=True)
def _line_add(table: np.ndarray, lo: int, hi: int, count: int, seed: int) -> float:
    """``count`` adds, 16 at a time into one random 64-byte line of ``table[lo:hi]``."""
    state = np.uint64(seed) | np.uint64(1)
    lines = np.uint64((hi - lo) // 16)
    total = 0.0
    for _ in range(count // 16):
        state ^= state << np.uint64(13)
        state ^= state >> np.uint64(7)
        state ^= state << np.uint64(17)
        base = lo + 16 * np.int64(state % lines)
        for j in range(16):
            value = np.float32((state >> np.uint64(j)) & np.uint64(1023)) * np.float32(1e-3)
            table[base + j] += value
            total += value
    return total


@numba.njit(nogil=True, cache=True)
def _compute(table: np.ndarray, lo: int, hi: int, count: int, seed: int) -> float:
    """The draws and float arithmetic of ``_gather_add`` without touching memory."""
    state = np.uint64(seed) | np.uint64(1)
    span = np.uint64(hi - lo)
    total = 0.0
    acc = np.float32(0.0)
    for _ in range(count):
        state ^= state << np.uint64(13)
        state ^= state >> np.uint64(7)
        state ^= state << np.uint64(17)
        index = lo + np.int64(state % span)
        acc += np.float32(index & 1023) * np.float32(1e-3)
        total += acc
    return total


QUIET_CORES = 0.25
"""A round is quiet when the rest of the machine used less than this many cores during
both of its runs: the ratio of the quiet rounds is the machine's own."""
KERNELS: dict[str, Callable[[np.ndarray, int, int, int, int], float]] = {
    "gather-add": _gather_add,
    "line-add": _line_add,
    "compute": _compute,
}


def _busy_seconds() -> float:
    """CPU seconds all processes of the machine have used (``/proc/stat``)."""
    with open("/proc/stat") as stat:
        fields = [int(x) for x in stat.readline().split()[1:]]
    busy = sum(fields) - fields[3] - fields[4]  # all but idle and iowait
    return busy / os.sysconf("SC_CLK_TCK")


def _own_seconds() -> float:
    return time.process_time()


def run(
    kernel: Callable[..., float], table: np.ndarray, count: int, threads: int
) -> tuple[float, float, float]:
    """``count`` kernel steps split over ``threads`` threads, each over its own contiguous
    half of ``table`` (one thread does both halves, one after another). Returns the wall
    seconds, this process's CPU seconds, and the cores the rest of the machine used
    meanwhile (its CPU seconds / wall seconds: the load that competed with this run)."""
    size = len(table)
    bounds = [size * k // 2 for k in range(3)]  # the same two halves for 1 and 2 threads
    parts = [(bounds[k], bounds[k + 1], count // 2, 17 + k) for k in range(2)]
    workers = [threading.Thread(target=kernel, args=(table, *part)) for part in parts]
    busy0, own0, start = _busy_seconds(), _own_seconds(), time.perf_counter()
    if threads == 1:
        for lo, hi, steps, seed in parts:
            kernel(table, lo, hi, steps, seed)
    else:
        for worker in workers:
            worker.start()
        for worker in workers:
            worker.join()
    wall = time.perf_counter() - start
    own = _own_seconds() - own0
    return wall, own, max(0.0, _busy_seconds() - busy0 - own) / wall


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--mbytes", type=float, nargs="+", default=[100.0])
    parser.add_argument("--steps", type=float, default=4e7, help="adds a run, all threads")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    count = int(args.steps)
    print(f"cpus {os.cpu_count()}, {count:.0e} steps a run, wall time, rounds interleaved")
    print(
        "kernel, MB: wall 1 / 2 threads ms (medians); wall ratio median (range); CPU time 2 / 1"
        " threads; cores the rest of the machine used during the runs; load average"
    )
    for mbytes in args.mbytes:
        table = np.zeros(int(mbytes * 2**20) // 4, dtype=np.float32)
        for name, kernel in KERNELS.items():
            run(kernel, table, 1 << 16, 2)  # compile (or load the cache) and fault in
            table[:] = 0.0
            ones, twos, ratios, cpus, others, loads = [], [], [], [], [], []
            for _ in range(args.rounds):
                loads.append(os.getloadavg()[0])
                one, cpu_one, other_one = run(kernel, table, count, 1)
                two, cpu_two, other_two = run(kernel, table, count, 2)
                ones.append(one)
                twos.append(two)
                ratios.append(one / two)
                cpus.append(cpu_two / max(cpu_one, 1e-9))
                others += [other_one, other_two]
            quiet = [
                ratio
                for ratio, a, b in zip(ratios, others[::2], others[1::2], strict=True)
                if max(a, b) < QUIET_CORES
            ]
            quiet_text = f"; quiet rounds {np.median(quiet):.2f}x ({len(quiet)})" if quiet else ""
            print(
                f"{name} {mbytes:g} MB: {1e3 * np.median(ones):.0f} / "
                f"{1e3 * np.median(twos):.0f} ms; {np.median(ratios):.2f}x "
                f"({min(ratios):.2f}-{max(ratios):.2f}); CPU {np.median(cpus):.2f}; "
                f"others {min(others):.2f}-{max(others):.2f} cores; "
                f"load {min(loads):.2f}-{max(loads):.2f}{quiet_text}",
                flush=True,
            )


if __name__ == "__main__":
    main()
