"""Every echo of a shot, on the real multi-echo scan tls_conifers (RIEGL VZ-400i, rTLS data).

    python benchmarks/bench_echoes.py blind   # later echoes' rate behind an echo (blind stretch)
    python benchmarks/bench_echoes.py cost    # a scan with echoes against its first echoes

``blind``: a map of the first echoes of the even shots; for the odd shots, between each echo
and the next (the stretch the all-echo model counts: a shot's ``s`` ends at its last echo),
the rate of the next echo observed against the rate the map predicts (the posterior mean
extinction of the voxels the beam crosses, ``(n + shape) / (s + rate)``), in bins of
distance behind the echo. Where the ratio is well below 1 the lidar is blind: the default
``sensor_model.echo_blind_stretch`` leaves that stretch out of ``s`` (docs/model.md).

``cost``: the same scan integrated with all its echoes (its shots grouped into segments,
one Poisson process per shot, then integrated) and its first echoes alone (plain rays from
the sensor), interleaved ``--rounds`` times in this process; the ratio of the two times,
per round (median and range), in wall-clock and in this thread's CPU seconds (steadier on
a shared machine), after one untimed round (the first round's first map paid for loading
the compiled kernels). Parsing (grouping the echoes into shots) is not timed.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from mfp_mapper import Mapper
from mfp_mapper.sensing.echoes import shot_segments
from mfp_mapper.sensing.pointcloud import parse_pointcloud2
from mfp_mapper.sources.scan_files import cloud_message_from_columns, read_ply

ROOT = Path(__file__).resolve().parents[1]
SCAN = ROOT.parent / "shared" / "data" / "tls_conifers" / "scan.ply"


def load(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The scan's points (sensor at the origin) and their shots, read as a scan file is."""
    cloud = parse_pointcloud2(cloud_message_from_columns(read_ply(path), 0.0, "scanner"))
    assert cloud.shot is not None
    return cloud.xyz, cloud.shot


def blind(path: Path, resolution: float, reach: float, bin_m: float, max_range: float) -> None:
    xyz, shot = load(path)
    seg = shot_segments(xyz, np.zeros(3), shot, None, 0.0)
    odd = seg.shot % 2 == 1
    train = ~odd & ~seg.continued
    mapper = Mapper(resolution, max_range=1e3)
    mapper.integrate(seg.points[train], np.zeros(3), 0.0)
    shape, rate = mapper.prior.shape, mapper.prior.rate
    pts = seg.points[odd]
    sid = seg.shot[odd]
    rng = np.linalg.norm(pts, axis=1)
    unit = pts / rng[:, None]
    has_next = np.zeros(len(pts), dtype=bool)
    has_next[:-1] = sid[1:] == sid[:-1]
    gap = np.full(len(pts), np.inf)
    gap[:-1][has_next[:-1]] = (rng[1:] - rng[:-1])[has_next[:-1]]
    edges = np.arange(0.0, reach + bin_m / 2, bin_m)
    expected = np.zeros(edges.size - 1)
    observed = np.zeros(edges.size - 1)
    step = resolution / 8.0
    offsets = np.arange(step / 2.0, reach, step)
    chunk = 20_000
    for lo in range(0, len(pts), chunk):
        r, u, g = rng[lo : lo + chunk], unit[lo : lo + chunk], gap[lo : lo + chunk]
        at = r[:, None] + offsets[None, :]
        # the beam is known to go on up to the next echo (the model's s ends at the last)
        exposed = (offsets[None, :] < g[:, None]) & np.isfinite(g)[:, None] & (at < max_range)
        where = u[:, None, :] * at[:, :, None]
        stats = mapper.query(where.reshape(-1, 3))
        mean_rate = ((stats.n + shape) / (stats.s + rate)).reshape(at.shape)
        k = np.minimum((offsets / bin_m).astype(int), edges.size - 2)
        expected += np.bincount(
            np.broadcast_to(k, at.shape)[exposed], (mean_rate * step)[exposed], edges.size - 1
        )
        seen = np.isfinite(g) & (g < reach) & (r + g < max_range)
        observed += np.bincount((g[seen] / bin_m).astype(int), minlength=edges.size - 1)[
            : edges.size - 1
        ]
    print(
        f"# {path.name}: {len(xyz):,} echoes, {int(seg.shot.max()) + 1:,} shots, "
        f"{int(seg.continued.sum()):,} later echoes; map of the even shots' first echoes "
        f"at {resolution} m (prior {shape:g}, {rate:g}); ranges below {max_range} m"
    )
    print("behind_echo_m  observed  expected  ratio")
    for k in range(edges.size - 1):
        ratio = observed[k] / expected[k] if expected[k] > 0 else float("nan")
        print(f"{edges[k]:4.1f}-{edges[k + 1]:4.1f}  {observed[k]:8.0f}  {expected[k]:8.1f}  "
              f"{ratio:5.2f}")  # fmt: skip


def cost(path: Path, resolution: float, rounds: int, blind_m: float) -> None:
    xyz, shot = load(path)
    first = shot_segments(xyz, np.zeros(3), shot, None, blind_m, first_only=True).points
    wall: dict[str, list[float]] = {"all": [], "first": []}
    cpu: dict[str, list[float]] = {"all": [], "first": []}
    rays = {"all": 0, "first": 0}
    for round_ in range(rounds + 1):  # round 0 warms up (kernels loaded, memory mapped)
        for name in ("first", "all"):
            mapper = Mapper(resolution, max_range=1e3)
            t0, c0 = time.perf_counter(), time.thread_time()
            if name == "first":  # the first echoes alone, as plain rays from the sensor
                summary = mapper.integrate(first, np.zeros(3), 0.0)
            else:  # every echo: shots grouped into segments, then integrated
                seg = shot_segments(xyz, np.zeros(3), shot, None, blind_m)
                summary = mapper.integrate(seg.points, seg.origins, 0.0, continued=seg.continued)
            if round_ == 0:
                continue
            wall[name].append(time.perf_counter() - t0)
            cpu[name].append(time.thread_time() - c0)
            rays[name] = summary.rays_used
    print(
        f"# {path.name} at {resolution} m, blind stretch {blind_m} m: {rays['first']:,} "
        f"first echoes, {rays['all']:,} echoes ({rays['all'] / rays['first']:.3f}x rays)"
    )
    for label, times in (("wall", wall), ("cpu", cpu)):
        ratios = [a / f for a, f in zip(times["all"], times["first"], strict=True)]
        print(f"{label}: first median {statistics.median(times['first']):.3f} s, all median "
              f"{statistics.median(times['all']):.3f} s; all / first: median "
              f"{statistics.median(ratios):.3f} (range {min(ratios):.3f}-{max(ratios):.3f}, "
              f"{rounds} rounds)")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("blind", "cost"))
    parser.add_argument("--scan", type=Path, default=SCAN)
    parser.add_argument("--resolution", type=float, default=0.1)
    parser.add_argument("--reach", type=float, default=3.0, help="metres behind an echo")
    parser.add_argument("--bin", type=float, default=0.1)
    parser.add_argument("--max-range", type=float, default=14.0, help="the scan's crop")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--blind", type=float, default=0.75, help="blind stretch (m), cost")
    args = parser.parse_args()
    if not args.scan.is_file():
        raise SystemExit(f"{args.scan}: not found (the tls_conifers scan of ../shared/data)")
    if args.what == "blind":
        blind(args.scan, args.resolution, args.reach, args.bin, args.max_range)
    else:
        cost(args.scan, args.resolution, args.rounds, args.blind)


if __name__ == "__main__":
    main()
