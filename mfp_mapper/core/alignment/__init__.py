"""Scan-to-map alignment by the forward model's likelihood (the paper's Eq. 22 road to SLAM).

The exact per-ray log-likelihood of a scan (``core.likelihood``) is piecewise constant in
the pose at voxel scale: moving a scan by less than a voxel changes no voxel a ray crosses,
so it has no gradient. This package optimises a *smoothed* version of the same model and
reports the exact one:

- **Extinction field** (``field``: ``LikelihoodField``): per voxel of the map, two numbers
  of the forward model with the Gamma(alpha, beta) prior: the log-probability per metre
  that a ray passes and the log-probability that a ray crossing the whole voxel returns in
  it, unknown voxels at the prior. Both are interpolated trilinearly between voxel centres
  (``kernels``, compiled), so the likelihood of a ray is continuous and almost everywhere
  differentiable in the pose.
- **Ray surrogate** (``surrogate_log_likelihood``): ``a(end point) + step * sum b(samples)``
  over samples every ``step`` metres along the last ``window`` metres of the ray before its
  return (the free space that decides between two nearby poses; the rest of the ray crosses
  space far from any surface, where a small shift changes little).
- **Pyramid** (``FieldPyramid``): coarser levels aggregate the statistics exactly (chord
  lengths and return counts add up over sub-voxels), so the same model at 2x, 4x the voxel
  edge gives a wider basin of convergence; the pose is refined coarse to fine
  (``solver``: ``align_scan``).
- **Motion prior**: a Gaussian on the correction (``prior_sigma_m``, ``prior_sigma_deg``).
- **Confidence** (``curvature``): the curvature of the fine-level objective at the
  optimum, whose inverse gives standard deviations per axis. A direction along which the
  likelihood is flat (a corridor's axis, an open field) makes the correction unsupported:
  the initial pose is kept and the reason is said.
- **Exact check** (``verify``: ``verify_exact``): an accepted correction must raise the
  exact likelihood significantly.

What an alignment is asked and answers is in ``options`` (``AlignOptions``, ``Alignment``,
``REFUSALS``). Pure maths on the map's statistics and on rays in the map frame: no I/O, no
ROS.
"""

from mfp_mapper.core.alignment.curvature import geometric_conditioning
from mfp_mapper.core.alignment.field import (
    FieldPyramid,
    LikelihoodField,
    surrogate_log_likelihood,
)
from mfp_mapper.core.alignment.options import REFUSALS, Alignment, AlignOptions
from mfp_mapper.core.alignment.solver import align_scan
from mfp_mapper.core.alignment.verify import verify_exact

__all__ = [
    "REFUSALS",
    "AlignOptions",
    "Alignment",
    "FieldPyramid",
    "LikelihoodField",
    "align_scan",
    "geometric_conditioning",
    "surrogate_log_likelihood",
    "verify_exact",
]
