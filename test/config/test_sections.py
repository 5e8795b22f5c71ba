"""The settings sections are the one definition of every setting: no setting is typed in two
settings classes of the package, and every section field is a complete setting."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

from mfp_mapper.config.sections import SECTIONS, MapSection, SensorModelSection
from mfp_mapper.config.setting import Section, setting

PACKAGE = Path(__file__).resolve().parents[2] / "mfp_mapper"

SETTINGS_CLASS_SUFFIXES = ("Settings", "Section", "Options", "Config")
"""A dataclass named so holds settings (``NodeConfig``, ``ReplayOptions``, ``LiveSettings``...)."""

NOT_SETTINGS = {
    "AlignOptions": "the core's alignment options (core knows nothing of the node's settings); "
    "mapping.live_localization.align_options sets them from the localization section",
    "SimulationConfig": "what the simulator writes into a recording (its topics, its lidar "
    "mounting), not how the mapper reads one",
}
"""Dataclasses named like settings classes that are not: with why."""


def _dataclasses() -> dict[str, tuple[str, list[str]]]:
    """Class name -> (module path, annotated field names) of every dataclass in the package."""
    found: dict[str, tuple[str, list[str]]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.ClassDef):
                continue
            if not any("dataclass" in ast.unparse(d) for d in node.decorator_list):
                continue
            names = [
                st.target.id
                for st in node.body
                if isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name)
            ]
            assert node.name not in found, f"two dataclasses named {node.name}"
            found[node.name] = (str(path.relative_to(PACKAGE.parent)), names)
    return found


def _typed_twice(classes: dict[str, tuple[str, list[str]]]) -> dict[str, list[str]]:
    """Setting field name -> the settings classes declaring it, where more than one does."""
    setting_fields = {s.field for section in SECTIONS for s in section.settings()}
    where: dict[str, list[str]] = {}
    for name, (module, fields) in classes.items():
        if not name.endswith(SETTINGS_CLASS_SUFFIXES) or name in NOT_SETTINGS:
            continue
        for field in fields:
            if field in setting_fields:
                where.setdefault(field, []).append(f"{module}:{name}")
    return {field: places for field, places in where.items() if len(places) > 1}


def test_no_setting_is_typed_in_two_settings_classes() -> None:
    classes = _dataclasses()
    assert set(NOT_SETTINGS) <= set(classes), "NOT_SETTINGS names a class that is gone"
    assert {cls.__name__ for cls in SECTIONS} <= set(classes)  # the walk sees the sections
    twice = _typed_twice(classes)
    assert not twice, f"settings typed in more than one settings class: {twice}"


def test_a_setting_typed_again_is_found() -> None:
    """The check above can fail: a class like the former ``LiveSettings`` is caught."""
    classes = _dataclasses()
    classes["LiveSettings"] = ("mfp_mapper/mapping/live.py", ["deskew", "odom_wait"])
    assert set(_typed_twice(classes)) == {"deskew", "odom_wait"}


def test_every_section_field_is_a_setting_named_after_its_field() -> None:
    keys = [section.KEY for section in SECTIONS]
    assert len(keys) == len(set(keys)) and all(keys)
    for section in SECTIONS:
        assert dataclasses.is_dataclass(section) and section.__dataclass_params__.frozen  # type: ignore[attr-defined]
        for s, f in zip(section.settings(), dataclasses.fields(section), strict=True):
            assert s.field == f.name and s.section == section.KEY
            assert s.name.removeprefix(section.PREFIX).replace(".", "_") == f.name
            assert s.held(s.default) == f.default, s.name


def test_a_field_not_named_after_its_setting_is_refused() -> None:
    @dataclasses.dataclass(frozen=True)
    class Misnamed(Section):
        KEY = "misnamed"

        max_gap: float = setting(0.5, "Named otherwise than its setting.", name="odom_max_gap")

    with pytest.raises(TypeError, match="must be named after odom_max_gap"):
        Misnamed.settings()


def test_core_values_apply_no_limit() -> None:
    import math

    assert math.isinf(SensorModelSection(max_range=-1.0).core("max_range"))
    assert SensorModelSection(max_range=20.0).core("max_range") == 20.0
    assert MapSection(max_voxels=0).core("max_voxels") is None
    assert math.isinf(MapSection().core("decay_time"))
