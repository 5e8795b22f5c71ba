"""Scan-to-map alignment (``core.alignment``): accuracy, robustness, refusals and time.

For each case a map is built at 0.2 m from some scans at their known poses, and every
other scan is aligned against it from its pose perturbed by exactly ``--shift`` metres in a
random direction and ``--angle`` degrees about a random axis (``--trials`` draws per scan):

- simulated scenes with exact truth (``test/localization_scenes.py``): the hall (``box``),
  ``vegetation`` (media only, no walls) and a featureless ``corridor`` (must be refused);
- real recordings in ../shared/data: ouster_street (map scans 0 and 2, align scan 1; its
  poses are the SDK's, not survey truth) and norlab_sequence (map the even scans, align the
  odd ones; its poses are ICP odometry).

Per case: accepted corrections, median error and the share within 10 cm and 1 deg (of the
accepted), wrong acceptances (error > 10 cm or 1 deg), the time per scan and its ratio to
integrating the same scan into the map.

    python benchmarks/bench_localize.py [--shift 0.5 --angle 5 --trials 2 --cases box,...]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "test")]  # the package and the test scenes

from localization_scenes import (  # noqa: E402
    Pose,
    localization_scene,
    perturb,
    pose_at,
    static_scan,
)

from mfp_mapper.core.alignment import (  # noqa: E402
    AlignOptions,
    FieldPyramid,
    align_scan,
    verify_exact,
)
from mfp_mapper.core.mapper import Mapper  # noqa: E402
from mfp_mapper.sensing.poses import quaternion_to_matrix  # noqa: E402
from mfp_mapper.sensing.scan_normals import scan_normals  # noqa: E402
from mfp_mapper.sources.pose_files import read_kitti_poses, read_odometry_csv  # noqa: E402
from mfp_mapper.sources.scan_files import read_kitti_bin, read_vtk_points  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
RES = 0.2


def sim_case(name: str) -> tuple[list[Pose], list[np.ndarray], list[int], list[int]]:
    scene, pos = localization_scene(name)
    rng = np.random.default_rng(0)
    poses = [pose_at(p, yaw=0.3 * k) for k, p in enumerate(pos)]
    scans = [static_scan(scene, p, rng) for p in poses]
    idx = list(range(len(poses)))
    return poses, scans, idx[0::2], idx[1::2]


def ouster_case() -> tuple[list[Pose], list[np.ndarray], list[int], list[int]]:
    d = DATA / "ouster_street"
    pos, quat = read_kitti_poses(d / "poses.txt")
    poses = [Pose(quaternion_to_matrix(q), p) for p, q in zip(pos, quat, strict=True)]
    files = sorted((d / "scans").glob("*.bin"))
    scans = []
    for f in files:
        cols = read_kitti_bin(f)
        xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
        scans.append(xyz[np.linalg.norm(xyz, axis=1) > 1.0])
    return poses, scans, [0, 2], [1]


def norlab_case() -> tuple[list[Pose], list[np.ndarray], list[int], list[int]]:
    d = DATA / "norlab_sequence"
    rows = read_odometry_csv(d / "trajectory.csv")
    files = sorted((d / "scans").glob("*.vtk"))
    poses = [
        Pose(quaternion_to_matrix(rows["quaternion"][k]), rows["position"][k])
        for k in range(len(files))
    ]
    scans = [read_vtk_points(f) for f in files]
    scans = [s[np.linalg.norm(s, axis=1) > 1.0] for s in scans]
    idx = list(range(len(files)))
    return poses, scans, idx[0::2], idx[1::2]


CASES = {
    "box": lambda: sim_case("box"),
    "vegetation": lambda: sim_case("vegetation"),
    "corridor": lambda: sim_case("corridor"),
    "ouster_street": ouster_case,
    "norlab_sequence": norlab_case,
}


def run_case(name: str, args: argparse.Namespace, opts: AlignOptions) -> None:
    if name in ("ouster_street", "norlab_sequence") and not (DATA / name).is_dir():
        print(f"{name:16s} skipped: {DATA / name} absent")
        return
    poses, scans, mapped, aligned = CASES[name]()
    mapper = Mapper(RES, max_range=100.0)
    t_int = []
    for k in mapped:
        t0 = time.perf_counter()
        mapper.integrate(poses[k].apply(scans[k]), poses[k].translation, stamp=float(k))
        t_int.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    pyramid = FieldPyramid.from_mapper(mapper, levels=opts.levels)
    t_pyramid = time.perf_counter() - t0
    rng = np.random.default_rng(1)
    errs, wrong, refused, secs, total = [], 0, 0, [], 0
    final = []  # every scan's error after localization (refused: its initial error)
    parts = {"normals": 0.0, "align": 0.0, "verify": 0.0}
    for k in aligned:
        for _ in range(args.trials):
            init = perturb(poses[k], rng, args.shift, args.angle)
            pts = init.apply(scans[k])
            t0 = time.perf_counter()
            nrm = scan_normals(pts)
            t1 = time.perf_counter()
            al = align_scan(pyramid, pts, init.translation, opts, normals=nrm)
            t2 = time.perf_counter()
            if not args.no_verify:
                al = verify_exact(mapper, al, pts, init.translation, float(k), opts)
            t3 = time.perf_counter()
            parts["normals"] += t1 - t0
            parts["align"] += t2 - t1
            parts["verify"] += t3 - t2
            secs.append(t3 - t0)
            total += 1
            if not al.accepted:
                refused += 1
                final.append(init.error_to(poses[k]))
                continue
            ref = Pose(al.rotation @ init.rotation, al.rotation @ init.translation + al.translation)
            e = ref.error_to(poses[k])
            errs.append(e)
            final.append(e)
            bad = e[0] > 0.1 or e[1] > 1.0
            wrong += int(bad)
            if bad and args.verbose:
                print(
                    f"  wrong: scan {k}: {e[0]:.3f} m {e[1]:.2f} deg, sigma "
                    f"{np.round(al.sigma, 3)}, constraints {al.conditioning}, "
                    f"gain/ray {al.gain_per_ray:.3f}"
                )
    e = np.array(errs).reshape(-1, 2)
    med = np.median(e, axis=0) if len(e) else np.array([np.nan, np.nan])
    within = float(np.mean((e[:, 0] <= 0.1) & (e[:, 1] <= 1.0))) if len(e) else float("nan")
    f = np.array(final).reshape(-1, 2)
    f_med = float(np.median(f[:, 0]))
    f_within = float(np.mean((f[:, 0] <= 0.1) & (f[:, 1] <= 1.0)))
    ratio = float(np.median(secs) / np.median(t_int))
    print(
        f"{name:16s} {total:3d} scans  accepted {total - refused:3d}  "
        f"median {100 * med[0]:5.1f} cm "
        f"{med[1]:5.2f} deg  within 10 cm/1 deg {100 * within:5.1f}%  wrong {wrong:2d}  "
        f"{1000 * np.median(secs):6.0f} ms/scan ({ratio:.1f}x integrating one scan)\n"
        f"{'':16s} all scans after localization: median {100 * f_med:5.1f} cm, within "
        f"10 cm/1 deg {100 * f_within:5.1f}%; ms/scan: "
        + ", ".join(f"{k} {1000 * v / total:.0f}" for k, v in parts.items())
        + f"; pyramid (once) {1000 * t_pyramid:.0f} ms"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--shift", type=float, default=0.5)
    ap.add_argument("--angle", type=float, default=5.0)
    ap.add_argument("--trials", type=int, default=1)
    ap.add_argument("--rays", type=int, default=3000)
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--step", type=float, default=0.5, help="free-space samples (voxels)")
    ap.add_argument("--probe-rays", type=int, default=1000)
    ap.add_argument("--live", action="store_true", help="AlignOptions.live() (flags ignored)")
    ap.add_argument("--no-verify", action="store_true", help="skip verify_exact")
    ap.add_argument("--verbose", action="store_true", help="print each wrong acceptance")
    args = ap.parse_args()
    opts = AlignOptions(
        levels=args.levels,
        max_rays=args.rays,
        step=args.step,
        probe_rays=args.probe_rays,
        exact_rays=args.rays,
    )
    if args.live:
        opts = AlignOptions.live()
        args.rays, args.levels, args.step, args.probe_rays = (
            opts.max_rays, opts.levels, opts.step, opts.probe_rays,
        )  # fmt: skip
    print(f"initial error {args.shift} m, {args.angle} deg; map {RES} m; {args.rays} rays, "
          f"{args.levels} levels, step {args.step}, {args.probe_rays} probe rays")  # fmt: skip
    for name in args.cases.split(","):
        run_case(name, args, opts)


if __name__ == "__main__":
    main()
