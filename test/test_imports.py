"""Heavy imports stay lazy: ``import mfp_mapper``, ``import mfp_mapper.cli``,
``mfp-mapper --help`` and the map-file queries (``mapio.queries``) load no numba (its import
compiles a probe kernel), no ROS, no bag reader and no plotting (checked in a fresh
interpreter)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("numba", "llvmlite", "rclpy", "rosbags", "matplotlib", "scipy", "yaml")

HELP = "import mfp_mapper.cli as c\ntry:\n    c.main({argv!r})\nexcept SystemExit:\n    pass"
PROBE = """
import json, sys
{code}
print(json.dumps(sorted({{m.split(".")[0] for m in sys.modules}} & set({heavy!r}))))
"""


def _heavy_modules_after(code: str) -> list[str]:
    script = PROBE.format(code=code, heavy=HEAVY)
    proc = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    return list(json.loads(proc.stdout.strip().splitlines()[-1]))


@pytest.mark.parametrize(
    "code",
    [
        "import mfp_mapper",
        "import mfp_mapper.cli",
        "import mfp_mapper.config.schema",
        "import mfp_mapper.mapio.queries, mfp_mapper.core.reflectivity_arrays",
        HELP.format(argv=["--help"]),
        HELP.format(argv=["replay", "--help"]),
    ],
)
def test_light_entry_points_import_nothing_heavy(code: str) -> None:
    assert _heavy_modules_after(code) == []


def test_the_probe_sees_heavy_imports() -> None:
    assert {"numba", "llvmlite"} <= set(_heavy_modules_after("import mfp_mapper.core.traversal"))


VENV_BIN = ROOT / ".venv" / "bin"


def _venv_or_skip() -> Path:
    if not (VENV_BIN / "python").exists():
        pytest.skip(f"{VENV_BIN.parent} is made by ./run setup; not there")
    return VENV_BIN


def test_the_venv_imports_this_checkout_from_any_directory(tmp_path: Path) -> None:
    """``./run setup`` installs the package editable: a user's own directory finds it."""
    bin_dir = _venv_or_skip()
    if (ROOT / ".venv").is_symlink():
        pytest.skip(
            ".venv is a link to another checkout's (a git worktree): its package is that one"
        )
    proc = subprocess.run(
        [str(bin_dir / "python"), "-c", "import mfp_mapper; print(mfp_mapper.__file__)"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert Path(proc.stdout.strip()).resolve() == (ROOT / "mfp_mapper" / "__init__.py").resolve()


@pytest.mark.parametrize("script", ["mfp-mapper", "mfp_mapper"])
def test_the_console_scripts_answer_help_from_any_directory(script: str, tmp_path: Path) -> None:
    """The command line and the node, as README tells a user to type them."""
    bin_dir = _venv_or_skip()
    proc = subprocess.run(
        [str(bin_dir / script), "--help"], cwd=tmp_path, capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "usage" in (proc.stdout + proc.stderr).lower()
    assert "Traceback" not in proc.stderr
