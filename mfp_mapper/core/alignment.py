"""Scan-to-map alignment by the forward model's likelihood (the paper's Eq. 22 road to SLAM).

The exact per-ray log-likelihood of a scan (``core.likelihood``) is piecewise constant in
the pose at voxel scale: moving a scan by less than a voxel changes no voxel a ray crosses,
so it has no gradient. This module optimises a *smoothed* version of the same model and
reports the exact one:

- **Extinction field** (``LikelihoodField``): per voxel of the map, two numbers of the
  forward model with the Gamma(alpha, beta) prior (MODEL.md): the log-probability per metre
  that a ray passes (``b = (n+alpha) log((s+beta)/(s+beta+r)) / r``) and the log-probability
  that a ray crossing the whole voxel returns in it
  (``a = log(1 - ((s+beta)/(s+beta+r))^(n+alpha))``), unknown voxels at the prior. Both
  are interpolated trilinearly between voxel centres, so the likelihood of a ray is
  continuous and almost everywhere differentiable in the pose.
- **Ray surrogate**: ``a(end point) + step * sum b(samples)`` over samples every ``step``
  metres along the last ``window`` metres of the ray before its return (the free space
  that decides between two nearby poses; the rest of the ray crosses space far from any
  surface, where a small shift changes little).
- **Pyramid**: coarser levels aggregate the statistics exactly (chord lengths and return
  counts add up over sub-voxels), so the same model at 2x, 4x the voxel edge gives a wider
  basin of convergence; the pose is refined coarse to fine.
- **Motion prior**: a Gaussian on the correction (``prior_sigma_m``, ``prior_sigma_deg``).
- **Confidence**: the curvature of the fine-level objective at the optimum (central
  differences of its analytic gradient), whose inverse gives standard deviations per axis.
  A direction along which the likelihood is flat (a corridor's axis, an open field) makes
  the correction unsupported: the initial pose is kept and the reason is said.

Pure maths on the map's statistics and on rays in the map frame: no I/O, no ROS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from mfp_mapper.core.likelihood import scan_log_likelihood

FloatArray = NDArray[np.float64]

__all__ = [
    "AlignOptions",
    "Alignment",
    "FieldPyramid",
    "LikelihoodField",
    "align_scan",
    "geometric_conditioning",
    "surrogate_log_likelihood",
    "verify_exact",
]

_BLOCK = 8  # voxels per block edge in the field's sparse storage


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


# --- the field ------------------------------------------------------------------------


@dataclass
class LikelihoodField:
    """The forward model's per-voxel log-probabilities at one voxel edge, sparse in blocks.

    ``a``: log P(return | crossing the whole voxel); ``b``: log P(pass) per metre. Blocks of
    8^3 voxels; ``index`` maps a block of the box ``[block_lo, block_lo + index.shape)``
    to its row in ``a``/``b`` (-1: no block, the prior everywhere in it).
    """

    resolution: float
    origin: FloatArray
    block_lo: NDArray[np.int64]
    index: NDArray[np.int32]
    a: NDArray[np.float32]
    b: NDArray[np.float32]
    prior_a: float
    prior_b: float

    @classmethod
    def from_statistics(
        cls,
        ijk: NDArray[np.integer],
        s: FloatArray,
        n: FloatArray,
        resolution: float,
        origin: FloatArray,
        *,
        shape: float = 1.0,
        rate: float = 1.0,
        factor: int = 1,
    ) -> LikelihoodField:
        """The field of voxels ``ijk`` (statistics ``s`` metres, ``n`` returns) aggregated
        ``factor`` x ``factor`` x ``factor`` (a power of two; exact: chords and returns add
        up), built as ``FieldPyramid`` builds its levels."""
        if factor < 1 or factor & (factor - 1):
            raise ValueError(f"factor must be a power of two, got {factor}")
        keys, s_b, n_b = _voxel_blocks(ijk, s, n)
        for _ in range(factor.bit_length() - 1):
            keys, s_b, n_b = _coarsen_blocks(keys, s_b, n_b)
        return _field_of_blocks(keys, s_b, n_b, resolution * factor, origin, shape, rate)

    def values(self, points: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Interpolated ``a``, ``b`` at points (N, 3) and their gradients (N, 3) each."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.zeros((pts.shape[0], 8))
        _values(*self._args(), pts, out)  # type: ignore[call-arg]
        return out[:, 0], out[:, 1], out[:, 2:5], out[:, 5:8]

    def _args(self) -> tuple[object, ...]:
        return (
            self.a,
            self.b,
            self.index,
            self.block_lo,
            self.prior_a,
            self.prior_b,
            self.resolution,
            self.origin,
        )


def _unique_rows(keys: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.intp]]:
    """np.unique(keys, axis=0, return_inverse=True), through one int64 key per row."""
    if keys.shape[0] == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.intp)
    lo = keys.min(axis=0)
    span = keys.max(axis=0) - lo + 1
    rel = keys - lo
    flat = (rel[:, 0] * span[1] + rel[:, 1]) * span[2] + rel[:, 2]
    uflat, inv = np.unique(flat, return_inverse=True)
    k = uflat % span[2]
    j = (uflat // span[2]) % span[1]
    i = uflat // (span[1] * span[2])
    return np.stack([i, j, k], axis=1) + lo, inv.reshape(-1)


def _voxel_blocks(
    ijk: NDArray[np.integer], s: FloatArray, n: FloatArray
) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32]]:
    """Voxel statistics into dense 8^3 blocks: block keys (B, 3), s and n (B, 8, 8, 8)."""
    ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    blocks = np.floor_divide(ijk, _BLOCK)
    keys, inv = _unique_rows(blocks)
    loc = ijk - blocks * _BLOCK
    s_b = np.zeros((len(keys), _BLOCK, _BLOCK, _BLOCK), dtype=np.float32)
    n_b = np.zeros((len(keys), _BLOCK, _BLOCK, _BLOCK), dtype=np.float32)
    s_b[inv, loc[:, 0], loc[:, 1], loc[:, 2]] = np.asarray(s, dtype=np.float64).reshape(-1)
    n_b[inv, loc[:, 0], loc[:, 1], loc[:, 2]] = np.asarray(n, dtype=np.float64).reshape(-1)
    return keys, s_b, n_b


def _coarsen_blocks(
    keys: NDArray[np.int64], s_b: NDArray[np.float32], n_b: NDArray[np.float32]
) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32]]:
    """Blocks of voxels twice as large: 2x2x2 sums (exact: chords and returns add up)."""
    h = _BLOCK // 2
    parents = np.floor_divide(keys, 2)
    pkeys, pinv = _unique_rows(parents)
    octant = keys - 2 * parents
    s_c = np.zeros((len(pkeys), _BLOCK, _BLOCK, _BLOCK), dtype=np.float32)
    n_c = np.zeros((len(pkeys), _BLOCK, _BLOCK, _BLOCK), dtype=np.float32)
    s_half = s_b.reshape(-1, h, 2, h, 2, h, 2).sum(axis=(2, 4, 6))
    n_half = n_b.reshape(-1, h, 2, h, 2, h, 2).sum(axis=(2, 4, 6))
    for ox in range(2):
        for oy in range(2):
            for oz in range(2):
                sel = np.flatnonzero(
                    (octant[:, 0] == ox) & (octant[:, 1] == oy) & (octant[:, 2] == oz)
                )
                xs, ys, zs = (
                    slice(ox * h, ox * h + h),
                    slice(oy * h, oy * h + h),
                    slice(oz * h, oz * h + h),
                )
                s_c[pinv[sel], xs, ys, zs] = s_half[sel]
                n_c[pinv[sel], xs, ys, zs] = n_half[sel]
    return pkeys, s_c, n_c


def _field_of_blocks(
    keys: NDArray[np.int64],
    s_b: NDArray[np.float32],
    n_b: NDArray[np.float32],
    res: float,
    origin: FloatArray,
    shape: float,
    rate: float,
) -> LikelihoodField:
    """The field of dense blocks of statistics (unobserved voxels: s = n = 0, the prior)."""
    a = np.empty(s_b.shape, dtype=np.float32)
    b = np.empty(s_b.shape, dtype=np.float32)
    _fill_log_probabilities(s_b.reshape(-1), n_b.reshape(-1), res, shape, rate,
                            a.reshape(-1), b.reshape(-1))  # fmt: skip
    prior_a, prior_b = (
        float(v[0]) for v in _log_probabilities(np.zeros(1), np.zeros(1), res, shape, rate)
    )
    if keys.shape[0]:
        lo = keys.min(axis=0)
        dims = keys.max(axis=0) - lo + 1
    else:
        lo, dims = np.zeros(3, np.int64), np.ones(3, np.int64)
    index = np.full(tuple(int(d) for d in dims), -1, dtype=np.int32)
    rel = keys - lo
    index[rel[:, 0], rel[:, 1], rel[:, 2]] = np.arange(len(keys), dtype=np.int32)
    return LikelihoodField(
        resolution=res,
        origin=np.asarray(origin, dtype=np.float64).reshape(3),
        block_lo=lo.astype(np.int64),
        index=index,
        a=a,
        b=b,
        prior_a=prior_a,
        prior_b=prior_b,
    )


@nb.njit(cache=True, nogil=True)
def _fill_log_probabilities(s, n, res, shape, rate, a, b):  # type: ignore[no-untyped-def]
    """``_log_probabilities`` element by element into float32 ``a``, ``b`` (no
    temporaries: 18M voxels of norlab's pyramid)."""
    for i in range(s.shape[0]):
        sv = np.float64(s[i])
        log_pass = (np.float64(n[i]) + shape) * math.log((sv + rate) / (sv + rate + res))
        a[i] = math.log(-math.expm1(log_pass))
        b[i] = log_pass / res


def _log_probabilities(
    s: FloatArray, n: FloatArray, res: float, shape: float, rate: float
) -> tuple[FloatArray, FloatArray]:
    """(log P(return over a full voxel edge), log P(pass) per metre) per voxel."""
    log_pass = (n + shape) * np.log((s + rate) / (s + rate + res))
    a = np.log(-np.expm1(log_pass))
    return a, log_pass / res


@dataclass
class FieldPyramid:
    """Fields of one map at voxel edges resolution * 2^k, finest first."""

    fields: list[LikelihoodField]

    @classmethod
    def from_statistics(
        cls,
        ijk: NDArray[np.integer],
        s: FloatArray,
        n: FloatArray,
        resolution: float,
        origin: FloatArray,
        *,
        levels: int = 3,
        shape: float = 1.0,
        rate: float = 1.0,
    ) -> FieldPyramid:
        """Fields at ``resolution * 2^k``, ``k < levels``, of voxels ``ijk`` (statistics
        ``s`` metres, ``n`` returns): exact sums of the statistics, as
        ``LikelihoodField.from_statistics`` with ``factor = 2^k``, but built once for all levels
        (one sort of the voxels, then 2x2x2 sums of 8^3 blocks: 1.4-2.1x faster than a
        sort per level on norlab's 3.6M voxels, in the same run)."""
        if levels < 1:
            raise ValueError(f"levels must be at least 1, got {levels}")
        keys, s_b, n_b = _voxel_blocks(ijk, s, n)
        fields = []
        for k in range(levels):
            if k:
                keys, s_b, n_b = _coarsen_blocks(keys, s_b, n_b)
            fields.append(_field_of_blocks(keys, s_b, n_b, resolution * 2**k, origin, shape, rate))
        return cls(fields)

    @classmethod
    def from_mapper(
        cls,
        mapper: object,
        *,
        stamp: float | None = None,
        levels: int = 3,
        shape: float = 1.0,
        rate: float = 1.0,
    ) -> FieldPyramid:
        """The pyramid of a ``Mapper``'s observed voxels, decayed to ``stamp`` when given."""
        stats = mapper.voxels(stamp)  # type: ignore[attr-defined]
        origin = np.asarray(mapper.origin or (0.0, 0.0, 0.0))  # type: ignore[attr-defined]
        return cls.from_statistics(
            stats.ijk,
            stats.s,
            stats.n,
            float(mapper.resolution),  # type: ignore[attr-defined]
            origin,
            levels=levels,
            shape=shape,
            rate=rate,
        )

    @property
    def resolution(self) -> float:
        return self.fields[0].resolution


# --- compiled kernels -------------------------------------------------------------------


@nb.njit(cache=True, nogil=True, inline="always")
def _voxel(a, b, index, block_lo, prior_a, prior_b, i, j, k):  # type: ignore[no-untyped-def]
    bi = (i >> 3) - block_lo[0]
    bj = (j >> 3) - block_lo[1]
    bk = (k >> 3) - block_lo[2]
    if (
        bi < 0
        or bj < 0
        or bk < 0
        or bi >= index.shape[0]
        or bj >= index.shape[1]
        or bk >= index.shape[2]
    ):
        return prior_a, prior_b
    row = index[bi, bj, bk]
    if row < 0:
        return prior_a, prior_b
    return a[row, i & 7, j & 7, k & 7], b[row, i & 7, j & 7, k & 7]


@nb.njit(cache=True, nogil=True)
def _interp(a, b, index, block_lo, prior_a, prior_b, res, origin, p, out):  # type: ignore[no-untyped-def]
    """Trilinear a, b at p between voxel centres; out = (a, b, da/dp (3), db/dp (3))."""
    inv = 1.0 / res
    cx = (p[0] - origin[0]) * inv - 0.5
    cy = (p[1] - origin[1]) * inv - 0.5
    cz = (p[2] - origin[2]) * inv - 0.5
    fx, fy, fz = math.floor(cx), math.floor(cy), math.floor(cz)
    tx, ty, tz = cx - fx, cy - fy, cz - fz
    i0, j0, k0 = int(fx), int(fy), int(fz)
    for q in range(8):
        out[q] = 0.0
    # the 8 corners in one block (2 in 3 lookups): that block is found once
    same = (i0 & 7) < 7 and (j0 & 7) < 7 and (k0 & 7) < 7
    row = -1
    if same:
        bi = (i0 >> 3) - block_lo[0]
        bj = (j0 >> 3) - block_lo[1]
        bk = (k0 >> 3) - block_lo[2]
        if (
            bi >= 0
            and bj >= 0
            and bk >= 0
            and bi < index.shape[0]
            and bj < index.shape[1]
            and bk < index.shape[2]
        ):
            row = index[bi, bj, bk]
        if row < 0:
            out[0] = prior_a
            out[1] = prior_b
            return
    li, lj, lk = i0 & 7, j0 & 7, k0 & 7
    for di in range(2):
        wx = tx if di else 1.0 - tx
        gx = 1.0 if di else -1.0
        for dj in range(2):
            wy = ty if dj else 1.0 - ty
            gy = 1.0 if dj else -1.0
            for dk in range(2):
                wz = tz if dk else 1.0 - tz
                gz = 1.0 if dk else -1.0
                if same:
                    va = a[row, li + di, lj + dj, lk + dk]
                    vb = b[row, li + di, lj + dj, lk + dk]
                else:
                    va, vb = _voxel(
                        a, b, index, block_lo, prior_a, prior_b, i0 + di, j0 + dj, k0 + dk
                    )
                w = wx * wy * wz
                out[0] += w * va
                out[1] += w * vb
                ex, ey, ez = gx * wy * wz * inv, wx * gy * wz * inv, wx * wy * gz * inv
                out[2] += ex * va
                out[3] += ey * va
                out[4] += ez * va
                out[5] += ex * vb
                out[6] += ey * vb
                out[7] += ez * vb


@nb.njit(cache=True, nogil=True)
def _values(a, b, index, block_lo, prior_a, prior_b, res, origin, pts, out):  # type: ignore[no-untyped-def]
    tmp = np.empty(8)
    for r in range(pts.shape[0]):
        _interp(a, b, index, block_lo, prior_a, prior_b, res, origin, pts[r], tmp)
        for q in range(8):
            out[r, q] = tmp[q]


@nb.njit(cache=True, nogil=True)
def _score(  # type: ignore[no-untyped-def]
    a,
    b,
    index,
    block_lo,
    prior_a,
    prior_b,
    res,
    origin,
    pts,
    orgs,
    rot,
    trans,
    center,
    window,
    step,
    per_ray,
    grads,
):
    """Surrogate log-likelihood of rays orgs[r] -> pts[r] moved by (rot, trans); fills
    per_ray (N,) and grads (N, 6): d/d(v, w) of x -> x + v + w x (x - center)."""
    tmp = np.empty(8)
    q = np.empty(3)
    p = np.empty(3)
    o = np.empty(3)
    total = 0.0
    for r in range(pts.shape[0]):
        for c in range(3):
            p[c] = rot[c, 0] * pts[r, 0] + rot[c, 1] * pts[r, 1] + rot[c, 2] * pts[r, 2] + trans[c]
            o[c] = (
                rot[c, 0] * orgs[r, 0] + rot[c, 1] * orgs[r, 1] + rot[c, 2] * orgs[r, 2] + trans[c]
            )
        dx, dy, dz = p[0] - o[0], p[1] - o[1], p[2] - o[2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        for c in range(6):
            grads[r, c] = 0.0
        if length <= 0.0:
            per_ray[r] = 0.0
            continue
        dx, dy, dz = dx / length, dy / length, dz / length
        _interp(a, b, index, block_lo, prior_a, prior_b, res, origin, p, tmp)
        f = tmp[0]
        g0, g1, g2 = tmp[2], tmp[3], tmp[4]
        lx, ly, lz = p[0] - center[0], p[1] - center[1], p[2] - center[2]
        grads[r, 0] += g0
        grads[r, 1] += g1
        grads[r, 2] += g2
        grads[r, 3] += ly * g2 - lz * g1
        grads[r, 4] += lz * g0 - lx * g2
        grads[r, 5] += lx * g1 - ly * g0
        reach = min(window, length)
        k = 1
        while k * step <= reach:
            back = k * step
            q[0], q[1], q[2] = p[0] - back * dx, p[1] - back * dy, p[2] - back * dz
            _interp(a, b, index, block_lo, prior_a, prior_b, res, origin, q, tmp)
            f += step * tmp[1]
            g0, g1, g2 = step * tmp[5], step * tmp[6], step * tmp[7]
            lx, ly, lz = q[0] - center[0], q[1] - center[1], q[2] - center[2]
            grads[r, 0] += g0
            grads[r, 1] += g1
            grads[r, 2] += g2
            grads[r, 3] += ly * g2 - lz * g1
            grads[r, 4] += lz * g0 - lx * g2
            grads[r, 5] += lx * g1 - ly * g0
            k += 1
        per_ray[r] = f
        total += f
    return total


def surrogate_log_likelihood(
    fld: LikelihoodField,
    points: FloatArray,
    origins: FloatArray,
    rotation: FloatArray | None = None,
    translation: FloatArray | None = None,
    *,
    window: float = 1.0,
    step: float = 0.5,
    center: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Per-ray smoothed log-likelihood (N,) of rays ``origins`` -> ``points`` (map frame)
    moved by ``rotation``/``translation`` (free space sampled every ``step`` voxel edges over
    the last ``window`` metres), and its gradient (N, 6) with respect to a
    further translation (metres) and rotation (radians) about ``center``."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    orgs = np.ascontiguousarray(np.broadcast_to(np.asarray(origins, dtype=np.float64), pts.shape))
    rot = np.eye(3) if rotation is None else np.ascontiguousarray(rotation, dtype=np.float64)
    trans = np.zeros(3) if translation is None else np.asarray(translation, dtype=np.float64)
    ctr = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64)
    per_ray = np.zeros(pts.shape[0])
    grads = np.zeros((pts.shape[0], 6))
    _score(  # type: ignore[call-arg]
        *fld._args(),
        pts,
        orgs,
        rot,
        trans,
        ctr,
        max(window, 2.0 * fld.resolution),
        step * fld.resolution,
        per_ray,
        grads,
    )
    return per_ray, grads


# --- the optimiser ----------------------------------------------------------------------


def _compose(
    rotvec: FloatArray, v: FloatArray, center: FloatArray, rot: FloatArray, trans: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The correction (R', t') = [x -> dR (x - c) + c + v] o (rot, trans)."""
    d_rot = Rotation.from_rotvec(rotvec).as_matrix()
    return d_rot @ rot, d_rot @ (trans - center) + center + v


def _spread_subset(count: int, wanted: int) -> NDArray[np.intp]:
    if count <= wanted:
        return np.arange(count)
    return np.unique(np.linspace(0, count - 1, wanted).round().astype(np.intp))


def align_scan(
    pyramid: FieldPyramid,
    points: FloatArray,
    origins: FloatArray,
    options: AlignOptions | None = None,
    *,
    normals: tuple[FloatArray, FloatArray] | None = None,
) -> Alignment:
    """Find the rigid correction of a scan (rays ``origins`` -> first returns ``points``,
    map frame, placed at the initial pose) that maximises its likelihood under the map.

    ``origins`` is (3,) or (N, 3) (a deskewed scan has one origin per point); rays without
    a return are not used. The rotation is about the mean sensor origin. ``normals``:
    (points, unit normals) of the scan's planar patches at the initial pose
    (``sensing.scan_normals``); when given, a correction along a direction they do not
    constrain is refused (``min_conditioning``).
    """
    opt = options or AlignOptions()
    pts_all = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    org_all = np.broadcast_to(np.asarray(origins, dtype=np.float64), pts_all.shape)
    finite = np.isfinite(pts_all).all(axis=1) & np.isfinite(org_all).all(axis=1)
    idx = np.flatnonzero(finite)
    idx = idx[_spread_subset(idx.size, opt.max_rays)]
    pts = np.ascontiguousarray(pts_all[idx])
    orgs = np.ascontiguousarray(org_all[idx])
    rays = pts.shape[0]
    if rays < 10:
        return _refused("too_few_rays", f"too few rays ({rays}) to align", rays)
    center = orgs.mean(axis=0)
    lever = opt.lever
    scale = np.array([1.0, 1.0, 1.0, 1.0 / lever, 1.0 / lever, 1.0 / lever])
    prior_w = np.array(
        [1.0 / opt.prior_sigma_m**2] * 3 + [1.0 / math.radians(opt.prior_sigma_deg) ** 2] * 3
    )
    rot, trans = np.eye(3), np.zeros(3)
    evaluations = 0
    per_ray = np.zeros(rays)
    grads = np.zeros((rays, 6))
    levels_done: list[dict[str, float]] = []

    def evaluate(
        fld: LikelihoodField,
        sub: NDArray[np.intp],
        rot1: FloatArray,
        trans1: FloatArray,
        acc1: FloatArray,
    ) -> tuple[float, FloatArray, FloatArray, float]:
        """Objective (log-likelihood of the rays ``sub`` scaled to all rays, minus the
        prior; nats), its gradient and the BHHH information matrix, both in scaled
        coordinates, at correction (rot1, trans1); and the rays' own log-likelihood sum."""
        nonlocal evaluations
        evaluations += 1
        per, grd = per_ray[: sub.size], grads[: sub.size]
        f = _score(  # type: ignore[call-arg]
            *fld._args(),
            pts[sub],
            orgs[sub],
            rot1,
            trans1,
            center,
            max(opt.window, 2 * fld.resolution),
            opt.step * fld.resolution,
            per,
            grd,
        )
        weight = rays / sub.size
        gs = grd * scale
        value = weight * f - 0.5 * float(np.sum(prior_w * acc1**2))
        grad = weight * gs.sum(axis=0) - prior_w * acc1 * scale
        info = weight * (gs.T @ gs) + np.diag(prior_w * scale * scale)
        return value, grad, info, float(f)

    acc = np.zeros(6)  # the correction so far, linearised (metres, radians), for the prior
    # the finest level scores all rays with the same window and step as the gain below:
    # its sums at the start (single level: the initial pose) and at the end are reused
    f_start = f_end = math.nan
    for level in reversed(range(len(pyramid.fields))):
        fld = pyramid.fields[level]
        sub = _spread_subset(rays, max(rays >> level, min(rays, 200)))
        value, grad, info, f_here = evaluate(fld, sub, rot, trans, acc)
        if level == 0 and len(pyramid.fields) == 1 and sub.size == rays:
            f_start = f_here
        start_value, damping, iterations = value, 1e-3, 0
        while iterations < opt.max_iterations:
            iterations += 1
            lhs = info + damping * np.diag(np.diag(info))
            x = np.linalg.solve(lhs, grad)  # ascent direction, scaled coordinates
            # BHHH steps are short far from the optimum (inconsistent per-ray scores make
            # the information matrix large): double the step while the objective improves
            best: (
                tuple[
                    float,
                    FloatArray,
                    FloatArray,
                    FloatArray,
                    FloatArray,
                    FloatArray,
                    FloatArray,
                    float,
                ]
                | None
            ) = None
            mult = 1.0
            while mult <= 64.0:
                if mult > 1.0 and mult * float(np.max(np.abs(x))) > fld.resolution:
                    break  # at most one voxel of the level per doubled step
                y = mult * x * scale
                rot1, trans1 = _compose(y[3:], y[:3], center, rot, trans)
                value1, grad1, info1, f1 = evaluate(fld, sub, rot1, trans1, acc + y)
                if value1 <= (value if best is None else best[0]):
                    break
                best = (value1, grad1, info1, rot1, trans1, acc + y, np.asarray(mult * x), f1)
                mult *= 2.0
            if best is not None:
                improved = best[0] - value
                value, grad, info, rot, trans, acc, step_x, f_here = best
                damping = max(damping / 3.0, 1e-7)
                small = float(np.max(np.abs(step_x))) < opt.tolerance * fld.resolution
                if small or improved < 1e-4 * rays:
                    break
            else:
                damping *= 4.0
                if damping > 1e6:
                    break
        if level == 0 and sub.size == rays:
            f_end = f_here
        levels_done.append(
            {
                "resolution": fld.resolution,
                "rays": float(sub.size),
                "objective_start": start_value,
                "objective_end": value,
                "iterations": float(iterations),
            }
        )
    fine = pyramid.fields[0]
    f_init = f_start
    if math.isnan(f_init):
        evaluations += 1
        f_init = float(
            np.sum(surrogate_log_likelihood(fine, pts, orgs, window=opt.window, step=opt.step)[0])
        )
    f_final = f_end
    curv, dirs = _curvature(fine, pts, orgs, rot, trans, center, opt, scale, info)
    evaluations += 13
    sigma, weakest, reason = _confidence(curv, dirs, scale, opt)
    refusal = "flat_likelihood" if reason else ""
    conditioning = -1
    if normals is not None:
        counts, g_vecs = geometric_conditioning(normals[0], normals[1], center, lever)
        low = int(np.argmin(counts))
        conditioning = int(counts[low])
        if conditioning < opt.min_constraints:
            main = _AXES[int(np.argmax(np.abs(g_vecs[:, low])))]
            weakest = g_vecs[:, low]
            refusal = "degenerate_geometry"
            reason = (
                f"degenerate geometry: only {conditioning} surface patches of the scan "
                f"constrain {main} (< {opt.min_constraints}); kept the initial pose"
            )
    shift = float(np.linalg.norm(trans + rot @ center - center))
    angle = math.degrees(float(np.linalg.norm(Rotation.from_matrix(rot).as_rotvec())))
    if not reason and (shift > opt.max_shift_m or angle > opt.max_angle_deg):
        refusal = "out_of_range"
        reason = (
            f"correction beyond the search range ({shift:.2f} m, {angle:.1f} deg > "
            f"{opt.max_shift_m:g} m or {opt.max_angle_deg:g} deg): kept the initial pose"
        )
    if not reason and opt.min_correction_voxels > 0.0:
        moved = pts @ rot.T + trans - pts
        rms = math.sqrt(float(np.mean(np.sum(moved * moved, axis=1))))
        if rms < opt.min_correction_voxels * fine.resolution:
            refusal = "aliasing"
            reason = (
                f"correction within the grid's aliasing range ({100 * rms:.1f} cm RMS < "
                f"{opt.min_correction_voxels:g} voxel); kept the initial pose"
            )
    if not reason and f_final - f_init < opt.min_gain_per_ray * rays:
        refusal = "no_gain"
        reason = (
            f"no significant gain ({(f_final - f_init) / rays:.3g} nats per ray < "
            f"{opt.min_gain_per_ray:g}); kept the initial pose"
        )
    accepted = not reason
    return Alignment(
        rotation=rot if accepted else np.eye(3),
        translation=trans if accepted else np.zeros(3),
        accepted=accepted,
        reason=reason,
        refusal=refusal,
        gain=f_final - f_init,
        gain_per_ray=(f_final - f_init) / rays,
        sigma=sigma,
        weakest=weakest,
        conditioning=conditioning,
        rays=rays,
        evaluations=evaluations,
        levels=levels_done,
        fit_per_ray=(f_final if accepted else f_init) / rays,
    )


def _curvature(
    fld: LikelihoodField,
    pts: FloatArray,
    orgs: FloatArray,
    rot: FloatArray,
    trans: FloatArray,
    center: FloatArray,
    opt: AlignOptions,
    scale: FloatArray,
    info: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Curvatures (6,) of the log-likelihood (nats per scaled unit squared) along the
    eigen-directions (columns of the 6x6 result) of the information matrix ``info``: the
    mean drop of the likelihood at +-``probe`` voxel edges, which is wide enough to average
    over the voxel-scale texture of the field (a sampled spread, not a local derivative)."""
    h = opt.probe * fld.resolution
    _, dirs = np.linalg.eigh(info)
    sub = _spread_subset(pts.shape[0], opt.probe_rays)
    weight = pts.shape[0] / sub.size
    pts, orgs = pts[sub], orgs[sub]

    def value(y: FloatArray) -> float:
        y = y * scale
        r1, t1 = _compose(y[3:], y[:3], center, rot, trans)
        f, _ = surrogate_log_likelihood(fld, pts, orgs, r1, t1, window=opt.window, step=opt.step)
        return float(f.sum())

    f0 = value(np.zeros(6))
    curv = np.empty(6)
    for c in range(6):
        drop = f0 - 0.5 * (value(h * dirs[:, c]) + value(-h * dirs[:, c]))
        curv[c] = 2.0 * weight * drop / (h * h)
    return curv, dirs


_AXES = ("x", "y", "z", "roll", "pitch", "yaw")


def _confidence(
    curv: FloatArray, dirs: FloatArray, scale: FloatArray, opt: AlignOptions
) -> tuple[FloatArray, FloatArray, str]:
    """Standard deviations per axis, the weakest direction, and a refusal reason if any."""
    weak = int(np.argmin(curv))
    weakest = dirs[:, weak]
    lam = curv[weak]
    sig_weak = math.inf if lam <= 0.0 else 1.0 / math.sqrt(lam)
    reason = ""
    if sig_weak > opt.max_sigma_m:
        main = _AXES[int(np.argmax(np.abs(weakest)))]
        shown = "unbounded" if not math.isfinite(sig_weak) else f"{sig_weak:.3g} m"
        reason = (
            f"degenerate geometry: the likelihood is flat along {main} "
            f"(std {shown} > {opt.max_sigma_m:g} m); kept the initial pose"
        )
    with np.errstate(divide="ignore"):
        inv = np.where(curv > 0.0, 1.0 / np.where(curv > 0.0, curv, 1.0), np.inf)
    with np.errstate(invalid="ignore"):
        var = np.nan_to_num((dirs**2) @ inv, nan=math.inf)
    sig = np.sqrt(var) * scale
    sig[3:] = np.degrees(sig[3:])
    return sig, weakest, reason


def geometric_conditioning(
    points: FloatArray, normals: FloatArray, center: FloatArray, lever: float
) -> tuple[NDArray[np.int64], FloatArray]:
    """Per eigen-direction (columns of the second result) of the point-to-plane information
    ``J^T J``, ``J_i = [n_i, (p_i - center) x n_i / lever]`` (Zhang et al. 2016), the number
    of planar patches that constrain it (``|J_i . e| > 0.3``): which directions (translation,
    rotation times ``lever``) the scan's surfaces pin down. A count, not an eigenvalue:
    a handful of walls seen edge-on must count, a thousand floor normals with a little
    noise along a corridor's axis must not."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] == 0:
        return np.zeros(6, np.int64), np.eye(6)
    jac = np.concatenate([nrm, np.cross(p - center, nrm) / lever], axis=1)
    _, evecs = np.linalg.eigh(jac.T @ jac)
    counts = np.count_nonzero(np.abs(jac @ evecs) > 0.3, axis=0).astype(np.int64)
    return counts, evecs


def verify_exact(
    mapper: object,
    alignment: Alignment,
    points: FloatArray,
    origins: FloatArray,
    stamp: float,
    options: AlignOptions | None = None,
    *,
    no_return: NDArray[np.bool_] | None = None,
) -> Alignment:
    """``alignment`` checked against the exact likelihood of the scan under ``mapper`` (a
    ``core.mapper.Mapper``; rays ``origins`` -> ``points`` in the map frame at the initial
    pose, as ``Mapper.integrate`` takes them): an accepted correction is refused unless the
    exact log-likelihood rises significantly (``AlignOptions.min_exact_z``). Fills
    ``exact_gain`` and ``exact_z``; a refused alignment is returned unchanged."""
    opt = options or AlignOptions()
    if not alignment.accepted:
        return alignment
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    org = np.broadcast_to(np.asarray(origins, dtype=np.float64), pts.shape)
    pick = _spread_subset(pts.shape[0], opt.exact_rays)
    p, o = pts[pick], np.ascontiguousarray(org[pick])
    nr = None if no_return is None else np.asarray(no_return, dtype=bool)[pick]
    rot, trans = alignment.rotation, alignment.translation
    before = scan_log_likelihood(mapper, p, o, stamp, no_return=nr)  # type: ignore[arg-type]
    after = scan_log_likelihood(
        mapper,  # type: ignore[arg-type]
        p @ rot.T + trans,
        o @ rot.T + trans,
        stamp,
        no_return=nr,
    )
    both, ib, ia = np.intersect1d(before.ray_source, after.ray_source, return_indices=True)
    diff = after.ray_log_likelihood[ia] - before.ray_log_likelihood[ib]
    gain = float(diff.sum())
    if both.size >= 2:
        err = float(np.std(diff, ddof=1)) / math.sqrt(both.size)
        z = float(np.mean(diff)) / err if err > 0.0 else math.copysign(math.inf, gain)
    else:
        z = math.nan
    out = replace(alignment, exact_gain=gain, exact_z=z)
    if not z > opt.min_exact_z:
        return replace(
            out,
            rotation=np.eye(3),
            translation=np.zeros(3),
            accepted=False,
            refusal="exact_check",
            reason=(
                f"no significant exact gain ({gain:.1f} nats over {both.size} rays, "
                f"{z:.2g} standard errors <= {opt.min_exact_z:g}); kept the initial pose"
            ),
        )
    return out


def _refused(refusal: str, reason: str, rays: int) -> Alignment:
    return Alignment(
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
