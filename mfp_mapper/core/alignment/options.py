"""What an alignment is asked to do (``AlignOptions``) and what it gives back (``Alignment``,
with its refusal names ``REFUSALS``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class AlignOptions:
    """How a scan is aligned; the defaults are those measured in README (Localization)."""

    levels: int = 3
    """Pyramid levels: voxel edges resolution * 2^k, k = levels-1 .. 0."""
    max_rays: int = 3000
    """Rays used per scan (a deterministic, evenly spread subset)."""
    window: float = 1.0
    """Metres of free space scored before each return (in voxels of the level: at least 2)."""
    prior_sigma_m: float = 1.0
    """Motion prior on the correction: translation standard deviation (metres)."""
    prior_sigma_deg: float = 10.0
    """Motion prior on the correction: rotation standard deviation (degrees)."""
    max_sigma_m: float = 0.05
    """Refuse a correction when the standard deviation along its weakest direction
    (translation, or rotation times ``lever``) exceeds this (metres)."""
    max_shift_m: float = 1.0
    """Refuse a correction that moves the sensor further than this (metres)."""
    max_angle_deg: float = 10.0
    """Refuse a correction that turns the scan by more than this (degrees)."""
    min_gain_per_ray: float = 0.02
    """Refuse a correction that raises the smoothed log-likelihood by less than this per ray
    (nats): within what the voxel-scale texture of a map gives; from 0.3 m / 3 deg off, real
    corrections gain 0.3 to 2 nats per ray, an already good KISS-ICP pose 0.004 to 0.01."""
    min_constraints: int = 5
    """Refuse when fewer planar patches of the scan than this constrain some direction
    (``geometric_conditioning``): 0 along a featureless corridor's axis, 13 to 27 of 2700
    along the weakest direction of the simulated hall, 15 to 35 of 1700 in vegetation."""
    lever: float = 5.0
    """Metres: converts rotations (radians) into displacements for scaling and refusal."""
    max_iterations: int = 30
    """Per pyramid level (Levenberg-Marquardt steps on the BHHH information matrix)."""
    tolerance: float = 0.05
    """Stop a level when a step moves less than this fraction of its voxel edge."""
    probe_rays: int = 1000
    """Rays used for the curvature probes (the curvature is scaled to all rays)."""
    step: float = 0.5
    """Free-space samples every ``step`` voxel edges of the level."""
    probe: float = 2.0
    """Curvature for the confidence: gradient differences at +-``probe`` voxel edges (fine
    level): wide enough to average over the voxel-scale texture of the field."""
    min_exact_z: float = 3.0
    """``verify_exact``: refuse a correction unless the exact log-likelihood of the scan's
    rays (``core.likelihood``, no smoothing) rises by more than this many standard errors
    of its mean per-ray change (a paired test over the rays scored at both poses). The
    smoothed field is biased at voxel scale: a scan already at its true pose can gain in
    it by moving a few centimetres, and lose in the exact model."""
    exact_rays: int = 3000
    """Rays scored by ``verify_exact`` (a deterministic, evenly spread subset)."""
    min_correction_voxels: float = 0.0
    """Refuse a correction that moves the scan's returns by less than this many voxels of
    the finest level (RMS): within the grid's aliasing range. Every likelihood on a voxel
    grid (smoothed or exact) prefers surfaces at voxel centres: a room whose walls lie
    off-centre is "explained better" shifted by up to half a voxel (measured: 6 cm at
    0.2 m in the simulated room of test_localize_bag, 14 cm with walls on the voxel
    boundaries), so a smaller correction cannot be told from that bias."""
    refine_min_voxels: float = 0.5
    """``min_correction_voxels`` when aligning against the map the same recording is
    building (``replay --refine-poses``), whose initial poses are usually better than that."""
    refresh_growth: float = 0.5
    """Aligning against a growing map (``replay --refine-poses``, ``mapping.localize``):
    rebuild the pyramid when the scans integrated since the last build reach this share
    of the scans it holds (builds after scans 1, 2, 3, 5, 8, 12, ...)."""
    refresh_m: float = 2.0
    """... or when the sensor is further than this (metres) from where it was built."""

    @classmethod
    def live(cls, **changes: object) -> AlignOptions:
        """Settings for aligning every scan at sensor rate (the node's localization mode,
        README: Localization): 1500 rays, 2 levels (0.4, 0.2 m at a 0.2 m map),
        free space sampled every voxel, 500 probe rays, 1000 rays for the exact check."""
        base = cls(levels=2, max_rays=1500, step=1.0, probe_rays=500, exact_rays=1000)
        return replace(base, **changes)  # type: ignore[arg-type]


REFUSALS = (
    "too_few_rays",
    "flat_likelihood",
    "degenerate_geometry",
    "out_of_range",
    "aliasing",
    "no_gain",
    "exact_check",
)
"""``Alignment.refusal``'s names: too few rays; a likelihood flat along some direction
(``max_sigma_m``); too few surface patches constraining one (``min_constraints``); a
correction beyond ``max_shift_m`` / ``max_angle_deg``; one within the grid's aliasing
(``min_correction_voxels``); a gain below ``min_gain_per_ray``; an exact gain not
significant (``verify_exact``)."""


@dataclass
class Alignment:
    """The result of aligning one scan.

    ``rotation``, ``translation``: the correction C (map frame) such that the refined pose
    is C * initial pose: a point x of the scan placed at the initial pose goes to
    ``rotation @ x + translation``. Identity when ``accepted`` is False.
    """

    rotation: FloatArray
    translation: FloatArray
    accepted: bool
    reason: str
    """Empty when accepted; otherwise why the correction was refused."""
    gain: float
    """Surrogate log-likelihood gain of the scan (nats, all rays used), refined - initial."""
    gain_per_ray: float
    sigma: FloatArray
    """Standard deviations (6,) of the correction: x, y, z (metres), roll, pitch, yaw
    about the map axes (degrees), from the curvature at the optimum."""
    weakest: FloatArray
    """Unit direction (6,) of least curvature, in (metres, radians * lever) coordinates."""
    conditioning: int
    """Planar patches along the scan's least constrained direction (-1: no normals given)."""
    rays: int
    evaluations: int
    levels: list[dict[str, float]] = field(default_factory=list)
    exact_gain: float = math.nan
    """Exact log-likelihood gain (nats, ``core.likelihood``, the rays scored by
    ``verify_exact``), corrected - initial; NaN when not verified."""
    exact_z: float = math.nan
    """That gain's mean per ray over its standard error (``verify_exact``)."""
    fit_per_ray: float = math.nan
    """Smoothed log-likelihood per ray (nats, finest level) at the pose kept: the corrected
    pose when accepted, else the initial one. How well the scan fits the map there, which a
    gain alone does not say (a scan far from its place can still gain a little)."""
    refusal: str = ""
    """The refusal's name, empty when accepted: one of ``REFUSALS`` (a counter name, where
    ``reason`` is a sentence for a person)."""

    @property
    def shift_m(self) -> float:
        return float(np.linalg.norm(self.translation))

    @property
    def angle_deg(self) -> float:
        return float(np.degrees(Rotation.from_matrix(self.rotation).magnitude()))

    @classmethod
    def refused(cls, refusal: str, reason: str, rays: int) -> Alignment:
        """No correction: refused as ``refusal`` (a ``REFUSALS`` name) for ``reason``,
        before any ray was scored."""
        return cls(
            rotation=np.eye(3),
            translation=np.zeros(3),
            accepted=False,
            refusal=refusal,
            reason=reason,
            gain=0.0,
            gain_per_ray=0.0,
            sigma=np.full(6, math.inf),
            weakest=np.zeros(6),
            conditioning=-1,
            rays=rays,
            evaluations=0,
        )
