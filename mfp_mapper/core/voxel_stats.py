"""What the Mapper returns: the summary of an integration and per-voxel statistics."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core import model

FloatArray = NDArray[np.float64]


@dataclass
class IntegrationSummary:
    """What one ``Mapper.integrate`` call did with its rays."""

    rays_in: int = 0
    rays_used: int = 0
    rays_truncated: int = 0
    """Rays longer than max_range: walked up to max_range, with no return."""
    rays_no_return: int = 0
    """Used rays flagged ``no_return``: free space up to their end point, no return."""
    rays_beyond_walk_limit: int = 0
    """Rays longer than ``MAX_RAY_VOXELS`` voxels (when max_range is longer still): walked
    that far, with no return."""
    rays_cut_by_budget: int = 0
    """Rays whose part beyond ``memory_bound.FREE_WALK_VOXELS`` was cut to keep the scan
    within its block budget (``memory_bound.scan_block_budget``): walked that far, no
    return."""
    rays_unindexable: int = 0
    """Rays dropped because they reach beyond the map's index range around its origin
    (also in ``dropped["out_of_bounds"]``): worth a log line."""
    dropped: dict[str, int] = field(default_factory=dict)
    """Rays not used, by reason: nonfinite, below_min_range, out_of_bounds."""
    voxels_touched: int = 0
    """Voxel updates (a voxel crossed by k rays counts k times)."""
    new_voxels: int = 0
    blocks_touched: int = 0
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    """CPU time of the call, the core's worker threads included."""
    commit_seconds: float = 0.0
    """Of ``seconds``, the time ``Mapper.commit`` took (the map lock held) for a staged scan."""

    @property
    def integrated(self) -> bool:
        """Whether the scan added anything (at least one usable ray); a scan with none left
        the map unchanged and is a drop, not an integration."""
        return self.rays_used > 0


@dataclass
class VoxelStats:
    """Statistics of a set of voxels, with the model's estimates computed on demand."""

    ijk: NDArray[np.int32]
    centers: FloatArray
    s: FloatArray
    n: FloatArray
    t_last: FloatArray
    observed: NDArray[np.bool_]
    resolution: float
    prior: model.Prior = model.UNIFORM
    """The map's prior on the extinction: every estimate below but the most likely DoO
    and mean free path depends on it."""

    def __len__(self) -> int:
        return int(self.s.shape[0])

    @property
    def most_likely_doo(self) -> FloatArray:
        return model.most_likely_doo(self.s, self.n)

    @property
    def mean_doo(self) -> FloatArray:
        return model.mean_doo(self.s, self.n, self.prior)

    @property
    def std(self) -> FloatArray:
        return model.std_doo(self.s, self.n, self.prior)

    @property
    def hit_probability(self) -> FloatArray:
        """Probability that a ray crossing one voxel edge of this voxel is reflected."""
        return model.hit_probability(self.s, self.n, self.resolution, self.prior)

    def doo_interval(self, level: float = 0.9) -> tuple[FloatArray, FloatArray]:
        """Central credible interval of the degree of occupancy."""
        return model.doo_interval(self.s, self.n, level, self.prior)

    @property
    def mean_free_path(self) -> FloatArray:
        return model.mean_free_path(self.s, self.n)

    def select(self, mask: NDArray[np.bool_] | NDArray[np.intp]) -> VoxelStats:
        """The subset of voxels picked by a boolean mask or index array."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        scalars = ("resolution", "prior")
        return VoxelStats(**{k: (v if k in scalars else v[mask]) for k, v in values.items()})


def decayed_stats(
    ijk: NDArray[np.integer],
    s: FloatArray,
    n: FloatArray,
    t_last: FloatArray,
    stamp: float | None,
    decay_time: float,
    resolution: float,
    offset: FloatArray,
    prior: model.Prior,
) -> VoxelStats:
    """``VoxelStats`` of voxels ``ijk`` holding ``s``, ``n`` as of ``t_last`` (-inf: never
    observed), decayed to ``stamp`` when given (a map with a ``decay_time``); ``offset``:
    the map-frame position of voxel (0, 0, 0)'s corner. What ``Mapper.query`` and the
    numba-free point queries of a map file (``mapio.queries``) return."""
    if stamp is not None and math.isfinite(decay_time):
        seen = np.isfinite(t_last)
        dt = np.where(seen, stamp - np.where(seen, t_last, 0.0), 0.0)
        s, n = model.decay(s, n, dt, decay_time)
    ijk32 = ijk.astype(np.int32)
    return VoxelStats(
        ijk=ijk32,
        centers=(ijk32 + 0.5).astype(np.float64) * resolution + offset,
        s=s,
        n=n,
        t_last=t_last,
        observed=model.observed(s, n),
        resolution=resolution,
        prior=prior,
    )


@dataclass
class SegmentStats:
    """What the map says of straight segments, each from a start to an end point."""

    length: FloatArray
    """Metres from start to end."""
    clear_probability: FloatArray
    """Probability that a ray from the start reaches the end unreflected: the product over
    the voxels crossed of ``E[m^l]`` (Eq. 34) with ``l`` the exact chord; a never-observed
    voxel counts with the prior alone."""
    unknown_length: FloatArray
    """Metres of the segment inside never-observed voxels."""

    def __len__(self) -> int:
        return int(self.length.shape[0])
