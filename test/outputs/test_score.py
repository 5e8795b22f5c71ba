"""Held-out scores (outputs/score.py) and the score / fit-prior commands."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from likelihood_reference import reference

from mfp_mapper.cli import main
from mfp_mapper.core.likelihood import ScanEvents
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.model import Prior, family_prior
from mfp_mapper.mapio.loading import load_map, save_map
from mfp_mapper.outputs import score


def test_metrics_match_their_definitions() -> None:
    rng = np.random.default_rng(2)
    p = rng.random(5000) ** 3
    y = rng.random(5000) < p * 0.8
    log_p = np.where(y, np.log(p), np.log1p(-p))
    m = score.Metrics()
    m.rays = 100
    m.add(p[:3000], y[:3000], log_p[:3000])
    m.add(p[3000:], y[3000:], log_p[3000:])
    r = m.result()
    assert r["events"] == 5000
    assert r["log_likelihood_per_ray"] == pytest.approx(log_p.sum() / 100)
    assert r["log_loss_per_event"] == pytest.approx(-log_p.mean())
    assert r["brier"] == pytest.approx(np.mean((p - y) ** 2))
    bins = np.minimum((p * 10).astype(int), 9)
    ece = (
        sum(abs(p[bins == k].sum() - y[bins == k].sum()) for k in range(10) if np.any(bins == k))
        / 5000
    )
    assert r["ece"] == pytest.approx(ece)
    assert sum(row["count"] for row in r["calibration"]) == 5000
    row = r["calibration"][0]
    assert row["mean_predicted"] == pytest.approx(p[bins == 0].mean())
    assert row["observed_frequency"] == pytest.approx(y[bins == 0].mean())


def _events(ijk: list[tuple[int, int, int]], hit: list[bool]) -> ScanEvents:
    k = len(ijk)
    z = np.zeros(k)
    return ScanEvents(
        np.zeros(k, np.int64), np.array(ijk, np.int32), z, z, z, np.array(hit, dtype=bool)
    )


def test_classic_map_is_octomap_log_odds_once_per_scan() -> None:
    """A voxel holding a return of the scan: +0.85 once (however many rays), else -0.4 once
    where crossed; clamped to [-2, 3.5]. Checked against a dictionary replay."""
    rng = np.random.default_rng(4)
    classic = score.ClassicMap()
    want: dict[tuple[int, int, int], float] = {}
    for _ in range(30):
        ijk = [tuple(int(v) for v in rng.integers(-3, 3, 3)) for _ in range(40)]
        hit = list(rng.random(40) < 0.3)
        classic.update(_events(ijk, hit))  # type: ignore[arg-type]
        scan: dict[tuple[int, int, int], bool] = {}
        for voxel, h in zip(ijk, hit, strict=True):
            scan[voxel] = scan.get(voxel, False) or bool(h)
        for voxel, h in scan.items():
            want[voxel] = min(max(want.get(voxel, 0.0) + (0.85 if h else -0.4), -2.0), 3.5)
    keys = list(want)
    got = classic.lookup(np.array(keys, dtype=np.int32))
    np.testing.assert_allclose(got, [want[k] for k in keys], atol=1e-12)
    assert classic.lookup(np.array([[50, 50, 50]], dtype=np.int32))[0] == 0.0


def test_classic_fit_recovers_the_constants() -> None:
    counts = score.ClassicCounts()
    counts.rays = 1
    rng = np.random.default_rng(1)
    log_odds = rng.choice([-2.0, -1.2, 0.0, 0.85, 2.5, 3.5], 200_000)
    p_o = 1 / (1 + np.exp(-log_odds))
    hit = rng.random(log_odds.size) < 0.05 * (1 - p_o) + 0.6 * p_o
    counts.add(log_odds, hit)
    a, b = counts.fit()
    assert a == pytest.approx(0.05, abs=0.005)
    assert b == pytest.approx(0.6, abs=0.02)
    assert (
        counts.metrics(a, b).result()["log_likelihood"]
        > counts.metrics(0.2, 0.47).result()["log_likelihood"]
    )


def test_fit_prior_recovers_the_population_prior() -> None:
    """Voxels whose extinction is drawn from Gamma(0.4, 0.2): training statistics from a
    Poisson process, held-out chords with returns drawn from the true extinction.
    Empirical Bayes finds the population's shape and rate back."""
    rng = np.random.default_rng(0)
    voxels = 200_000
    u = rng.gamma(0.4, 1 / 0.2, voxels)
    s = rng.uniform(0.0, 0.6, voxels)
    n = rng.poisson(u * s).astype(float)
    chord = rng.uniform(0.02, 0.3, voxels)
    hit = rng.random(voxels) < -np.expm1(-u * chord)
    sample = score.EventSample(budget=10**7)
    sample.add(ScanEvents(np.arange(voxels), np.zeros((voxels, 3), np.int32), s, n, chord, hit))
    sample.rays = voxels
    fitted = score.fit_prior(sample)
    assert fitted.shape == pytest.approx(0.4, rel=0.15)
    assert fitted.rate == pytest.approx(0.2, rel=0.25)
    assert fitted.gain > 0
    # the gradient is that of the log-likelihood
    arrays = sample.arrays()
    value, grad = score.sample_log_likelihood(arrays, 0.5, 0.3, gradient=True)
    h = 1e-6
    for axis in range(2):
        x = np.log([0.5, 0.3])
        x[axis] += h
        shifted = score.sample_log_likelihood(arrays, *np.exp(x))[0]
        assert (shifted - value) / h == pytest.approx(grad[axis], rel=1e-3)


