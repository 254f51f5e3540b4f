"""Property tests for estimator.core.geometry and estimator.core.projection: group identities,
stability near 0 and pi, analytic Jacobians against central differences, batch shapes and input
validation."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from posefuse.estimator.core import geometry as g
from posefuse.estimator.core import projection as pj

PI = np.pi
FAST = settings(deadline=None, max_examples=60)

K = np.array([[900.0, 0.5, 320.0], [0.0, 910.0, 240.0], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------- strategies
finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)


@st.composite
def unit_axes(draw) -> np.ndarray:
    v = np.array([draw(finite), draw(finite), draw(finite)])
    n = np.linalg.norm(v)
    assume(n > 1e-3)
    return v / n


@st.composite
def rotvecs(draw, max_angle: float = PI - 1e-6) -> np.ndarray:
    """Rotation vectors with angles spread over [0, max_angle], including tiny ones."""
    axis = draw(unit_axes())
    kind = draw(st.sampled_from(["uniform", "tiny", "near_max"]))
    if kind == "uniform":
        angle = draw(st.floats(0.0, max_angle))
    elif kind == "tiny":
        angle = 10.0 ** draw(st.floats(-14.0, -1.0))
    else:
        angle = max_angle - 10.0 ** draw(st.floats(-9.0, -1.0))
    return axis * angle


@st.composite
def transforms(draw) -> np.ndarray:
    w = draw(rotvecs())
    t = np.array([draw(st.floats(-5.0, 5.0)) for _ in range(3)])
    return g.make_transform(g.so3_exp(w), t)


def _rotation_distance(R1: np.ndarray, R2: np.ndarray) -> float:
    return float(np.max(np.abs(R1 - R2)))


# --------------------------------------------------------------------------- hat / vee
@FAST
@given(st.lists(finite, min_size=3, max_size=3), st.lists(finite, min_size=3, max_size=3))
def test_hat_is_cross_product_and_vee_inverts_it(w, v):
    w, v = np.array(w), np.array(v)
    W = g.hat(w)
    np.testing.assert_allclose(W @ v, np.cross(w, v), atol=1e-15)
    np.testing.assert_array_equal(W, -W.T)
    np.testing.assert_array_equal(g.vee(W), w)


def test_vee_takes_skew_part():
    M = np.arange(9.0).reshape(3, 3)
    np.testing.assert_allclose(g.vee(M), g.vee(0.5 * (M - M.T)))


# --------------------------------------------------------------------------- so3 exp / log
@FAST
@given(rotvecs(max_angle=2 * PI))
def test_so3_exp_is_rotation_and_matches_references(w):
    R = g.so3_exp(w)
    assert g.is_rotation(R, atol=1e-12)
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(R, scipy.linalg.expm(g.hat(w)), atol=1e-13)


def _exp_series(W: np.ndarray, coef=lambda k: 1.0 / np.prod(np.arange(1.0, k + 1))) -> np.ndarray:
    """sum_{k=0..10} coef(k) W^k; for |W| <= 0.011 the remainder is below 1e-23."""
    out, P = np.zeros((3, 3)), np.eye(3)
    for k in range(11):
        out = out + coef(k) * P
        P = P @ W
    return out


@pytest.mark.parametrize("angle", [1e-300, 1e-12, 1e-8, 1e-5, 0.01 - 1e-15, 0.01, 0.01 + 1e-15])
def test_so3_exp_small_angles_machine_precision(angle):
    w = np.array([0.48, -0.6, 0.64]) * angle
    R = g.so3_exp(w)
    # exact second-order expansion; the remainder is far below double precision here
    np.testing.assert_allclose(R, _exp_series(g.hat(w)), rtol=0, atol=2.3e-16)  # 1 ulp of 1
    np.testing.assert_allclose(g.vee(R), w * (np.sin(angle) / angle), rtol=1e-15)


@FAST
@given(rotvecs())
def test_log_exp_roundtrip(w):
    w_back = g.so3_log(g.so3_exp(w))
    angle = np.linalg.norm(w)
    # relative to the angle for tiny angles (components far below |w| * eps are not
    # representable in R and cannot be recovered), absolute otherwise
    assert np.linalg.norm(w_back - w) <= 1e-14 * min(angle, 1.0)


@FAST
@given(rotvecs(), st.sampled_from([1.0, 1e-3, 1e-9]))
def test_exp_of_one_vector_equals_the_batched_path(w, scale):
    # one (3,) vector takes a scalar path; the batch path must give the same rotation
    w = np.asarray(w) * scale
    np.testing.assert_allclose(g.so3_exp(w), g.so3_exp(w[None])[0], rtol=0, atol=4e-16)


@FAST
@given(rotvecs(), st.sampled_from([1.0, 1e-3, 1e-9]))
def test_log_of_one_matrix_equals_the_batched_path(w, scale):
    # one (3, 3) matrix takes a scalar path below the near-pi branch (cos < -1/2, left to the
    # batch path); both give the same vector
    R = g.so3_exp(np.asarray(w) * scale)
    one, batched = g.so3_log(R), g.so3_log(R[None])[0]
    np.testing.assert_allclose(one, batched, rtol=0, atol=1e-15 * max(1.0, np.linalg.norm(w)))


@FAST
@given(unit_axes(), st.sampled_from([1e-12, 1e-8, 1e-4, 0.01]))
def test_log_tiny_angles_relative_accuracy(axis, angle):
    w = axis * angle
    w_back = g.so3_log(g.so3_exp(w))
    assert np.linalg.norm(w_back - w) <= 1e-13 * angle
    assert abs(g.rotation_angle(g.so3_exp(w)) - angle) <= 1e-13 * angle


@FAST
@given(unit_axes(), st.sampled_from([1e-6, 1e-9, 1e-12]))
def test_log_near_pi(axis, gap):
    angle = PI - gap
    w = axis * angle
    R = g.so3_exp(w)
    w_back = g.so3_log(R)
    np.testing.assert_allclose(w_back, w, rtol=0, atol=1e-12)
    assert np.linalg.norm(w_back) <= PI
    np.testing.assert_allclose(g.so3_exp(w_back), R, rtol=0, atol=1e-14)
    assert abs(g.rotation_angle(R) - angle) < 1e-14


@FAST
@given(unit_axes())
def test_log_exactly_pi(axis):
    R = 2.0 * np.outer(axis, axis) - np.eye(3)  # rotation by exactly pi about axis
    w_back = g.so3_log(R)
    assert abs(np.linalg.norm(w_back) - PI) < 1e-14
    assert min(np.abs(w_back - PI * axis).max(), np.abs(w_back + PI * axis).max()) < 1e-13
    np.testing.assert_allclose(g.so3_exp(w_back), R, rtol=0, atol=1e-14)
    np.testing.assert_allclose(g.rotation_angle(R), PI, rtol=0, atol=1e-15)


def test_log_exactly_pi_about_coordinate_axes_is_deterministic():
    for i in range(3):
        R = -np.eye(3)
        R[i, i] = 1.0
        expected = np.zeros(3)
        expected[i] = PI
        np.testing.assert_allclose(g.so3_log(R), expected, atol=1e-15)


@FAST
@given(st.integers(0, 2**32 - 1))
def test_exp_log_random_rotations(seed):
    Rs = g.random_rotations(20, seed=seed)
    ws = g.so3_log(Rs)
    assert np.all(np.linalg.norm(ws, axis=-1) <= PI)
    np.testing.assert_allclose(g.so3_exp(ws), Rs, rtol=0, atol=1e-14)
    np.testing.assert_allclose(ws, Rotation.from_matrix(Rs).as_rotvec(), atol=1e-12)


def test_log_identity_is_zero():
    np.testing.assert_array_equal(g.so3_log(np.eye(3)), np.zeros(3))
    assert g.rotation_angle(np.eye(3)) == 0.0


# --------------------------------------------------------------------------- Jacobians
def _central_diff(f, x: np.ndarray, eps: float) -> np.ndarray:
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = eps
        cols.append((f(x + e) - f(x - e)) / (2 * eps))
    return np.stack(cols, axis=-1)


jac_rotvecs = rotvecs(max_angle=PI - 1e-2)


@FAST
@given(jac_rotvecs)
def test_left_jacobian_numeric(w):
    R_inv = g.so3_exp(w).T
    num = _central_diff(lambda d: g.so3_log(g.so3_exp(w + d) @ R_inv), np.zeros(3), 1e-6)
    np.testing.assert_allclose(g.so3_left_jacobian(w), num, atol=1e-8)


@FAST
@given(jac_rotvecs)
def test_right_jacobian_numeric(w):
    R_inv = g.so3_exp(w).T
    num = _central_diff(lambda d: g.so3_log(R_inv @ g.so3_exp(w + d)), np.zeros(3), 1e-6)
    np.testing.assert_allclose(g.so3_right_jacobian(w), num, atol=1e-8)


@FAST
@given(jac_rotvecs)
def test_inverse_jacobians_numeric(w):
    # log(exp(d) exp(w)) ~= w + J_l^-1 d and log(exp(w) exp(d)) ~= w + J_r^-1 d
    R = g.so3_exp(w)
    num_l = _central_diff(lambda d: g.so3_log(g.so3_exp(d) @ R), np.zeros(3), 1e-6)
    num_r = _central_diff(lambda d: g.so3_log(R @ g.so3_exp(d)), np.zeros(3), 1e-6)
    np.testing.assert_allclose(g.so3_left_jacobian_inv(w), num_l, atol=1e-7)
    np.testing.assert_allclose(g.so3_right_jacobian_inv(w), num_r, atol=1e-7)


@FAST
@given(rotvecs())
def test_jacobian_identities(w):
    Jl, Jr = g.so3_left_jacobian(w), g.so3_right_jacobian(w)
    np.testing.assert_allclose(Jr, g.so3_left_jacobian(-w), atol=1e-15)
    np.testing.assert_allclose(Jl, g.so3_exp(w) @ Jr, atol=1e-14)
    np.testing.assert_allclose(g.so3_left_jacobian_inv(w) @ Jl, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(g.so3_right_jacobian_inv(w) @ Jr, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(Jl @ g.so3_left_jacobian_inv(w), np.eye(3), atol=1e-12)


@FAST
@given(rotvecs(max_angle=PI))
def test_inverse_jacobian_gram_closed_form(w):
    # the normal matrix the mixture's refinement uses, against the explicit products
    Jl_inv, Jr_inv = g.so3_left_jacobian_inv(w), g.so3_right_jacobian_inv(w)
    gram = g.so3_jacobian_inv_gram(w)
    np.testing.assert_allclose(gram, Jr_inv.T @ Jr_inv, atol=1e-12)
    np.testing.assert_allclose(gram, Jl_inv.T @ Jl_inv, atol=1e-12)
    # and J^T r = r, which makes the gradient a weighted sum of the residuals
    np.testing.assert_allclose(Jr_inv.T @ w, w, atol=1e-12)


def test_inverse_jacobian_gram_batched():
    w = np.random.default_rng(3).normal(size=(4, 5, 3))
    Jr_inv = g.so3_right_jacobian_inv(w)
    expected = np.swapaxes(Jr_inv, -1, -2) @ Jr_inv
    np.testing.assert_allclose(g.so3_jacobian_inv_gram(w), expected, atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, 0.01 - 1e-12, 0.01, 0.01 + 1e-12])
def test_jacobians_continuous_across_taylor_switch(angle):
    w = np.array([0.6, 0.0, -0.8]) * angle
    W = g.hat(w)
    # J_l = sum W^k / (k+1)!;  J_l^-1 = sum B_k W^k / k! (Bernoulli numbers, B_1 = -1/2)
    bern = {0: 1.0, 1: -0.5, 2: 1 / 6, 4: -1 / 30, 6: 1 / 42, 8: -1 / 30, 10: 5 / 66}
    fact = lambda k: float(np.prod(np.arange(1.0, k + 1)))  # noqa: E731
    Jl = _exp_series(W, lambda k: 1.0 / fact(k + 1))
    Jl_inv = _exp_series(W, lambda k: bern.get(k, 0.0) / fact(k))
    np.testing.assert_allclose(g.so3_left_jacobian(w), Jl, rtol=0, atol=2.3e-16)
    np.testing.assert_allclose(g.so3_left_jacobian_inv(w), Jl_inv, rtol=0, atol=2.3e-16)
    np.testing.assert_allclose(g.so3_right_jacobian(w), Jl.T, rtol=0, atol=2.3e-16)
    np.testing.assert_allclose(g.so3_right_jacobian_inv(w), Jl_inv.T, rtol=0, atol=2.3e-16)


@FAST
@given(
    st.floats(-2.0, 2.0),
    st.floats(-2.0, 2.0),
    st.floats(0.05, 10.0),
)
def test_project_jacobian_numeric(x, y, z):
    p = np.array([x, y, z])
    num = _central_diff(lambda q: pj.project(q, K), p, 1e-7 * max(z, 1.0))
    J = pj.project_jacobian(p, K)
    scale = np.abs(J).max()
    np.testing.assert_allclose(J, num, rtol=0, atol=1e-6 * scale)


def test_project_values_and_principal_point():
    np.testing.assert_allclose(pj.project([0.0, 0.0, 2.0], K), [320.0, 240.0])
    p = np.array([0.1, -0.2, 2.0])
    expected = (K @ p)[:2] / p[2]
    np.testing.assert_allclose(pj.project(p, K), expected, rtol=1e-15)


def test_project_behind_camera_and_in_front():
    pts = np.array([[0.1, 0.2, 1.0], [0.1, 0.2, -1.0], [0.0, 0.0, 0.0], [0, 0, np.nan]])
    with np.errstate(all="raise"):
        uv = pj.project(pts, K)
        pj.project_jacobian(pts, K)
    assert uv.shape == (4, 2)
    np.testing.assert_array_equal(pj.in_front(pts), [True, False, False, False])
    assert not pj.in_front([0.0, 0.0, 1e-7])
    assert pj.in_front([0.0, 0.0, 1e-7], min_z=0.0)


# --------------------------------------------------------------------------- SE(3)
@FAST
@given(rotvecs(), st.lists(st.floats(-10.0, 10.0), min_size=3, max_size=3))
def test_se3_exp_log_roundtrip_and_expm(phi, rho):
    xi = np.concatenate([rho, phi])
    T = g.se3_exp(xi)
    twist = np.zeros((4, 4))
    twist[:3, :3] = g.hat(phi)
    twist[:3, 3] = rho
    np.testing.assert_allclose(T, scipy.linalg.expm(twist), atol=1e-12)
    np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(g.se3_log(T), xi, atol=1e-12)


def test_se3_order_is_translation_then_rotation():
    T = g.se3_exp([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(T, g.make_transform(np.eye(3), [1.0, 2.0, 3.0]))
    T = g.se3_exp([0.0, 0.0, 0.0, 0.0, 0.0, 0.5])
    np.testing.assert_allclose(T[:3, :3], Rotation.from_euler("z", 0.5).as_matrix(), atol=1e-15)


@FAST
@given(transforms(), transforms(), st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3))
def test_compose_invert_transform_points(T_a_b, T_b_c, p_c):
    p_c = np.array(p_c)
    T_b_a = g.invert(T_a_b)
    np.testing.assert_allclose(g.compose(T_a_b, T_b_a), np.eye(4), atol=1e-13)
    np.testing.assert_allclose(g.compose(T_b_a, T_a_b), np.eye(4), atol=1e-13)
    np.testing.assert_allclose(T_b_a, np.linalg.inv(T_a_b), atol=1e-12)
    np.testing.assert_allclose(g.invert(T_b_a), T_a_b, atol=1e-14)
    np.testing.assert_array_equal(T_b_a[3], [0.0, 0.0, 0.0, 1.0])

    T_a_c = g.compose(T_a_b, T_b_c)
    p_a = g.transform_points(T_a_c, p_c)
    np.testing.assert_allclose(
        p_a, g.transform_points(T_a_b, g.transform_points(T_b_c, p_c)), atol=1e-12
    )
    np.testing.assert_allclose(p_a, (T_a_c @ np.append(p_c, 1.0))[:3], atol=1e-12)
    np.testing.assert_allclose(g.transform_points(g.invert(T_a_c), p_a), p_c, atol=1e-12)


def test_invert_has_the_bits_of_the_inverse_written_by_hand():
    """invert is ``R.T`` and ``-R.T @ t`` as the callers it replaced wrote them, to the bit and to
    the sign of a zero (an axis-aligned camera above the origin has exact zeros in -R^T t)."""
    rng = np.random.default_rng(3)
    flips = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.eye(3)]
    rotations = flips + list(Rotation.random(200, rng=rng).as_matrix())
    moves = [np.zeros(3), np.array([0.0, 0.0, 1.2]), np.array([-0.0, 0.3, 0.0])]
    for R in rotations:
        for t in moves + [rng.normal(size=3)]:
            T = g.make_transform(R, t)
            by_hand = np.eye(4)
            by_hand[:3, :3] = T[:3, :3].T
            by_hand[:3, 3] = -T[:3, :3].T @ T[:3, 3]
            assert g.invert(T).tobytes() == by_hand.tobytes()
    batch = np.stack([g.make_transform(R, moves[1]) for R in rotations])
    assert g.invert(batch).tobytes() == np.stack([g.invert(T) for T in batch]).tobytes()


def test_frame_naming_example():
    T_world_cam = g.make_transform(Rotation.from_euler("x", PI).as_matrix(), [0.0, 0.0, 1.0])
    T_world_obj = g.make_transform(np.eye(3), [0.1, 0.0, 0.0])
    T_cam_obj = g.compose(g.invert(T_world_cam), T_world_obj)
    # the object origin is 1 m in front of a camera looking down -z_world
    np.testing.assert_allclose(T_cam_obj[:3, 3], [0.1, 0.0, 1.0], atol=1e-15)


def test_make_transform_broadcasts():
    Rs = g.random_rotations(4, seed=1)
    T = g.make_transform(Rs, np.zeros(3))
    assert T.shape == (4, 4, 4)
    T = g.make_transform(np.eye(3), np.ones((2, 5, 3)))
    assert T.shape == (2, 5, 4, 4)
    np.testing.assert_array_equal(T[..., 3, :], np.broadcast_to([0, 0, 0, 1.0], (2, 5, 4)))


# --------------------------------------------------------------------------- utilities
def test_is_rotation():
    R = g.random_rotations(5, seed=3)
    assert g.is_rotation(R).all()
    assert g.is_rotation(R).shape == (5,)
    assert not g.is_rotation(np.diag([1.0, 1.0, -1.0]))  # reflection
    assert not g.is_rotation(1.001 * np.eye(3))
    assert not g.is_rotation(np.full((3, 3), np.nan))
    assert not g.is_rotation(np.diag([1.0, 1.0, np.inf]))
    assert g.is_rotation(np.eye(3) + 1e-8)
    assert not g.is_rotation(np.eye(3) + 1e-8, atol=1e-10)


def test_random_rotations_seeded():
    a = g.random_rotations(10, seed=42)
    b = g.random_rotations(10, seed=42)
    c = g.random_rotations(10, seed=43)
    assert a.shape == (10, 3, 3)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    assert g.random_rotations(1, seed=np.random.default_rng(0)).shape == (1, 3, 3)
    assert g.random_rotations(0, seed=0).shape == (0, 3, 3)
    with pytest.raises(ValueError):
        g.random_rotations(3, seed=None)
    with pytest.raises(ValueError):
        g.random_rotations(-1, seed=0)


@FAST
@given(rotvecs(max_angle=PI))
def test_rotation_angle(w):
    angle = np.linalg.norm(w)
    assert abs(g.rotation_angle(g.so3_exp(w)) - angle) <= 1e-14 * min(angle, 1.0)


# --------------------------------------------------------------------------- batches
def _loop(f, x: np.ndarray, core_ndim: int) -> np.ndarray:
    batch = x.shape[: x.ndim - core_ndim]
    flat = x.reshape((-1,) + x.shape[x.ndim - core_ndim :])
    out = np.stack([f(xi) for xi in flat])
    return out.reshape(batch + out.shape[1:])


@pytest.mark.parametrize("batch", [(), (5,), (4, 3), (2, 1, 3)])
def test_batched_functions_match_loops(batch):
    rng = np.random.default_rng(7)
    n = int(np.prod(batch))
    w = rng.normal(size=batch + (3,))
    w[..., :] *= (rng.uniform(0, PI, size=batch) / np.linalg.norm(w, axis=-1))[..., None]
    if n >= 2:  # put a tiny and a near-pi angle in every batch
        flat = w.reshape(-1, 3)
        flat[0] *= 1e-10
        flat[1] *= (PI - 1e-9) / np.linalg.norm(flat[1])
    R = g.so3_exp(w)
    assert R.shape == batch + (3, 3)
    fns3 = [
        g.hat,
        g.so3_exp,
        g.so3_left_jacobian,
        g.so3_right_jacobian,
        g.so3_left_jacobian_inv,
        g.so3_right_jacobian_inv,
    ]
    for f in fns3:
        np.testing.assert_allclose(f(w), _loop(f, w, 1), rtol=0, atol=1e-15)
    for f in [g.vee, g.so3_log, g.rotation_angle, g.is_rotation]:
        np.testing.assert_allclose(f(R), _loop(f, R, 2), rtol=0, atol=1e-15)
    xi = np.concatenate([rng.normal(size=batch + (3,)), w], axis=-1)
    T = g.se3_exp(xi)
    assert T.shape == batch + (4, 4)
    np.testing.assert_allclose(T, _loop(g.se3_exp, xi, 1), atol=1e-15)
    np.testing.assert_allclose(g.se3_log(T), _loop(g.se3_log, T, 2), atol=1e-15)
    np.testing.assert_allclose(g.invert(T), _loop(g.invert, T, 2), atol=1e-15)
    np.testing.assert_allclose(
        g.compose(T, g.invert(T)), np.broadcast_to(np.eye(4), T.shape), atol=1e-12
    )
    pts = rng.normal(size=batch + (3,)) + [0.0, 0.0, 3.0]
    np.testing.assert_allclose(pj.project(pts, K), _loop(lambda p: pj.project(p, K), pts, 1))
    assert pj.project_jacobian(pts, K).shape == batch + (2, 3)
    assert pj.in_front(pts).shape == batch


def test_transform_points_shapes():
    rng = np.random.default_rng(11)
    Ts = g.se3_exp(rng.normal(size=(4, 6)))
    pts = rng.normal(size=(7, 3))
    assert g.transform_points(Ts[0], pts[0]).shape == (3,)
    assert g.transform_points(Ts[0], pts).shape == (7, 3)
    out = g.transform_points(Ts, pts)  # (4,4,4) with (7,3) -> (4,7,3)
    assert out.shape == (4, 7, 3)
    for i in range(4):
        np.testing.assert_allclose(out[i], g.transform_points(Ts[i], pts), atol=1e-15)
    per = rng.normal(size=(4, 7, 3))  # (B,N,3) paired with (B,4,4)
    out = g.transform_points(Ts, per)
    for i in range(4):
        np.testing.assert_allclose(out[i], g.transform_points(Ts[i], per[i]), atol=1e-15)
    one_each = g.transform_points(Ts, per[:, :1, :])
    assert one_each.shape == (4, 1, 3)
    assert g.transform_points(Ts, pts[0]).shape == (4, 3)


# --------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    ("fn", "args", "names"),
    [
        (g.hat, (np.zeros(4),), "hat"),
        (g.hat, (np.zeros((3, 2)),), "hat"),
        (g.vee, (np.zeros(3),), "vee"),
        (g.vee, (np.zeros((3, 4)),), "vee"),
        (g.so3_exp, (np.zeros((5, 2)),), "so3_exp"),
        (g.so3_log, (np.zeros((4, 4)),), "so3_log: R"),
        (g.so3_log, (np.zeros(9),), "so3_log: R"),
        (g.so3_left_jacobian, (np.zeros(6),), "so3_left_jacobian: w"),
        (g.so3_right_jacobian, (np.zeros(2),), "so3_right_jacobian: w"),
        (g.so3_left_jacobian_inv, (np.zeros((2, 4)),), "so3_left_jacobian_inv: w"),
        (g.so3_right_jacobian_inv, (1.0,), "so3_right_jacobian_inv: w"),
        (g.se3_exp, (np.zeros(3),), "se3_exp"),
        (g.se3_log, (np.eye(3),), "se3_log"),
        (g.make_transform, (np.eye(4), np.zeros(3)), "make_transform: R"),
        (g.make_transform, (np.eye(3), np.zeros(4)), "make_transform: t"),
        (g.make_transform, (np.zeros((2, 3, 3)), np.zeros((3, 3))), "make_transform: batch"),
        (g.compose, (np.eye(3), np.eye(4)), "compose: T_a_b"),
        (g.compose, (np.eye(4), np.eye(3)), "compose: T_b_c"),
        (g.invert, (np.eye(3),), "invert: T_a_b"),
        (g.transform_points, (np.eye(4), np.zeros((5, 4))), "transform_points: pts_b"),
        (g.transform_points, (np.eye(3), np.zeros((5, 3))), "transform_points: T_a_b"),
        (pj.project, (np.zeros((5, 2)), K), "project: pts_cam"),
        (pj.project, (np.ones(3), K[:2]), "project: K"),
        (pj.project, (np.ones(3), np.eye(3) * 2), "project: the last row of K"),
        (pj.project_jacobian, (np.ones(4), K), "project_jacobian: pts_cam"),
        (pj.project_jacobian, (np.ones(3), K.ravel()), "project_jacobian: K"),
        (pj.in_front, (np.ones(2),), "in_front: pts_cam"),
        (g.rotation_angle, (np.eye(4),), "rotation_angle: R"),
        (g.is_rotation, (np.zeros(3),), "is_rotation"),
    ],
)
def test_bad_shapes_raise_value_error(fn, args, names):
    """Refused with one message that starts with the function and the argument it names, so a
    user's mistake points at what to fix (case and spelling as in the signature)."""
    with pytest.raises(ValueError) as info:
        fn(*args)
    assert str(info.value).startswith(names), str(info.value)


