"""The node never dies on a map file: on every hostile map (test/hostile_maps.py) it logs one
line, starts empty and saves beside ``map_path``, never over it; real nodes over DDS."""

from __future__ import annotations

import math
import os
import re
import stat
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hostile_maps import KINDS
from ros_helpers import Feeder, NodeProcess

from mfp_mapper.config.schema import NodeConfig
from mfp_mapper.mapio.loading import load_map
from mfp_mapper.ros.map_files import initial_mapper


class Recorder:
    """A logger keeping (level, text) of each line."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def __getattr__(self, level: str) -> Any:
        return lambda text, **_: self.lines.append((level, str(text)))


def _entries(root: Path) -> dict[str, tuple[object, ...]]:
    """Every entry under ``root``: type, size and modification time (FIFOs never opened)."""
    out: dict[str, tuple[object, ...]] = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            p = Path(folder) / name
            st = p.lstat()
            body = p.read_bytes() if stat.S_ISREG(st.st_mode) and st.st_size < 1 << 26 else b""
            out[str(p.relative_to(root))] = (
                stat.S_IFMT(st.st_mode),
                st.st_size,
                st.st_mtime_ns,
                body,
            )
    return out


NODE_ACCEPTS = {"directory_as_file"}
"""Kinds the node takes as they are: an empty directory as map_path is a new tiled map,
saved there (README, "Saving the map"); the CLI's commands, which read a map, refuse it."""


@pytest.mark.parametrize("kind", sorted(set(KINDS) - NODE_ACCEPTS))
def test_node_start_on_each_hostile_map(kind: str, tmp_path: Path) -> None:
    src = tmp_path / "in"
    src.mkdir()
    path = KINDS[kind][0](src)
    before = _entries(src)
    log = Recorder()
    cfg = NodeConfig.from_values(  # the files' decay time: their stamps are checked under it
        {"map_path": str(path), "save_on_shutdown": True, "decay_time": 30.0}
    )
    mapper, elsewhere = initial_mapper(cfg, log)
    assert len(log.lines) == 1, log.lines
    level, text = log.lines[0]
    assert level == "error" and "\n" not in text
    assert f"cannot load map_path {str(path)!r}" in text and KINDS[kind][1] in text
    assert "starting an empty map" in text and repr(elsewhere) in text
    assert elsewhere is not None and Path(elsewhere).parent == path.parent
    assert not os.path.lexists(elsewhere)
    assert mapper.num_voxels == 0
    summary = mapper.integrate(np.array([[2.0, 0.0, 0.0]]), np.zeros(3), 1.0)
    assert summary.integrated and mapper.num_voxels > 0  # usable
    assert _entries(src) == before


SERVED = ("index_tile_blocks_1e400", "zip_bomb", "origin_1e15", "future_t_last", "symlink_to_fifo")
"""The kinds the audit saw kill the node (OverflowError, MemoryError) or leave it unusable
(every scan out of bounds, every scan decayed away), and one that would block its start."""


@pytest.fixture()
def hostile(tmp_path: Path) -> Iterator[dict[str, Path]]:
    maps = {}
    for kind in SERVED:
        folder = tmp_path / kind
        folder.mkdir()
        maps[kind] = KINDS[kind][0](folder)
    yield maps


def _call_again(f: Any, client: Any, request: Any, tries: int = 3) -> Any:
    """A service call repeated when its answer does not come within 30 s (idempotent calls
    only): a response sent before the client's reader matched is lost, not late."""
    for attempt in range(tries):
        try:
            return f.call(client, request, timeout=30.0)
        except TimeoutError:
            if attempt == tries - 1:
                raise
    raise AssertionError("unreachable")


