"""Core insertion benchmark: mfp_mapper against OctoMap (and Bonxai) on identical rays.

Each measurement runs in its own subprocess, so peak memory is that mapper's alone.
Prints rays/s, the ratio to OctoMap measured in the same run, peak memory and voxel
counts; then the latency of one VLP-16 scan, cold and warm start, and a real frame.

    python benchmarks/bench_core.py            # the box-world scene at 0.4, 0.2, 0.1 m
    python benchmarks/bench_core.py --quick    # 0.2 m only, fewer repetitions
    python benchmarks/bench_core.py --bonxai ~/src/Bonxai --rounds 5 --resolutions 0.2 0.1

``--bonxai DIR`` takes a Bonxai source tree (https://github.com/facontidavide/Bonxai, not
part of this project: clone it yourself; Eigen 3 headers are needed, e.g.
``apt install libeigen3-dev``). The benchmark writes a small driver (``BONXAI_DRIVER``
below: one ``ProbabilisticMap::insertPointCloud`` per scan), compiles it with that tree's
``probabilistic_map.cpp`` (``$CXX``, default ``c++``, ``-O3 -march=native``) into a cache
directory outside the repository, and runs it on the same rays as the other mappers.
With ``--rounds N`` the mappers run interleaved, one process each per round, and the
ratios are per round (median and range).
"""

from __future__ import annotations

import argparse
import hashlib
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
OUSTER = ROOT.parent / "shared" / "data" / "ouster_street"
"""Three real OS1-128 scans with KITTI poses (``--ouster``): a real recording's rays."""
NORLAB = ROOT.parent / "shared" / "data" / "norlab_sequence"
"""14 real scans of a VLP-32C-like lidar with odometry (``--norlab``): a second recording."""
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
    if name == "ouster_street":
        poses = np.loadtxt(OUSTER / "poses.txt").reshape(-1, 3, 4)
        scans = []
        for k, pose in enumerate(poses):
            xyz = np.fromfile(OUSTER / "scans" / f"{k:06d}.bin", dtype=np.float32)
            xyz = xyz.reshape(-1, 4)[:, :3].astype(np.float64)
            xyz = xyz[np.linalg.norm(xyz, axis=1) > 0.3]
            scans.append((xyz @ pose[:, :3].T + pose[:, 3], pose[:, 3].copy()))
        return scans
    if name == "norlab_sequence":
        from mfp_mapper.sensing.poses import quaternion_to_matrix
        from mfp_mapper.sources.pose_files import read_odometry_csv
        from mfp_mapper.sources.scan_files import read_vtk_points

        rows = read_odometry_csv(NORLAB / "trajectory.csv")
        scans = []
        for k, path in enumerate(sorted((NORLAB / "scans").glob("*.vtk"))):
            xyz = read_vtk_points(path)
            xyz = xyz[np.linalg.norm(xyz, axis=1) > 0.3]
            rotation = quaternion_to_matrix(rows["quaternion"][k])
            position = np.asarray(rows["position"][k], dtype=np.float64)
            scans.append((xyz @ rotation.T + position, position.copy()))
        return scans
    from mfp_mapper.sources.scan_files import read_pcd

    cols = read_pcd(NEBULA / name)
    points = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
    points = points[np.isfinite(points).all(axis=1) & (np.linalg.norm(points, axis=1) > 0.3)]
    return [(points, np.zeros(3))]


