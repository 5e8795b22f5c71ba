"""PLY export: header, properties and values readable back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mfp_mapper.core import model
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.outputs.export import PLY_PROPERTIES, export_ply, read_ply


@pytest.fixture
def mapper() -> Mapper:
    m = Mapper(0.5, frame_id="odom")
    rng = np.random.default_rng(0)
    pts = rng.uniform([2, -2, 0], [6, 2, 2], (500, 3))
    m.integrate(pts, np.zeros(3), 1.0)
    return m


def test_ply_header_is_binary_little_endian_with_the_properties(
    mapper: Mapper, tmp_path: Path
) -> None:
    path = tmp_path / "map.ply"
    count = export_ply(mapper, path)
    raw = path.read_bytes()
    header = raw[: raw.index(b"end_header\n")].decode("ascii").splitlines()
    assert header[0] == "ply" and header[1] == "format binary_little_endian 1.0"
    assert f"element vertex {count}" in header
    props = [line.split()[2] for line in header if line.startswith("property")]
    assert props == list(PLY_PROPERTIES)
    assert all(line.startswith("property float ") for line in header if "property" in line)
    body = len(raw) - raw.index(b"end_header\n") - len("end_header\n")
    assert body == count * 4 * len(PLY_PROPERTIES)


def test_ply_values_read_back(mapper: Mapper, tmp_path: Path) -> None:
    path = tmp_path / "map.ply"
    count = export_ply(mapper, path)
    vox = mapper.voxels()
    assert count == int(vox.observed.sum())
    ply = read_ply(path)
    order = np.lexsort((ply["z"], ply["y"], ply["x"]))
    ref = np.lexsort((vox.centers[:, 2], vox.centers[:, 1], vox.centers[:, 0]))
    np.testing.assert_allclose(ply["x"][order], vox.centers[ref, 0], atol=1e-5)
    np.testing.assert_allclose(ply["s"][order], vox.s[ref], rtol=1e-6)
    np.testing.assert_allclose(ply["n"][order], vox.n[ref])
    np.testing.assert_allclose(
        ply["degree_of_occupancy"][order], model.most_likely_doo(vox.s[ref], vox.n[ref]), atol=1e-6
    )
    want_std = model.std_doo(vox.s[ref], vox.n[ref], vox.prior)
    np.testing.assert_allclose(ply["std"][order], want_std, atol=1e-6)
    mfp = ply["mean_free_path"][order]
    hit = vox.n[ref] > 0
    assert np.all(np.isnan(mfp[~hit]))  # infinite: written as NaN
    np.testing.assert_allclose(mfp[hit], vox.s[ref][hit] / vox.n[ref][hit], rtol=1e-6)


def test_ply_filters(mapper: Mapper, tmp_path: Path) -> None:
    all_count = export_ply(mapper, tmp_path / "a.ply")
    occ = export_ply(mapper, tmp_path / "b.ply", min_doo=0.5)
    assert 0 < occ < all_count
    assert np.all(read_ply(tmp_path / "b.ply")["degree_of_occupancy"] >= 0.5)
    assert export_ply(Mapper(0.5), tmp_path / "empty.ply") == 0
    assert read_ply(tmp_path / "empty.ply")["x"].size == 0


def test_ply_readable_by_open3d_when_installed(mapper: Mapper, tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d", reason="open3d is not installed")
    path = tmp_path / "map.ply"
    count = export_ply(mapper, path)
    assert len(o3d.io.read_point_cloud(str(path)).points) == count


def test_ply_and_query_of_a_map_with_reflectivity(tmp_path: Path) -> None:
    """The reflectivity properties (mean intensity, fullest bin) of the PLY, one file or
    tiled, and the query rows' histograms, against the map's own histograms."""
    from mfp_mapper.cli import main
    from mfp_mapper.core.reflectivity import ReflectivityBins, ScanReflectivity
    from mfp_mapper.mapio.loading import save_map

    bins = ReflectivityBins("intensity", (2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0))
    m = Mapper(0.5, frame_id="odom")
    rng = np.random.default_rng(1)
    pts = rng.uniform([2, -2, 0], [6, 2, 2], (500, 3))
    values = np.where(pts[:, 0] < 4.0, 3.0, 100.0)  # near: bin 1; far: bin 6
    m.integrate(pts, np.zeros(3), 1.0, reflectivity=ScanReflectivity(values, bins))
    vox = m.voxels()
    order_ref = np.lexsort((vox.centers[:, 2], vox.centers[:, 1], vox.centers[:, 0]))
    for tiled in (False, True):
        path = tmp_path / ("map.ply" if not tiled else "tiled.ply")
        if tiled:
            save_map(m, tmp_path / "tiled_map", tile_blocks=1)
            assert main(["export", str(tmp_path / "tiled_map"), "-o", str(path)]) == 0
        else:
            export_ply(m, path)
        ply = read_ply(path)
        order = np.lexsort((ply["z"], ply["y"], ply["x"]))
        fullest = ply["reflectivity_bin"][order]
        hit = vox.n[order_ref] > 0
        near = vox.centers[order_ref, 0] < 4.0
        assert np.all(fullest[~hit] == -1) and np.isnan(ply["reflectivity"][order][~hit]).all()
        assert set(fullest[hit & near].tolist()) <= {1.0, 6.0}  # a voxel across x = 4 m
        assert np.all(fullest[hit & (vox.centers[order_ref, 0] < 3.5)] == 1)
        assert np.all(fullest[hit & (vox.centers[order_ref, 0] > 4.5)] == 6)
        assert ply["reflectivity"][order][hit & (vox.centers[order_ref, 0] > 4.5)] == pytest.approx(
            np.sqrt(64.0 * 128.0)
        )
    # query: the histogram of the voxel holding a point
    out = tmp_path / "q.json"
    save_map(m, tmp_path / "m.npz")
    far = vox.centers[order_ref][hit & (vox.centers[order_ref, 0] > 4.5)][0]
    import contextlib
    import io
    import json

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        assert main(["query", str(tmp_path / "m.npz"), *map(str, far), "--json"]) == 0
    row = json.loads(buffer.getvalue())[0]["reflectivity"]
    assert row["field"] == "intensity" and row["most_likely_bin"] == 6
    assert sum(row["counts"]) == pytest.approx(m.query(far[None]).n[0])
    plain = Mapper(0.5)
    plain.integrate(pts, np.zeros(3), 1.0)
    export_ply(plain, out.with_suffix(".ply"))
    assert "reflectivity" not in read_ply(out.with_suffix(".ply"))
