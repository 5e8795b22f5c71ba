"""The extinction field of a map and its pyramid.

Per voxel of the map, two numbers of the forward model with the Gamma(alpha, beta) prior:
the log-probability per metre that a ray passes (``b = (n+alpha) log((s+beta)/(s+beta+r)) / r``)
and the log-probability that a ray crossing the whole voxel returns in it
(``a = log(1 - ((s+beta)/(s+beta+r))^(n+alpha))``), unknown voxels at the prior, stored
sparse in 8^3 blocks and interpolated trilinearly between voxel centres. Coarser levels of
the pyramid aggregate the statistics exactly (chord lengths and return counts add up over
sub-voxels). ``surrogate_log_likelihood`` scores rays in a field.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.alignment.kernels import (
    fill_log_probabilities,
    interpolate_points,
    score_rays,
)

FloatArray = NDArray[np.float64]

BLOCK = 8
"""Voxels per block edge in the field's sparse storage."""


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
        blocks = StatisticBlocks.of_voxels(ijk, s, n)
        for _ in range(factor.bit_length() - 1):
            blocks = blocks.coarsened()
        return blocks.field(resolution * factor, origin, shape, rate)

    def values(self, points: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Interpolated ``a``, ``b`` at points (N, 3) and their gradients (N, 3) each."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.zeros((pts.shape[0], 8))
        interpolate_points(*self.kernel_args(), pts, out)  # type: ignore[call-arg]
        return out[:, 0], out[:, 1], out[:, 2:5], out[:, 5:8]

    def kernel_args(self) -> tuple[object, ...]:
        """The field as the compiled kernels take it (``kernels``' argument order)."""
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


@dataclass
class StatisticBlocks:
    """A map's voxel statistics in dense 8^3 blocks: block keys (B, 3), chord lengths ``s``
    and return counts ``n`` (B, 8, 8, 8; unobserved voxels 0)."""

    keys: NDArray[np.int64]
    s: NDArray[np.float32]
    n: NDArray[np.float32]

    @classmethod
    def of_voxels(cls, ijk: NDArray[np.integer], s: FloatArray, n: FloatArray) -> StatisticBlocks:
        """Voxels ``ijk`` with statistics ``s``, ``n`` into their blocks."""
        ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
        blocks = np.floor_divide(ijk, BLOCK)
        keys, inv = _unique_rows(blocks)
        loc = ijk - blocks * BLOCK
        s_b = np.zeros((len(keys), BLOCK, BLOCK, BLOCK), dtype=np.float32)
        n_b = np.zeros((len(keys), BLOCK, BLOCK, BLOCK), dtype=np.float32)
        s_b[inv, loc[:, 0], loc[:, 1], loc[:, 2]] = np.asarray(s, dtype=np.float64).reshape(-1)
        n_b[inv, loc[:, 0], loc[:, 1], loc[:, 2]] = np.asarray(n, dtype=np.float64).reshape(-1)
        return cls(keys, s_b, n_b)

    def coarsened(self) -> StatisticBlocks:
        """Blocks of voxels twice as large: 2x2x2 sums (exact: chords and returns add up)."""
        h = BLOCK // 2
        keys = self.keys
        parents = np.floor_divide(keys, 2)
        pkeys, pinv = _unique_rows(parents)
        octant = keys - 2 * parents
        s_c = np.zeros((len(pkeys), BLOCK, BLOCK, BLOCK), dtype=np.float32)
        n_c = np.zeros((len(pkeys), BLOCK, BLOCK, BLOCK), dtype=np.float32)
        s_half = self.s.reshape(-1, h, 2, h, 2, h, 2).sum(axis=(2, 4, 6))
        n_half = self.n.reshape(-1, h, 2, h, 2, h, 2).sum(axis=(2, 4, 6))
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
        return StatisticBlocks(pkeys, s_c, n_c)

    def field(self, res: float, origin: FloatArray, shape: float, rate: float) -> LikelihoodField:
        """The field of these blocks at voxel edge ``res`` under the Gamma(``shape``,
        ``rate``) prior (unobserved voxels: s = n = 0, the prior)."""
        keys = self.keys
        a = np.empty(self.s.shape, dtype=np.float32)
        b = np.empty(self.s.shape, dtype=np.float32)
        fill_log_probabilities(self.s.reshape(-1), self.n.reshape(-1), res, shape, rate,
                               a.reshape(-1), b.reshape(-1))  # fmt: skip
        prior_a, prior_b = (
            float(v[0]) for v in log_probabilities(np.zeros(1), np.zeros(1), res, shape, rate)
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


def log_probabilities(
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
        blocks = StatisticBlocks.of_voxels(ijk, s, n)
        fields = []
        for k in range(levels):
            if k:
                blocks = blocks.coarsened()
            fields.append(blocks.field(resolution * 2**k, origin, shape, rate))
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
    score_rays(  # type: ignore[call-arg]
        *fld.kernel_args(),
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