def _family_sample(rng: np.random.Generator, scale: float, resolution: float) -> score.EventSample:
    """Voxels whose extinction is drawn from the family's prior at ``resolution``."""
    prior = family_prior(scale, resolution)
    voxels = 100_000
    u = rng.gamma(prior.shape, 1 / prior.rate, voxels)
    s = rng.uniform(0.0, 3 * resolution, voxels)
    n = rng.poisson(u * s).astype(float)
    chord = rng.uniform(0.1, 1.0, voxels) * resolution
    hit = rng.random(voxels) < -np.expm1(-u * chord)
    sample = score.EventSample(budget=10**7)
    sample.add(ScanEvents(np.arange(voxels), np.zeros((voxels, 3), np.int32), s, n, chord, hit))
    sample.rays = voxels // 20
    return sample


def test_fit_scale_recovers_the_family_and_leaves_one_out() -> None:
    """Samples drawn from shape = a * resolution, rate = a * resolution / 2 (a = 2 per metre)
    at two resolutions: the fit finds a back; leaving a recording out, the others' a scores
    it within a few percent of its own two-parameter fit, better than the uniform prior."""
    rng = np.random.default_rng(5)
    samples = [
        score.RecordingSample(name, res, _family_sample(rng, 2.0, res))
        for name in ("hall", "street")
        for res in (0.1, 0.2)
    ]
    assert family_prior(2.0, 0.1) == Prior(0.2, 0.1)
    assert score.fit_scale(samples) == pytest.approx(2.0, rel=0.1)
    own = {k: score.fit_prior(r.sample).prior for k, r in enumerate(samples)}
    rows = score.leave_one_out(samples, own)
    assert [(r.recording, r.resolution) for r in rows] == [
        (r.recording, r.resolution) for r in samples
    ]
    for row in rows:
        assert row.scale == pytest.approx(2.0, rel=0.15)
        assert -0.01 < row.gap < 0.05
        assert row.family > row.uniform
    with pytest.raises(ValueError, match="two recordings"):
        score.leave_one_out(samples[:2], own)


def test_fit_prior_refuses_nothing_to_fit() -> None:
    """No held-out return (every ray cut at max_range), or no event at all: a ValueError
    that says so, never a prior "fitted" to nothing."""
    rng = np.random.default_rng(1)
    k = 1000
    passes = ScanEvents(
        np.arange(k), np.zeros((k, 3), np.int32), rng.uniform(0, 1, k), np.zeros(k),
        rng.uniform(0.01, 0.1, k), np.zeros(k, dtype=bool),
    )  # fmt: skip
    sample = score.EventSample()
    sample.add(passes)
    sample.rays = k
    with pytest.raises(ValueError, match="nothing to fit: none of the 1,000 held-out rays"):
        score.fit_prior(sample)
    with pytest.raises(ValueError, match="nothing to fit: no held-out ray"):
        score.fit_prior(score.EventSample())


