"""The node's live localization mode, without ROS: each placed cloud aligned against the map.

Clouds are placed in the odometry frame (odometry or TF ``odom -> base``, as AMCL takes
them); the localizer keeps the correction ``map <- odom`` (4x4) and, for each cloud:

1. applies a pending ``/initialpose`` (the robot's pose in the map at a stamp): the
   correction becomes ``T_map_base * inv(T_odom_base)``, and the next clouds search wider;
2. moves the placed rays by the correction (the initial guess in the map frame);
3. aligns them against the map's field (``core.alignment.align_scan``, a ``FieldPyramid``
   built in the background from the loaded map, rebuilt every ``rebuild_period`` seconds
   when mapping goes on), on the worker thread, at most once per ``min_period``; while
   localized with the tracking options (``tracking_levels``, ``tracking_rays``,
   ``tracking_iterations``, ``AlignOptions.live``) and the scan normals of the last
   ``normals_refresh`` metres; a correction of the wide search (and with
   ``exact_check_tracking`` every one) is checked against the exact likelihood
   (``verify_exact``, refusal ``exact_check``);
4. on acceptance composes the correction with the alignment's; a refusal keeps the last
   correction and is counted under its reason: never a silent wrong pose.

State: ``waiting_for_map`` (no field yet), ``initializing`` (no correction accepted since the
start or the last ``/initialpose``), ``localized``, ``lost`` (``lost_after`` consecutive
refusals while localized). Before the first acceptance, and when lost, the search range is
the wider ``initial_max_shift`` / ``initial_max_angle``. A refusal for lack of gain
(``no_gain``, or ``exact_check``: the scan's surfaces constrain every direction and the
best pose in range is no better than the current one) confirms a localized or lost pose
(lost -> localized) rather than counting toward lost; while ``initializing`` it ends it
only under the checks of a first acceptance below (a right ``/initialpose``, or odometry
that starts where the map says, finds no gain: without this it stayed ``initializing``).

A gain only says the pose is a local optimum; it does not say the scan belongs there (after
odometry jumps 5 m a scan still finds a small gain against the wrong walls). So each scan's
fit (``Alignment.fit_per_ray``, the smoothed log-likelihood per ray at the pose kept) is
compared with a reference: the fit of the scans accepted or confirmed before it (set by the
first acceptance after the start or an ``/initialpose``, then a moving average). A scan that
fits ``fit_drop`` nats per ray worse is refused as ``poor_fit`` whatever the alignment said:
its correction is not applied, its pose is not vouched for, and it counts toward ``lost``
(AMCL's short- against long-term likelihood, without the random particles: a jump further
than the wide search needs an ``/initialpose``).

A first acceptance or confirmation (after the start or an ``/initialpose``) is claimed only
when it fits as well as the scans before the ``/initialpose`` did, keeps the robot within
the wide window of where the evidence put it (``beyond_window``), and is the best of wide
searches started just beyond the window around it (``PROBES``; a better one is moved to, unclaimed:
``better_elsewhere``). ``sigma`` includes what the grid cannot resolve (``with_grid``).
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from mfp_mapper.config.frames import frame_name
from mfp_mapper.config.sections import LocalizationSection
from mfp_mapper.core.alignment import (
    Alignment,
    AlignOptions,
    FieldPyramid,
    align_scan,
    verify_exact,
)
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.model import ALIGNMENT_PRIOR
from mfp_mapper.sensing.pipeline import PlacedScan
from mfp_mapper.sensing.scan_normals import scan_normals

FloatArray = NDArray[np.float64]

__all__ = ["LiveLocalizer", "align_options", "compile_alignment_kernels"]

STATES = ("waiting_for_map", "initializing", "localized", "lost")


def align_options(settings: LocalizationSection, wide: bool) -> AlignOptions:
    """The alignment's options: the wider search range before the first acceptance; while
    tracking those of ``AlignOptions.live`` (fewer curvature probe rays) with
    ``tracking_rays`` and ``tracking_iterations``."""
    base = (
        AlignOptions()
        if wide
        else AlignOptions.live(  # free space sampled every half voxel, as the wide search:
            # every voxel lets the hall's 7 cm aliasing gain (a wrong correction accepted)
            max_iterations=max(settings.tracking_iterations, 1),
            step=AlignOptions.step,
        )
    )
    return replace(
        base,
        max_rays=settings.max_rays if wide else settings.tracking_rays,
        max_sigma_m=settings.max_sigma,
        min_gain_per_ray=settings.min_gain_per_ray,
        min_constraints=settings.min_constraints,
        max_shift_m=settings.initial_max_shift if wide else settings.max_shift,
        max_angle_deg=settings.initial_max_angle if wide else settings.max_angle,
    )


PROBES = tuple(
    (dx, dy, turn)
    for turn in (0, 1, -1)
    for dx, dy in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))
    if (dx, dy, turn) != (0, 0, 0)
)
"""Starts of the check of a first acceptance (``LiveLocalizer._better_elsewhere``): shifts
by twice ``initial_max_shift`` along x, y and the diagonals, turns by twice
``initial_max_angle``, and both (26 wide searches, once per ``/initialpose`` or start)."""


def with_grid(sigma: Any, resolution: float, points: FloatArray, origins: FloatArray) -> Any:
    """The alignment's standard deviations (m, m, m, deg, deg, deg) with what the grid
    cannot resolve added in quadrature: ``resolution / sqrt(12)`` in position, that over the
    median ray length in angle."""
    grid_m = resolution / math.sqrt(12.0)
    lengths = np.linalg.norm(np.asarray(points) - np.asarray(origins), axis=1)
    reach = max(float(np.median(lengths)) if lengths.size else resolution, resolution)
    grid = np.array([grid_m] * 3 + [math.degrees(grid_m / reach)] * 3)
    given = np.asarray(sigma, dtype=np.float64)
    bounded = np.isfinite(given) & (np.abs(given) < 1e100)  # unbounded stays as it was
    return np.where(bounded, np.hypot(np.where(bounded, given, 0.0), grid), given)


FIT_AVERAGE = 0.1
"""Weight of a new scan's fit in the reference (a moving average over about 10 scans)."""

