"""What a map publication costs the node, read from the whole map or from changed blocks.

    .venv/bin/python benchmarks/bench_map_cloud.py --resolution 0.1
    .venv/bin/python benchmarks/bench_map_cloud.py --resolution 0.2 --step 20 --scans 40

The real norlab scans (``../shared/data/norlab_sequence``, VLP-32C-like, 100 m range) are
integrated as the node does (parse, place, ``Mapper.integrate``); with ``--step`` each scan
is moved that many metres further along x, a robot driving through a growing map (0: the
recording's barely moving robot, every scan reaching nearly the whole map). After each scan
the map is "published" as ``ros.map_outputs`` does, timed without ROS:

- whole: ``Mapper.voxels(min_doo=0.1)`` and ``Mapper.reflectivity`` (the map lock's part
  of a publication with ``publish_changed_blocks`` false) and the rows built after it;
- changed: ``MapCloud.read`` (under the lock: the returns of the blocks the scan changed)
  and ``MapCloud.apply`` (after it: the rows of the whole cloud), checked equal to whole;
- grid: ``Mapper.hit_probability_grid`` of ``~/projected_map``, from the whole band and
  continued from the last scan's (``previous``: the columns the scan changed; checked
  equal), both under the lock, and its ``--grid-radius`` window around the robot
  (``hit_probability_map.radius``).

Printed per scan after the first few: ms of each (best of ``--repeat`` calls, whole and
changed interleaved), voxels and blocks read, and the lock-time ratio whole / changed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "benchmarks"), str(ROOT / "test"), str(ROOT / "test" / "ros")]
sys.path.insert(0, str(ROOT))

from bench_node import ODOM_PERIOD, SCAN_PERIOD, make_stream  # noqa: E402

from mfp_mapper import Mapper  # noqa: E402
from mfp_mapper.config.sections import PlacementSection, SensorModelSection  # noqa: E402
from mfp_mapper.core.gridmap import unobserved_hit_probability  # noqa: E402
from mfp_mapper.mapping.loop import ScanLoop  # noqa: E402
from mfp_mapper.mapping.map_cloud import MapCloud, rows_of  # noqa: E402
from mfp_mapper.sensing.poses import Extrinsic, PoseBuffer  # noqa: E402
from mfp_mapper.sources.scan_files import packed_cloud_message  # noqa: E402

MIN_DOO = 0.1


def _best(fn, repeat: int) -> tuple[object, float]:
    best, out = math.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, 1000 * best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--resolution", type=float, default=0.1)
    parser.add_argument("--scans", type=int, default=20)
    parser.add_argument("--step", type=float, default=0.0, help="metres along x a scan")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--skip", type=int, default=4, help="scans before the figures")
    parser.add_argument("--grid-radius", type=float, default=30.0, help="the grid's window (m)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    stream = make_stream("norlab", 14, args.resolution)
    t0 = 1000.0
    poses = PoseBuffer(max_age=1e9)
    for rel in np.arange(0.0, (args.scans + 1) * SCAN_PERIOD + 1e-9, ODOM_PERIOD):
        pos, q = stream.pose(float(rel))
        poses.add(t0 + rel, pos + [args.step * rel / SCAN_PERIOD, 0.0, 0.0], q)
    mapper = Mapper(args.resolution, max_range=100.0)
    loop = ScanLoop(mapper, PlacementSection(), SensorModelSection(max_range=100.0))
    free = unobserved_hit_probability(mapper.resolution, mapper.prior.shape, mapper.prior.rate)
    trinary = (0.25, min(free, 0.25))
    cloud = MapCloud()
    rows_out = []
    previous = None
    for k in range(args.scans):
        c = stream.clouds[k % len(stream.clouds)]
        msg = packed_cloud_message(c, t0 + k * SCAN_PERIOD, "base_link")
        placed = loop.place(loop.prepare(msg), poses, Extrinsic(translation=np.zeros(3)))
        t_scan = time.perf_counter()
        mapper.integrate(placed.points, placed.origins, placed.stamp, placed.no_return)
        scan_ms = 1000 * (time.perf_counter() - t_scan)
        changes, read_ms = _best(lambda: cloud.read(mapper, MIN_DOO, 0.0), 1)  # once: it moves on
        rows, apply_ms = _best(lambda ch=changes: cloud.apply(ch, 0.0), 1)
        whole_read = lambda: (v := mapper.voxels(min_doo=MIN_DOO), mapper.reflectivity(v.centers))  # noqa: E731
        (vox, hist), whole_ms = _best(whole_read, args.repeat)
        whole_rows, rows_ms = _best(lambda v=vox, h=hist: rows_of(v, h), 1)
        grid, grid_ms = _best(
            lambda: mapper.hit_probability_grid(0.1, 2.0, max_cells=25_000_000, trinary=trinary),
            args.repeat,
        )
        continued, continued_ms = _best(
            lambda p=previous: mapper.hit_probability_grid(
                0.1, 2.0, max_cells=25_000_000, trinary=trinary, previous=p
            ),
            1,
        )
        previous = continued.cells
        assert np.array_equal(continued.data, grid.data) and continued.origin == grid.origin
        robot = mapper.last_origin
        _, window_ms = _best(
            lambda r=robot: mapper.hit_probability_grid(
                0.1, 2.0, center=(r[0], r[1]), radius=args.grid_radius,
                max_cells=25_000_000, trinary=trinary,
            ),
            args.repeat,
        )  # fmt: skip
        assert len(rows) == len(whole_rows), (len(rows), len(whole_rows))
        a, b = np.lexsort(rows.centers.T), np.lexsort(whole_rows.centers.T)
        assert np.array_equal(rows.degree_of_occupancy[a], whole_rows.degree_of_occupancy[b])
        row = {
            "scan": k,
            "integrate_ms": round(scan_ms, 1),
            "voxels": mapper.num_voxels,
            "published": len(rows),
            "changed_blocks": cloud.last_changed_blocks,
            "changed_voxels": len(changes.voxels),
            "whole_lock_ms": round(whole_ms, 1),
            "whole_after_ms": round(rows_ms, 1),
            "changed_lock_ms": round(read_ms, 1),
            "changed_after_ms": round(apply_ms, 1),
            "grid_ms": round(grid_ms, 1),
            "grid_continued_ms": round(continued_ms, 1),
            "grid_window_ms": round(window_ms, 1),
        }
        print(json.dumps(row), flush=True)
        if k >= args.skip:
            rows_out.append(row)
    med = {k: float(np.median([r[k] for r in rows_out])) for k in rows_out[0] if k != "scan"}
    print(
        f"\nmedian over scans {args.skip}..{args.scans - 1} at {args.resolution} m, step "
        f"{args.step} m: map {med['voxels']:.0f} voxels, {med['published']:.0f} published; "
        f"cloud under the lock: whole {med['whole_lock_ms']:.1f} ms, changed blocks "
        f"{med['changed_lock_ms']:.1f} ms ({med['changed_blocks']:.0f} blocks): "
        f"{med['whole_lock_ms'] / max(med['changed_lock_ms'], 1e-3):.1f}x; after the lock: "
        f"whole {med['whole_after_ms']:.1f}, changed {med['changed_after_ms']:.1f} ms; grid "
        f"{med['grid_ms']:.1f} ms, continued from the last {med['grid_continued_ms']:.1f} ms "
        f"({med['grid_ms'] / max(med['grid_continued_ms'], 1e-3):.1f}x), "
        f"{args.grid_radius:g} m around the robot "
        f"{med['grid_window_ms']:.1f} ms; integrate {med['integrate_ms']:.0f} ms a scan; load "
        f"average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"
    )
    if args.json:
        args.json.write_text(json.dumps({"args": vars(args) | {"json": None}, "rows": rows_out}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