def child(kind: str, scene: str, resolution: float, threads: int, max_range: float) -> dict:
    """Runs in the subprocess: insert every scan of ``scene``, report time and memory."""
    scans = _scene(scene)
    rays = sum(len(p) for p, _ in scans)
    cut = 0  # mfp_mapper's rays cut by a scan's block bound (none on these scenes)
    if kind == "octomap":
        import octomap

        tree = octomap.OcTree(resolution)
        base = _rss_kib("VmRSS")
        per_scan, cpu = [], []
        for points, origin in scans:
            t0, c0 = time.perf_counter(), time.process_time()
            tree.insertPointCloud(points, origin, maxrange=max_range)
            per_scan.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        voxels = tree.getNumLeafNodes()
        map_mb = float(tree.memoryUsage()) / 1e6
    else:
        from mfp_mapper import Mapper

        warm = Mapper(resolution, threads=threads)
        warm.integrate(scans[0][0][:64], scans[0][1], 0.0)  # load the compiled kernels
        warm.close()
        mapper = Mapper(resolution, threads=threads, max_range=max_range)
        base = _rss_kib("VmRSS")
        per_scan, cpu = [], []
        for k, (points, origin) in enumerate(scans):
            t0, c0 = time.perf_counter(), time.process_time()
            summary = mapper.integrate(points, origin, float(k))
            per_scan.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            cut += summary.rays_cut_by_budget
        voxels = mapper.num_voxels
        map_mb = mapper.memory_bytes / 1e6
        mapper.close()
    peak_mb = (_rss_kib("VmHWM") - base) / 1024.0
    # after the first scan: what a running mapper pays per scan (the first one also pays for
    # fresh memory, which a virtual machine makes slow and variable)
    later = float(np.median(per_scan[1:])) if len(per_scan) > 1 else per_scan[0]
    return {
        "rays": rays,
        "seconds": sum(per_scan),
        "later_scan_ms": 1e3 * later,
        "later_scan_cpu_ms": 1e3 * float(np.median(cpu[1:] if len(cpu) > 1 else cpu)),
        "voxels": voxels,
        "rays_cut": cut,
        "peak_mb": peak_mb,
        "map_mb": map_mb,
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


BONXAI_DRIVER = r"""
// Insert scans into Bonxai's ProbabilisticMap, one insertPointCloud per scan.
// argv[1] = resolution, argv[2] = max_range, argv[3] = rays file
// (int64 scans; per scan: int64 n, 3 doubles origin, n*3 doubles points).
#include <chrono>
#include <ctime>
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>
#include "bonxai_map/probabilistic_map.hpp"
static long rss_kib(const char* field) {
  std::ifstream f("/proc/self/status");
  std::string line;
  size_t n = std::string(field).size();
  while (std::getline(f, line))
    if (line.compare(0, n, field) == 0 && line[n] == ':') return std::stol(line.substr(n + 1));
  return 0;
}
int main(int argc, char** argv) {
  if (argc != 4) { std::fprintf(stderr, "usage: driver RES MAX_RANGE RAYS\n"); return 2; }
  const double res = std::stod(argv[1]), max_range = std::stod(argv[2]);
  std::FILE* in = std::fopen(argv[3], "rb");
  if (!in) { std::perror(argv[3]); return 2; }
  long long scans = 0;
  if (std::fread(&scans, 8, 1, in) != 1) return 2;
  std::vector<std::vector<Eigen::Vector3d>> clouds(scans);
  std::vector<Eigen::Vector3d> origins(scans);
  long long rays = 0;
  for (long long k = 0; k < scans; ++k) {
    long long n = 0;
    double o[3];
    if (std::fread(&n, 8, 1, in) != 1 || std::fread(o, 8, 3, in) != 3) return 2;
    origins[k] = Eigen::Vector3d(o[0], o[1], o[2]);
    std::vector<double> buf(3 * n);
    if (std::fread(buf.data(), 8, 3 * n, in) != size_t(3 * n)) return 2;
    clouds[k].resize(n);
    for (long long i = 0; i < n; ++i)
      clouds[k][i] = Eigen::Vector3d(buf[3 * i], buf[3 * i + 1], buf[3 * i + 2]);
    rays += n;
  }
  std::fclose(in);
  const long base = rss_kib("VmRSS");
  Bonxai::ProbabilisticMap map(res);
  std::vector<double> wall(scans), cpu(scans);
  for (long long k = 0; k < scans; ++k) {
    auto t0 = std::chrono::steady_clock::now();
    std::clock_t c0 = std::clock();
    map.insertPointCloud(clouds[k], origins[k], max_range);
    cpu[k] = double(std::clock() - c0) / CLOCKS_PER_SEC;
    wall[k] = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }
  std::printf("{\"rays\": %lld, \"per_scan\": [", rays);
  for (long long k = 0; k < scans; ++k) std::printf("%s%.9f", k ? ", " : "", wall[k]);
  std::printf("], \"cpu\": [");
  for (long long k = 0; k < scans; ++k) std::printf("%s%.9f", k ? ", " : "", cpu[k]);
  std::printf("], \"voxels\": %zu, \"peak_mb\": %.3f, \"map_mb\": %.3f}\n",
              map.grid().activeCellsCount(), (rss_kib("VmHWM") - base) / 1024.0,
              map.grid().memUsage() / 1e6);
  return 0;
}
"""
"""C++ source of the Bonxai driver: argv = resolution, max_range, rays file (int64 scans;
per scan int64 n, origin as 3 float64, n x 3 float64 points); prints one JSON line."""


def build_bonxai(tree: Path) -> Path:
    """Compile ``BONXAI_DRIVER`` against the Bonxai source ``tree`` (cached by content)."""
    include_core = tree / "bonxai_core" / "include"
    include_map = tree / "bonxai_map" / "include"
    source = tree / "bonxai_map" / "src" / "probabilistic_map.cpp"
    if not (include_core / "bonxai" / "bonxai.hpp").exists() or not source.exists():
        raise SystemExit(f"--bonxai: {tree} is not a Bonxai source tree (no {source})")
    cxx = os.environ.get("CXX", "c++")
    flags = ["-O3", "-march=native", "-std=c++17", "-DNDEBUG"]
    digest = hashlib.sha256(
        "\0".join([BONXAI_DRIVER, cxx, *flags, str(tree.resolve())]).encode()
        + (include_core / "bonxai" / "bonxai.hpp").read_bytes()
        + source.read_bytes()
    ).hexdigest()[:16]
    out_dir = Path(tempfile.gettempdir()) / f"mfp_bench_bonxai_{digest}"
    exe = out_dir / "bonxai_driver"
    if exe.exists():
        return exe
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "driver.cpp").write_text(BONXAI_DRIVER)
    eigen = [f"-I{d}" for d in ("/usr/include/eigen3", "/usr/local/include/eigen3")]
    cmd = [cxx, *flags, f"-I{include_core}", f"-I{include_map}", *eigen,
           str(out_dir / "driver.cpp"), str(source), "-o", str(exe) + ".tmp"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"--bonxai: compiling the driver failed:\n{done.stderr[-2000:]}")
    os.replace(str(exe) + ".tmp", exe)
    return exe


