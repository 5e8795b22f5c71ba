"""The numba kernels a process has compiled (or loaded from numba's cache), for tests that
run a warm-up and then real work in a fresh process and check that nothing compiled after
the warm-up (a kernel compiled mid-stream with a cold cache holds the map for seconds)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numba


def signatures() -> dict[str, set[str]]:
    """Every loaded module of the package's compiled kernels, by name: their signatures."""
    found: dict[str, set[str]] = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("mfp_mapper"):
            for value in vars(module).values():
                if isinstance(value, numba.core.registry.CPUDispatcher):
                    key = value.py_func.__module__ + "." + value.py_func.__name__
                    found[key] = {str(s) for s in value.signatures}
    return found


def new_signatures(before: dict[str, set[str]], after: dict[str, set[str]]) -> dict[str, list[str]]:
    """The signatures in ``after`` that ``before`` did not have, by kernel."""
    new = {name: kernels - before.get(name, set()) for name, kernels in after.items()}
    return {name: sorted(kernels) for name, kernels in new.items() if kernels}


def run_fresh(script: str, *args: str) -> Any:
    """Run ``script`` (Python source; its last line of output JSON) in a fresh process with
    the tests' helpers importable; its parsed output."""
    test_dir = Path(__file__).resolve().parent
    run = subprocess.run(
        [sys.executable, "-c", script, *args],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(test_dir), *sys.path])},
    )
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.strip().splitlines()[-1])