def test_a_non_finite_score_says_why() -> None:
    """An event of probability 0 makes the log-likelihood -inf: the summary says so."""
    m = score.Metrics()
    m.rays = 2
    m.add(np.array([0.0, 0.5]), np.array([True, False]), np.array([-np.inf, math.log(0.5)]))
    row = m.result()
    assert row["impossible_events"] == 1
    rep = {**row, "log_density_per_ray": -math.inf, "prior": {"shape": 1.0, "rate": 1.0}}
    lines = score.summary_lines(rep)
    assert "-inf: 1 scored event(s) had probability 0" in lines[-1]
    fine = score.Metrics()
    fine.rays = 1
    fine.add(np.array([0.5]), np.array([True]), np.array([math.log(0.5)]))
    assert score.nonfinite_reason({**fine.result(), "log_density_per_ray": 0.0}) is None


def test_event_sample_halving_keeps_weights_unbiased() -> None:
    rng = np.random.default_rng(3)
    count = 400_000
    hit = rng.random(count) < 0.01
    ev = ScanEvents(
        np.zeros(count, np.int64), np.zeros((count, 3), np.int32), rng.random(count),
        np.zeros(count), rng.random(count), hit,
    )  # fmt: skip
    sample = score.EventSample(budget=50_000)
    sample.add(ev)
    *_, hits, weights = sample.arrays()
    assert sample.size <= 50_000
    assert hits.sum() == hit.sum()  # every return is kept
    assert weights.sum() == pytest.approx(count, rel=0.02)


# --- through the command line, on the real street scans -------------------------------------


def _street_folder(shared_data: Path, tmp_path: Path, keep: list[int], stride: int) -> Path:
    """A scan folder of some of the street scans (every ``stride``-th point)."""
    street = shared_data / "ouster_street"
    folder = tmp_path / f"street_{'_'.join(map(str, keep))}"
    folder.mkdir()
    poses = np.loadtxt(street / "poses.txt").reshape(-1, 12)
    for k, index in enumerate(keep):
        xyz = np.fromfile(street / "scans" / f"{index:06d}.bin", np.float32).reshape(-1, 4)
        xyz[::stride].tofile(folder / f"{k:06d}.bin")
    np.savetxt(tmp_path / f"poses_{folder.name}.txt", poses[keep])
    return folder


def test_score_agrees_with_an_independent_implementation(shared_data: Path, tmp_path: Path) -> None:
    """score MAP INPUT against the pure-Python walk of test/core/test_likelihood.py."""
    train = _street_folder(shared_data, tmp_path, [0, 2], 8)
    held = _street_folder(shared_data, tmp_path, [1], 400)
    map_path = tmp_path / "street.npz"
    poses = tmp_path / "poses_{}.txt"
    assert main([
        "replay", str(train), "--poses", str(poses).format(train.name), "-o", str(map_path),
        "--resolution", "0.25", "--max-range", "30", "-q",
    ]) == 0  # fmt: skip
    out = tmp_path / "score.json"
    assert main([
        "score", str(map_path), str(held), "--poses", str(poses).format(held.name),
        "--max-range", "30", "--json", str(out), "-q",
    ]) == 0  # fmt: skip
    got = json.loads(out.read_text())
    assert (tmp_path / "score.png").stat().st_size > 0
    # the reference: rays from the sensor of scan 1 to its points, world frame, no deskew
    mapper = load_map(map_path)
    pose = np.loadtxt(str(poses).format(held.name)).reshape(3, 4)
    xyz = np.fromfile(held / "000000.bin", np.float32).reshape(-1, 4)[:, :3].astype(float)
    pts = xyz @ pose[:, :3].T + pose[:, 3]
    keep = np.linalg.norm(xyz, axis=1) > 0
    pts = pts[keep]
    flags = np.zeros(len(pts), dtype=bool)
    prior = mapper.prior  # the default: the family at 0.25 m
    want, events = reference(mapper, pts, pose[:, 3], 1.0, flags, prior.shape, prior.rate)
    assert got["rays"] == len(pts)
    assert got["events"] == len(events)
    assert got["log_likelihood_per_ray"] == pytest.approx(want.mean(), rel=0.01)
    assert got["log_likelihood_per_ray"] == pytest.approx(want.mean(), rel=1e-6)
    density = want.sum() - sum(math.log(e[2]) for e in events if e[3])
    assert got["log_density_per_ray"] == pytest.approx(density / len(pts), rel=1e-6)
    # several maps: one row each; the map's prior can be overridden by the flags
    rows = tmp_path / "rows.json"
    assert main([
        "score", str(map_path), str(map_path), str(held), "--poses",
        str(poses).format(held.name), "--max-range", "30", "--prior-shape", "0.5",
        "--json", str(rows), "-q",
    ]) == 0  # fmt: skip
    table = json.loads(rows.read_text())["rows"]
    assert [r["label"] for r in table] == [str(map_path)] * 2
    want_prior, _ = reference(mapper, pts, pose[:, 3], 1.0, flags, 0.5, prior.rate)
    assert table[0]["log_likelihood_per_ray"] == pytest.approx(want_prior.mean(), rel=1e-6)
    uniform, _ = reference(mapper, pts, pose[:, 3], 1.0, flags, 1.0, 1.0)
    assert table[0]["uniform_prior"]["log_likelihood_per_ray"] == pytest.approx(
        uniform.mean(), rel=1e-6
    )
    assert got["uniform_prior"]["log_likelihood_per_ray"] == pytest.approx(uniform.mean(), rel=1e-6)
    # --prior-scale: the family at the map's resolution
    assert main([
        "score", str(map_path), str(held), "--poses", str(poses).format(held.name),
        "--max-range", "30", "--prior-scale", "0.1", "--json", str(rows), "-q",
    ]) == 0  # fmt: skip
    scaled = json.loads(rows.read_text())
    assert scaled["prior"] == {"shape": pytest.approx(0.025), "rate": pytest.approx(0.0125)}


