"""``align_scan``: the correction of a scan that maximises its smoothed likelihood under a
map's field pyramid (Levenberg-Marquardt on the BHHH information matrix, coarse to fine,
with a Gaussian motion prior), then the refusals that keep the initial pose."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from mfp_mapper.core.alignment.curvature import (
    AXES,
    confidence,
    curvature,
    geometric_conditioning,
)
from mfp_mapper.core.alignment.field import (
    FieldPyramid,
    LikelihoodField,
    surrogate_log_likelihood,
)
from mfp_mapper.core.alignment.kernels import score_rays
from mfp_mapper.core.alignment.options import Alignment, AlignOptions
from mfp_mapper.core.alignment.rays import ScanRays, axis_scale, compose, spread_subset

FloatArray = NDArray[np.float64]


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
    idx = idx[spread_subset(idx.size, opt.max_rays)]
    pts = np.ascontiguousarray(pts_all[idx])
    orgs = np.ascontiguousarray(org_all[idx])
    rays = pts.shape[0]
    if rays < 10:
        return Alignment.refused("too_few_rays", f"too few rays ({rays}) to align", rays)
    center = orgs.mean(axis=0)
    lever = opt.lever
    scale = axis_scale(lever)
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
        f = score_rays(  # type: ignore[call-arg]
            *fld.kernel_args(),
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
        sub = spread_subset(rays, max(rays >> level, min(rays, 200)))
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
                rot1, trans1 = compose(y[3:], y[:3], center, rot, trans)
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
    curv, dirs = curvature(fine, ScanRays(pts, orgs, center), rot, trans, info, opt)
    evaluations += 13
    sigma, weakest, reason = confidence(curv, dirs, opt)
    refusal = "flat_likelihood" if reason else ""
    conditioning = -1
    if normals is not None:
        counts, g_vecs = geometric_conditioning(normals[0], normals[1], center, lever)
        low = int(np.argmin(counts))
        conditioning = int(counts[low])
        if conditioning < opt.min_constraints:
            main = AXES[int(np.argmax(np.abs(g_vecs[:, low])))]
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
