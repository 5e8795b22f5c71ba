"""Scan-to-map alignment (core.alignment): the field against the model's formulas, the
gradient against finite differences, the pyramid's exact aggregation, recovery from
perturbed poses in a simulated hall, and refusal in a featureless corridor."""

from __future__ import annotations

import numpy as np
import pytest
from localization_scenes import (
    Pose,
    localization_scene,
    perturb,
    pose_at,
    static_scan,
)

from mfp_mapper.core.alignment import (
    REFUSALS,
    AlignOptions,
    FieldPyramid,
    LikelihoodField,
    align_scan,
    geometric_conditioning,
    surrogate_log_likelihood,
    verify_exact,
)
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.sensing.scan_normals import scan_normals


def _model(s: np.ndarray, n: np.ndarray, r: float, alpha: float, beta: float) -> tuple:
    """Brute force: log P(return over r) and log P(pass) per metre of docs/model.md."""
    p_pass = ((s + beta) / (s + beta + r)) ** (n + alpha)
    return np.log(1.0 - p_pass), np.log(p_pass) / r


def test_field_at_voxel_centres_is_the_model_and_unknown_is_the_prior() -> None:
    rng = np.random.default_rng(0)
    ijk = np.unique(rng.integers(-20, 20, size=(300, 3)), axis=0)
    s = rng.uniform(0.0, 5.0, len(ijk))
    n = rng.integers(0, 4, len(ijk)).astype(float)
    origin = np.array([0.3, -1.0, 0.05])
    fld = LikelihoodField.from_statistics(ijk, s, n, 0.2, origin, shape=0.5, rate=0.1)
    a, b, _, _ = fld.values((ijk + 0.5) * 0.2 + origin)
    a_ref, b_ref = _model(s, n, 0.2, 0.5, 0.1)
    np.testing.assert_allclose(a, a_ref, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(b, b_ref, rtol=1e-5, atol=1e-5)
    far = fld.values(np.array([[100.0, 100.0, 100.0]]))
    a0, b0 = _model(np.zeros(1), np.zeros(1), 0.2, 0.5, 0.1)
    assert far[0][0] == pytest.approx(a0[0], rel=1e-6)
    assert far[1][0] == pytest.approx(b0[0], rel=1e-6)


def test_pyramid_levels_add_up_the_statistics_exactly() -> None:
    ijk = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 1], [3, 3, 3], [-1, 0, 0]])
    s = np.array([0.5, 1.0, 2.0, 3.0, 0.25])
    n = np.array([1.0, 0.0, 2.0, 1.0, 0.0])
    pyr = FieldPyramid.from_statistics(ijk, s, n, 0.1, np.zeros(3), levels=3)
    coarse = pyr.fields[1]  # 0.2 m: voxel (0,0,0) holds the first three
    a, b, _, _ = coarse.values(np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [-0.1, 0.1, 0.1]]))
    a_ref, b_ref = _model(np.array([3.5, 3.0, 0.25]), np.array([3.0, 1.0, 0.0]), 0.2, 1, 1)
    np.testing.assert_allclose(a, a_ref, rtol=1e-5)
    np.testing.assert_allclose(b, b_ref, rtol=1e-5)
    assert pyr.fields[2].resolution == pytest.approx(0.4)


def test_gradient_matches_finite_differences_of_the_surrogate() -> None:
    rng = np.random.default_rng(1)
    ijk = np.array([[i, j, k] for i in range(-10, 10) for j in range(-10, 10) for k in range(4)])
    s = rng.uniform(0.1, 4.0, len(ijk))
    n = rng.integers(0, 5, len(ijk)).astype(float)
    fld = LikelihoodField.from_statistics(ijk, s, n, 0.2, np.zeros(3))
    pts = rng.uniform([-1.5, -1.5, 0.1], [1.5, 1.5, 0.7], size=(50, 3))
    org = np.array([0.05, 0.02, 0.4])
    center = np.array([0.1, -0.2, 0.3])
    _, g = surrogate_log_likelihood(fld, pts, org, center=center)
    eps = 1e-6
    for c in range(6):
        y = np.zeros(6)
        y[c] = eps
        from scipy.spatial.transform import Rotation

        rot = Rotation.from_rotvec(y[3:]).as_matrix()
        trans = y[:3] + center - rot @ center
        f_plus, _ = surrogate_log_likelihood(fld, pts, org, rot, trans)
        rot_m = Rotation.from_rotvec(-y[3:]).as_matrix()
        f_minus, _ = surrogate_log_likelihood(
            fld, pts, org, rot_m, -y[:3] + center - rot_m @ center
        )
        numeric = (f_plus - f_minus) / (2 * eps)
        np.testing.assert_allclose(g[:, c], numeric, rtol=1e-3, atol=1e-4)


def _scene_map(name: str, scans: int = 24) -> tuple[list[Pose], Mapper, np.random.Generator]:
    scene, pos = localization_scene(name)
    rng = np.random.default_rng(0)
    poses = [pose_at(p, yaw=0.3 * k) for k, p in enumerate(pos[:scans])]
    mapper = Mapper(0.2, max_range=60.0)
    for k in range(0, len(poses), 2):
        pts = static_scan(scene, poses[k], rng)
        mapper.integrate(poses[k].apply(pts), poses[k].translation, stamp=float(k))
    return poses, mapper, rng


