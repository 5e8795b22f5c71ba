"""Hostile map files (test/hostile_maps.py, generated here, never committed) against the
reader and the four commands that read maps: each refuses with one line naming the file
and the problem, exit status 1, no traceback, nothing written and the input untouched."""

from __future__ import annotations

import hashlib
import math
import os
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from hostile_maps import (
    KINDS,
    PARTIAL_READERS,
    QUERY_POINT,
    good_arrays,
    write_legacy_map,
    zip_bomb,
)

from mfp_mapper.cli import main
from mfp_mapper.mapio.checks import (
    EXPANSION_SLACK,
    FUTURE_TOLERANCE_S,
    MAX_EXPANSION,
    MAX_ORIGIN_VOXELS,
)
from mfp_mapper.mapio.loading import load_map, save_map
from mfp_mapper.mapio.mapfile import MapFileError, read_map_arrays, write_map_arrays
from mfp_mapper.mapio.tiles import write_tiled

ROOT = Path(__file__).resolve().parents[2]
QUERY = [str(v) for v in QUERY_POINT]
COMMANDS: dict[str, Callable[[Path, Path, Path], list[str]]] = {
    "query": lambda m, out, good: ["query", str(m), *QUERY],
    "export": lambda m, out, good: ["export", str(m), "-o", str(out / "map.ply")],
    "render": lambda m, out, good: ["render", str(m), "-o", str(out / "render")],
    "merge": lambda m, out, good: ["merge", str(m), str(good), "-o", str(out / "merged.npz")],
    "export_nav2": lambda m, out, good: [
        "export",
        str(m),
        "-o",
        str(out / "map.yaml"),
        "--z-min",
        "-1",
        "--z-max",
        "1",
    ],  # fmt: skip
    "evaluate": lambda m, out, good: ["evaluate", str(m), str(out / "truth.json")],
}
"""The commands that read a map: the audit's four, the Nav2 export and evaluate."""


@pytest.fixture(autouse=True)
def watchdog() -> Iterator[None]:
    """A reader that opened a FIFO would block forever: fail the test after 240 s instead
    (not sooner: a test that integrates a scan first compiles the walk when the numba cache
    is cold, 34-37 s with Jazzy's numba 0.58 on this 2-core machine, past a minute under
    load)."""

    def expire(signum: int, frame: object) -> None:
        raise TimeoutError("the reader blocked (a FIFO opened?)")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(240)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def snapshot(root: Path) -> dict[str, tuple[object, ...]]:
    """Every entry under ``root`` (symlinks not followed, FIFOs never opened): type, size,
    modification time, target or content hash."""
    out: dict[str, tuple[object, ...]] = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            p = Path(folder) / name
            st = p.lstat()
            key = str(p.relative_to(root))
            if stat.S_ISREG(st.st_mode):
                digest = hashlib.sha256(p.read_bytes()).hexdigest() if st.st_size < 1 << 30 else ""
                out[key] = ("file", st.st_size, st.st_mtime_ns, digest)
            elif stat.S_ISLNK(st.st_mode):
                out[key] = ("link", os.readlink(p))
            else:
                out[key] = (stat.S_IFMT(st.st_mode), st.st_mtime_ns)
    return out


def _build(kind: str, tmp_path: Path) -> tuple[Path, Path]:
    src = tmp_path / "in"
    src.mkdir()
    return KINDS[kind][0](src), src


def test_the_corpus_has_the_audits_kinds() -> None:
    """At least the 27 kinds the audit names or implies, each with its expected reason."""
    assert len(KINDS) >= 27
    assert all(words for _, words in KINDS.values())


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_the_reader_refuses_each_kind_naming_the_problem(kind: str, tmp_path: Path) -> None:
    path, src = _build(kind, tmp_path)
    before = snapshot(src)
    with pytest.raises(MapFileError) as err:
        load_map(path)
    assert KINDS[kind][1] in str(err.value)
    assert str(path) in str(err.value)
    assert "\n" not in str(err.value)
    assert snapshot(src) == before


