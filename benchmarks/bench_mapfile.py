"""Map-file benchmark: save and load of a 10 M-voxel map against numpy on the same arrays.

Builds a map of ``--voxels`` observed voxels (a dense box of them, random statistics and
times, so every block holds voxels of several times), then times, in one run:

* numpy reading the file's arrays (``np.load`` and every array read): the baseline;
* ``Mapper.load`` (read, check headers and values, find duplicates, fill the store);
* ``Mapper.save`` (deflate level 1) and the node's save (``~/save_map``, the autosave and
  the save at shutdown: a snapshot of the map, then stored uncompressed), and, for
  comparison, numpy writing the same arrays (``np.savez``, uncompressed);
* ``Mapper.query`` of a few points after the load;
* what a user runs on such a map: ``export`` (PLY of the voxels with DoO >= 0.1, the Nav2
  map) and ``render`` (the pictures), each as a ratio to numpy's read.

    python benchmarks/bench_mapfile.py             # 10 M voxels
    python benchmarks/bench_mapfile.py --voxels 30e6 --repeat 1
    python benchmarks/bench_mapfile.py --voxels 1e6
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from mfp_mapper.mapio.loading import load_map, save_map  # noqa: E402


def _timed(fn):  # type: ignore[no-untyped-def]
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def _numpy_read(path: Path) -> int:
    with np.load(path, allow_pickle=False) as f:
        return sum(f[k].nbytes for k in f.files)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--voxels", type=float, default=10e6)
    parser.add_argument("--repeat", type=int, default=2, help="best of this many runs")
    args = parser.parse_args()
    from mfp_mapper import Mapper
    from mfp_mapper.core.store import VoxelArrays
    from mfp_mapper.mapio.mapfile import map_arrays, write_map_arrays

    count = int(args.voxels)
    side = round(count ** (1 / 3))
    grid = np.stack(np.meshgrid(*(np.arange(side),) * 3, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(0)
    ijk = (grid - side // 2).astype(np.int32)
    rng.shuffle(ijk)
    n_vox = len(ijk)
    voxels = VoxelArrays(
        ijk, rng.uniform(0.01, 5.0, n_vox), rng.integers(0, 5, n_vox).astype(np.float64),
        rng.uniform(90.0, 100.0, n_vox),
    )  # fmt: skip
    mapper = Mapper.from_arrays(voxels, resolution=0.1, decay_time=600.0)
    with tempfile.TemporaryDirectory() as tmp:
        path, plain = Path(tmp) / "map.npz", Path(tmp) / "plain.npz"
        stored = Path(tmp) / "stored.npz"
        arrays = {"ijk": ijk, "s": voxels.s, "n": voxels.n, "t_last": voxels.t_last}

        def node_save() -> None:  # what the node does: snapshot, then write stored
            write_map_arrays(stored, map_arrays(mapper), compress=False)

        save, np_save, node, snap = [], [], [], []
        for _ in range(args.repeat):  # interleaved
            save.append(_timed(lambda: save_map(mapper, path))[0])
            np_save.append(_timed(lambda: np.savez(plain, **arrays))[0])
            node.append(_timed(node_save)[0])
            snap.append(_timed(lambda: map_arrays(mapper))[0])
        np_read, load, node_load = [], [], []
        for _ in range(args.repeat):
            np_read.append(_timed(lambda: _numpy_read(stored))[0])
            load.append(_timed(lambda: load_map(path))[0])
            node_load.append(_timed(lambda: load_map(stored))[0])
        save, np_save, node_s, snap = min(save), min(np_save), min(node), min(snap)
        np_read, load, node_load = min(np_read), min(load), min(node_load)
        loaded = load_map(path)
        points = (rng.uniform(-side / 2, side / 2, (10, 3)) + 0.5) * 0.1
        loaded.query(points)  # compiles nothing new; first-call overhead excluded
        query = min(_timed(lambda: loaded.query(points))[0] for _ in range(5))
        size, stored_size = path.stat().st_size, stored.stat().st_size
        from mfp_mapper.outputs.export import export_ply
        from mfp_mapper.outputs.nav2_map import write_nav2_map
        from mfp_mapper.outputs.render import render_map

        ply = _timed(lambda: export_ply(loaded, Path(tmp) / "map.ply", min_doo=0.1))[0]
        nav2 = _timed(lambda: write_nav2_map(loaded, Path(tmp) / "nav.yaml", -1.0, 1.0))[0]
        render = _timed(lambda: render_map(loaded, Path(tmp) / "pictures"))[0]
    print(
        f"map of {mapper.num_voxels / 1e6:.2f} M voxels: {size / 1e6:.0f} MB (deflate 1), "
        f"{stored_size / 1e6:.0f} MB (stored)"
    )
    print(f"  numpy read of its arrays  {np_read:7.3f} s   1.00x")
    print(f"  Mapper.load (stored)      {node_load:7.3f} s   {node_load / np_read:.2f}x numpy read")
    print(f"  Mapper.load (deflate 1)   {load:7.3f} s   {load / np_read:.2f}x numpy read")
    print(f"  np.savez (uncompressed)   {np_save:7.3f} s   1.00x")
    print(f"  node save (stored)        {node_s:7.3f} s   {node_s / np_save:.2f}x np.savez")
    print(f"    of which the snapshot   {snap:7.3f} s   {snap / np_save:.2f}x np.savez")
    print(f"  Mapper.save (deflate 1)   {save:7.3f} s   {save / np_save:.2f}x np.savez")
    print(f"  query of 10 points        {query * 1e3:7.3f} ms  {query / np_read:.2e}x numpy read")
    print(f"  export PLY (DoO >= 0.1)   {ply:7.3f} s   {ply / np_read:.2f}x numpy read")
    print(f"  export Nav2 map           {nav2:7.3f} s   {nav2 / np_read:.2f}x numpy read")
    print(f"  render (all pictures)     {render:7.3f} s   {render / np_read:.2f}x numpy read")


if __name__ == "__main__":
    main()
