"""The warm-up of a live node (``core.mapper.compile_kernels``): after it, a stream of scans
with intensities, staged and committed or integrated, the map's reads and the histograms'
merges compile no kernel of the package (with a cold numba cache a kernel compiled mid-stream
held the map for seconds and the node dropped clouds ``queue_full``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

_STREAM = r"""
import json, sys
import numba
import numpy as np
from box_world import anchors_scene
from mfp_mapper.core.mapper import Mapper, compile_kernels
from mfp_mapper.core.reflectivity import ScanReflectivity
from mfp_mapper.sensing.reflectivity import bins_for


def signatures():
    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("mfp_mapper"):
            for value in vars(module).values():
                if isinstance(value, numba.core.registry.CPUDispatcher):
                    key = value.py_func.__module__ + "." + value.py_func.__name__
                    found[key] = {str(s) for s in value.signatures}
    return found


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
after = signatures()
new = {k: sorted(v - before.get(k, set())) for k, v in after.items() if v - before.get(k, set())}
print(json.dumps({"new": new, "rows": len(stored.ijk)}))
"""


@pytest.mark.parametrize("threads", [1, 2])
def test_a_stream_compiles_nothing_after_the_warm_up(threads: int) -> None:
    """In a fresh process: ``compile_kernels`` with the node's thread count, then eight
    box-world scans with intensities (thousands of histogram rows a scan: the fresh rows
    are merged into the settled ones on the way), the map's reads and its stored
    histograms. No kernel of the package compiles (or loads) after the warm-up."""
    test_dir = Path(__file__).resolve().parents[1]
    run = subprocess.run(
        [sys.executable, "-c", _STREAM, str(threads)],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(test_dir), *sys.path])},
    )
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["rows"] > 4096, result  # more than the fresh rows hold before a merge
    assert result["new"] == {}, result["new"]