CONFIRMING = ("no_gain", "exact_check")
"""Refusals that say the current pose is as good as the best one found in range: they
confirm a localized pose instead of counting toward ``lost``."""


def pose_matrix(position: Any, rotation: Any) -> FloatArray:
    m = np.eye(4)
    m[:3, :3] = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    m[:3, 3] = np.asarray(position, dtype=np.float64).reshape(3)
    return m


def move_scan(placed: PlacedScan, m: FloatArray) -> PlacedScan:
    """The placed rays moved by the rigid transform ``m`` (4x4)."""
    rot, t = m[:3, :3], m[:3, 3]
    return replace(
        placed,
        points=np.asarray(placed.points, dtype=np.float64) @ rot.T + t,
        origins=np.asarray(placed.origins, dtype=np.float64) @ rot.T + t,
    )


class LiveLocalizer:
    """The correction ``map <- odom`` and its alignment state (module docstring).

    ``localize`` runs on the worker thread (a wide search, with ``done``, on a thread of its
    own while the worker holds its clouds back: one alignment at a time); ``initial_pose``,
    ``transform`` and ``report`` from any thread (under ``self.lock``, never held through an
    alignment).
    """

    def __init__(
        self, settings: LocalizationSection, global_frame: str, *, log: Callable[[str], None]
    ) -> None:
        self.settings = settings
        """The ``localization.*`` parameters (replaced whole on a change)."""
        self.global_frame = global_frame
        """The map frame the correction is to (the node's ``frame_id`` or the loaded map's)."""
        self.lock = threading.Lock()
        self._log = log
        self.correction = np.eye(4)
        self.correction_stamp = math.nan
        """The stamp of the cloud that last set the correction (NaN: never set)."""
        self.version = 0
        """Bumped at each change of the correction (the node publishes it then)."""
        self.pyramid: FieldPyramid | None = None
        self.pyramid_voxels = 0
        self.pyramid_seconds = 0.0
        self.state = "waiting_for_map"
        self.accepted = 0
        self.refused: Counter[str] = Counter()
        self.skipped = 0
        self.skipped_motion = 0
        self.initial_poses = 0
        self.pose_version = 0
        self.pose: tuple[float, FloatArray, FloatArray] | None = None
        self.consecutive_refused = 0
        self._fit_before = math.nan
        """The fit reference before the last ``/initialpose``: a first acceptance after it
        that fits ``fit_drop`` worse is not claimed (``poor_fit``)."""
        self._anchor = np.eye(4)
        """The correction the evidence gave last: at the start, the identity (odometry);
        after an ``/initialpose``, the one it set."""
        self.fit_reference = math.nan
        """Smoothed log-likelihood per ray of the scans accepted or confirmed (NaN: none yet
        since the start or the last ``/initialpose``)."""
        self.last: dict[str, Any] = {}
        self.ms_sum = 0.0
        self.ms_max = 0.0
        self.aligned = 0
        self._last_align_stamp = -math.inf
        self._last_align_odom: FloatArray | None = None
        self._pending: tuple[float, FloatArray] | None = None
        self._mapper: Mapper | None = None
        self._whole_map: Any = None
        self._normals: tuple[FloatArray, FloatArray, FloatArray | None] | None = None
        """The last scan normals (map frame) and the odometry pose they were computed at."""
        self.exact_checked = 0
        self.normals_computed = 0
        self._building: threading.Thread | None = None
        self._built_at = -math.inf
        self._build_running = False
        """A build thread runs (under ``lock``)."""
        self._rebuild_due = False
        """A forced build came while one ran: that thread builds again (under ``lock``)."""
        self._searching = False
        """A wide search runs in the background (``localize`` with ``done``)."""
        self._searched: PlacedScan | Exception | None = None

    # --- the field ------------------------------------------------------------------------

    @property
    def odom_frame(self) -> str:
        """The odometry frame clouds are placed in (``localization.odom_frame``, tf1's leading
        slash stripped)."""
        return frame_name(self.settings.odom_frame)

    def build(self, mapper: Mapper, whole_map: Any) -> None:
        """Build the field from the map: its statistics copied under ``whole_map`` (a
        merge is never half in), the pyramid computed without any lock. Blocking."""
        t0 = time.perf_counter()
        with whole_map:
            stats = mapper.voxels()
            resolution, origin = float(mapper.resolution), np.asarray(mapper.origin or (0, 0, 0))
        # the objective localization was tuned on, not the map's own prior
        shape, rate = ALIGNMENT_PRIOR.shape, ALIGNMENT_PRIOR.rate
        if len(stats.s) == 0:  # an empty map (reset): nothing to localize against
            with self.lock:
                self.pyramid, self.pyramid_voxels = None, 0
                self.state = "waiting_for_map"
            return
        pyramid = FieldPyramid.from_statistics(
            stats.ijk, stats.s, stats.n, resolution, origin, shape=shape, rate=rate
        )
        with self.lock:
            self.pyramid = pyramid
            self._mapper, self._whole_map = mapper, whole_map
            self.pyramid_voxels = len(stats.s)
            self.pyramid_seconds = time.perf_counter() - t0
            if self.state == "waiting_for_map":
                self.state = "initializing"

    def build_in_background(self, mapper: Mapper, whole_map: Any, force: bool = False) -> bool:
        """Start ``build`` in a thread of its own unless one runs or (without ``force``) the
        last started less than ``rebuild_period`` ago; True when started. ``force`` while one
        runs (a reset, a cleared box during a build): that thread builds once more after it,
        from the map as it is then (the build under way may have copied the map before)."""
        now = time.monotonic()
        with self.lock:
            if self._build_running:
                self._rebuild_due = self._rebuild_due or force
                return False
            if not force and now - self._built_at < self.settings.rebuild_period:
                return False
            self._built_at = now
            self._build_running = True

        def run() -> None:
            while True:
                try:
                    self.build(mapper, whole_map)
                except Exception as err:  # a failed build keeps the previous field
                    self._log(
                        f"building the localization field failed: {type(err).__name__}: {err}"
                    )
                with self.lock:
                    if not self._rebuild_due:
                        self._build_running = False
                        return
                    self._rebuild_due = False

        self._building = threading.Thread(target=run, name="mfp_localization_field", daemon=True)
        self._building.start()
        return True

    def wait_built(self, timeout: float) -> None:
        """Wait for a background build (tests, tools)."""
        if self._building is not None:
            self._building.join(timeout)

    # --- inputs ---------------------------------------------------------------------------

    def initial_pose(
        self, stamp: float, position: Any, quaternion: Any, odom_base: FloatArray | None = None
    ) -> bool:
        """``/initialpose``: the robot's pose in the map frame at ``stamp``. With the robot's
        odometry pose at that stamp (``odom_base``) map <- odom is reset at once; without,
        at the next cloud (``localize``, with its pose source). True when applied now."""
        m = pose_matrix(position, Rotation.from_quat(np.asarray(quaternion, float)).as_matrix())
        if odom_base is None:
            with self.lock:
                self._pending = (float(stamp), m)
            return False
        with self.lock:
            self._pending = None
        self._reset(m, odom_base, float(stamp))
        return True

    def clock_jumped(self, now: float) -> None:
        """The node's clock jumped back (a bag loop): the rate and motion gates start over
        and the correction is stamped ``now`` (a stamp from before the jump would be in the
        future of every lookup); the correction itself stands. An alignment under way (of a
        cloud from before the jump) is then ``superseded``."""
        with self.lock:
            self._last_align_stamp, self._last_align_odom = -math.inf, None
            self._normals = None
            if math.isfinite(self.correction_stamp):
                self.correction_stamp = min(self.correction_stamp, now)
            self.version += 1

    def transform(self) -> tuple[FloatArray, float, int]:
        """(map <- odom, the stamp of the cloud that set it, version)."""
        with self.lock:
            return self.correction.copy(), self.correction_stamp, self.version

    # --- the worker -----------------------------------------------------------------------

    def localize(
        self,
        placed: PlacedScan,
        robot_pose: Callable[[float], FloatArray | None],
        done: Callable[[], None] | None = None,
    ) -> PlacedScan | None:
        """The placed cloud (odometry frame) in the map frame, at the corrected pose.
        ``robot_pose(stamp)``: the robot in the odometry frame (4x4) or None.

        With ``done``, a wide search runs in a thread of its own (``mfp_localization_search``)
        on its own copy of the scan and the correction, holding no lock of the caller's
        through the search: None is returned at once, ``done()`` is called when the search
        ended and ``finished()`` gives the cloud then (``searching`` says whether one runs).
        Tracking alignments, short, run on the calling thread."""
        cfg = self.settings
        with self.lock:
            pending, self._pending = self._pending, None
        if pending is not None:
            self._apply_initial_pose(pending, placed.stamp, robot_pose)
        with self.lock:
            correction, pyramid = self.correction.copy(), self.pyramid
            wide = self.state != "localized"
            version = self.version
        moved = move_scan(placed, correction)
        if pyramid is None:
            return moved
        since = placed.stamp - self._last_align_stamp  # far below 0: a bag loop
        if cfg.min_period > 0.0 and -cfg.min_period < since < cfg.min_period:
            with self.lock:
                self.skipped += 1
            return moved
        odom = robot_pose(placed.stamp)
        if not wide and self._still(odom):
            with self.lock:
                self.skipped_motion += 1
            return moved
        self._last_align_stamp, self._last_align_odom = placed.stamp, odom
        job = (placed, moved, correction, pyramid, wide, version, odom)
        if done is None or not wide:
            return self._align(*job)

        def search() -> None:
            result: PlacedScan | Exception
            try:
                result = self._align(*job)
            except Exception as err:  # handed to the worker, which counts the cloud
                result = err
            with self.lock:
                self._searched, self._searching = result, False
            done()

        with self.lock:
            self._searched, self._searching = None, True
        threading.Thread(target=search, name="mfp_localization_search", daemon=True).start()
        return None

    @property
    def searching(self) -> bool:
        """Whether a wide search started by ``localize`` (with ``done``) is still running."""
        with self.lock:
            return self._searching

    def finished(self) -> PlacedScan | None:
        """The cloud of the last wide search run in the background, in the map frame (once;
        None while it runs or when taken); raises what the search raised."""
        with self.lock:
            result, self._searched = self._searched, None
        if isinstance(result, Exception):
            raise result
        return result

    def _align(
        self,
        placed: PlacedScan,
        moved: PlacedScan,
        correction: FloatArray,
        pyramid: FieldPyramid,
        wide: bool,
        version: int,
        odom: FloatArray | None,
    ) -> PlacedScan:
        """Align ``moved`` (``placed`` moved by ``correction``, version ``version``) and
        record the outcome; the cloud at the corrected pose, or ``moved`` when refused."""
        cfg = self.settings
        t0 = time.perf_counter()
        ret = np.ones(len(moved.points), dtype=bool)
        if moved.no_return is not None:
            ret = ~moved.no_return
        pts = moved.points[ret]
        org = moved.origins if np.ndim(moved.origins) == 1 else moved.origins[ret]
        if not wide:  # tracking: the correction is small, the coarse levels cost for nothing
            pyramid = FieldPyramid(pyramid.fields[: max(cfg.tracking_levels, 1)])
        options = align_options(cfg, wide)
        normals = self._scan_normals(pts, odom, wide)
        al = align_scan(pyramid, pts, org, options, normals=normals)
        if al.accepted and cfg.exact_check and (wide or cfg.exact_check_tracking):
            al = self._verify(al, moved, options)
        step = pose_matrix(al.translation, al.rotation)
        if (al.accepted or al.refusal in CONFIRMING) and wide and self.state == "initializing":
            al, step = self._better_elsewhere(al, step, pyramid, pts, org, options, normals)
        al = replace(al, sigma=with_grid(al.sigma, pyramid.fields[0].resolution, pts, org))
        ms = 1e3 * (time.perf_counter() - t0)
        if not self._record(al, ms, placed.stamp, step, wide, odom, version):
            return moved  # an /initialpose came meanwhile: this correction is not used
        # accepted: the placed cloud moved once, by the composed correction
        return move_scan(placed, step @ correction) if al.accepted else moved

    def _better_elsewhere(
        self,
        al: Alignment,
        step: FloatArray,
        pyramid: FieldPyramid,
        pts: FloatArray,
        org: FloatArray,
        options: AlignOptions,
        normals: tuple[FloatArray, FloatArray],
    ) -> tuple[Alignment, FloatArray]:
        """Before a first acceptance (start, ``/initialpose``) is claimed: the wide search
        from ``PROBES`` starts just beyond its window around the pose found. When one of
        them fits the map ``fit_drop`` nats per ray better, the pose found is a local
        optimum (an initial pose given outside the window): it is refused as
        ``better_elsewhere`` and the correction moved to the better pose, unclaimed (the
        next scans search from there). Else (alignment, step) as they were."""
        drop = self.settings.fit_drop
        if not math.isfinite(al.fit_per_ray) or drop <= 0.0:
            return al, step
        centre = step[:3, :3] @ np.mean(np.atleast_2d(org), axis=0) + step[:3, 3]
        shift, angle = 2.0 * options.max_shift_m, 2.0 * options.max_angle_deg
        best: tuple[float, FloatArray] | None = None
        for dx, dy, yaw in PROBES:
            rot = Rotation.from_euler("z", yaw * angle, degrees=True).as_matrix()
            probe = np.eye(4)
            probe[:3, :3] = rot
            probe[:3, 3] = centre + shift * np.array([dx, dy, 0.0]) - rot @ centre
            moved = probe @ step
            r, t = moved[:3, :3], moved[:3, 3]
            tried = align_scan(
                pyramid,
                pts @ r.T + t,
                np.atleast_2d(org) @ r.T + t,
                options,
                normals=(normals[0] @ r.T + t, normals[1] @ r.T),
            )
            usable = tried.accepted or tried.refusal in CONFIRMING
            fit = tried.fit_per_ray
            if usable and math.isfinite(fit) and (best is None or fit > best[0]):
                best = (fit, pose_matrix(tried.translation, tried.rotation) @ moved)
        if best is None or best[0] < al.fit_per_ray + drop:
            return al, step
        away = float(np.linalg.norm(best[1][:3, 3] - step[:3, 3]))
        reason = (
            f"a pose {away:.2f} m away fits the map {best[0] - al.fit_per_ray:.2f} nats per "
            "ray better than the one found: the initial guess was outside the search window; "
            "moved there, not claimed"
        )
        refused = replace(al, accepted=False, reason=reason, refusal="better_elsewhere")
        return refused, best[1]

    def _scan_normals(
        self, pts: FloatArray, odom: FloatArray | None, wide: bool
    ) -> tuple[FloatArray, FloatArray]:
        """The scan's surface normals (map frame): computed in the wide search and once the
        robot moved ``normals_refresh`` since the last ones, else those reused (the same
        surfaces of the map, seen a few centimetres apart)."""
        last = self._normals
        if not wide and last is not None and odom is not None and last[2] is not None:
            moved = float(np.linalg.norm(odom[:3, 3] - last[2][:3, 3]))
            if moved < self.settings.normals_refresh:
                return last[0], last[1]
        points, normals = scan_normals(pts)
        self._normals = (points, normals, odom)
        self.normals_computed += 1
        return points, normals

    def _verify(self, al: Alignment, moved: PlacedScan, options: AlignOptions) -> Alignment:
        """``verify_exact`` against the map itself (read under ``whole_map``)."""
        with self.lock:
            mapper, whole_map = self._mapper, self._whole_map
        if mapper is None or whole_map is None:
            return al
        with whole_map:
            checked = verify_exact(
                mapper,
                al,
                moved.points,
                moved.origins,
                moved.stamp,
                options,
                no_return=moved.no_return,
            )
        with self.lock:
            self.exact_checked += 1
        return checked

    def _still(self, odom: FloatArray | None) -> bool:
        """Whether the robot moved less than ``update_min_d`` and turned less than
        ``update_min_a`` since the last alignment (odometry)."""
        last = self._last_align_odom
        if odom is None or last is None:
            return False
        d = np.linalg.inv(last) @ odom
        moved = float(np.linalg.norm(d[:3, 3]))
        turned = float(np.degrees(Rotation.from_matrix(d[:3, :3]).magnitude()))
        return moved < self.settings.update_min_d and turned < self.settings.update_min_a

    def _apply_initial_pose(
        self,
        pending: tuple[float, FloatArray],
        scan_stamp: float,
        robot_pose: Callable[[float], FloatArray | None],
    ) -> None:
        stamp, map_base = pending
        odom_base = robot_pose(stamp) if stamp > 0.0 else None
        if odom_base is None:
            odom_base = robot_pose(scan_stamp)
        if odom_base is None:
            odom_base = np.eye(4)
        self._reset(map_base, odom_base, scan_stamp)

    def _reset(self, map_base: FloatArray, odom_base: FloatArray, stamp: float) -> None:
        """map <- odom such that the robot at ``odom_base`` is at ``map_base``."""
        with self.lock:
            self.correction = map_base @ np.linalg.inv(odom_base)
            self._anchor = self.correction.copy()
            self.correction_stamp = stamp
            self.version += 1
            self.initial_poses += 1
            self.consecutive_refused = 0
            if math.isfinite(self.fit_reference):  # the fit scans had where they belonged
                self._fit_before = self.fit_reference
            self.fit_reference = math.nan  # another place: its own fit
            self._normals = None
            if self.pyramid is not None:
                self.state = "initializing"
        self._log(
            "initial pose set: map -> odom now "
            f"{_describe(self.correction)}; refining from the next clouds"
        )

    def _record(
        self,
        al: Alignment,
        ms: float,
        stamp: float,
        step: FloatArray,
        wide: bool,
        odom: FloatArray | None,
        version: int,
    ) -> bool:
        """Count an alignment and apply it when accepted; False when the correction it
        started from was replaced meanwhile (``/initialpose``): then it is counted as
        ``superseded`` and not applied."""
        lost = False
        with self.lock:
            self.aligned += 1
            self.ms_sum += ms
            self.ms_max = max(self.ms_max, ms)
            self.last = {
                "stamp": stamp,
                "accepted": al.accepted,
                "reason": al.reason,
                "shift_m": round(float(np.linalg.norm(al.translation)), 4),
                "angle_deg": round(al.angle_deg, 4),
                "sigma": [round(float(v), 5) if math.isfinite(v) else None for v in al.sigma],
                "gain_per_ray": round(float(al.gain_per_ray), 5),
                "exact_z": round(float(al.exact_z), 2) if math.isfinite(al.exact_z) else None,
                "constraints": al.conditioning,
                "rays": al.rays,
                "ms": round(ms, 2),
                "wide_search": wide,
            }
            if self.version != version:
                self.refused["superseded"] += 1
                return False
            self.last["fit_per_ray"] = (
                round(float(al.fit_per_ray), 4) if math.isfinite(al.fit_per_ray) else None
            )
            # a first claim: an acceptance, or while initializing a confirmation of the pose
            # (no gain in the wide search, none better just beyond it: a right /initialpose)
            first = al.accepted or (
                self.state == "initializing"
                and al.refusal in CONFIRMING
                and math.isfinite(al.fit_per_ray)
            )
            poor = self._poor_fit(al)
            if poor:
                al = replace(al, accepted=False, reason=poor, refusal="poor_fit")
                self.last.update(accepted=False, reason=poor)
            elif (
                first
                and self.state != "localized"
                and self._beyond_window(step @ self.correction, odom)
            ):
                beyond = self._beyond_window(step @ self.correction, odom)
                al = replace(al, accepted=False, reason=beyond, refusal="beyond_window")
                self.last.update(accepted=False, reason=beyond)
            elif math.isfinite(al.fit_per_ray) and (al.accepted or al.refusal in CONFIRMING):
                ref = self.fit_reference
                if first and (math.isnan(ref) or self.state != "localized"):
                    self.fit_reference = al.fit_per_ray  # (re)gained: the fit here
                elif not math.isnan(ref):
                    self.fit_reference = ref + FIT_AVERAGE * (al.fit_per_ray - ref)
            if al.accepted:
                self.correction = step @ self.correction
                self.correction_stamp = stamp
                self.version += 1
                self.accepted += 1
                self.consecutive_refused = 0
                self.state = "localized"
                self._vouch(stamp, odom, al.sigma)
                return True
            self.refused[al.refusal] += 1
            if al.refusal in ("better_elsewhere", "beyond_window"):  # searched from, unclaimed
                self.correction = step @ self.correction
                self.correction_stamp = stamp
                self.version += 1
                return True
            if al.refusal in CONFIRMING:  # the best pose in range is no better: the current stands
                self.consecutive_refused = 0
                # lost: localized before, and the scans agree again; initializing: confirmed
                # under the checks of a first acceptance
                if self.state == "lost" or first:
                    self.state = "localized"
                if self.state == "localized":
                    self._vouch(stamp, odom, al.sigma)
                return True
            self.consecutive_refused += 1
            lost = (
                self.state == "localized" and self.consecutive_refused >= self.settings.lost_after
            )
            if lost:
                self.state = "lost"
        if lost:
            self._log(
                f"localization lost: {self.consecutive_refused} corrections refused in a row "
                f"(last: {al.reason}); keeping map -> odom, searching wider"
            )
        return True

    def _beyond_window(self, correction: FloatArray, odom: FloatArray | None) -> str:
        """(under the lock) Why the robot's pose under ``correction`` is too far from where
        the evidence put it (the odometry at the start, the last ``/initialpose``) to be
        claimed: farther than ``initial_max_shift`` / ``initial_max_angle``; or ''."""
        if odom is None:
            return ""
        d = np.linalg.inv(self._anchor @ odom) @ (correction @ odom)
        shift = float(np.linalg.norm(d[:3, 3]))
        turn = float(np.degrees(Rotation.from_matrix(d[:3, :3]).magnitude()))
        cfg = self.settings
        if shift <= cfg.initial_max_shift and turn <= cfg.initial_max_angle:
            return ""
        return (
            f"the pose found is {shift:.2f} m / {turn:.1f} deg from where the odometry or the "
            f"initial pose put the robot (> {cfg.initial_max_shift:g} m / "
            f"{cfg.initial_max_angle:g} deg): searched from, not claimed; give an /initialpose"
        )

    def _poor_fit(self, al: Alignment) -> str:
        """(under the lock) Why the scan fits the map too poorly to be used, or ''."""
        drop, ref, fit = self.settings.fit_drop, self.fit_reference, al.fit_per_ray
        if math.isnan(ref) and (al.accepted or al.refusal in CONFIRMING):
            ref = self._fit_before  # a first claim: as well as before, if any
        if drop <= 0.0 or math.isnan(ref) or not math.isfinite(fit) or fit >= ref - drop:
            return ""
        return (
            f"scan fits the map {ref - fit:.2f} nats per ray worse than the scans before "
            f"(> {drop:g}): odometry jumped or the robot is elsewhere; pose not used"
        )

    def _vouch(self, stamp: float, odom: FloatArray | None, sigma: FloatArray) -> None:
        """(under the lock) The robot's pose in the map at ``stamp``, as the node vouches for
        it (accepted, or confirmed while localized): for ``~/pose``."""
        if odom is None:
            return
        self.pose_version += 1
        self.pose = (stamp, self.correction @ odom, np.asarray(sigma, dtype=np.float64).copy())

    def pose_estimate(self) -> tuple[int, tuple[float, FloatArray, FloatArray] | None]:
        """(version, (stamp, map <- robot 4x4, sigma (6,): m, m, m, deg, deg, deg) or None)."""
        with self.lock:
            return self.pose_version, self.pose

    # --- health ---------------------------------------------------------------------------

    def report(self) -> dict[str, Any]:
        """What ``~/status`` says under ``localization``."""
        with self.lock:
            m = self.correction
            yaw = float(Rotation.from_matrix(m[:3, :3]).as_euler("xyz", degrees=True)[2])
            return {
                "state": self.state,
                "freeze_map": self.settings.freeze_map,
                "global_frame": self.global_frame,
                "odom_frame": self.odom_frame,
                "map_to_odom": {
                    "x": round(float(m[0, 3]), 4),
                    "y": round(float(m[1, 3]), 4),
                    "z": round(float(m[2, 3]), 4),
                    "yaw_deg": round(yaw, 4),
                    "angle_deg": round(
                        float(np.degrees(Rotation.from_matrix(m[:3, :3]).magnitude())), 4
                    ),
                },
                "aligned": self.aligned,
                "accepted": self.accepted,
                "refused": dict(self.refused),
                "skipped_rate": self.skipped,
                "skipped_motion": self.skipped_motion,
                "consecutive_refused": self.consecutive_refused,
                "fit_reference": (
                    round(self.fit_reference, 4) if math.isfinite(self.fit_reference) else None
                ),
                "initial_poses": self.initial_poses,
                "ms_mean": round(self.ms_sum / self.aligned, 2) if self.aligned else None,
                "ms_max": round(self.ms_max, 2) if self.aligned else None,
                "exact_checked": self.exact_checked,
                "normals_computed": self.normals_computed,
                "field_voxels": self.pyramid_voxels,
                "field_build_s": round(self.pyramid_seconds, 3),
                "last": dict(self.last),
            }