def test_score_split_and_fit_prior_on_real_scans(shared_data: Path, tmp_path: Path) -> None:
    folder = _street_folder(shared_data, tmp_path, [0, 1, 2], 4)
    poses = str(tmp_path / f"poses_{folder.name}.txt")
    prior_json = tmp_path / "prior.json"
    common = ["--poses", poses, "--resolution", "0.4", "-q"]
    assert main(["fit-prior", str(folder), *common, "--json", str(prior_json)]) == 0
    prior = json.loads(prior_json.read_text())
    assert {"shape", "rate", "gain"} <= set(prior) and prior["gain"] > 0
    out = tmp_path / "split.json"
    flags = ["--prior-shape", str(prior["shape"]), "--prior-rate", str(prior["rate"])]
    assert main(["score", "--split", "even-odd", str(folder), *common, *flags,
                 "--json", str(out)]) == 0  # fmt: skip
    got = json.loads(out.read_text())
    for key in ("model", "uniform_prior", "classic_paper", "classic_fitted"):
        part = got if key == "model" else got[key]
        assert set(score.scored_keys()) <= set(part)
    assert got["rays"] == got["classic_paper"]["rays"] == got["uniform_prior"]["rays"]
    assert got["events"] == got["classic_paper"]["events"]
    assert got["log_likelihood_per_ray"] > got["uniform_prior"]["log_likelihood_per_ray"]
    assert (
        got["uniform_prior"]["log_likelihood_per_ray"]
        > got["classic_paper"]["log_likelihood_per_ray"]
    )
    assert (
        got["classic_fitted"]["log_likelihood_per_ray"]
        >= got["classic_paper"]["log_likelihood_per_ray"]
    )
    rows = tmp_path / "rows.json"
    assert main(["score", "--split", "even-odd", str(folder), "--poses", poses, "-q",
                 "--resolution", "0.4,0.8", "--decay-time", "0,5", "--no-classic",
                 "--json", str(rows)]) == 0  # fmt: skip
    table = json.loads(rows.read_text())["rows"]
    assert [r["label"] for r in table] == [
        f"resolution {r} m, decay_time {d} s" for r in ("0.4", "0.8") for d in ("0", "5")
    ]
    assert all(math.isfinite(r["log_likelihood_per_ray"]) for r in table)