def write_rays(scans: list[tuple[np.ndarray, np.ndarray]], path: Path) -> None:
    """The scans in the driver's input format."""
    with path.open("wb") as f:
        f.write(np.int64(len(scans)).tobytes())
        for points, origin in scans:
            f.write(np.int64(len(points)).tobytes())
            f.write(np.ascontiguousarray(origin, dtype=np.float64).tobytes())
            f.write(np.ascontiguousarray(points, dtype=np.float64).tobytes())


def run_bonxai(exe: Path, rays: Path, resolution: float, max_range: float) -> dict:
    out = subprocess.run(
        [str(exe), repr(resolution), repr(max_range), str(rays)],
        check=True,
        capture_output=True,
        text=True,
    )
    r = json.loads(out.stdout.strip().splitlines()[-1])
    per_scan, cpu = r.pop("per_scan"), r.pop("cpu")
    r["seconds"] = sum(per_scan)
    r["later_scan_ms"] = 1e3 * float(np.median(per_scan[1:] if len(per_scan) > 1 else per_scan))
    r["later_scan_cpu_ms"] = 1e3 * float(np.median(cpu[1:] if len(cpu) > 1 else cpu))
    return dict(r)


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


def _insertion_rows(
    args: argparse.Namespace,
    env: dict[str, str],
    scene: str,
    res: float,
    bonxai: Path | None,
    rays_file: Path,
    row: str,
) -> None:
    """Run every mapper ``args.rounds`` times, interleaved, and print one row per mapper."""
    runs: dict[str, list[dict]] = {}
    for _ in range(args.rounds):
        if not args.no_octomap:
            runs.setdefault("OctoMap (1 thread)", []).append(
                run_child(["insert", "octomap", scene, str(res), "1"], env)
            )
        if bonxai:
            runs.setdefault("Bonxai (1 thread)", []).append(
                run_bonxai(bonxai, rays_file, res, 100.0)
            )
        for threads in args.threads:
            runs.setdefault(f"mfp_mapper ({threads} thr)", []).append(
                run_child(["insert", "mfp", scene, str(res), str(threads)], env)
            )
    base = runs.get("OctoMap (1 thread)")

    def median(name: str, key: str) -> float:
        return float(np.median([r[key] for r in runs[name]]))

    for name, rs in runs.items():
        seconds, later = median(name, "seconds"), median(name, "later_scan_ms")
        ratio = later_ratio = "-"
        if base:
            ratio = f"{median('OctoMap (1 thread)', 'seconds') / seconds:.1f}"
            later_ratio = f"{median('OctoMap (1 thread)', 'later_scan_ms') / later:.1f}"
        peak = median(name, "peak_mb")
        print(
            row.format(
                f"{res:.2f}", name, f"{seconds:.3f}", f"{rs[0]['rays'] / seconds:.0f}", ratio,
                f"{later:.1f}", later_ratio, f"{peak:.0f}", rs[0]["voxels"],
                f"{1e6 * peak / max(rs[0]['voxels'], 1):.1f}",
            )
        )  # fmt: skip
    one = "mfp_mapper (1 thr)"
    for name, rs in runs.items():  # identical rays give one map, whatever the threads
        if name.startswith("mfp_mapper") and (
            any(r["rays_cut"] for r in rs)
            or (one in runs and {r["voxels"] for r in rs} != {runs[one][0]["voxels"]})
        ):
            print(
                f"{res:.2f}   NOT THE SAME WORK: {name} cut {rs[0]['rays_cut']} rays by the "
                f"scan block bound and holds {rs[0]['voxels']} voxels ({one}: "
                f"{runs[one][0]['voxels'] if one in runs else '-'}); its times do not compare"
            )
    for name in runs:
        if name.startswith("mfp_mapper") and name != one and one in runs:
            per_round = [
                [o[key] / m[key] for o, m in zip(runs[one], runs[name], strict=True)]
                for key in ("later_scan_ms", "later_scan_cpu_ms")
            ]
            print(
                f"{res:.2f}   1 thread / {name}, later scans, per round: wall "
                f"{_spread(per_round[0])} (> 1: the threads faster), CPU time "
                f"{_spread(per_round[1])} (< 1: the threads' extra work)"
            )
    if bonxai:
        for name in runs:
            if name.startswith("mfp_mapper"):
                for key, what in (("later_scan_ms", "wall"), ("later_scan_cpu_ms", "CPU")):
                    per_round = [
                        b[key] / m[key]
                        for b, m in zip(runs["Bonxai (1 thread)"], runs[name], strict=True)
                    ]
                    print(
                        f"{res:.2f}   Bonxai / {name}, later scans ({what} time), per round: "
                        f"{_spread(per_round)} (> 1: mfp_mapper faster)"
                    )
                print(
                    f"{res:.2f}   map memory {name} / Bonxai (Mapper.memory_bytes / memUsage): "
                    f"{median(name, 'map_mb'):.1f} / {median('Bonxai (1 thread)', 'map_mb'):.1f}"
                    f" MB = {median(name, 'map_mb') / median('Bonxai (1 thread)', 'map_mb'):.2f}"
                    f"; peak RSS {median(name, 'peak_mb'):.0f} / "
                    f"{median('Bonxai (1 thread)', 'peak_mb'):.0f} MB (< 1: mfp_mapper smaller)"
                )


