"""How likely a map finds a lidar scan: the scan likelihood of the mean-free-path model.

For each ray of a scan, placed exactly as ``Mapper.integrate`` would place it
(``Mapper.place_rays``) and walked by the same traversal (``traversal.read_walk``, the
read-only twin of the integrating walk), the events are:

* every voxel crossed before the end voxel: "passed" over its chord ``l``, with
  probability ``((s+beta)/(s+beta+l))^(n+alpha)`` (Eq. 34 with ``s0 -> l``, Gamma prior);
* the end voxel of a ray with a return: "returned here" over the voxel's FULL chord ``L``
  (from where the ray entered to where it would leave it), probability
  ``1 - ((s+beta)/(s+beta+L))^(n+alpha)``;
* the end voxel of a ray without a return (``no_return`` flag, or cut at ``max_range``):
  "passed" over the chord up to its end point.

``s`` and ``n`` are the voxel's statistics decayed to the scan's ``stamp``; a voxel never
observed has ``s = n = 0`` (the prior alone). ``alpha``/``beta`` are the shape and rate of
the Gamma prior on the extinction ``u = -log m`` (``alpha = beta = 1``: the paper's uniform
prior on m). A ray's log-likelihood is the sum of its events' log-probabilities.

Read-only: nothing in the map changes, so any number of threads may score (e.g. candidate
poses of one scan) while nothing integrates into the same Mapper.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.traversal import Rays, read_walk, visit_bounds

UNIFORM_SHAPE = 1.0
"""Shape alpha of the Gamma prior on the extinction equal to the uniform prior on m."""
UNIFORM_RATE = 1.0
"""Rate beta (metres) of the Gamma prior on the extinction equal to the uniform prior on m."""

FloatArray = NDArray[np.float64]


@dataclass
class ScanEvents:
    """The events of the scored rays, in walk order (ray by ray)."""

    ray: NDArray[np.int64]
    """Index of the event's ray in ``ScanLikelihood.ray_log_likelihood``."""
    ijk: NDArray[np.int32]
    """Voxel index (map-file convention, relative to the map's origin)."""
    s: FloatArray
    """Metres of ray in the voxel, decayed to the scan's stamp."""
    n: FloatArray
    """Returns in the voxel, decayed to the scan's stamp."""
    chord: FloatArray
    """Metres the event covers: the chord crossed, or the end voxel's full chord."""
    hit: NDArray[np.bool_]
    """True: "returned here"; False: "passed"."""

    def __len__(self) -> int:
        return int(self.s.shape[0])

    def hit_probability(
        self, shape: float = UNIFORM_SHAPE, rate: float = UNIFORM_RATE
    ) -> FloatArray:
        """The model's probability of a return over each event's chord, with this prior."""
        return hit_probability(self.s, self.n, self.chord, shape, rate)

    def log_probability(
        self, shape: float = UNIFORM_SHAPE, rate: float = UNIFORM_RATE
    ) -> FloatArray:
        """Log-probability of each event's outcome, with this prior."""
        return event_log_probability(self.s, self.n, self.chord, self.hit, shape, rate)


@dataclass
class ScanLikelihood:
    """The likelihood of one scan under a map."""

    total: float
    """Sum of the rays' log-likelihoods (nats)."""
    ray_log_likelihood: FloatArray
    """Log-likelihood of each scored ray (nats)."""
    ray_source: NDArray[np.int64]
    """Index of each scored ray's input point (dropped points have no ray)."""
    events: int
    """Number of events (voxels passed and returns)."""
    dropped: dict[str, int]
    """Input points not scored, by reason (as ``IntegrationSummary.dropped``)."""
    event_arrays: ScanEvents | None = None
    """Every event, when asked for (``events=True``)."""

    @property
    def rays(self) -> int:
        return int(self.ray_log_likelihood.shape[0])


def hit_probability(
    s: ArrayLike, n: ArrayLike, chord: ArrayLike, shape: float, rate: float
) -> FloatArray:
    """``1 - ((s+rate)/(s+rate+chord))^(n+shape)``: a return within ``chord`` metres."""
    s_, n_, c_ = (np.asarray(a, dtype=np.float64) for a in (s, n, chord))
    return -np.expm1(-(n_ + shape) * np.log1p(c_ / (s_ + rate)))