def compile_alignment_kernels(settings: LocalizationSection, resolution: float) -> float:
    """Run the alignment's compiled kernels once, as the live localization runs them (the
    wide search and tracking, with ``settings``' options, for a scan with one origin and a
    deskewed one with an origin a point), on the field of a throwaway map of a synthetic
    room, so that numba compiles them, or loads them from its cache, before the first
    cloud is localized (``core.mapper.compile_kernels`` does the same for the map's
    kernels; with a cold cache the first alignment took 2.4 s, not 0.2); returns the
    seconds it took."""
    t0 = time.perf_counter()
    at = np.arange(2048) + 0.5  # a Fibonacci sphere of directions, within 20 degrees of level
    z = np.sin(np.radians(20.0)) * (1.0 - 2.0 * at / len(at))
    azimuth = np.pi * (1.0 + 5.0**0.5) * at
    ring = np.sqrt(1.0 - z * z)
    directions = np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=1)
    # half sizes of the walls, floor and ceiling, in voxels: the same work at any resolution
    # (a room in metres took 6.5 s at 0.02 m)
    room = np.array([30.0, 20.0, 10.0]) * resolution
    points = directions * np.min(room / np.maximum(np.abs(directions), 1e-9), axis=1)[:, None]
    reach = 2.0 * float(np.linalg.norm(room))
    mapper = Mapper(resolution, origin=np.zeros(3), max_range=reach)
    try:
        for scan in range(3):
            mapper.integrate(points, np.zeros(3), float(scan))
        stats = mapper.voxels()
    finally:
        mapper.close()
    pyramid = FieldPyramid.from_statistics(
        stats.ijk, stats.s, stats.n, float(resolution), np.zeros(3),
        shape=ALIGNMENT_PRIOR.shape, rate=ALIGNMENT_PRIOR.rate,
    )  # fmt: skip
    moved = points + np.array([0.5, 0.0, 0.0]) * resolution
    normals = scan_normals(moved)
    for wide in (True, False):
        levels = (
            pyramid if wide else FieldPyramid(pyramid.fields[: max(settings.tracking_levels, 1)])
        )
        for origins in (np.zeros(3), np.zeros_like(moved)):
            align_scan(levels, moved, origins, align_options(settings, wide), normals=normals)
    return time.perf_counter() - t0


def _describe(m: FloatArray) -> str:
    yaw = float(Rotation.from_matrix(m[:3, :3]).as_euler("xyz", degrees=True)[2])
    return f"x {m[0, 3]:.3f} y {m[1, 3]:.3f} z {m[2, 3]:.3f} m, yaw {yaw:.2f} deg"
