"""Which intensity field of a cloud feeds the reflectivity field, and its bin edges.

Drivers publish the returned intensity under a few names, each on its own scale:

===================  =============================  ===========================================
field                who publishes it               scale
===================  =============================  ===========================================
``reflectivity``     ouster-ros (uint16), the       calibrated reflectivity: 0-100 diffuse
                     Ouster SDK's scans             (Lambertian %), 101-255 retro-reflectors
``intensity``        velodyne_pointcloud (float32), 0-255 (Velodyne's calibrated reflectivity
                     Nebula (uint8), Livox, Hesai   has the same 0-100 / 101-255 split)
===================  =============================  ===========================================

A cloud with ``reflectivity`` uses it (ouster-ros also publishes ``intensity``, the signal
strength, which falls with range); otherwise ``intensity``. Both are 8-bit scales whose
returns crowd the low end (on ouster_street half of the returns are below 8, 1% above 100),
so the edges are log-spaced: ``J`` bins over the 8 octaves below ``FULL_SCALE``, the edges
``256 * 2**(-8 (J - k) / J)``, k = 1..J-1 (J = 8: 2, 4, 8, ..., 128); below the first edge
(0 and 1) is bin 0, from the last edge up bin J-1. Fixed edges per field, never fitted to
the data: maps of the same field and J merge. (A source whose ``intensity`` is on a 0-1
scale, like KITTI's own velodyne files, lands in bin 0: the histograms then say nothing.)
"""

from __future__ import annotations

import numpy as np

from mfp_mapper.core.reflectivity import ReflectivityBins
from mfp_mapper.sensing.pointcloud import INTENSITY_FIELDS

__all__ = ["FULL_SCALE", "INTENSITY_FIELDS", "bins_for"]
FULL_SCALE = {"reflectivity": 256.0, "intensity": 256.0}
"""One past the largest value of each field's scale (8-bit scales)."""
OCTAVES = 8
"""How many halvings below ``FULL_SCALE`` the edges span."""


def bins_for(field: str, count: int) -> ReflectivityBins | None:
    """The bins of ``count`` (J) log-spaced bins for ``field`` (module docstring); None for
    ``count`` 0 or a field without a known scale."""
    if count <= 0 or field not in FULL_SCALE:
        return None
    k = np.arange(1, count)
    edges = FULL_SCALE[field] * np.exp2(-OCTAVES * (count - k) / count)
    return ReflectivityBins(field, tuple(float(e) for e in edges))