def event_log_probability(
    s: ArrayLike, n: ArrayLike, chord: ArrayLike, hit: ArrayLike, shape: float, rate: float
) -> FloatArray:
    """Log-probability of each event's outcome (``hit``: a return, else a pass)."""
    s_, n_, c_ = (np.asarray(a, dtype=np.float64) for a in (s, n, chord))
    log_pass = -(n_ + shape) * np.log1p(c_ / (s_ + rate))
    with np.errstate(divide="ignore"):
        return np.where(np.asarray(hit, dtype=bool), np.log(-np.expm1(log_pass)), log_pass)


def check_prior(shape: float, rate: float) -> None:
    """ValueError unless the Gamma prior's shape and rate are finite and positive."""
    if not (math.isfinite(shape) and shape > 0.0 and math.isfinite(rate) and rate > 0.0):
        raise ValueError(
            f"the prior's shape and rate must be finite and > 0, got shape={shape}, rate={rate}"
        )


def score_rays(
    mapper: Mapper,
    rays: Rays,
    stamp: float,
    *,
    shape: float | None = None,
    rate: float | None = None,
    events: bool = False,
) -> tuple[FloatArray, int, ScanEvents | None]:
    """Per-ray log-likelihood of rays already placed by ``mapper.place_rays`` (reuse them
    to score one scan under several priors); the event count; the events when asked.
    ``shape``/``rate`` default to the mapper's prior (``Mapper.prior``)."""
    shape = mapper.prior.shape if shape is None else shape
    rate = mapper.prior.rate if rate is None else rate
    check_prior(shape, rate)
    if not math.isfinite(stamp):
        raise ValueError(f"stamp must be finite seconds, got {stamp}")
    view, shard_mask = mapper.store_view()
    count = len(rays)
    out = np.empty(count)
    capacity = int(visit_bounds(rays.origins_vox, rays.ends_vox).sum()) if events and count else 0
    ev = ScanEvents(
        np.empty(capacity, dtype=np.int64),
        np.empty((capacity, 3), dtype=np.int32),
        np.empty(capacity),
        np.empty(capacity),
        np.empty(capacity),
        np.empty(capacity, dtype=np.bool_),
    )
    if count == 0:
        return out, 0, (ev if events else None)
    used = read_walk(
        rays.origins_vox, rays.ends_vox, rays.lengths, rays.has_return, view, shard_mask,
        float(stamp), mapper.decay_time, float(shape), float(rate), out, events,
        ev.ray, ev.ijk, ev.s, ev.n, ev.chord, ev.hit,
    )  # fmt: skip
    if not events:
        return out, int(used), None
    trimmed = ScanEvents(
        ev.ray[:used], ev.ijk[:used], ev.s[:used], ev.n[:used], ev.chord[:used], ev.hit[:used]
    )
    return out, int(used), trimmed


def scan_log_likelihood(
    mapper: Mapper,
    points: ArrayLike,
    origins: ArrayLike,
    stamp: float,
    *,
    no_return: ArrayLike | None = None,
    shape: float | None = None,
    rate: float | None = None,
    events: bool = False,
) -> ScanLikelihood:
    """The log-likelihood of one scan under ``mapper``, read at ``stamp`` (seconds).

    ``points`` (N, 3) and ``origins`` ((3,) or (N, 3)) in the map frame, exactly what
    ``Mapper.integrate`` takes (``no_return`` (N,) flags rays that saw nothing up to their
    point); rays are placed, cut and dropped as integration does. ``shape``/``rate``: the Gamma
    prior on the extinction (default: the mapper's, ``Mapper.prior``). ``events=True`` also
    returns every event (memory: about 45 bytes per voxel crossed). The map is only read: safe
    to call from several threads at once (e.g. one per candidate pose) while nothing integrates
    into ``mapper``.
    """
    rays, dropped = mapper.place_rays(points, origins, no_return)
    per_ray, count, ev = score_rays(mapper, rays, stamp, shape=shape, rate=rate, events=events)
    source = rays.source if rays.source is not None else np.arange(len(rays))
    return ScanLikelihood(float(per_ray.sum()), per_ray, source, count, dropped, ev)


def total_log_likelihood(
    mapper: Mapper,
    points: ArrayLike,
    origins: ArrayLike,
    stamp: float,
    *,
    no_return: ArrayLike | None = None,
    shape: float | None = None,
    rate: float | None = None,
) -> float:
    """Just the sum of ``scan_log_likelihood``'s per-ray values: the objective of a pose
    search (call it once per candidate pose of the same scan)."""
    return scan_log_likelihood(
        mapper, points, origins, stamp, no_return=no_return, shape=shape, rate=rate
    ).total