def test_score_refuses_bad_usage(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    assert main(["score", str(folder), "-q"]) == 1
    assert "give a map" in capsys.readouterr().err
    map_path = tmp_path / "m.npz"
    save_map(Mapper(0.2), map_path)
    assert main(["score", str(map_path), str(folder), "--split", "even-odd", "-q"]) == 1
    assert "give no map" in capsys.readouterr().err
    shutil.rmtree(folder)


def test_score_splits_the_shots_of_one_real_tls_scan(shared_data: Path, tmp_path: Path) -> None:
    """tls_conifers is one scan: --split shots maps its even rays and scores the odd ones
    (a subsample of the scan, written as a one-scan folder)."""
    from mfp_mapper.sources.scan_files import read_ply

    cols = read_ply(shared_data / "tls_conifers" / "scan.ply")
    xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float32)[::40]
    folder = tmp_path / "tls"
    folder.mkdir()
    np.c_[xyz, np.zeros(len(xyz), np.float32)].astype(np.float32).tofile(folder / "0.bin")
    out = tmp_path / "tls.json"
    assert main(["score", "--split", "shots", str(folder), "--poses", "identity",
                 "--resolution", "0.4", "--json", str(out), "-q"]) == 0  # fmt: skip
    got = json.loads(out.read_text())
    assert got["rays"] == len(xyz) // 2
    assert got["log_likelihood_per_ray"] > got["classic_paper"]["log_likelihood_per_ray"]


def test_score_norlab_sequence_even_odd(shared_data: Path, tmp_path: Path) -> None:
    """The first six norlab scans with their odometry: three mapped, three scored."""
    data = shared_data / "norlab_sequence"
    out = tmp_path / "norlab.json"
    assert main(["score", "--split", "even-odd", str(data / "scans"), "--poses",
                 str(data / "icp_odom.csv"), "--end", "#6", "--resolution", "0.4",
                 "--json", str(out), "-q"]) == 0  # fmt: skip
    got = json.loads(out.read_text())
    assert got["rays"] > 100_000
    assert got["log_likelihood_per_ray"] > got["classic_paper"]["log_likelihood_per_ray"]
    assert 0.0 <= got["ece"] < 0.1


