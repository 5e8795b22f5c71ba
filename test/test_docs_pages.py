"""What docs/mapfiles.md and docs/localization.md say, checked: mapfiles.md's Python examples
run as a user would copy them (the API block writes ``map.npz`` with ``save_map`` and reads it
back with ``load_map``; the numpy-only block reads that file without mfp_mapper), and
localization.md's hand-written settings table matches the settings schema."""

from __future__ import annotations

import re
import runpy
from pathlib import Path

import numpy as np
import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "mapfiles.md"


def _python_block(containing: str) -> str:
    blocks = re.findall(r"```python\n(.*?)```", PAGE.read_text(encoding="utf-8"), re.S)
    found = [b for b in blocks if containing in b]
    assert len(found) == 1, f"one python block of {PAGE.name} should contain {containing!r}"
    return found[0]


def test_python_api_and_numpy_examples_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    api = tmp_path / "api_example.py"
    api.write_text(_python_block("save_map(m,"), encoding="utf-8")
    api_globals = runpy.run_path(str(api))
    assert (tmp_path / "map.npz").is_file()
    assert "[ True]" in capsys.readouterr().out  # the queried voxel holds a return
    assert api_globals["m2"].num_voxels == api_globals["m"].num_voxels > 0

    reader = tmp_path / "numpy_example.py"
    reader.write_text(_python_block('np.load("map.npz"'), encoding="utf-8")
    read = runpy.run_path(str(reader))
    stats = api_globals["m"].voxels()
    order_file = np.lexsort(read["ijk"].T)
    order_map = np.lexsort(stats.ijk.T)
    np.testing.assert_allclose(read["centres"][order_file], stats.centers[order_map])
    np.testing.assert_allclose(
        read["most_likely_doo"][order_file], stats.most_likely_doo[order_map], rtol=1e-6
    )


def test_localization_page_lists_every_localization_parameter_and_what_is_fixed() -> None:
    """docs/localization.md's settings table (written by hand) names every ``localization.*``
    parameter of the schema once, marked *(fixed)* exactly when it cannot change at run time."""
    from mfp_mapper.config.schema import SETTINGS

    page = (PAGE.parent / "localization.md").read_text(encoding="utf-8")
    rows = [line for line in page.splitlines() if line.startswith("| `localization.")]
    settings = [s for s in SETTINGS if s.name.startswith("localization.")]
    assert settings
    for setting in settings:
        suffix = setting.name.removeprefix("localization.")
        cells = [row.split(" | ")[0] for row in rows]
        found = [
            row
            for row, names in zip(rows, cells, strict=True)
            if f"`{setting.name}`" in names or f"`.{suffix}`" in names
        ]
        assert len(found) == 1, f"{setting.name}: {len(found)} rows of the table name it"
        assert ("*(fixed)*" in found[0]) == (not setting.dynamic), setting.name
