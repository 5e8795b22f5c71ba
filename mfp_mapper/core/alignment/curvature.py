"""How sure an alignment is: the curvature of the smoothed likelihood at the optimum, the
standard deviations and weakest direction it gives, and the count of the scan's planar
patches that constrain each direction."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.alignment.field import LikelihoodField, surrogate_log_likelihood
from mfp_mapper.core.alignment.options import AlignOptions
from mfp_mapper.core.alignment.rays import ScanRays, axis_scale, compose

FloatArray = NDArray[np.float64]

AXES = ("x", "y", "z", "roll", "pitch", "yaw")
"""Names of a correction's six coordinates."""


def curvature(
    fld: LikelihoodField,
    rays: ScanRays,
    rot: FloatArray,
    trans: FloatArray,
    info: FloatArray,
    opt: AlignOptions,
) -> tuple[FloatArray, FloatArray]:
    """Curvatures (6,) of the log-likelihood of ``rays`` corrected by (``rot``, ``trans``)
    (nats per scaled unit squared, ``rays.axis_scale``) along the eigen-directions (columns
    of the 6x6 result) of the information matrix ``info``: the mean drop of the likelihood
    at +-``probe`` voxel edges, which is wide enough to average over the voxel-scale texture
    of the field (a sampled spread, not a local derivative)."""
    h = opt.probe * fld.resolution
    scale = axis_scale(opt.lever)
    _, dirs = np.linalg.eigh(info)
    probes, weight = rays.subset(opt.probe_rays)

    def value(y: FloatArray) -> float:
        y = y * scale
        r1, t1 = compose(y[3:], y[:3], probes.center, rot, trans)
        f, _ = surrogate_log_likelihood(
            fld, probes.points, probes.origins, r1, t1, window=opt.window, step=opt.step
        )
        return float(f.sum())

    f0 = value(np.zeros(6))
    curv = np.empty(6)
    for c in range(6):
        drop = f0 - 0.5 * (value(h * dirs[:, c]) + value(-h * dirs[:, c]))
        curv[c] = 2.0 * weight * drop / (h * h)
    return curv, dirs


def confidence(
    curv: FloatArray, dirs: FloatArray, opt: AlignOptions
) -> tuple[FloatArray, FloatArray, str]:
    """Standard deviations per axis, the weakest direction, and a refusal reason if any."""
    weak = int(np.argmin(curv))
    weakest = dirs[:, weak]
    lam = curv[weak]
    sig_weak = math.inf if lam <= 0.0 else 1.0 / math.sqrt(lam)
    reason = ""
    if sig_weak > opt.max_sigma_m:
        main = AXES[int(np.argmax(np.abs(weakest)))]
        shown = "unbounded" if not math.isfinite(sig_weak) else f"{sig_weak:.3g} m"
        reason = (
            f"degenerate geometry: the likelihood is flat along {main} "
            f"(std {shown} > {opt.max_sigma_m:g} m); kept the initial pose"
        )
    with np.errstate(divide="ignore"):
        inv = np.where(curv > 0.0, 1.0 / np.where(curv > 0.0, curv, 1.0), np.inf)
    with np.errstate(invalid="ignore"):
        var = np.nan_to_num((dirs**2) @ inv, nan=math.inf)
    sig = np.sqrt(var) * axis_scale(opt.lever)
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
