"""Map-file benchmark: size, save, load and queries of map files against numpy, one run.

For a real map (the 14 norlab scans, or the 3 ouster_street scans, at ``--resolution``; or
a map file given with ``--map``) and a synthetic one of ``--voxels`` voxels (a box filled
at 70%, 2% of voxels with returns, random statistics and times), the same voxels are
written and read in the same run by

* numpy, the baseline: ``np.save`` of ``ijk`` int32 and ``s``, ``n``, ``t_last`` float64
  (36 bytes a voxel) one after the other into one file, and ``np.savez`` (uncompressed) of
  the same arrays; read back with ``np.load``;
* ``save_map`` (a version 4 file: the blocks packed from the store, written, fsynced,
  renamed) and the node's save (``map_blocks`` under the lock, then ``write_map_path``);
  ``load_map`` (read, CRCs and values checked, blocks set in the store);
* ``mfp-mapper query`` as it runs (``MapFileQueries``: open the file, read the blocks of
  10 points, answer; and 100 segments of 20 m), against numpy's read of the voxel arrays
  (with ``--histograms``, the synthetic map's voxels with returns hold reflectivity
  histograms of 8 bins, as replay's default keeps for clouds with an intensity field);
  and the command as a process (the ``mfp-mapper`` console script beside this Python, as
  docs/cli.md has a user type it) against a Python process reading them with numpy.

Reads find the file in the page cache (it was just written), as numpy's do. Every timed
write starts after ``os.sync()`` (a save's fsync would otherwise wait for the previous
writes' dirty pages) and replaces the file its previous round wrote (as a node saving
over its map does; numpy's ``open(..., "wb")`` truncates it), in another order each
round: over four rounds each write comes right after each other one once
(``balanced_order``; in a fixed order the node's save, timed right after ``np.savez``
had written 600 MB, measured 2-3x ``save_map``, the same code). Times are the best of
``--repeat`` interleaved rounds.

    python benchmarks/bench_mapfile.py                       # norlab + 30 M synthetic voxels
    python benchmarks/bench_mapfile.py --voxels 1e6 --scene none
    python benchmarks/bench_mapfile.py --map street.npz --voxels 0
    python benchmarks/bench_mapfile.py --voxels 9.6e6 --scene none --histograms
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "test"), str(ROOT / "benchmarks")]

from mfp_mapper import Mapper  # noqa: E402
from mfp_mapper.core.store import VoxelArrays  # noqa: E402
from mfp_mapper.mapio.loading import load_map, save_map  # noqa: E402
from mfp_mapper.mapio.mapfile import (  # noqa: E402
    map_blocks,
    mapper_from_contents,
    read_map_file,
)
from mfp_mapper.mapio.queries import MapFileQueries  # noqa: E402
from mfp_mapper.mapio.tiles import write_map_path  # noqa: E402


def _timed(fn):  # type: ignore[no-untyped-def]
    os.sync()  # every write starts with no dirty pages of the previous one (fsync waits)
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def balanced_order(names: list[str], round_: int) -> list[str]:
    """``names`` in the order of row ``round_`` of a Williams square (an even count of
    names): over as many rounds as names, each comes right after each other one once."""
    count = len(names)
    first = [0] + [(k + 1) // 2 if k % 2 else count - k // 2 for k in range(1, count)]
    return [names[(i + round_) % count] for i in first]


def synthetic(count: int, seed: int = 0, histograms: bool = False) -> Mapper:
    """A box filled at 70% with ``count`` voxels, 2% with returns, times 90-100 s; with
    ``histograms``, each voxel with returns holds a reflectivity histogram of 8 bins."""
    rng = np.random.default_rng(seed)
    side = round((count / 0.7) ** (1 / 3))
    axis = np.arange(side, dtype=np.int32) - side // 2
    ijk = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    ijk = ijk[rng.random(ijk.shape[0]) < count / ijk.shape[0]]
    k = ijk.shape[0]
    n = np.where(rng.random(k) < 0.02, rng.integers(1, 5, k), 0).astype(np.float64)
    voxels = VoxelArrays(ijk, rng.uniform(0.01, 5.0, k), n, rng.uniform(90.0, 100.0, k))
    table = None
    if histograms:
        from mfp_mapper.core.reflectivity import ReflectivityArrays
        from mfp_mapper.sensing.reflectivity import bins_for

        bins = bins_for("reflectivity", 8)
        assert bins is not None
        hit = n > 0
        counts = rng.multinomial(n[hit].astype(np.int64), np.full(8, 1 / 8)).astype(np.float64)
        table = ReflectivityArrays(bins, ijk[hit], counts, np.full(int(hit.sum()), 100.0))
    return Mapper.from_arrays(voxels, resolution=0.1, decay_time=600.0, reflectivity=table)


def real(scene: str, resolution: float) -> Mapper:
    from bench_core import _scene

    mapper = Mapper(resolution, max_range=100.0)
    for k, (points, origin) in enumerate(_scene(scene)):
        mapper.integrate(points, origin, float(k) * 0.1)
    mapper.close()
    return mapper


def numpy_save(path: Path, a: VoxelArrays) -> None:
    with open(path, "wb") as f:
        for arr in (a.ijk, a.s, a.n, a.t_last):
            np.save(f, arr)


def numpy_read(path: Path) -> int:
    with open(path, "rb") as f:
        return sum(np.load(f).nbytes for _ in range(4))


def numpy_load_npz(path: Path) -> int:
    with np.load(path, allow_pickle=False) as f:
        return sum(f[k].nbytes for k in f.files)


def run(name: str, mapper: Mapper, repeat: int, tmp: Path) -> None:
    voxels = mapper.stored_voxels()
    ijk = voxels.ijk
    v64 = VoxelArrays(ijk, voxels.s.astype(np.float64), voxels.n, voxels.t_last)
    path, node_path = tmp / "map.npz", tmp / "node.npz"
    np_path, npz_path = tmp / "numpy.npy", tmp / "numpy.npz"
    arrays = {"ijk": ijk, "s": v64.s, "n": v64.n, "t_last": v64.t_last}

    def node_save() -> None:  # the node: snapshot under its lock, write outside it
        write_map_path(node_path, map_blocks(mapper))

    writes = {
        "np_save": lambda: numpy_save(np_path, v64),
        "save": lambda: save_map(mapper, path),
        "np_savez": lambda: np.savez(npz_path, **arrays),
        "node": node_save,
    }
    t: dict[str, list[float]] = {k: [] for k in (*writes, "snap")}
    for round_ in range(repeat):  # interleaved, each round in another order
        for key in balanced_order(list(writes), round_):
            t[key].append(_timed(writes[key])[0])
        t["snap"].append(_timed(lambda: map_blocks(mapper))[0])
    keys = ("np_read", "np_npz", "load", "read", "fill", "q_pts", "q_seg")
    r: dict[str, list[float]] = {k: [] for k in keys}
    rng = np.random.default_rng(1)
    centre = (ijk.mean(axis=0) + 0.5) * mapper.resolution + np.asarray(mapper.origin or (0, 0, 0))
    points = centre + rng.normal(scale=5.0, size=(10, 3))
    starts = centre + rng.normal(scale=5.0, size=(100, 3))
    d = rng.normal(size=(100, 3))
    ends = starts + 20.0 * d / np.linalg.norm(d, axis=1)[:, None]
    for _ in range(repeat):
        r["np_read"].append(_timed(lambda: numpy_read(np_path))[0])
        r["np_npz"].append(_timed(lambda: numpy_load_npz(npz_path))[0])
        r["load"].append(_timed(lambda: load_map(path))[0])
        seconds, contents = _timed(lambda: read_map_file(path))
        r["read"].append(seconds)
        r["fill"].append(_timed(lambda c=contents: mapper_from_contents(c, path))[0])
        r["q_pts"].append(_timed(lambda: MapFileQueries(path).query(points))[0])
        r["q_seg"].append(_timed(lambda: MapFileQueries(path).query_segments(starts, ends))[0])
    launcher = Path(sys.executable).parent / "mfp-mapper"  # the console script docs/cli.md uses
    cli = [str(launcher)] if launcher.exists() else [sys.executable, "-m", "mfp_mapper.cli"]
    cli += ["query", str(path)]
    cli += [f"{v:.3f}" for v in points.ravel()]
    reader = f"import numpy as np; f = open({str(np_path)!r}, 'rb'); [np.load(f) for _ in range(4)]"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for _ in range(repeat):  # whole processes, as a user runs them (imports included)
        r.setdefault("cli", []).append(
            _timed(lambda: subprocess.run(cli, env=env, check=True, capture_output=True))[0]
        )
        r.setdefault("np_proc", []).append(
            _timed(lambda: subprocess.run([sys.executable, "-c", reader], check=True))[0]
        )
    loaded = load_map(path)
    assert loaded.num_voxels == mapper.num_voxels
    expect = mapper.query(points)
    got = MapFileQueries(path).query(points)
    assert np.array_equal(expect.s, got.s) and np.array_equal(expect.n, got.n)
    histograms = mapper.reflectivity(points), MapFileQueries(path).reflectivity(points)
    assert (histograms[0] is None) == (histograms[1] is None)
    if histograms[0] is not None and histograms[1] is not None:
        assert np.array_equal(histograms[0][1], histograms[1][1])
    b = {k: min(v) for k, v in {**t, **r}.items()}
    base_w = min(b["np_save"], b["np_savez"])
    base_r = min(b["np_read"], b["np_npz"])
    count = mapper.num_voxels
    size = path.stat().st_size
    table = mapper.stored_reflectivity()
    held = "" if table is None else f", {len(table)} reflectivity histograms"
    print(f"{name}: {count / 1e6:.2f} M voxels, {mapper.num_blocks} blocks{held}")
    print(f"  file {size / 1e6:8.1f} MB  {size / count:6.2f} bytes/voxel (numpy's arrays: 36)")
    print(f"  np.save (4 arrays)    {b['np_save']:7.3f} s")
    print(f"  np.savez (stored)     {b['np_savez']:7.3f} s")
    print(f"  save_map              {b['save']:7.3f} s   {b['save'] / base_w:5.2f}x numpy write")
    print(f"  node save             {b['node']:7.3f} s   {b['node'] / base_w:5.2f}x numpy write")
    print(f"    of which snapshot   {b['snap']:7.3f} s   {b['snap'] / base_w:5.2f}x numpy write")
    print(f"  np.load (4 arrays)    {b['np_read']:7.3f} s")
    print(f"  np.load (npz)         {b['np_npz']:7.3f} s")
    print(f"  load_map              {b['load']:7.3f} s   {b['load'] / base_r:5.2f}x numpy read")
    print(f"    read and check      {b['read']:7.3f} s   {b['read'] / base_r:5.2f}x numpy read")
    print(f"    fill the store      {b['fill']:7.3f} s   {b['fill'] / base_r:5.2f}x numpy read")
    print(f"  (the store: {mapper.memory_bytes / count:.1f} bytes/voxel in memory)")
    print(f"  query 10 points       {b['q_pts']:7.3f} s   {b['q_pts'] / base_r:5.3f}x numpy read")
    print(f"  query 100 segments    {b['q_seg']:7.3f} s   {b['q_seg'] / base_r:5.3f}x numpy read")
    print(f"  process: numpy read   {b['np_proc']:7.3f} s   (python -c: imports and np.load)")
    print(f"  process: query        {b['cli']:7.3f} s   {b['cli'] / b['np_proc']:5.2f}x numpy read"
          " (mfp-mapper query, 10 points)")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--voxels", type=float, default=30e6, help="synthetic map (0: none)")
    parser.add_argument(
        "--scene", default="norlab_sequence", choices=["norlab_sequence", "ouster_street", "none"]
    )
    parser.add_argument("--resolution", type=float, default=0.1)
    parser.add_argument("--map", type=Path, help="a map file to measure instead of the scene")
    parser.add_argument("--repeat", type=int, default=2, help="best of this many (interleaved)")
    parser.add_argument(
        "--histograms", action="store_true", help="synthetic map: reflectivity histograms"
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        if args.map is not None:
            run(str(args.map), load_map(args.map), args.repeat, Path(tmp))
        elif args.scene != "none":
            data = ROOT.parent / "shared" / "data" / args.scene
            if data.is_dir():
                run(f"{args.scene} at {args.resolution:g} m", real(args.scene, args.resolution),
                    args.repeat, Path(tmp))  # fmt: skip
            else:
                print(f"{args.scene}: skipped ({data} is absent)")
        if args.voxels > 0:
            run("synthetic", synthetic(int(args.voxels), histograms=args.histograms),
                args.repeat, Path(tmp))  # fmt: skip


if __name__ == "__main__":
    main()