def test_fit_prior_with_no_return_exits_nonzero(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--max-range 0.05 cuts every ray before its return: nothing to fit, exit status 1."""
    folder = _street_folder(shared_data, tmp_path, [0, 1, 2], 40)
    poses = str(tmp_path / f"poses_{folder.name}.txt")
    out = tmp_path / "prior.json"
    assert main(["fit-prior", str(folder), "--poses", poses, "--max-range", "0.05",
                 "--resolution", "0.4", "--json", str(out), "-q"]) == 1  # fmt: skip
    assert "nothing to fit" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("command", ["score", "fit-prior"])
def test_an_unwritable_output_is_refused_before_computing(
    command: str, shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    """--json into a folder that does not exist: exit status 1 before any scan is read."""
    folder = _street_folder(shared_data, tmp_path, [0, 1, 2], 40)
    poses = str(tmp_path / f"poses_{folder.name}.txt")

    def no_replay(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("computed before checking the output")

    monkeypatch.setattr(score, "run_input", no_replay)
    split = ["--split", "even-odd"] if command == "score" else []
    missing = tmp_path / "missing" / "out.json"
    assert main([command, *split, str(folder), "--poses", poses, "--json", str(missing),
                 "-q"]) == 1  # fmt: skip
    assert "does not exist" in capsys.readouterr().err


def test_fit_prior_over_two_recordings_fits_the_family(shared_data: Path, tmp_path: Path) -> None:
    """Two recordings, --poses once each: the family's scale and the leave-one-out table."""
    first = _street_folder(shared_data, tmp_path, [0, 1, 2], 8)
    second = _street_folder(shared_data, tmp_path, [2, 1, 0], 8)
    out = tmp_path / "fit.json"
    poses = [str(tmp_path / f"poses_{f.name}.txt") for f in (first, second)]
    assert main(["fit-prior", str(first), str(second), "--poses", poses[0], "--poses",
                 poses[1], "--resolution", "0.4", "--json", str(out), "-q"]) == 0  # fmt: skip
    fit = json.loads(out.read_text())
    assert 1e-4 < fit["scale"] < 10.0
    assert [s["recording"] for s in fit["samples"]] == [str(first), str(second)]
    rows = fit["leave_one_out"]
    assert [r["recording"] for r in rows] == [str(first), str(second)]
    for row in rows:
        assert row["log_likelihood_per_ray"] > row["uniform_log_likelihood_per_ray"]
        assert row["gap_to_own"] == pytest.approx(
            (row["own_log_likelihood_per_ray"] - row["log_likelihood_per_ray"])
            / abs(row["own_log_likelihood_per_ray"])
        )
    # --poses given twice for three inputs: refused before any work
    assert main(["fit-prior", str(first), str(second), str(first), "--poses", poses[0],
                 "--poses", poses[1], "-q"]) == 1  # fmt: skip


def test_every_echo_predicts_held_out_echoes_of_a_real_tls_scan(
    shared_data: Path, tmp_path: Path
) -> None:
    """tls_conifers (RIEGL, target_index/target_count), its shots split 50/50: the map of
    every echo (one process per shot, blind stretch left out) predicts the held-out later
    echoes at least 0.25 nats/echo better than the map of first echoes, and the first
    echoes no worse (issue 30)."""
    out = tmp_path / "tls.json"
    assert main(["score", "--split", "shots", str(shared_data / "tls_conifers"), "--poses",
                 "identity", "--resolution", "0.2", "--max-range", "1000", "--no-classic",
                 "--json", str(out), "-q"]) == 0  # fmt: skip
    echoes = json.loads(out.read_text())["echoes"]
    every, first = echoes["all"], echoes["first_only"]
    assert every["later_echoes"] == first["later_echoes"] > 20_000
    assert every["first_echoes"] == first["first_echoes"] > 450_000
    gain = every["later_echo_log_likelihood_per_echo"] - first["later_echo_log_likelihood_per_echo"]
    assert gain >= 0.25
    assert every["first_echo_log_likelihood_per_ray"] >= first["first_echo_log_likelihood_per_ray"]


def test_reflectivity_predicts_held_out_returns_on_real_scans(
    shared_data: Path, tmp_path: Path
) -> None:
    """ouster_street, the score command's even-odd split (scans 0 and 2 build the map, scan 1
    is scored): the held-out returns' reflectivity bins, against an independent numpy
    computation, and at least 0.3 nats/return better than one global histogram (issue 30)."""
    folder = _street_folder(shared_data, tmp_path, [0, 1, 2], 1)
    poses_path = tmp_path / f"poses_{folder.name}.txt"
    out = tmp_path / "refl.json"
    assert main([
        "score", "--split", "even-odd", str(folder), "--poses", str(poses_path), "-q",
        "--resolution", "0.2", "--max-range", "30", "--no-classic", "--json", str(out),
    ]) == 0  # fmt: skip
    got = json.loads(out.read_text())["reflectivity"]
    assert got["field"] == "intensity" and got["bins"] == 8 and got["concentration"] == 1.0
    assert got["gain_per_return"] >= 0.3
    # the reference: world-frame points binned on 2, 4, ..., 128, voxels floor(p / 0.2)
    poses = np.loadtxt(poses_path).reshape(-1, 3, 4)
    edges = 2.0 ** np.arange(1, 8)

    def returns(k: int) -> tuple[np.ndarray, np.ndarray]:
        rec = np.fromfile(folder / f"{k:06d}.bin", np.float32).reshape(-1, 4).astype(float)
        reach = np.linalg.norm(rec[:, :3], axis=1)
        rec = rec[(reach > 0) & (reach <= 30.0)]
        world = rec[:, :3] @ poses[k][:, :3].T + poses[k][:, 3]
        return np.floor(world / 0.2).astype(np.int64), np.searchsorted(edges, rec[:, 3], "right")

    (ka, ba), (kb, bb) = returns(0), returns(2)
    keys, inverse = np.unique(np.concatenate([ka, kb]), axis=0, return_inverse=True)
    hist = np.zeros((len(keys), 8))
    np.add.at(hist, (inverse.ravel(), np.concatenate([ba, bb])), 1.0)
    background = hist.sum(axis=0) + 0.5
    background /= background.sum()
    held_keys, held_bins = returns(1)
    row = {tuple(k): i for i, k in enumerate(keys.tolist())}
    counts = np.array(
        [hist[row[k]] if k in row else np.zeros(8) for k in map(tuple, held_keys.tolist())]
    )
    p = (counts[np.arange(len(held_bins)), held_bins] + background[held_bins]) / (counts.sum(1) + 1)
    assert got["returns"] == len(held_bins)
    assert got["log_likelihood_per_return"] == pytest.approx(np.log(p).mean(), rel=1e-6)
    assert got["baseline_per_return"] == pytest.approx(
        np.log(background[held_bins]).mean(), rel=1e-9
    )
