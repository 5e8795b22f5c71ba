"""A long run's reflectivity histograms: what a scan's returns cost as the table grows.

A table of ``--rows`` voxels (a plane of them, as a long run's surfaces), then ``--scans``
scans of 40,000 returns each, 38,000 in voxels the table holds and 2,000 in new ones
(``ReflectivityTable.add``). It prints the time of a scan (mean, median, slowest: a scan
that merges the fresh rows into the settled ones, ``core.reflectivity.FRESH_ROWS_MIN``)
against scans of as many returns that all land in voxels the table holds, measured in the
same run: what the new voxels cost on top of finding the rows. (Before the fresh rows,
every scan that added a voxel copied the whole table.)

    python benchmarks/bench_reflectivity_table.py
    python benchmarks/bench_reflectivity_table.py --rows 100000 1000000 --scans 200
    python benchmarks/bench_reflectivity_table.py --decay-time 10   # decay: scans 0.1 s apart
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mfp_mapper.core.reflectivity import ReflectivityTable
from mfp_mapper.sensing.reflectivity import bins_for

OLD_RETURNS, NEW_RETURNS = 38_000, 2_000


def run(rows: int, scans: int, rng: np.random.Generator, decay_time: float) -> None:
    bins = bins_for("intensity", 8)
    assert bins is not None
    table = ReflectivityTable(bins)
    side = int(np.ceil(np.sqrt(rows)))
    xs, ys = np.meshgrid(np.arange(side), np.arange(side))
    plane = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size, dtype=np.int64)], axis=1)[:rows]
    table.add(plane, np.zeros(rows, dtype=np.int64), 0.0, decay_time)
    times = []
    for k in range(scans):
        seen = plane[rng.integers(0, rows, OLD_RETURNS)]
        new = np.stack(
            [
                rng.integers(0, side, NEW_RETURNS),
                rng.integers(0, side, NEW_RETURNS),
                np.full(NEW_RETURNS, 1 + k),
            ],
            axis=1,
        )
        ijk = np.concatenate([seen, new])
        values = rng.integers(0, bins.count, len(ijk))
        t0 = time.perf_counter()
        table.add(ijk, values, 0.1 * (1 + k), decay_time)
        times.append(1e3 * (time.perf_counter() - t0))
    known = []  # the same number of returns, all in voxels the table holds
    for k in range(max(scans // 5, 5)):
        ijk = plane[rng.integers(0, rows, OLD_RETURNS + NEW_RETURNS)]
        values = rng.integers(0, bins.count, len(ijk))
        t0 = time.perf_counter()
        table.add(ijk, values, 0.1 * (1 + scans + k), decay_time)
        known.append(1e3 * (time.perf_counter() - t0))
    scan, base = np.array(times[1:]), float(np.median(known))
    print(
        f"{len(table):>9,} rows ({table.nbytes / 1e6:.0f} MB): a scan {scan.mean():.1f} ms "
        f"mean, {np.median(scan):.1f} median, {scan.max():.1f} slowest; with no new voxel "
        f"{base:.1f} ms; mean / that {scan.mean() / base:.2f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", type=int, nargs="+", default=[100_000, 1_000_000, 4_000_000])
    parser.add_argument("--scans", type=int, default=100)
    parser.add_argument(
        "--decay-time", type=float, default=np.inf, help="s (default: none); scans 0.1 s apart"
    )
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(
        f"{args.scans} scans of {OLD_RETURNS + NEW_RETURNS:,} returns, {NEW_RETURNS:,} new, "
        f"0.1 s apart, decay time {args.decay_time} s"
    )
    for rows in args.rows:
        run(rows, args.scans, rng, args.decay_time)


if __name__ == "__main__":
    main()