def _spread(values: list[float]) -> str:
    """Median (min-max) of per-round values."""
    if len(values) == 1:
        return f"{values[0]:.2f}"
    return f"{np.median(values):.2f} ({min(values):.2f}-{max(values):.2f})"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="0.2 m only, fewer repetitions")
    parser.add_argument("--resolutions", type=float, nargs="+", default=None)
    parser.add_argument("--no-octomap", action="store_true", help="skip the baseline (no ratios)")
    parser.add_argument(
        "--bonxai", type=Path, metavar="DIR", help="a Bonxai source tree: also run Bonxai"
    )
    parser.add_argument("--rounds", type=int, default=1, help="interleaved rounds (default 1)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="mfp_mapper's")
    parser.add_argument("--no-extras", action="store_true", help="only the insertion table")
    parser.add_argument(
        "--ouster",
        action="store_true",
        help=f"also the real OS1-128 scans of {OUSTER} (at --resolutions, else 0.2 m)",
    )
    parser.add_argument(
        "--norlab",
        action="store_true",
        help=f"also the 14 real VLP-32C scans of {NORLAB} (at --resolutions, else 0.2 m)",
    )
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
    bonxai = build_bonxai(args.bonxai) if args.bonxai else None
    print("scene: VLP-16 pattern, 16 x 1800 rays, 11 scans (box world); one process per row")
    if args.rounds > 1:
        print(f"{args.rounds} rounds, mappers interleaved; times are medians over the rounds")
    row = "{:>5} {:<18} {:>8} {:>10} {:>9} {:>10} {:>9} {:>8} {:>11} {:>8}"
    header = ("res", "mapper", "seconds", "rays/s", "x OctoMap", "ms/scan*", "x OctoMap")
    print(row.format(*header, "peak MB", "voxels", "B/voxel"))
    scenes = [("anchors", resolutions)]
    vlp32 = NEBULA / "velodyne_vlp32_1713492677464078412.pcd"
    if vlp32.exists() and not args.no_extras:
        scenes.append((vlp32.name, [0.1]))
    if args.ouster:
        if not OUSTER.exists():
            raise SystemExit(f"--ouster: {OUSTER} not found")
        scenes.append(("ouster_street", resolutions if args.resolutions else [0.2]))
    if args.norlab:
        if not NORLAB.exists():
            raise SystemExit(f"--norlab: {NORLAB} not found")
        scenes.append(("norlab_sequence", resolutions if args.resolutions else [0.2]))
    with tempfile.TemporaryDirectory() as tmp:
        for scene, scene_res in scenes:
            if scene != "anchors":
                print(f"real scans: {scene}")
            rays_file = Path(tmp) / "rays.bin"
            if bonxai:
                write_rays(_scene(scene), rays_file)
            for res in scene_res:
                _insertion_rows(args, env, scene, res, bonxai, rays_file, row)
    if args.no_extras:
        return
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
