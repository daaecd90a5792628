"""Body model: loading, forward kinematics, and analytic derivatives against finite differences."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.errors import InputError
from stages.joints import JOINT_NAMES
from stages.tracking.body import skew
from stages.tracking.body_file import load_body
from stages.tracking.distances import DISTANCES, pose_jacobian
from stages.tracking.geometry import ellipsoid_point

STEP = 1e-6  # central differences: truncation ~STEP², round-off ~1e-16/STEP


def _random_pose(body, seed):
    rng = np.random.default_rng(seed)
    return body.clip(body.zero_pose() + rng.normal(0.0, 0.5, body.pose_size))


def _random_data(body, count, spread, seed):
    """``count`` points around chest height with unit normals, and every (datum, ellipsoid) pair (i, p)."""
    rng = np.random.default_rng(seed)
    y = rng.normal(0.0, spread, (count, 3)) + [0.0, 0.0, 1.0]
    n = rng.normal(size=(count, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    i = np.repeat(np.arange(count), body.n_ellipsoids)
    p = np.tile(np.arange(body.n_ellipsoids), count)
    return y, n, i, p


def _numeric_jacobian(f, pose):
    cols = []
    for d in range(pose.size):
        step = np.zeros_like(pose)
        step[d] = STEP
        cols.append((f(pose + step) - f(pose - step)) / (2 * STEP))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("name, n_dofs", [("paper", 28), ("default", 31)])
def test_bodies_have_the_papers_counts(name, n_dofs):
    body = load_body(name)
    assert body.n_ellipsoids == 21
    assert body.pose_size == n_dofs
    assert body.joint_positions(body.zero_pose()).shape == (len(JOINT_NAMES), 3)


def test_paper_body_has_eleven_two_dof_joints():
    body = load_body("paper")
    joint_dofs = np.bincount(body.dof_segment)[1:]
    assert len(joint_dofs) == 11 and np.all(joint_dofs == 2)


def test_zero_pose_stands_on_the_floor_facing_forward():
    body = load_body("default", height_m=1.80)
    joints = dict(zip(JOINT_NAMES, body.joint_positions(body.zero_pose()), strict=True))
    assert 0.0 < joints["l_ankle"][2] < 0.1
    assert joints["l_hip"][0] < 0 < joints["r_hip"][0]  # x points to the subject's right
    assert joints["l_toe"][1] > joints["l_ankle"][1]  # facing +y
    ell = body.ellipsoids(body.zero_pose())
    z_extent = np.sqrt(np.sum((ell.R[:, 2, :] * ell.semi_axes) ** 2, axis=1))  # half-height of each
    top = np.max(ell.t[:, 2] + z_extent)
    assert top == pytest.approx(1.80, abs=0.02)


def test_default_neck_is_the_top_of_the_thorax_below_the_shoulders():
    # joints.csv's neck is the start of CMU lowerneck: 3-8.5 cm below the shoulder joint centres in the
    # CMU skeletons (standing, about 1.6-1.75 m tall), not level with them.
    body = load_body("default", height_m=1.75)
    joints = body.joint_positions(body.zero_pose())
    j = {name: joints[k] for k, name in enumerate(JOINT_NAMES)}
    below = 0.5 * (j["l_shoulder"][2] + j["r_shoulder"][2]) - j["neck"][2]
    assert 0.03 <= below <= 0.085
    assert j["head"][2] - j["neck"][2] > 0.15


def test_scaling_scales_every_length():
    small, large = load_body("default", height_m=1.5), load_body("default", height_m=1.8)
    np.testing.assert_allclose(large.joint_positions(large.zero_pose()),
                               small.joint_positions(small.zero_pose()) * 1.8 / 1.5, atol=1e-12)


def test_unknown_body_and_bad_height_are_input_errors():
    with pytest.raises(InputError, match="no such body"):
        load_body("centaur")
    with pytest.raises(InputError, match="height_m"):
        load_body("default", height_m=-1.0)


@pytest.mark.parametrize("name", ["paper", "default"])
def test_forward_kinematics_matches_a_rotation_vector_reference(name):
    body = load_body(name)
    pose = _random_pose(body, 5)
    kin = body.fk(pose)
    R, t = np.empty((len(body.segment_names), 3, 3)), np.empty((len(body.segment_names), 3))
    for s in range(len(body.segment_names)):  # down the tree, one DOF after the other
        parent = body.parent[s]
        R_s = np.eye(3) if parent < 0 else R[parent]
        t_s = np.zeros(3) if parent < 0 else t[parent] + R[parent] @ body.offset[s]
        for d in np.flatnonzero(body.dof_segment == s):
            if body.dof_revolute[d]:
                R_s = R_s @ Rotation.from_rotvec(body.dof_axis[d] * pose[d]).as_matrix()
            else:
                t_s = t_s + R_s @ body.dof_axis[d] * pose[d]
        R[s], t[s] = R_s, t_s
    np.testing.assert_allclose(kin.R, R, atol=1e-12)
    np.testing.assert_allclose(kin.t, t, atol=1e-12)


def test_ellipsoids_ride_on_their_segments_and_many_poses_pose_alike():
    body = load_body("default")
    poses = np.stack([_random_pose(body, seed) for seed in (2, 3, 4)])
    for pose in poses:
        kin, ell = body.fk(pose), body.ellipsoids(pose)
        R_seg, t_seg = kin.R[body.ellipsoid_segment], kin.t[body.ellipsoid_segment]
        np.testing.assert_allclose(ell.R, R_seg @ body.ellipsoid_rotation, atol=1e-12)
        np.testing.assert_allclose(ell.t, t_seg + np.einsum("eab,eb->ea", R_seg, body.ellipsoid_centre), atol=1e-12)
    many = body.posed_ellipsoids(poses)
    for h, pose in enumerate(poses):
        one = body.ellipsoids(pose)
        np.testing.assert_array_equal(many.R[h], one.R)
        np.testing.assert_array_equal(many.t[h], one.t)
        np.testing.assert_array_equal(many.semi_axes[h], one.semi_axes)


@pytest.mark.parametrize("name", ["paper", "default"])
def test_joint_jacobian_matches_finite_differences(name):
    body = load_body(name)
    pose = _random_pose(body, 0)
    J = body.joint_jacobian(pose)
    np.testing.assert_allclose(J, _numeric_jacobian(body.joint_positions, pose), atol=1e-7)


def test_ellipsoid_rotation_derivative_is_skew_times_rotation():
    body = load_body("default")
    pose = _random_pose(body, 1)
    kin = body.fk(pose)
    d = body.dof_names.index("l_upperarm.flex")
    numeric = _numeric_jacobian(lambda q: body.ellipsoids(q).R, pose)[..., d]
    K = skew(kin.axis[d])
    moved = body.moves[d, body.ellipsoid_segment]
    expected = np.where(moved[:, None, None], K @ body.ellipsoids(kin).R, 0.0)
    np.testing.assert_allclose(numeric, expected, atol=1e-7)


@pytest.mark.parametrize("distance", DISTANCES)
def test_residual_jacobian_matches_finite_differences(distance):
    body = load_body("default")
    y, n, i, p = _random_data(body, 20, 0.3, seed=2)

    def e(q):
        kin = body.fk(q)
        return DISTANCES[distance].residuals(y, n, i, p, kin, body.ellipsoids(kin)).e

    pose = _random_pose(body, 3)
    kin = body.fk(pose)
    B = DISTANCES[distance].residuals(y, n, i, p, kin, body.ellipsoids(kin), jacobian=True).B
    J = pose_jacobian(B, body.segment_twists(kin)[body.ellipsoid_segment[p]])
    numeric = _numeric_jacobian(e, pose)
    np.testing.assert_allclose(J, numeric, atol=1e-6 * max(1.0, np.abs(numeric).max()))


def test_normal_point_lies_on_the_ellipsoid_with_the_given_normal():
    rng = np.random.default_rng(4)
    R = Rotation.from_rotvec(np.array([0.6, 0.0, 0.8]) * rng.uniform(0, 3, (50, 1))).as_matrix()
    t = rng.normal(size=(50, 3))
    semi = rng.uniform(0.05, 0.3, (50, 3))
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    x = ellipsoid_point(n, R, t, semi)
    local = np.einsum("kba,kb->ka", R, x - t)  # Rᵀ (x − t)
    np.testing.assert_allclose(np.sum((local / semi) ** 2, axis=1), 1.0, atol=1e-12)
    gradient = np.einsum("kab,kb->ka", R, local / semi**2)  # outward normal direction at x
    gradient /= np.linalg.norm(gradient, axis=1, keepdims=True)
    np.testing.assert_allclose(gradient, n, atol=1e-12)


@pytest.mark.parametrize("distance", DISTANCES)
def test_dense_residuals_equal_pairwise_ones(distance):
    body = load_body("paper")
    y, n, i, p = _random_data(body, 30, 0.4, seed=5)
    kin = body.fk(_random_pose(body, 6))
    ell = body.ellipsoids(kin)
    pairwise = DISTANCES[distance].residuals(y, n, i, p, kin, ell).e
    dense = DISTANCES[distance].all_residuals(y, n, ell)
    np.testing.assert_allclose(dense.reshape(pairwise.shape), pairwise, atol=1e-12)


def test_length_factor_stretches_the_segment_along_its_axis():
    """The thigh group (`axis: z`) moves the knee along the zero pose's vertical only: the hip joint sits a little
    behind the knee (the body file says why), and that offset is not stretched."""
    body = load_body("default")
    g = body.length_groups.index("thigh")
    factors = np.ones(len(body.length_groups))
    factors[g] = 1.1
    longer = body.with_lengths(factors)
    j = {name: k for k, name in enumerate(JOINT_NAMES)}
    before, after = body.joint_positions(body.zero_pose()), longer.joint_positions(longer.zero_pose())
    thigh = before[j["l_knee"]] - before[j["l_hip"]]
    np.testing.assert_allclose(after[j["l_knee"]] - after[j["l_hip"]], thigh * [1.0, 1.0, 1.1], atol=1e-12)
    np.testing.assert_allclose(after[j["l_ankle"]] - after[j["l_knee"]],
                               before[j["l_ankle"]] - before[j["l_knee"]], atol=1e-12)  # shank unchanged
    np.testing.assert_allclose(after[j["neck"]], before[j["neck"]], atol=1e-12)
    on_thigh = body.ellipsoid_segment == body.segment_names.index("l_thigh")
    np.testing.assert_allclose(longer.semi_axes[on_thigh, 0], body.semi_axes[on_thigh, 0] * 1.1, rtol=2e-3)
    np.testing.assert_allclose(longer.semi_axes[on_thigh, 1:], body.semi_axes[on_thigh, 1:], rtol=2e-3)
    back = longer.with_lengths(np.ones(len(body.length_groups)))  # stretches compose: back to the start
    np.testing.assert_allclose(back.joint_positions(back.zero_pose()), before, atol=1e-12)
    np.testing.assert_allclose(back.semi_axes, body.semi_axes, atol=1e-12)


def test_length_groups_subset_freezes_the_others_at_their_stretch():
    body = load_body("default")
    factors = np.ones(len(body.length_groups))
    factors[body.length_groups.index("thigh")] = 1.1
    factors[body.length_groups.index("shank")] = 0.9
    stretched = body.with_lengths(factors)
    kept = stretched.with_length_groups(("shank",))
    assert kept.length_groups == ("shank",)
    np.testing.assert_allclose(kept.length_factors, [0.9])
    np.testing.assert_allclose(kept.joint_positions(kept.zero_pose()), stretched.joint_positions(stretched.zero_pose()))
    back = kept.with_lengths(np.ones(1))  # the shank returns to the file's length, the thigh keeps 1.1
    expected = body.with_lengths(np.where(np.array(body.length_groups) == "thigh", 1.1, 1.0))
    np.testing.assert_allclose(back.joint_positions(back.zero_pose()), expected.joint_positions(expected.zero_pose()),
                               atol=1e-12)
    assert body.with_length_groups(()).length_factors.shape == (0,)
    with pytest.raises(InputError, match="neck"):
        body.with_length_groups(("neck",))


def test_shoulder_factor_moves_the_shoulders_apart_without_widening_the_chest():
    body = load_body("default")
    factors = np.ones(len(body.length_groups))
    factors[body.length_groups.index("shoulders")] = 0.8
    narrow = body.with_lengths(factors)
    j = {name: k for k, name in enumerate(JOINT_NAMES)}
    before, after = body.joint_positions(body.zero_pose()), narrow.joint_positions(narrow.zero_pose())
    for side in ("l_", "r_"):
        shift = np.array([before[j[side + "shoulder"], 0] * -0.2, 0.0, 0.0])  # the chest's joint is at x = 0
        for joint in ("shoulder", "elbow", "wrist"):  # the arm moves rigidly with its shoulder
            np.testing.assert_allclose(after[j[side + joint]], before[j[side + joint]] + shift, atol=1e-12)
    np.testing.assert_allclose(after[j["neck"]], before[j["neck"]], atol=1e-12)
    np.testing.assert_allclose(narrow.semi_axes, body.semi_axes, atol=1e-12)  # no ellipsoid changes shape
    back = narrow.with_length_groups(("shoulders",)).with_lengths(np.ones(1))
    np.testing.assert_allclose(back.joint_positions(back.zero_pose()), before, atol=1e-12)


def test_girth_factor_scales_only_the_short_semi_axes():
    body = load_body("default")
    g = body.length_groups.index("girth")
    assert body.length_prior_sd[g] > body.length_prior_sd[body.length_groups.index("shank")]  # builds vary more
    factors = np.ones(len(body.length_groups))
    factors[g] = 1.2
    stout = body.with_lengths(factors)
    np.testing.assert_allclose(stout.joint_positions(stout.zero_pose()), body.joint_positions(body.zero_pose()))
    np.testing.assert_allclose(stout.semi_axes[:, 0], body.semi_axes[:, 0], rtol=1e-12)
    np.testing.assert_allclose(stout.semi_axes[:, 1:], body.semi_axes[:, 1:] * 1.2, rtol=1e-12)
    only = stout.with_length_groups(("girth",))
    np.testing.assert_allclose(only.with_lengths(np.ones(1)).semi_axes, body.semi_axes, atol=1e-12)


def test_lengths_stretched_together_equal_each_stretched_alone():
    full = load_body("default")
    rng = np.random.default_rng(3)
    for body in (full, full.with_length_groups(("upperarm", "shank", "girth", "forearm", "shoulders"))):
        G = len(body.length_groups)
        body = body.with_lengths(np.exp(rng.normal(0.0, 0.1, G)))
        one_step = body.length_factors * np.where(np.eye(G, dtype=bool), np.exp(1e-5), 1.0)  # the Jacobian's
        for factors in (one_step, body.length_factors * np.exp(rng.normal(0.0, 0.1, (3, G)))):
            for together, factor in zip(body.with_each_lengths(factors), factors, strict=True):
                alone = body.with_lengths(factor)
                for field in ("offset", "ellipsoid_rotation", "ellipsoid_centre", "semi_axes", "joint_offset",
                              "length_factors"):
                    np.testing.assert_allclose(getattr(together, field), getattr(alone, field), rtol=0, atol=1e-12)


def test_length_derivatives_are_those_of_the_stretched_bodies():
    """`length_derivatives` (centres and shape matrices of the posed ellipsoids per unit ln ℓ) against central
    differences of `with_lengths`, for every kind of factor: stretches, the girth and the shoulders' joint group."""
    full = load_body("default")
    rng = np.random.default_rng(5)
    for body in (full, full.with_length_groups(("upperarm", "shank", "girth", "forearm", "shoulders"))):
        G = len(body.length_groups)
        body = body.with_lengths(np.exp(rng.normal(0.0, 0.1, G)))
        pose = body.clip(body.zero_pose() + np.r_[np.zeros(3), rng.normal(0.0, 0.4, body.pose_size - 3)])
        dt, dM = body.length_derivatives(body.fk(pose))
        step = 1e-6
        for g in range(G):
            ends = []
            for sign in (1.0, -1.0):
                factors = body.length_factors.copy()
                factors[g] *= np.exp(sign * step)
                ellipsoids = body.with_lengths(factors).ellipsoids(pose)
                ends.append((ellipsoids.t, ellipsoids.shapes[0]))
            np.testing.assert_allclose(dt[g], (ends[0][0] - ends[1][0]) / (2 * step), atol=1e-8)
            np.testing.assert_allclose(dM[g], (ends[0][1] - ends[1][1]) / (2 * step), atol=1e-8)
            assert np.abs(dt[g]).max() > 1e-3 or np.abs(dM[g]).max() > 1e-4  # every factor moves something