def test_random_rotations_refuses_what_is_not_a_count_or_a_seed():
    with pytest.raises(ValueError, match=r"^random_rotations: an explicit seed is required$"):
        g.random_rotations(2, None)
    for n in (-1, 2.5, True, "3"):
        with pytest.raises(ValueError) as info:
            g.random_rotations(n, 0)
        assert str(info.value) == f"random_rotations: n must be a non-negative int, got {n!r}"


def test_in_front_and_is_rotation_at_their_bounds():
    """A point exactly at min_z is not in front (strictly beyond); an exact rotation is one at
    atol = 0 (the bounds are inclusive there)."""
    pts = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5 + 1e-12], [0.0, 0.0, np.nan]])
    np.testing.assert_array_equal(pj.in_front(pts, min_z=0.5), [False, True, False])
    assert g.is_rotation(np.eye(3), atol=0.0)
    assert g.is_rotation(np.diag([1.0, -1.0, -1.0]), atol=0.0)


def test_project_of_a_point_at_depth_zero_warns_nothing():
    """Points at z = 0 project to inf / nan without a floating-point warning (callers mask them
    with in_front)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv = pj.project(np.array([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0]]), K)
    assert not np.isfinite(uv).all()


@pytest.mark.parametrize("deg", [121.0, 135.0, 150.0, 170.0, 179.0])
@pytest.mark.parametrize("axis", [[1.0, 1.0, 1.0], [1.0, -2.0, 0.5], [-0.3, 0.2, -1.0]])
def test_log_between_two_thirds_of_pi_and_pi_with_oblique_axes(deg, axis):
    """The near-pi branch (cos t < -1/2) on axes that are no coordinate axis: there the largest
    column of the symmetric part is shorter than 1 and must be normalised."""
    a = np.asarray(axis) / np.linalg.norm(axis)
    w = a * np.deg2rad(deg)
    np.testing.assert_allclose(g.so3_log(g.so3_exp(w)), w, atol=1e-12)


@pytest.mark.parametrize("axis", [[1.0, 1.0, 1.0], [0.2, -1.0, 0.4], [-1.0, 0.5, -0.5]])
def test_log_exactly_pi_makes_the_largest_component_positive(axis):
    a = np.asarray(axis) / np.linalg.norm(axis)
    R = 2.0 * np.outer(a, a) - np.eye(3)  # exactly pi about a
    w = g.so3_log(R)
    assert np.linalg.norm(w) == pytest.approx(np.pi, abs=1e-12)
    k = int(np.argmax(np.abs(w)))
    assert w[k] > 0
    np.testing.assert_allclose(np.abs(w), np.abs(a) * np.pi, atol=1e-7)
