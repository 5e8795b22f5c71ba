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