def test_hall_scans_come_back_from_0_3_m_and_3_deg() -> None:
    scene, _ = localization_scene("box")
    poses, mapper, rng = _scene_map("box", 12)
    pyramid = FieldPyramid.from_mapper(mapper)
    for k in (1, 5):
        truth = poses[k]
        local = static_scan(scene, truth, rng)
        init = perturb(truth, rng, 0.3, 3.0)
        pts = init.apply(local)
        al = align_scan(pyramid, pts, init.translation, AlignOptions(), normals=scan_normals(pts))
        assert al.accepted, al.reason
        refined = Pose(al.rotation @ init.rotation, al.rotation @ init.translation + al.translation)
        shift, angle = refined.error_to(truth)
        assert shift < 0.05 and angle < 0.5, (shift, angle)
        assert al.gain > 0.0
        assert np.all(np.isfinite(al.sigma)) and np.all(al.sigma[:3] < 0.05)


def test_corridor_correction_is_refused_along_its_axis() -> None:
    scene, _ = localization_scene("corridor")
    poses, mapper, rng = _scene_map("corridor", 12)
    pyramid = FieldPyramid.from_mapper(mapper)
    truth = poses[5]
    init = perturb(truth, rng, 0.3, 3.0)
    pts = init.apply(static_scan(scene, truth, rng))
    al = align_scan(pyramid, pts, init.translation, AlignOptions(), normals=scan_normals(pts))
    assert not al.accepted
    assert "degenerate" in al.reason and "constrain x" in al.reason
    np.testing.assert_array_equal(al.rotation, np.eye(3))
    np.testing.assert_array_equal(al.translation, np.zeros(3))


def test_geometric_conditioning_counts_the_constraining_patches() -> None:
    rng = np.random.default_rng(3)
    floor = np.c_[rng.uniform(-5, 5, (200, 2)), np.zeros(200)]
    up = np.tile([0.0, 0.0, 1.0], (200, 1))
    counts, vecs = geometric_conditioning(floor, up, np.zeros(3), 5.0)
    assert counts.min() == 0  # a floor alone pins z, roll and pitch only
    wall_x = np.c_[np.full(50, 4.0), rng.uniform(-5, 5, (50, 2))]
    wall_y = np.c_[rng.uniform(-5, 5, 50), np.full(50, 4.0), rng.uniform(0, 3, 50)]
    pts = np.concatenate([floor, wall_x, wall_y])
    nrm = np.concatenate([up, np.tile([1.0, 0, 0], (50, 1)), np.tile([0, 1.0, 0], (50, 1))])
    counts, _ = geometric_conditioning(pts, nrm, np.zeros(3), 5.0)
    assert counts.min() >= 50


def test_too_few_rays_are_refused_with_a_reason() -> None:
    pyr = FieldPyramid.from_statistics(np.zeros((1, 3)), np.ones(1), np.ones(1), 0.2, np.zeros(3))
    al = align_scan(pyr, np.ones((3, 3)), np.zeros(3))
    assert not al.accepted and "too few rays" in al.reason


@pytest.mark.parametrize(
    ("options", "key", "reason"),
    [
        ({"max_sigma_m": 1e-9}, "flat_likelihood", "degenerate geometry: the likelihood is flat"),
        ({"min_constraints": 10**9}, "degenerate_geometry", "degenerate geometry: only"),
        ({"max_shift_m": 1e-6}, "out_of_range", "correction beyond the search range"),
        ({"min_correction_voxels": 1e6}, "aliasing", "correction within the grid's aliasing"),
        ({"min_gain_per_ray": 1e6}, "no_gain", "no significant gain"),
        ({"min_exact_z": float("inf")}, "exact_check", "no significant exact gain"),
    ],
)
def test_every_refusal_has_its_name_beside_its_reason(
    options: dict[str, float], key: str, reason: str
) -> None:
    """``Alignment.refusal``: the counter name a refusal is reported under (the localizer's
    ``~/status`` counts), set where the refusal is decided, beside the sentence."""
    scene, _ = localization_scene("box")
    poses, mapper, rng = _scene_map("box", 6)
    truth = poses[1]
    init = perturb(truth, rng, 0.3, 3.0)
    pts = init.apply(static_scan(scene, truth, rng))
    opt = AlignOptions(**options)  # type: ignore[arg-type]
    al = align_scan(
        FieldPyramid.from_mapper(mapper), pts, init.translation, opt, normals=scan_normals(pts)
    )
    if key == "exact_check":
        assert al.accepted and al.refusal == "", al.reason
        al = verify_exact(mapper, al, pts, init.translation, 100.0, opt)
    assert not al.accepted and al.refusal == key and al.reason.startswith(reason), al.reason
    assert key in REFUSALS


def test_too_few_rays_have_their_refusal_name() -> None:
    pyr = FieldPyramid.from_statistics(np.zeros((1, 3)), np.ones(1), np.ones(1), 0.2, np.zeros(3))
    al = align_scan(pyr, np.ones((3, 3)), np.zeros(3))
    assert al.refusal == "too_few_rays" and al.reason.startswith("too few rays (3) to align")
