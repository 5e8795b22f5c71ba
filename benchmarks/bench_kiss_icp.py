"""KISS-ICP poses (``--odometry kiss-icp``): error against known poses, and time.

- the structured hall of ``test/odometry_scenes.py`` (uneven 1 m floor tiles, pillars,
  crates; a robot starting from rest on a 4 m circle at up to 2 m/s; a simulated VLP-16),
  with and without de-skew, at KISS-ICP voxels of 0.3 m (max range 30 m) and 1 m (100 m);
- the real norlab sequence (14 VTK scans) against its ICP odometry.

Errors are relative to the first pose: max and RMS translation, max rotation; the time is
KISS-ICP's alone, as a ratio to the time of mapping the same clouds with known poses.

    python benchmarks/bench_kiss_icp.py [--scans 20]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "test")]

from odometry_scenes import lidar_truth, pose_errors, structured_recording  # noqa: E402

from mfp_mapper.mapping.replay import ReplayOptions, replay  # noqa: E402
from mfp_mapper.sensing.poses import quaternion_to_matrix  # noqa: E402
from mfp_mapper.sources.bags import open_reader  # noqa: E402
from mfp_mapper.sources.lidar_odometry import estimate_poses  # noqa: E402
from mfp_mapper.sources.pose_files import read_odometry_csv  # noqa: E402
from mfp_mapper.sources.scan_folder import open_scan_folder  # noqa: E402
from mfp_mapper.sources.simulate import simulate  # noqa: E402


def _line(
    name: str, stamps: np.ndarray, est: np.ndarray, ref: np.ndarray, seconds: float, base: float
) -> None:
    tr, rot = pose_errors(est, ref)
    path = float(np.sum(np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1)))
    print(
        f"{name:44s} {len(stamps):3d} poses, path {path:5.2f} m: translation max "
        f"{tr.max():.3f} rms {np.sqrt(np.mean(tr**2)):.3f} m, rotation max "
        f"{np.degrees(rot.max()):.2f} deg; {seconds:.2f} s ({seconds / base:.1f}x mapping)"
    )


def structured(scans: int) -> None:
    cfg = structured_recording(scans=scans)
    with tempfile.TemporaryDirectory() as tmp:
        bag = simulate(Path(tmp) / "bag", cfg, "mcap").bag
        t0 = time.perf_counter()
        replay(bag, ReplayOptions.of(resolution=0.1), progress=False)
        base = time.perf_counter() - t0
        for max_range in (30.0, 100.0):
            for deskew in (True, False):
                reader = open_reader(bag)
                conns = [c for c in reader.connections if c.topic == cfg.cloud_topic]
                clouds = (
                    (None, lambda c=c, r=r, rd=reader: rd.deserialize(r, c.msgtype))
                    for c, _, r in reader.messages(connections=conns)
                )
                t0 = time.perf_counter()
                stamps, poses = estimate_poses(
                    clouds, ReplayOptions.of(max_range=max_range, deskew=deskew)
                )
                seconds = time.perf_counter() - t0
                reader.close()
                name = f"hall, voxel {max_range / 100:g} m, de-skew {'on' if deskew else 'off'}"
                _line(name, stamps, poses, lidar_truth(cfg, stamps), seconds, base)


def norlab() -> None:
    sequence = ROOT / ".." / "shared" / "data" / "norlab_sequence"
    if not sequence.is_dir():
        print("norlab sequence absent: skipped")
        return
    folder = open_scan_folder(sequence / "scans")
    loads = [(s.stamp, lambda k=k: folder.message(k)) for k, s in enumerate(folder.scans)]
    t0 = time.perf_counter()
    stamps, poses = estimate_poses(loads, ReplayOptions())
    seconds = time.perf_counter() - t0
    odometry = read_odometry_csv(sequence / "icp_odom.csv")
    ref = np.tile(np.eye(4), (len(stamps), 1, 1))
    for k, stamp in enumerate(stamps):
        j = int(np.argmin(np.abs(odometry["stamp"] - stamp)))
        ref[k, :3, :3] = quaternion_to_matrix(odometry["quaternion"][j])
        ref[k, :3, 3] = odometry["position"][j]
    from mfp_mapper.sources.opener import open_recording

    t0 = time.perf_counter()
    opts = ReplayOptions.of(resolution=0.2)
    with open_recording(sequence / "scans", opts, sequence / "icp_odom.csv") as recording:
        replay(recording, opts, progress=False)
    base = time.perf_counter() - t0
    _line("norlab (real, 14 scans) vs its ICP odometry", stamps, poses, ref, seconds, base)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=20)
    args = parser.parse_args()
    structured(args.scans)
    norlab()


if __name__ == "__main__":
    main()
