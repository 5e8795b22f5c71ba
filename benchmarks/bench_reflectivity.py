"""Map memory with and without the reflectivity field (Appendix B), on real scans.

Integrates the three ouster_street scans (Ouster OS-1-128, ``x y z reflectivity``, with their
poses) per resolution, with and without intensities, in the same process, and prints
``Mapper.memory_bytes`` of both and the ratio: the sparse histogram table's cost; then the
CPU seconds (``time.process_time``: the machine is shared) of ``integrate`` for the three
scans, with and without, interleaved over ``--rounds`` (which goes first alternates; medians
and the median of the per-round ratios, measured in the same run).

    python benchmarks/bench_reflectivity.py [--data ../shared/data] [--resolutions 0.2 0.1]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.reflectivity import ScanReflectivity
from mfp_mapper.sensing.reflectivity import bins_for


def street_scans(data: Path) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(world points, sensor position, reflectivity) of each ouster_street scan."""
    street = data / "ouster_street"
    poses = np.loadtxt(street / "poses.txt").reshape(-1, 3, 4)
    out = []
    for k, pose in enumerate(poses):
        rec = np.fromfile(street / "scans" / f"{k:06d}.bin", "<f4").reshape(-1, 4).astype(float)
        out.append((rec[:, :3] @ pose[:, :3].T + pose[:, 3], pose[:, 3], rec[:, 3]))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data"))
    parser.add_argument("--resolutions", type=float, nargs="+", default=[0.2, 0.1])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    scans = street_scans(args.data)
    bins = bins_for("reflectivity", 8)
    assert bins is not None
    Mapper(1.0).integrate(
        scans[0][0], scans[0][1], 0.0, reflectivity=ScanReflectivity(scans[0][2], bins)
    )
    for resolution in args.resolutions:
        seconds: dict[bool, list[float]] = {False: [], True: []}
        sizes = {}
        table, voxels = None, 0
        for round_ in range(args.rounds):
            for with_intensity in (False, True) if round_ % 2 == 0 else (True, False):
                mapper = Mapper(resolution)
                t0 = time.process_time()
                for stamp, (points, origin, values) in enumerate(scans):
                    refl = ScanReflectivity(values, bins) if with_intensity else None
                    mapper.integrate(points, origin, float(stamp), reflectivity=refl)
                seconds[with_intensity].append(time.process_time() - t0)
                sizes[with_intensity] = mapper.memory_bytes
                if with_intensity:
                    table = mapper.stored_reflectivity()
                    voxels = mapper.num_voxels
        rows = 0 if table is None else len(table)
        share = 100 * rows / max(voxels, 1)
        extra = 100 * (sizes[True] / sizes[False] - 1)
        print(
            f"{resolution:g} m: {voxels:,} voxels, {rows:,} with returns "
            f"({share:.1f}%); memory {sizes[False] / 2**20:.2f} MiB without, "
            f"{sizes[True] / 2**20:.2f} MiB with histograms (+{extra:.1f}%)"
        )
        plain, with_hist = (statistics.median(seconds[k]) for k in (False, True))
        ratio = statistics.median(a / b for a, b in zip(seconds[True], seconds[False], strict=True))
        print(
            f"  integrate, 3 scans: {plain:.3f} CPU s without, {with_hist:.3f} CPU s with "
            f"histograms (x{ratio:.3f}, median of {args.rounds} interleaved rounds)"
        )


if __name__ == "__main__":
    main()
