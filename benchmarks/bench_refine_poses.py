"""``replay --refine-poses`` against KISS-ICP's poses alone, on the real recordings.

For each recording, poses from ``--odometry kiss-icp`` (mapping.localize, not refined) and
the same with every scan aligned against the map built so far (``--refine-poses``, 0.2 m),
compared with the recording's reference poses (ouster_street: the SDK's poses;
norlab_sequence: its ICP odometry; ``sim_room``: a simulated bag's exact odometry, the
room of test/cli/test_localize_bag.py): absolute trajectory error (RMS, metres, after expressing
both trajectories relative to their first pose) and relative error per metre travelled
(translation of consecutive relative motions, summed, over the distance).

    python benchmarks/bench_refine_poses.py
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from mfp_mapper.config.replay_options import ReplayOptions  # noqa: E402
from mfp_mapper.core.alignment import AlignOptions  # noqa: E402
from mfp_mapper.mapping.localize import replay_refined  # noqa: E402
from mfp_mapper.sources.pose_files import read_kitti_poses, read_odometry_csv  # noqa: E402

DATA = ROOT.parent / "shared" / "data"


def _relative(pos: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray, Rotation]:
    r0 = Rotation.from_quat(quat[0])
    rots = r0.inv() * Rotation.from_quat(quat)
    return r0.inv().apply(pos - pos[0]), rots


def errors(est: tuple[np.ndarray, np.ndarray], ref: tuple[np.ndarray, np.ndarray]) -> tuple:
    pe, re = _relative(*est)
    pr, rr = _relative(*ref)
    ate = float(np.sqrt(np.mean(np.sum((pe - pr) ** 2, axis=1))))
    rot = float(np.degrees(np.max((re.inv() * rr).magnitude())))
    # relative pose error per metre: consecutive motions
    drift, dist = 0.0, 0.0
    for k in range(1, len(pe)):
        de = re[k - 1].inv().apply(pe[k] - pe[k - 1])
        dr = rr[k - 1].inv().apply(pr[k] - pr[k - 1])
        drift += float(np.linalg.norm(de - dr))
        dist += float(np.linalg.norm(dr))
    return ate, rot, drift / dist if dist > 0 else float("nan"), dist


def sim_case(root: Path) -> tuple[str, Path, tuple[np.ndarray, np.ndarray]]:
    """A simulated bag (40 scans around the room of test_localize_bag, walls off the voxel
    boundaries) and its exact odometry (the poses replay reads from it)."""
    from mfp_mapper.sources.simulate import preset, simulate

    small = preset("small")
    scene = replace(small.scene, room_lo=(-7.07, -6.94, -0.05), room_hi=(6.96, 7.03, 3.93))
    bag = simulate(root / "sim", replace(small, scene=scene, scans=40), "mcap").bag
    truth = replay_refined(bag, ReplayOptions.of(resolution=0.2), refine=False)
    body = Rotation.from_quat(np.array([s.quaternion for s in truth.scans]))
    mount = Rotation.from_euler("xyz", small.lidar_rpy)
    # KISS-ICP gives the lidar's poses: truth = body pose * lidar mount
    pos = np.array([s.position for s in truth.scans]) + body.apply(small.lidar_translation)
    return "sim_room", bag, (pos, (body * mount).as_quat())


def main() -> None:
    cases = []
    if (DATA / "ouster_street").is_dir():
        p, q = read_kitti_poses(DATA / "ouster_street" / "poses.txt")
        cases.append(("ouster_street", DATA / "ouster_street" / "scans", (p, q)))
    if (DATA / "norlab_sequence").is_dir():
        rows = read_odometry_csv(DATA / "norlab_sequence" / "trajectory.csv")
        cases.append(
            ("norlab_sequence", DATA / "norlab_sequence" / "scans",
             (rows["position"], rows["quaternion"]))
        )  # fmt: skip
    import tempfile

    tmp = tempfile.TemporaryDirectory()
    cases.append(sim_case(Path(tmp.name)))
    opts = ReplayOptions.of(resolution=0.2, odometry="kiss-icp")
    print("recording        poses                 ATE (m)  max rot (deg)  RPE (m/m)  time (s)")
    every_scan = AlignOptions(refresh_growth=0.0, refresh_m=0.0)  # the old rule: same poses
    for name, folder, ref in cases:
        for label, refine, align in (
            ("kiss-icp", False, AlignOptions()),
            ("kiss-icp + refine", True, AlignOptions()),
            ("  pyramid every scan", True, every_scan),
        ):
            t0 = time.perf_counter()
            res = replay_refined(folder, opts, refine=refine, align=align)
            secs = time.perf_counter() - t0
            pos = np.array([s.position for s in res.scans])
            quat = np.array([s.quaternion for s in res.scans])
            n = min(len(pos), len(ref[0]))
            ate, rot, rpe, dist = errors((pos[:n], quat[:n]), (ref[0][:n], ref[1][:n]))
            align_s = sum(s.seconds for s in res.scans)
            print(f"{name:16s} {label:20s} {ate:8.4f}  {rot:12.3f}  {rpe:9.4f}  {secs:7.1f}"
                  f"   ({n} scans, {dist:.2f} m, {res.accepted} refined, "
                  f"{1000 * align_s / max(n, 1):.0f} ms/scan aligning, "
                  f"{res.pyramid_builds} pyramid builds)")  # fmt: skip


if __name__ == "__main__":
    main()
