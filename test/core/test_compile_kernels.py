"""The warm-up of a live node (``core.mapper.compile_kernels``): after it, a stream of scans
with intensities, staged and committed or integrated, the map's reads and the histograms'
merges compile no kernel of the package (with a cold numba cache a kernel compiled mid-stream
held the map for seconds and the node dropped clouds ``queue_full``)."""

from __future__ import annotations

import pytest
from kernel_signatures import run_fresh

_STREAM = r"""
import json, sys
import numpy as np
from box_world import anchors_scene
from kernel_signatures import new_signatures, signatures
from mfp_mapper.core.mapper import Mapper, compile_kernels
from mfp_mapper.core.reflectivity import ScanReflectivity
from mfp_mapper.sensing.reflectivity import bins_for


threads = int(sys.argv[1])
compile_kernels(0.2, threads=threads)
before = signatures()
bins = bins_for("intensity", 8)
rng = np.random.default_rng(0)
mapper = Mapper(0.2, threads=threads)
for k, (points, origin) in enumerate(anchors_scene(n_scans=8)):
    values = ScanReflectivity(rng.uniform(0.0, 255.0, len(points)), bins)
    if k % 2:
        mapper.integrate(points, origin, float(k), reflectivity=values)
    else:
        mapper.commit(mapper.stage(points, origin, float(k), reflectivity=values))
    mapper.reflectivity(points[:64], float(k))
mapper.query(points[:64])
mapper.voxels(min_doo=0.1)
stored = mapper.stored_reflectivity()
new = new_signatures(before, signatures())
print(json.dumps({"new": new, "rows": len(stored.ijk)}))
"""


@pytest.mark.parametrize("threads", [1, 2])
def test_a_stream_compiles_nothing_after_the_warm_up(threads: int) -> None:
    """In a fresh process: ``compile_kernels`` with the node's thread count, then eight
    box-world scans with intensities (thousands of histogram rows a scan: the fresh rows
    are merged into the settled ones on the way), the map's reads and its stored
    histograms. No kernel of the package compiles (or loads) after the warm-up."""
    result = run_fresh(_STREAM, str(threads))
    assert result["rows"] > 4096, result  # more than the fresh rows hold before a merge
    assert result["new"] == {}, result["new"]
