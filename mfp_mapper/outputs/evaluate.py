"""Compare a map with the ground truth of a simulated scene (``mfp-mapper evaluate``).

For each medium of known extinction ``lambda``: the voxels lying fully inside it, the pooled
estimate ``sum(n) / sum(s)`` against ``lambda``, the median error of the per-voxel estimate
``n/s``, and how often the central credible interval (``model.extinction_interval``, 90% by
default) contains ``lambda`` — about 90% of the voxels for a calibrated map. Voxels of free
air (at least one voxel away from every surface and volume) should hold no returns.

``compare_no_return`` replays a bag twice, without and with the recovery of no-return rays
(``--no-return-range``), and reports the bias of both maps.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.config.replay_options import ReplayOptions
from mfp_mapper.core import model
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.replay import replay

FloatArray = NDArray[np.float64]


@dataclass
class MediumResult:
    name: str
    extinction: float
    voxels_inside: int
    voxels_observed: int
    returns: float
    length: float
    pooled: float
    """sum(n) / sum(s) over the observed voxels inside (returns per metre)."""
    pooled_relative_error: float
    median_abs_error: float
    """median over observed voxels of |n/s - lambda| (per metre)."""
    median_relative_error: float
    coverage: float
    """Share of observed voxels whose credible interval contains lambda."""
    median_evidence: float
    """Median s (metres of rays) per observed voxel."""


@dataclass
class FreeAirResult:
    voxels_observed: int = 0
    voxels_with_returns: int = 0
    returns: float = 0.0
    length: float = 0.0

    @property
    def pooled(self) -> float:
        return self.returns / self.length if self.length > 0 else 0.0


@dataclass
class Evaluation:
    resolution: float
    level: float
    media: list[MediumResult]
    free_air: FreeAirResult
    warnings: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {
            "resolution": self.resolution,
            "level": self.level,
            "media": [asdict(m) for m in self.media],
            "free_air": {**asdict(self.free_air), "pooled": self.free_air.pooled},
            "warnings": list(self.warnings),
        }

    def format(self) -> str:
        pct = f"{100 * self.level:.0f}%"
        lines = []
        for m in self.media:
            if m.voxels_observed == 0:
                lines.append(
                    f"{m.name}: lambda {m.extinction:.3f} /m; none of its {m.voxels_inside} "
                    "voxels was observed"
                )
                continue
            lines.append(
                f"{m.name}: lambda {m.extinction:.3f} /m (mean free path "
                f"{1 / m.extinction:.2f} m); {m.voxels_observed} of {m.voxels_inside} voxels "
                f"inside observed, median {m.median_evidence:.1f} m of rays each"
            )
            lines.append(
                f"  pooled n/s = {m.pooled:.3f} /m ({100 * m.pooled_relative_error:+.1f}% vs "
                f"lambda); per-voxel median |n/s - lambda| = {m.median_abs_error:.3f} /m "
                f"({100 * m.median_relative_error:.0f}%)"
            )
            lines.append(
                f"  {pct} interval contains lambda in {100 * m.coverage:.1f}% of the voxels "
                f"(calibrated: about {pct})"
            )
        fa = self.free_air
        lines.append(
            f"free air: {fa.voxels_observed:,} voxels observed, {fa.voxels_with_returns} with "
            f"a return; pooled n/s = {fa.pooled:.2g} /m"
        )
        lines.extend(f"warning: {w}" for w in self.warnings)
        return "\n".join(lines)


def inside_voxels(lo: Any, hi: Any, resolution: float) -> NDArray[np.int64]:
    """Indices (N, 3) of the voxels lying entirely inside the box [lo, hi]."""
    eps = 1e-9
    first = np.ceil(np.asarray(lo, dtype=np.float64) / resolution - eps).astype(np.int64)
    last = np.floor(np.asarray(hi, dtype=np.float64) / resolution + eps).astype(np.int64)
    axes = [np.arange(a, b) for a, b in zip(first, last, strict=True)]
    if any(ax.size == 0 for ax in axes):
        return np.empty((0, 3), dtype=np.int64)
    grid = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.reshape(-1) for g in grid], axis=1)


def evaluate_map(
    mapper: Mapper,
    truth: dict[str, Any],
    level: float = 0.9,
    min_length: float = 0.0,
    no_return_recovered: bool = False,
) -> Evaluation:
    """Evaluate ``mapper`` against ``truth`` (the JSON written by ``simulate``).

    ``min_length``: only voxels with at least this many metres of rays (s) count.
    ``no_return_recovered``: the map was made with ``no_return_range`` > 0 and recovered
    the omitted rays (no warning about them).
    """
    r = mapper.resolution
    scene = truth["scene"]
    media: list[MediumResult] = []
    for med in scene["media"]:
        lam = float(med["extinction"])
        ijk = inside_voxels(med["lo"], med["hi"], r)
        stats = mapper.query((ijk + 0.5) * r)
        use = stats.observed & (stats.s >= max(min_length, 0.0)) & (stats.s > 0)
        s, n = stats.s[use], stats.n[use]
        if s.size:
            est = n / s
            lo, hi = model.extinction_interval(s, n, level, mapper.prior)
            pooled = float(n.sum() / s.sum())
            abs_err = np.abs(est - lam)
            result = MediumResult(
                name=str(med["name"]),
                extinction=lam,
                voxels_inside=int(ijk.shape[0]),
                voxels_observed=int(s.size),
                returns=float(n.sum()),
                length=float(s.sum()),
                pooled=pooled,
                pooled_relative_error=pooled / lam - 1.0,
                median_abs_error=float(np.median(abs_err)),
                median_relative_error=float(np.median(abs_err) / lam),
                coverage=float(np.mean((lo <= lam) & (lam <= hi))),
                median_evidence=float(np.median(s)),
            )
        else:
            nan = math.nan
            result = MediumResult(
                str(med["name"]), lam, int(ijk.shape[0]), 0, 0.0, 0.0, nan, nan, nan, nan, nan, nan
            )
        media.append(result)
    ev = Evaluation(r, level, media, _free_air(mapper, scene))
    ev.warnings.extend(_warnings(mapper, truth, media, no_return_recovered))
    return ev


def _free_air(mapper: Mapper, scene: dict[str, Any]) -> FreeAirResult:
    vox = mapper.voxels()
    if len(vox) == 0:
        return FreeAirResult()
    r = mapper.resolution
    lo_v = vox.ijk * r
    hi_v = lo_v + r
    room_lo = np.asarray(scene["room_lo"], dtype=np.float64) + r
    room_hi = np.asarray(scene["room_hi"], dtype=np.float64) - r
    if not scene.get("enclosed", True):
        room_hi[2] = np.inf
    free = np.all(lo_v >= room_lo, axis=1) & np.all(hi_v <= room_hi, axis=1)
    for box in (*scene["solids"], *scene["media"]):
        blo = np.asarray(box["lo"], dtype=np.float64) - r
        bhi = np.asarray(box["hi"], dtype=np.float64) + r
        touches = np.all(hi_v > blo, axis=1) & np.all(lo_v < bhi, axis=1)
        free &= ~touches
    sel = vox.select(free)
    return FreeAirResult(
        voxels_observed=len(sel),
        voxels_with_returns=int(np.count_nonzero(sel.n > 0)),
        returns=float(sel.n.sum()),
        length=float(sel.s.sum()),
    )


def _warnings(
    mapper: Mapper, truth: dict[str, Any], media: list[MediumResult], recovered: bool
) -> list[str]:
    out = []
    rays = truth.get("rays", {})
    through = int(rays.get("omitted_through_media", 0))
    if through and not recovered:
        out.append(
            f"{through:,} simulated rays crossed a medium and returned nothing; a driver omits "
            "them, so the map never saw the space they crossed and n/s is biased upward "
            "(close the scene with walls and a ceiling, or simulate --organized and replay "
            "with --no-return-range)"
        )
    odom = truth.get("frames", {}).get("odom")
    if odom and mapper.frame_id and mapper.frame_id != odom:
        out.append(f"the map frame is {mapper.frame_id!r}, the truth is in {odom!r}")
    if math.isfinite(mapper.decay_time):
        out.append("the map decays (decay_time set): the statistics are not a static average")
    out.extend(
        f"medium {m.name!r} has no voxel fully inside it at resolution {mapper.resolution} m"
        for m in media
        if m.voxels_inside == 0
    )
    return out


@dataclass
class NoReturnComparison:
    """One bag mapped without and with the recovery of no-return rays."""

    no_return_range: float
    rays_no_return: int
    without: Evaluation
    recovered: Evaluation

    def to_json(self) -> dict[str, Any]:
        return {
            "no_return_range": self.no_return_range,
            "rays_no_return": self.rays_no_return,
            "without": self.without.to_json(),
            "recovered": self.recovered.to_json(),
        }

    def format(self) -> str:
        lines = [
            f"no-return rays: {self.rays_no_return:,} recovered up to {self.no_return_range:g} m"
        ]
        for before, after in zip(self.without.media, self.recovered.media, strict=True):
            pct = f"{100 * self.without.level:.0f}%"
            lines.append(
                f"{before.name}: pooled n/s {100 * before.pooled_relative_error:+.1f}% vs lambda "
                f"without recovery, {100 * after.pooled_relative_error:+.1f}% with; {pct} "
                f"interval coverage {100 * before.coverage:.1f}% -> {100 * after.coverage:.1f}%"
            )
        return "\n".join(lines)


def compare_no_return(
    bag: str | Path,
    truth: dict[str, Any],
    no_return_range: float,
    options: ReplayOptions | None = None,
    level: float = 0.9,
) -> NoReturnComparison:
    """Replay ``bag`` without and with ``no_return_range`` and evaluate both maps."""

    if not no_return_range > 0:
        raise ValueError(f"no_return_range must be > 0 m, got {no_return_range}")
    base = options or ReplayOptions()
    plain = replay(bag, base.but(no_return_range=0.0), progress=False)
    with_rays = replay(bag, base.but(no_return_range=no_return_range), progress=False)
    return NoReturnComparison(
        no_return_range,
        with_rays.summary.rays_no_return,
        evaluate_map(plain.mapper, truth, level),
        evaluate_map(with_rays.mapper, truth, level, no_return_recovered=True),
    )
