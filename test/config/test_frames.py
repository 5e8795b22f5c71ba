"""Frame ids (config.frames): tf1's leading slash is dropped in one place."""

from __future__ import annotations

from pathlib import Path

from mfp_mapper.config.frames import frame_name

PACKAGE = Path(__file__).resolve().parents[2] / "mfp_mapper"


def test_frame_name_drops_leading_slashes_only() -> None:
    assert frame_name("/base_link") == "base_link"
    assert frame_name("//odom") == "odom"
    assert frame_name("os_sensor/lidar") == "os_sensor/lidar"
    assert frame_name("") == ""


def test_no_module_strips_a_frame_id_itself() -> None:
    own = PACKAGE / "config" / "frames.py"
    inline = [
        str(path.relative_to(PACKAGE))
        for path in PACKAGE.rglob("*.py")
        if path != own and ('lstrip("/")' in path.read_text() or "lstrip('/')" in path.read_text())
    ]
    assert not inline, f"strip frame ids with config.frames.frame_name: {inline}"