def test_nodes_on_hostile_maps_stay_up_and_save_beside_them(
    ros_domain: int, tmp_path: Path, hostile: dict[str, Path]
) -> None:
    from nav_msgs.srv import GetMap
    from std_srvs.srv import Trigger

    before = {k: _entries(p.parent) for k, p in hostile.items()}
    params = {
        "publish_rate": 0.0,
        "save_on_shutdown": True,
        "status_period": 0.5,
        "decay_time": 30.0,
    }
    nodes, feeders = {}, {}
    for k, (kind, path) in enumerate(hostile.items()):
        name = f"mfp_hostile{k}"
        nodes[kind] = NodeProcess(
            ros_domain, {**params, "map_path": str(path)}, tmp_path / f"{kind}.log", name=name
        )
        feeders[kind] = Feeder(node_name=name, feeder_name=f"feeder_hostile{k}")
    saved: dict[str, str] = {}
    try:
        for kind, f in feeders.items():
            ready = lambda f=f: f.save.service_is_ready() and f.get_map.service_is_ready()  # noqa: E731
            assert f.wait(ready, 90.0), nodes[kind].log()
            # a call right after discovery can lose its response in Fast DDS ("failed to send
            # response (timeout): client will not receive response", seen once): ask again
            info = _call_again(f, f.get_map, GetMap.Request()).map.info
            assert (info.width, info.height) == (0, 0)
            answer = f.call(f.save, Trigger.Request(), timeout=60.0)
            assert answer.success, answer.message
            assert "kept as it was" in answer.message and str(hostile[kind]) in answer.message
            found = re.search(r"saved 0 voxels to (\S+)", answer.message)
            assert found is not None, answer.message
            saved[kind] = found.group(1)
            status = f.wait_status(lambda s: "voxels" in s, 10.0)
            assert status is not None and status["voxels"] == 0
            assert nodes[kind].alive()
    finally:
        for f in feeders.values():
            f.destroy()
        codes = {kind: node.stop() for kind, node in nodes.items()}
    for kind, path in hostile.items():
        log = nodes[kind].log()
        assert codes[kind] == 0, log
        assert log.count("cannot load map_path") == 1 and "Traceback" not in log, log
        assert KINDS[kind][1] in log
        other = Path(saved[kind])
        assert other.parent == path.parent and other.is_file()  # saved again on shutdown
        assert load_map(other).num_voxels == 0
        other.unlink()
        assert _entries(path.parent) == before[kind], kind  # the user's file untouched


def test_a_map_of_another_frame_is_relabelled_with_a_warning(tmp_path: Path) -> None:
    """frame_id 'map' and a map saved in 'world' (e.g. by ``replay``): the node relabels the
    map (what the user asked) but says so, once; a map of the same frame is taken silently."""
    from mfp_mapper.core.mapper import Mapper
    from mfp_mapper.mapio.loading import save_map

    mapper = Mapper(0.2, frame_id="world")
    mapper.integrate(np.array([[2.0, 0.0, 0.0]]), np.zeros(3), 1.0)
    save_map(mapper, tmp_path / "w.npz")
    for frame_id, warned in (("map", True), ("world", False), ("", False)):
        log = Recorder()
        values = {"map_path": str(tmp_path / "w.npz"), "frame_id": frame_id, "resolution": 0.2}
        loaded, _ = initial_mapper(NodeConfig.from_values(values), log)
        warnings = [text for level, text in log.lines if level == "warning"]
        assert bool(warnings) == warned, log.lines
        if warned:
            assert "built in frame 'world', parameter frame_id is 'map'" in warnings[0]
        assert loaded.frame_id == (frame_id or "world")


def test_a_static_map_stamped_ahead_is_refused_by_a_decaying_node(tmp_path: Path) -> None:
    """A map saved without decay whose ``t_last`` lies a year ahead, loaded by a node with
    ``decay_time``: the node's decay would make every later scan add nothing, so the file is
    refused with the reason (checked against the node's decay time, not the file's) and the
    node starts an empty map saved beside it (issue 32 item 8)."""
    from hostile_maps import good_arrays

    from mfp_mapper.mapio.mapfile import write_map_arrays

    path = tmp_path / "static.npz"
    ahead = np.full(3, time.time() + 365 * 86400.0)
    write_map_arrays(path, good_arrays(t_last=ahead, decay_time=np.float64(math.inf)))
    for decay, refused in ((0.0, False), (10.0, True)):
        log = Recorder()
        values = {"map_path": str(path), "decay_time": decay, "resolution": 0.1}
        mapper, elsewhere = initial_mapper(NodeConfig.from_values(values), log)
        errors = [text for level, text in log.lines if level == "error"]
        assert bool(errors) == refused and (elsewhere is not None) == refused, log.lines
        assert mapper.num_voxels == (0 if refused else 3)
        if refused:
            assert "decay_time 10 s every later scan would add nothing" in errors[0], errors