@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("kind", sorted(KINDS))
def test_every_command_refuses_each_kind_in_one_line(
    kind: str, command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, src = _build(kind, tmp_path)
    good = tmp_path / "good.npz"
    write_map_arrays(good, good_arrays())
    out = tmp_path / "out"
    out.mkdir()
    before = snapshot(src)
    rc = main(COMMANDS[command](path, out, good))
    captured = capsys.readouterr()
    if PARTIAL_READERS.get(kind) == command:  # the damage lies in blocks it never reads
        assert rc == 0 and captured.err == "", captured
        assert snapshot(src) == before
        return
    lines = captured.err.splitlines()
    assert rc == 1, captured
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("mfp-mapper: error: "), captured.err
    assert KINDS[kind][1] in lines[0], captured.err
    assert captured.out == ""
    assert snapshot(src) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.npz", "in", "out"]
    assert list(out.iterdir()) == []  # nothing written, no scratch folder left


@pytest.mark.parametrize("tiled", [False, True], ids=["npz", "tiled"])
@pytest.mark.parametrize("command", sorted(set(COMMANDS) - {"evaluate"}))  # needs a truth
def test_the_corpus_base_map_is_accepted_by_every_command(
    command: str, tiled: bool, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The maps the kinds are made from are fine: each refusal is the damage's doing."""
    path = tmp_path / ("tiled" if tiled else "map.npz")
    if tiled:
        write_tiled(path, good_arrays(), tile_blocks=1)
    else:
        write_map_arrays(path, good_arrays())
    good = tmp_path / "good.npz"
    write_map_arrays(good, good_arrays(ijk=np.array([[0, 0, 0], [2, 0, 0], [3, 0, 0]])))
    out = tmp_path / "out"
    out.mkdir()
    rc = main(COMMANDS[command](path, out, good))
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert captured.out.strip()


@pytest.mark.parametrize("kind", ["index_tile_blocks_1e400", "zip_bomb", "origin_1e15"])
def test_the_installed_command_prints_no_traceback(kind: str, tmp_path: Path) -> None:
    """Through a real process, as a user types it: one line on stderr, exit status 1."""
    path, _ = _build(kind, tmp_path)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for argv in (["query", str(path), *QUERY], ["export", str(path), "-o", "x.ply"]):
        proc = subprocess.run(
            [sys.executable, "-m", "mfp_mapper.cli", *argv],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert proc.returncode == 1, proc.stderr
        assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
        assert KINDS[kind][1] in proc.stderr


def test_the_zip_bomb_is_an_honest_archive(tmp_path: Path) -> None:
    """The same construction at 10^5 voxels (3.6 MB, under the slack) is read whole, CRCs
    checked: the 3.6 GB one is refused for its size, not for damage."""
    path = zip_bomb(tmp_path, count=10**5)
    with pytest.raises(MapFileError, match="more than once"):  # all voxels (0, 0, 0)
        read_map_arrays(path)


def test_expansion_limit_leaves_room_for_real_maps(tmp_path: Path) -> None:
    """A map of a real-looking scene declares a few bytes per byte of file; constant
    arrays (a foreign writer's zeros) compress far more and stay within the slack."""
    from box_world import anchors_scene

    from mfp_mapper import Mapper

    m = Mapper(0.1, decay_time=30.0)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=3, azimuths=300)):
        m.integrate(points, origin, 100.0 + k)
    save_map(m, tmp_path / "real.npz")
    declared = 36 * m.num_voxels
    assert declared / (tmp_path / "real.npz").stat().st_size < MAX_EXPANSION / 8
    count = EXPANSION_SLACK // 36 // 2  # about 0.9 million voxels of zeros
    ijk = np.stack(np.unravel_index(np.arange(count), (256, 256, 256)), axis=1)
    flat = good_arrays(ijk=ijk.astype(np.int32), s=np.ones(count), n=np.zeros(count),
                       t_last=np.zeros(count))  # fmt: skip
    write_map_arrays(tmp_path / "flat.npz", flat)
    assert read_map_arrays(tmp_path / "flat.npz")["s"].shape == (count,)


def test_far_but_honest_origins_and_stamps_are_accepted(tmp_path: Path) -> None:
    """The limits refuse damage, not maps: a UTM origin, stamps within the tolerance of the
    file's time, and any stamp on a static map (nothing decays)."""
    now = time.time()
    cases = {
        "utm.npz": good_arrays(origin=np.array([512_345.6, 5_412_345.7, 250.0])),
        "edge.npz": good_arrays(origin=np.array([MAX_ORIGIN_VOXELS * 0.1 * 0.99, 0.0, 0.0])),
        "skew.npz": good_arrays(t_last=np.full(3, now + FUTURE_TOLERANCE_S / 2)),
        "static.npz": good_arrays(t_last=np.full(3, now + 1e9), decay_time=np.float64(math.inf)),
    }
    for name, arrays in cases.items():
        write_map_arrays(tmp_path / name, arrays)
        assert load_map(tmp_path / name).num_voxels == 3, name


def test_a_stale_modification_time_is_the_stated_remedy(tmp_path: Path) -> None:
    """A file whose stamps are right but whose modification time is older (copied with an
    old date) loads once touched, as the refusal says."""
    path = tmp_path / "map.npz"
    write_map_arrays(path, good_arrays(t_last=np.full(3, 2e9)))
    os.utime(path, (1.5e9, 1.5e9))
    with pytest.raises(MapFileError, match="touch"):
        load_map(path)
    os.utime(path, (2e9, 2e9))
    assert load_map(path).num_voxels == 3


def test_export_never_writes_infinite_coordinates(tmp_path: Path) -> None:
    """A map built in memory (no file check) with an origin beyond float32's range: the PLY
    export refuses it rather than write infinite coordinates, and leaves no file."""
    from mfp_mapper.core.mapper import Mapper
    from mfp_mapper.core.store import VoxelArrays
    from mfp_mapper.outputs.export import export_ply

    voxels = VoxelArrays(np.zeros((1, 3), np.int32), np.ones(1), np.ones(1), np.zeros(1))
    far = Mapper.from_arrays(voxels, resolution=0.1, origin=(1e39, 0.0, 0.0))
    with pytest.raises(ValueError, match="beyond float32"):
        export_ply(far, tmp_path / "far.ply")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("writer", ["version2-deflated", "version2-stored", "version3"])
def test_random_damage_is_refused_or_loaded_never_raised(writer: str, tmp_path: Path) -> None:
    """300 seeded random damages of a map file (bytes flipped, cut, zeroed) and of a tiled
    map's index: each loads or raises MapFileError, never another exception."""
    import random

    rng = random.Random(21)
    base = tmp_path / "base.npz"
    if writer == "version3":
        write_map_arrays(base, good_arrays())
    else:
        write_legacy_map(base, good_arrays(), compress=writer.endswith("deflated"))
    data = base.read_bytes()
    tiled = tmp_path / "tiled"
    write_tiled(tiled, good_arrays(), tile_blocks=1)
    index = (tiled / "index.json").read_text()
    outcomes = {"loaded": 0, "refused": 0}
    for k in range(300):
        on_index = k % 3 == 2
        raw = bytearray(index.encode() if on_index else data)
        kind = rng.choice(["flip", "cut", "zero", "digit"])
        at = rng.randrange(len(raw))
        if kind == "flip":
            for _ in range(rng.randint(1, 4)):
                raw[rng.randrange(len(raw))] ^= 1 << rng.randrange(8)
        elif kind == "cut":
            del raw[at:]
        elif kind == "zero":
            raw[at : at + rng.randint(1, 64)] = bytes(min(64, len(raw) - at))
        else:  # a digit changed into another or into 'e9' (numbers in headers and JSON)
            digits = [i for i, c in enumerate(raw) if chr(c).isdigit()]
            i = rng.choice(digits)
            raw[i : i + 1] = rng.choice([b"e9", b"9", b"-", b"e400", b"0"])
        if on_index:
            (tiled / "index.json").write_bytes(bytes(raw))
            target = tiled
        else:
            target = tmp_path / f"damaged{k}.npz"
            target.write_bytes(bytes(raw))
        try:
            load_map(target)
            outcomes["loaded"] += 1
        except MapFileError as err:
            assert "\n" not in str(err)
            outcomes["refused"] += 1
    (tiled / "index.json").write_text(index)
    assert outcomes["refused"] > 100, outcomes


def test_stamps_are_checked_under_the_decay_that_will_apply(tmp_path: Path) -> None:
    """A file's times are checked against the settings that will decay it (issue 32 item 8):
    a static file stamped a year ahead is refused by a reader that decays it (every later
    scan would add nothing), and a decaying one is taken by a reader that never decays."""
    ahead = time.time() + 365 * 86400.0
    static = tmp_path / "static.npz"
    write_map_arrays(static, good_arrays(t_last=np.full(3, ahead), decay_time=np.float64(math.inf)))
    assert load_map(static).num_voxels == 3
    with pytest.raises(MapFileError, match="decay_time 10 s"):
        load_map(static, decay_time=10.0)
    decaying = tmp_path / "decaying.npz"
    write_map_arrays(decaying, good_arrays(t_last=np.full(3, ahead)))
    with pytest.raises(MapFileError, match="after the file was written"):
        load_map(decaying)
    assert load_map(decaying, decay_time=math.inf).num_voxels == 3
    tiled = tmp_path / "tiled"
    save_map(load_map(static), tiled)
    assert load_map(tiled).num_voxels == 3
    with pytest.raises(MapFileError, match="decay_time 10 s"):
        load_map(tiled, decay_time=10.0)
