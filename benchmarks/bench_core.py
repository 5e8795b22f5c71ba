"""Core insertion benchmark: mfp_mapper against OctoMap on identical rays, in one run.

Each measurement runs in its own subprocess, so peak memory is that mapper's alone.
Prints rays/s, the ratio to OctoMap measured in the same run, peak memory and voxel
counts; then the latency of one VLP-16 scan, cold and warm start, and a real frame.

    python benchmarks/bench_core.py            # the ANCHORS.md scene at 0.4, 0.2, 0.1 m
    python benchmarks/bench_core.py --quick    # 0.2 m only, fewer repetitions
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
NEBULA = ROOT.parent / "shared" / "data" / "nebula_frames"
sys.path[:0] = [str(ROOT), str(ROOT / "test")]  # the package and the test scenes


def _rss_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def _scene(name: str) -> list[tuple[np.ndarray, np.ndarray]]:
    from box_world import anchors_scene

    if name == "anchors":
        return anchors_scene()
    from mfp_mapper.sources.scan_files import read_pcd

    cols = read_pcd(NEBULA / name)
    points = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
    points = points[np.isfinite(points).all(axis=1) & (np.linalg.norm(points, axis=1) > 0.3)]
    return [(points, np.zeros(3))]


def child(kind: str, scene: str, resolution: float, threads: int, max_range: float) -> dict:
    """Runs in the subprocess: insert every scan of ``scene``, report time and memory."""
    scans = _scene(scene)
    rays = sum(len(p) for p, _ in scans)
    if kind == "octomap":
        import octomap

        tree = octomap.OcTree(resolution)
        base = _rss_kib("VmRSS")
        per_scan = []
        for points, origin in scans:
            t0 = time.perf_counter()
            tree.insertPointCloud(points, origin, maxrange=max_range)
            per_scan.append(time.perf_counter() - t0)
        voxels = tree.getNumLeafNodes()
    else:
        from mfp_mapper import Mapper

        warm = Mapper(resolution, threads=threads)
        warm.integrate(scans[0][0][:64], scans[0][1], 0.0)  # load the compiled kernels
        warm.close()
        mapper = Mapper(resolution, threads=threads, max_range=max_range)
        base = _rss_kib("VmRSS")
        per_scan = []
        for k, (points, origin) in enumerate(scans):
            t0 = time.perf_counter()
            mapper.integrate(points, origin, float(k))
            per_scan.append(time.perf_counter() - t0)
        voxels = mapper.num_voxels
        mapper.close()
    peak_mb = (_rss_kib("VmHWM") - base) / 1024.0
    # after the first scan: what a running mapper pays per scan (the first one also pays for
    # fresh memory, which a virtual machine makes slow and variable)
    later = float(np.median(per_scan[1:])) if len(per_scan) > 1 else per_scan[0]
    return {
        "rays": rays,
        "seconds": sum(per_scan),
        "later_scan_ms": 1e3 * later,
        "voxels": voxels,
        "peak_mb": peak_mb,
    }


def scan_latency(resolution: float, threads: int, repeats: int) -> dict:
    """Median time of one VLP-16 scan (28.8k rays, 30 m max range) after warm-up."""
    from box_world import anchors_scene

    from mfp_mapper import Mapper

    scans = anchors_scene(n_scans=repeats + 2)
    mapper = Mapper(resolution, threads=threads, max_range=30.0)
    times = []
    for k, (points, origin) in enumerate(scans):
        t0 = time.perf_counter()
        mapper.integrate(points, origin, float(k))
        times.append(time.perf_counter() - t0)
    mapper.close()
    return {"median_ms": 1e3 * float(np.median(times[2:])), "rays": len(scans[0][0])}


def start_time() -> dict:
    """Seconds from interpreter start to the first integrated scan (run as a fresh process)."""
    t0 = time.perf_counter()
    from box_world import anchors_scene

    from mfp_mapper import Mapper

    points, origin = anchors_scene(n_scans=1)[0]
    Mapper(0.1).integrate(points, origin, 0.0)
    return {"seconds": time.perf_counter() - t0}


def run_child(args: list[str], env: dict[str, str] | None = None) -> dict:
    out = subprocess.run(
        [sys.executable, __file__, "--child", *args],
        check=True,
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="0.2 m only, fewer repetitions")
    parser.add_argument("--resolutions", type=float, nargs="+", default=None)
    parser.add_argument("--no-octomap", action="store_true", help="skip the baseline (no ratios)")
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        what, *rest = args.child
        if what == "insert":
            kind, scene, res, threads = rest
            result = child(kind, scene, float(res), int(threads), 100.0)
        elif what == "latency":
            result = scan_latency(float(rest[0]), int(rest[1]), int(rest[2]))
        else:
            result = start_time()
        print(json.dumps(result))
        return

    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    resolutions = args.resolutions or ([0.2] if args.quick else [0.4, 0.2, 0.1])
    print("scene: VLP-16 pattern, 16 x 1800 rays, 11 scans (ANCHORS.md); one process per row")
    row = "{:>5} {:<18} {:>8} {:>10} {:>9} {:>10} {:>9} {:>8} {:>11} {:>8}"
    header = ("res", "mapper", "seconds", "rays/s", "x OctoMap", "ms/scan*", "x OctoMap")
    print(row.format(*header, "peak MB", "voxels", "B/voxel"))
    scenes = [("anchors", resolutions)]
    vlp32 = NEBULA / "velodyne_vlp32_1713492677464078412.pcd"
    if vlp32.exists():
        scenes.append((vlp32.name, [0.1]))
    for scene, scene_res in scenes:
        if scene != "anchors":
            print(f"real frame: {scene}")
        for res in scene_res:
            base = (
                None
                if args.no_octomap
                else run_child(["insert", "octomap", scene, str(res), "1"], env)
            )
            rows = [("OctoMap (1 thread)", base)] if base else []
            for threads in (1, 2):
                rows.append(
                    (
                        f"mfp_mapper ({threads} thr)",
                        run_child(["insert", "mfp", scene, str(res), str(threads)], env),
                    )
                )
            for name, r in rows:
                rate = r["rays"] / r["seconds"]
                ratio = f"{base['seconds'] / r['seconds']:.1f}" if base else "-"
                later = f"{base['later_scan_ms'] / r['later_scan_ms']:.1f}" if base else "-"
                per_voxel = 1e6 * r["peak_mb"] / max(r["voxels"], 1)
                print(
                    row.format(
                        f"{res:.2f}",
                        name,
                        f"{r['seconds']:.3f}",
                        f"{rate:.0f}",
                        ratio,
                        f"{r['later_scan_ms']:.1f}",
                        later,
                        f"{r['peak_mb']:.0f}",
                        r["voxels"],
                        f"{per_voxel:.1f}",
                    )
                )
    repeats = "5" if args.quick else "20"
    for threads in (1, 2):
        lat = run_child(["latency", "0.1", str(threads), repeats], env)
        print(
            f"one VLP-16 scan ({lat['rays']} rays, 30 m, 0.1 m), {threads} thread(s): "
            f"median {lat['median_ms']:.1f} ms"
        )
    print("* median time of the scans after the first (the first also faults in fresh memory)")
    with tempfile.TemporaryDirectory() as cache:
        cold_env = {**env, "NUMBA_CACHE_DIR": cache}
        cold = run_child(["start"], cold_env)["seconds"]
        warm = run_child(["start"], cold_env)["seconds"]
    print(
        f"start to first integrated scan: cold (empty numba cache) {cold:.2f} s, warm {warm:.2f} s"
    )


if __name__ == "__main__":
    main()
