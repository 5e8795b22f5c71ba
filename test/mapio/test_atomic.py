"""Atomic writes: umask permissions, symlinks kept, temporary files of interrupted writes."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from mfp_mapper.mapio.atomic import (
    TEMP_SUFFIX,
    atomic_output,
    remove_stale_temp_files,
    write_text_atomic,
)


def test_new_files_follow_the_umask(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        write_text_atomic(tmp_path / "a.txt", "x")
        os.umask(0o077)
        write_text_atomic(tmp_path / "b.txt", "x")
    finally:
        os.umask(old)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "b.txt").stat().st_mode & 0o777 == 0o600


def test_an_existing_file_keeps_its_mode(tmp_path: Path) -> None:
    path = tmp_path / "a.txt"
    path.write_text("old")
    path.chmod(0o640)
    write_text_atomic(path, "new")
    assert path.read_text() == "new" and path.stat().st_mode & 0o777 == 0o640


def test_writing_through_a_symlink_replaces_the_target(tmp_path: Path) -> None:
    real = tmp_path / "store" / "map.txt"
    real.parent.mkdir()
    real.write_text("old")
    link = tmp_path / "current.txt"
    link.symlink_to(real)
    write_text_atomic(link, "new")
    assert link.is_symlink() and link.resolve() == real.resolve()
    assert real.read_text() == "new"


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "a.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError), atomic_output(path) as f:
        f.write(b"half")
        raise RuntimeError("interrupted")
    assert path.read_text() == "old"
    assert list(tmp_path.iterdir()) == [path]


def _killed_writer_leaves(tmp_path: Path) -> Path:
    """A process killed in the middle of a write (SIGKILL: no cleanup) and its temp file."""
    code = (
        "import os, sys\n"
        "from mfp_mapper.mapio.atomic import atomic_output\n"
        "with atomic_output(sys.argv[1]) as f:\n"
        "    f.write(b'half'); f.flush(); os.kill(os.getpid(), 9)\n"
    )
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "map.npz")], check=False)
    left = list(tmp_path.glob(f"*{TEMP_SUFFIX}"))
    assert len(left) == 1 and left[0].name.startswith(".map.npz.")
    return left[0]


def test_the_next_write_removes_temporaries_of_killed_writes(tmp_path: Path) -> None:
    _killed_writer_leaves(tmp_path)
    write_text_atomic(tmp_path / "map.npz", "whole")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.npz"]


def test_sweep_at_start_keeps_writes_in_progress(tmp_path: Path) -> None:
    stale = _killed_writer_leaves(tmp_path)
    foreign = tmp_path / f".notes.txt.x{TEMP_SUFFIX}"  # not a name atomic_output makes
    foreign.write_text("keep")
    with atomic_output(tmp_path / "other.txt") as f:
        f.write(b"in progress")
        assert remove_stale_temp_files(tmp_path) == [stale]
        assert len(list(tmp_path.glob(f".other.txt.*{TEMP_SUFFIX}"))) == 1
    assert foreign.exists() and (tmp_path / "other.txt").read_bytes() == b"in progress"
