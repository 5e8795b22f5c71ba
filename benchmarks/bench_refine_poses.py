"""``replay --refine-poses`` against KISS-ICP's poses alone, on the real recordings.

For each recording, poses from ``--odometry kiss-icp`` (mapping.localize, not refined) and
the same with every scan aligned against the map built so far (``--refine-poses``, 0.2 m),
compared with the recording's reference poses (ouster_street: the SDK's poses;
norlab_sequence: its ICP odometry): absolute trajectory error (RMS, metres, after expressing
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
from mfp_mapper.mapping.localize import replay_refined_folder  # noqa: E402
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
    opts = replace(ReplayOptions(), resolution=0.2, odometry="kiss-icp")
    print("recording        poses                 ATE (m)  max rot (deg)  RPE (m/m)  time (s)")
    for name, folder, ref in cases:
        for refine in (False, True):
            t0 = time.perf_counter()
            res = replay_refined_folder(folder, None, opts, refine=refine)
            secs = time.perf_counter() - t0
            pos = np.array([s.position for s in res.scans])
            quat = np.array([s.quaternion for s in res.scans])
            n = min(len(pos), len(ref[0]))
            ate, rot, rpe, dist = errors((pos[:n], quat[:n]), (ref[0][:n], ref[1][:n]))
            label = "kiss-icp + refine" if refine else "kiss-icp"
            print(f"{name:16s} {label:20s} {ate:8.4f}  {rot:12.3f}  {rpe:9.4f}  {secs:7.1f}"
                  f"   ({n} scans, {dist:.2f} m, {res.accepted} refined)")  # fmt: skip


if __name__ == "__main__":
    main()
