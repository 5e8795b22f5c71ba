"""The node's localization mode without ROS: time per VLP-16 scan against a saved 0.2 m map.

Both paths go through the live worker (``mapping.live.LiveIntegrator.process``: parse,
place, then either localize or integrate), interleaved scan by scan in one run, one core
(``Mapper(threads=1)``, the worker thread's CPU time):

- **localize**: ``localization.enabled`` with the map frozen: the cloud is placed in the
  odometry frame, moved by map <- odom and aligned against the map's field;
- **integrate**: the plain mapping worker integrating the same cloud into a copy of the map.

The scene is the simulated hall (``test/localization_scenes.py``): the map from 12 static
VLP-16 scans (16 x 1800 rays) on a 6 m circle, saved and loaded back; the stream is
``--scans`` scans at 10 Hz on a 5 m circle (inside the map's) at ``--speed`` m/s, seen
through odometry that is off the truth by 0.3 m and 3 degrees (``--drift``: and drifting
by that much per metre travelled). The first scan searches wide (from that offset), the
next ones track. Printed: the correction's error to the true offset after the stream
(with drift: after each scan, against the drifting truth), and per path the median and
95th percentile of the CPU time per scan, with the ratio localize / integrate.

    python benchmarks/bench_live_localization.py [--scans 40 --tracking-rays 1500 --drift 0.02 0.5]

``--tracking-rays``, ``--tracking-iterations``, ``--normals-refresh``,
``--exact-check-tracking``, ``--no-exact-check``: the ``localization.*`` settings of those
names (defaults: the node's).

The stream is stamped at 10 Hz; ``--min-period`` aligns at most one scan per that many
seconds (``localization.min_period``), the others only placed with the last correction.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "test")]

from localization_scenes import localization_scene, pose_at, static_scan  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from mfp_mapper.config.sections import LocalizationSection, PlacementSection  # noqa: E402
from mfp_mapper.core.mapper import Mapper  # noqa: E402
from mfp_mapper.mapio.loading import load_map, save_map  # noqa: E402
from mfp_mapper.mapping.live import LiveIntegrator, LiveSettings  # noqa: E402
from mfp_mapper.mapping.live_localization import LiveLocalizer, pose_matrix  # noqa: E402
from mfp_mapper.mapping.pose_correction import LocalizerCorrection  # noqa: E402
from mfp_mapper.sensing.poses import OdometrySample, PoseBuffer  # noqa: E402
from mfp_mapper.sources.scan_files import cloud_message_from_columns  # noqa: E402

OFFSET = pose_matrix((0.3, -0.1, 0.0), Rotation.from_euler("z", 3.0, degrees=True).as_matrix())
T0 = 1000.0


def hall_map() -> tuple[Any, Mapper, Mapper]:
    """The scene, the saved map loaded back (localize) and a copy of it (integrate)."""
    scene, pos = localization_scene("box")
    rng = np.random.default_rng(0)
    built = Mapper(0.2, max_range=60.0, frame_id="map", threads=1)
    for k in range(0, 24, 2):
        pose = pose_at(pos[k], yaw=0.3 * k)
        built.integrate(pose.apply(static_scan(scene, pose, rng)), pose.translation, float(k))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "hall.npz"
        save_map(built, path)
        a, b = (load_map(path, threads=1) for _ in range(2))
    return scene, a, b


def worker(mapper: Mapper, localizer: LiveLocalizer | None) -> LiveIntegrator:
    settings = LiveSettings(PlacementSection(deskew=False, cloud_queue_size=5, odom_wait=0.5))
    return LiveIntegrator(
        mapper,
        settings,
        PoseBuffer(max_age=1e6, max_gap=0.5),
        log=lambda key, text, error: None,
        now=lambda: T0 + 1e5,
        map_frame="" if localizer is not None else "odom",
        correction=None if localizer is None else LocalizerCorrection(localizer),
    )


def feed(w: LiveIntegrator, odom: np.ndarray, msg: Any, stamp: float) -> float:
    """Odometry around ``stamp``, then the cloud processed on this thread; CPU seconds."""
    q = Rotation.from_matrix(odom[:3, :3]).as_quat()
    for t in (stamp - 0.04, stamp + 0.04):
        w.add_odometry(OdometrySample(t, "odom", "base_link", odom[:3, 3].copy(), q))
    w.submit(msg)
    with w._cv:  # noqa: SLF001 - the benchmark times one cloud through process()
        item = w._queue.popleft()  # noqa: SLF001
    cpu = time.thread_time()
    assert w.process(item)
    return time.thread_time() - cpu


def _error(m: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    d = np.linalg.inv(truth) @ m
    return float(np.linalg.norm(d[:3, 3])), float(
        np.degrees(Rotation.from_matrix(d[:3, :3]).magnitude())
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", type=int, default=40)
    ap.add_argument("--rays", type=int, default=3000, help="rays of the wide search")
    ap.add_argument("--tracking-rays", type=int, default=1000, help="rays while localized")
    ap.add_argument("--tracking-iterations", type=int, default=10)
    ap.add_argument("--normals-refresh", type=float, default=0.5, help="m; 0: every scan")
    ap.add_argument("--no-exact-check", action="store_true", help="localization.exact_check off")
    ap.add_argument(
        "--exact-check-tracking", action="store_true", help="localization.exact_check_tracking"
    )
    ap.add_argument("--min-period", type=float, default=0.0)
    ap.add_argument("--tracking-levels", type=int, default=1)
    ap.add_argument("--update-min-d", type=float, default=0.0)
    ap.add_argument("--update-min-a", type=float, default=0.0)
    ap.add_argument("--speed", type=float, default=1.0, help="m/s along the circle")
    ap.add_argument(
        "--drift",
        type=float,
        nargs=2,
        default=(0.0, 0.0),
        metavar=("M_PER_M", "DEG_PER_M"),
        help="odometry drift: metres (along x) and degrees (yaw) per metre travelled",
    )
    args = ap.parse_args()
    scene, map_a, map_b = hall_map()
    loc = LiveLocalizer(
        LocalizationSection(
            max_rays=args.rays,
            tracking_rays=args.tracking_rays,
            tracking_iterations=args.tracking_iterations,
            normals_refresh=args.normals_refresh,
            exact_check=not args.no_exact_check,
            exact_check_tracking=args.exact_check_tracking,
            min_period=args.min_period,
            tracking_levels=args.tracking_levels,
            update_min_d=args.update_min_d,
            update_min_a=args.update_min_a,
        ),
        "map",
        log=lambda text: None,
    )
    t0 = time.perf_counter()
    loc.build(map_a, worker(map_a, None).whole_map)
    build_s = time.perf_counter() - t0
    w_loc, w_int = worker(map_a, loc), worker(map_b, None)
    rng = np.random.default_rng(3)
    t_loc: list[float] = []
    t_int: list[float] = []
    errors: list[tuple[float, float]] = []
    true_c = OFFSET
    for k in range(args.scans):
        a = args.speed * 0.1 * k / 5.0  # radians along the 5 m circle, 10 scans per second
        truth = pose_at(np.array([5.0 * np.cos(a), 5.0 * np.sin(a), 1.2]), yaw=a + 1.0)
        pts = static_scan(scene, truth, rng).astype(np.float32)
        stamp = T0 + 0.1 * k  # a 10 Hz stream
        msg = cloud_message_from_columns({c: pts[:, i] for i, c in enumerate("xyz")}, stamp)
        msg.header.frame_id = "base_link"
        travelled = args.speed * 0.1 * k
        drift = pose_matrix(
            (args.drift[0] * travelled, 0.0, 0.0),
            Rotation.from_euler("z", args.drift[1] * travelled, degrees=True).as_matrix(),
        )
        true_c = OFFSET @ drift  # the true map <- odom of a drifting odometry
        odom = np.linalg.inv(true_c) @ pose_matrix(truth.translation, truth.rotation)
        truth_odom = pose_matrix(truth.translation, truth.rotation)
        order = [(w_loc, odom, t_loc), (w_int, truth_odom, t_int)]
        for w, pose, out in order if k % 2 == 0 else order[::-1]:
            out.append(feed(w, pose, msg, stamp))
        errors.append(_error(loc.correction, true_c))
    rep = loc.report()
    err_m, err_deg = errors[-1]
    e = np.array(errors[1:])
    ms_l, ms_i = 1e3 * np.array(t_loc), 1e3 * np.array(t_int)
    print(
        f"hall, VLP-16 ({len(pts)} returns/scan), 0.2 m map of {map_a.num_voxels} voxels "
        f"(field built in {build_s:.2f} s), {args.scans} scans, {args.rays} rays in the wide "
        f"search, {args.tracking_rays} while tracking ({args.tracking_iterations} iterations, "
        f"normals every {args.normals_refresh:g} m, exact check "
        f"{'off' if args.no_exact_check else 'on'}"
        f"{', also tracking' if args.exact_check_tracking else ', wide search only'})"
    )
    print(
        f"correction error after the stream: {100 * err_m:.2f} cm, {err_deg:.3f} deg; "
        f"state {rep['state']}; accepted {rep['accepted']}, refused {rep['refused']}; "
        f"{rep['exact_checked']} exact checks, normals computed {rep['normals_computed']} times"
    )
    if args.drift[0] or args.drift[1]:
        print(
            f"odometry drift {args.drift[0]:g} m and {args.drift[1]:g} deg per metre over "
            f"{args.speed * 0.1 * (args.scans - 1):.1f} m: correction error after each scan "
            f"median {100 * np.median(e[:, 0]):.1f} cm / {np.median(e[:, 1]):.2f} deg, max "
            f"{100 * e[:, 0].max():.1f} cm / {e[:, 1].max():.2f} deg"
        )
    print(f"first scan (wide search from 0.3 m / 3 deg): localize {ms_l[0]:.0f} ms CPU")
    for name, ms in (("localize ", ms_l[1:]), ("integrate", ms_i[1:])):
        print(
            f"{name} median {np.median(ms):6.1f} ms CPU/scan, p95 {np.percentile(ms, 95):6.1f} "
            f"ms -> {1e3 / np.median(ms):5.1f} Hz on one core"
        )
    print(f"ratio localize / integrate (median): {np.median(ms_l[1:]) / np.median(ms_i[1:]):.2f}")
    share = float(np.sum(ms_l[1:])) / (1e3 * 0.1 * (args.scans - 1))
    aligned = ms_l[1:][ms_l[1:] > 20.0]
    print(
        f"a 10 Hz stream at {args.speed:g} m/s, min_period {args.min_period:g} s, update_min_d "
        f"{args.update_min_d:g} m / _a {args.update_min_a:g} deg: {rep['aligned']} of "
        f"{args.scans} scans aligned (median {np.median(aligned) if len(aligned) else 0:.0f} "
        f"ms each), localization CPU {100 * share:.0f}% of one core "
        f"({'keeps up' if share < 1.0 else 'falls behind'})"
    )


if __name__ == "__main__":
    main()
