"""The field's compiled kernels (numba): per-voxel log-probabilities, trilinear
interpolation of a sparse blocked field, and the ray surrogate with its gradient.

A field is passed as its arrays and numbers, in the order of ``LikelihoodField.kernel_args``:
``a``, ``b`` (float32, blocks x 8 x 8 x 8), ``index`` (block row per block of the box,
-1: none), ``block_lo``, ``prior_a``, ``prior_b``, ``res``, ``origin``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def fill_log_probabilities(s, n, res, shape, rate, a, b):  # type: ignore[no-untyped-def]
    """``field.log_probabilities`` element by element into float32 ``a``, ``b`` (no
    temporaries: 18M voxels of norlab's pyramid)."""
    for i in range(s.shape[0]):
        sv = np.float64(s[i])
        log_pass = (np.float64(n[i]) + shape) * math.log((sv + rate) / (sv + rate + res))
        a[i] = math.log(-math.expm1(log_pass))
        b[i] = log_pass / res


@nb.njit(cache=True, nogil=True, inline="always")
def voxel(a, b, index, block_lo, prior_a, prior_b, i, j, k):  # type: ignore[no-untyped-def]
    """(a, b) of voxel (i, j, k): its block's values, the prior outside every block."""
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
def interpolate(a, b, index, block_lo, prior_a, prior_b, res, origin, p, out):  # type: ignore[no-untyped-def]
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
                    va, vb = voxel(
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
def interpolate_points(a, b, index, block_lo, prior_a, prior_b, res, origin, pts, out):  # type: ignore[no-untyped-def]
    tmp = np.empty(8)
    for r in range(pts.shape[0]):
        interpolate(a, b, index, block_lo, prior_a, prior_b, res, origin, pts[r], tmp)
        for q in range(8):
            out[r, q] = tmp[q]


@nb.njit(cache=True, nogil=True)
def score_rays(  # type: ignore[no-untyped-def]
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
        interpolate(a, b, index, block_lo, prior_a, prior_b, res, origin, p, tmp)
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
            interpolate(a, b, index, block_lo, prior_a, prior_b, res, origin, q, tmp)
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
