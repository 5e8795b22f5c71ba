"""``verify_exact``: an accepted correction checked against the exact likelihood of the scan
(``core.likelihood``, no smoothing)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.alignment.options import Alignment, AlignOptions
from mfp_mapper.core.alignment.rays import spread_subset
from mfp_mapper.core.likelihood import scan_log_likelihood

FloatArray = NDArray[np.float64]


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
    pick = spread_subset(pts.shape[0], opt.exact_rays)
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
