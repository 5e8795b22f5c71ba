"""The Gamma prior on the extinction (docs/model.md): formulas, the Mapper, map files."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate, stats

from mfp_mapper.config.replay_options import add_replay_flags, options_from_args
from mfp_mapper.core import model
from mfp_mapper.core.gridmap import hit_probability_one, unobserved_hit_probability
from mfp_mapper.core.likelihood import scan_log_likelihood
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapio.loading import load_map, save_map
from mfp_mapper.mapio.mapfile import map_arrays, write_map_arrays
from mfp_mapper.mapio.tiles import TiledMap, write_tiled

PRIOR = model.Prior(0.3, 0.05)


@pytest.mark.parametrize(("s", "n"), [(0.0, 0.0), (0.4, 0.0), (2.0, 3.0), (0.07, 1.0)])
def test_moments_are_those_of_the_gamma_posterior(s: float, n: float) -> None:
    """E[m^z] = E[exp(-z u)] under Gamma(n + alpha, rate s + beta), by quadrature."""
    post = stats.gamma(n + PRIOR.shape, scale=1.0 / (s + PRIOR.rate))
    for z in (0.1, 1.0, 2.0):
        want, _ = integrate.quad(
            lambda u, z=z: math.exp(-z * u) * post.pdf(u), 0, np.inf, limit=200
        )
        assert model.moment_m(s, n, z, PRIOR) == pytest.approx(want, rel=1e-6)
    m1 = post.expect(lambda u: np.exp(-u))
    m2 = post.expect(lambda u: np.exp(-2 * u))
    assert model.mean_doo(s, n, PRIOR) == pytest.approx(1 - m1, rel=1e-6)
    assert model.std_doo(s, n, PRIOR) == pytest.approx(math.sqrt(m2 - m1 * m1), rel=1e-5)
    lo, hi = model.extinction_interval(s, n, 0.9, PRIOR)
    assert float(lo) == pytest.approx(post.ppf(0.05), rel=1e-6)
    assert float(hi) == pytest.approx(post.ppf(0.95), rel=1e-6)
    assert model.hit_probability(s, n, 0.1, PRIOR) == pytest.approx(
        1 - model.moment_m(s, n, 0.1, PRIOR), rel=1e-12
    )
    assert hit_probability_one(s, n, 0.1, PRIOR.shape, PRIOR.rate) == pytest.approx(
        float(model.hit_probability(s, n, 0.1, PRIOR)), rel=1e-12
    )


def test_uniform_prior_is_the_paper() -> None:
    assert model.UNIFORM.is_uniform
    assert model.UNIFORM.unknown_doo == pytest.approx(model.UNKNOWN_DOO)
    assert model.UNIFORM.unknown_std == pytest.approx(model.UNKNOWN_STD)
    # docs/model.md's worked value s = 2, n = 3
    assert float(model.std_doo(2.0, 3.0)) == pytest.approx(0.171718, abs=1e-6)
    assert PRIOR.unknown_doo == pytest.approx(1 - (0.05 / 1.05) ** 0.3)
    with pytest.raises(ValueError, match="shape and rate"):
        model.Prior(0.0, 1.0)
    with pytest.raises(ValueError, match="shape and rate"):
        Mapper(0.1, prior_rate=math.inf)


def _mapper(prior: model.Prior) -> Mapper:
    rng = np.random.default_rng(5)
    mapper = Mapper(0.2, prior_shape=prior.shape, prior_rate=prior.rate)
    for k in range(3):
        mapper.integrate(rng.normal(size=(300, 3)) * 2.0, np.zeros(3), float(k))
    return mapper


def test_every_estimate_reads_the_mappers_prior(tmp_path: Path) -> None:
    mapper = _mapper(PRIOR)
    st = mapper.voxels()
    assert st.prior == PRIOR
    np.testing.assert_allclose(st.mean_doo, model.mean_doo(st.s, st.n, PRIOR))
    np.testing.assert_allclose(st.hit_probability, model.hit_probability(st.s, st.n, 0.2, PRIOR))
    assert st.select(st.n > 0).prior == PRIOR
    unknown = mapper.query([[100.0, 100.0, 100.0]])
    assert float(unknown.mean_doo[0]) == pytest.approx(PRIOR.unknown_doo)
    # the grid: the largest p_hit of a column, with the prior
    grid = mapper.hit_probability_grid(-0.1, 0.1)
    band = st.select(np.abs(st.centers[:, 2]) <= 0.1)
    assert grid.data.max() == int(np.rint(100 * band.hit_probability.max()))
    assert unobserved_hit_probability(0.2, PRIOR.shape, PRIOR.rate) == pytest.approx(
        1 - (0.05 / 0.25) ** 0.3
    )
    # the likelihood defaults to the map's prior
    pts = np.random.default_rng(1).normal(size=(50, 3))
    a = scan_log_likelihood(mapper, pts, np.zeros(3), 3.0).total
    b = scan_log_likelihood(mapper, pts, np.zeros(3), 3.0, shape=0.3, rate=0.05).total
    assert a == b


def test_map_files_keep_the_prior_and_old_files_mean_uniform(tmp_path: Path) -> None:
    mapper = _mapper(PRIOR)
    save_map(mapper, tmp_path / "m.npz")
    assert load_map(tmp_path / "m.npz").prior == PRIOR
    old = {k: v for k, v in map_arrays(mapper).items() if not k.startswith("prior_")}
    write_map_arrays(tmp_path / "old.npz", old)
    assert load_map(tmp_path / "old.npz").prior == model.UNIFORM
    assert load_map(tmp_path / "m.npz", prior_shape=2.0).prior == model.Prior(2.0, 0.05)
    write_tiled(tmp_path / "tiled", map_arrays(mapper), 2)
    tiled = TiledMap(tmp_path / "tiled")
    assert tiled.prior == PRIOR
    assert tiled.load().prior == PRIOR
    assert tiled.query([[100.0, 0.0, 0.0]]).prior == PRIOR


def test_the_family_and_unset_shape_or_rate() -> None:
    """shape = a * resolution, rate = a * resolution / 2; a shape or rate of 0 is unset: the
    family's value at the map's resolution; given values override it."""
    assert model.family_prior(0.03, 0.2) == model.Prior(0.006, 0.003)
    assert model.resolve_prior(0.1, 0.0, 0.0, 0.03) == model.family_prior(0.03, 0.1)
    assert model.resolve_prior(0.1, 0.5, 0.0, 0.03) == model.Prior(0.5, 0.0015)
    assert model.resolve_prior(0.1, 0.5, 0.2, 0.0) == model.Prior(0.5, 0.2)
    with pytest.raises(ValueError, match=r"prior\.scale"):
        model.resolve_prior(0.1, 0.0, 0.2, 0.0)
    with pytest.raises(ValueError, match="finite and > 0"):
        model.resolve_prior(0.1, -1.0, 0.2, 0.03)
    mapper = Mapper(0.2, prior_shape=0.0, prior_rate=0.0, prior_scale=0.03)
    assert mapper.prior == model.Prior(0.006, 0.003)
    assert Mapper(0.2).prior == model.family_prior(0.0275, 0.2)  # the settings' default


def test_map_files_record_the_resolved_family_prior(tmp_path: Path) -> None:
    """A map built with the family records the numbers it used; loading it with the
    settings' family at another scale re-derives them at the file's resolution."""
    mapper = Mapper(0.2, prior_shape=0.0, prior_rate=0.0, prior_scale=0.03)
    mapper.integrate(np.array([[1.0, 0.0, 0.0]]), np.zeros(3), 0.0)
    save_map(mapper, tmp_path / "m.npz")
    arrays = np.load(tmp_path / "m.npz")
    assert float(arrays["prior_shape"]) == pytest.approx(0.006)
    assert float(arrays["prior_rate"]) == pytest.approx(0.003)
    assert load_map(tmp_path / "m.npz").prior == mapper.prior
    again = load_map(tmp_path / "m.npz", prior_shape=0.0, prior_rate=0.0, prior_scale=0.05)
    assert again.prior == model.family_prior(0.05, 0.2)


def test_replay_flags_and_node_parameters() -> None:
    from mfp_mapper.config.schema import check_parameters

    parser = argparse.ArgumentParser()
    parser.add_argument("--config")
    add_replay_flags(parser)
    opts = options_from_args(parser.parse_args(["--prior-shape", "0.3", "--prior-rate", "0.05"]))
    assert (opts.map.prior_shape, opts.map.prior_rate) == (0.3, 0.05)
    assert Mapper.of(opts.map, opts.sensor_model).prior == PRIOR
    cfg = check_parameters({"prior.shape": 0.3, "prior.rate": 0.05})
    assert Mapper.of(cfg.map, cfg.sensor_model).prior == PRIOR
    with pytest.raises(ValueError, match=r"prior\.rate"):
        check_parameters({"prior.rate": -1.0})
    # 0, the default: from the family, prior.scale at the map's resolution
    cfg = check_parameters({"prior.scale": 0.05, "resolution": 0.2})
    assert Mapper.of(cfg.map, cfg.sensor_model).prior == model.family_prior(0.05, 0.2)
    cfg = check_parameters({"prior.shape": 1.0, "prior.rate": 1.0})
    assert Mapper.of(cfg.map, cfg.sensor_model).prior == model.UNIFORM
