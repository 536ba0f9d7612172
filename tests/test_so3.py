"""Property tests of the SO(3) toolkit (jaxlie-style): group identities, Jacobians, near 0 and near pi."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from magcal_cli import so3

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
unit_dirs = arrays(np.float64, 3, elements=finite).filter(lambda v: np.linalg.norm(v) > 1e-3).map(
    lambda v: v / np.linalg.norm(v))


@st.composite
def tangent(draw: st.DrawFn) -> np.ndarray:
    """Rotation vectors across the whole ball: tiny (1e-9..1e-5), ordinary, and within 1e-6 of pi."""
    axis = draw(unit_dirs)
    kind = draw(st.sampled_from(["tiny", "mid", "near_pi"]))
    if kind == "tiny":
        angle = draw(st.floats(1e-9, 1e-5))
    elif kind == "mid":
        angle = draw(st.floats(1e-5, np.pi - 1e-3))
    else:
        angle = np.pi - draw(st.floats(1e-9, 1e-6))
    return axis * angle


@given(tangent())
def test_log_inverts_exp(phi: np.ndarray) -> None:
    """Log(Exp(phi)) == phi for |phi| < pi, including the Taylor branch and the neighbourhood of pi."""
    np.testing.assert_allclose(so3.log(so3.exp(phi)), phi, atol=1e-9)


@given(tangent())
def test_exp_is_a_rotation(phi: np.ndarray) -> None:
    """Exp lands on SO(3): orthonormal with determinant +1."""
    r = so3.exp(phi)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-14)


@given(tangent())
def test_exp_matches_scipy(phi: np.ndarray) -> None:
    """The closed form with Taylor branches agrees with scipy's Rotation.from_rotvec."""
    from scipy.spatial.transform import Rotation

    np.testing.assert_allclose(so3.exp(phi), Rotation.from_rotvec(phi).as_matrix(), atol=1e-14)


def _numeric_right_jacobian(phi: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Central differences of Log(Exp(phi)^T Exp(phi + d)) with respect to d."""
    base = so3.exp(phi)
    cols = []
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        cols.append((so3.log(base.T @ so3.exp(phi + d)) - so3.log(base.T @ so3.exp(phi - d))) / (2 * eps))
    return np.stack(cols, axis=1)


@given(tangent().filter(lambda p: np.linalg.norm(p) < np.pi - 1e-3))
def test_right_jacobian_matches_finite_differences(phi: np.ndarray) -> None:
    """Exp(phi + d) = Exp(phi) Exp(J_r(phi) d) to first order (tolerance 1e-7: central differences, eps 1e-6)."""
    np.testing.assert_allclose(so3.right_jacobian(phi), _numeric_right_jacobian(phi), atol=1e-7)


@given(tangent())
def test_right_jacobian_inverse(phi: np.ndarray) -> None:
    """J_r^-1 J_r = I everywhere below 2 pi, including near pi where the closed form uses cot(t/2)."""
    np.testing.assert_allclose(so3.right_jacobian_inv(phi) @ so3.right_jacobian(phi), np.eye(3), atol=1e-9)


@given(tangent())
def test_left_jacobian_is_rotated_right_jacobian(phi: np.ndarray) -> None:
    """J_l(phi) = Exp(phi) J_r(phi)."""
    np.testing.assert_allclose(so3.left_jacobian(phi), so3.exp(phi) @ so3.right_jacobian(phi), atol=1e-12)


@given(arrays(np.float64, 3, elements=finite), arrays(np.float64, 3, elements=finite))
def test_hat_is_cross_product_and_vee_inverts_it(a: np.ndarray, b: np.ndarray) -> None:
    """hat(a) b = a x b and vee(hat(a)) = a."""
    np.testing.assert_allclose(so3.hat(a) @ b, np.cross(a, b), atol=1e-15)
    np.testing.assert_allclose(so3.vee(so3.hat(a)), a, atol=0)


@given(tangent())
def test_quaternion_and_rpy_round_trips(phi: np.ndarray) -> None:
    """from_quat(as_quat(R)) == R (w >= 0) and from_rpy(as_rpy(R)) == R."""
    r = so3.exp(phi)
    q = so3.as_quat(r)
    assert q[0] >= 0
    np.testing.assert_allclose(so3.from_quat(q), r, atol=1e-12)
    # near gimbal lock (pitch = +-90 deg) the Euler extraction (scipy's method) switches to its locked branch and
    # drops a term of the size of its switching threshold: a sweep of pitch = 90 deg - 1e-12..1e-1 measured 1.9e-7
    np.testing.assert_allclose(so3.from_rpy(so3.as_rpy(r)), r, atol=1e-6)


def test_rpy_convention_is_z_y_x() -> None:
    """rpy (roll, pitch, yaw) means Rz(yaw) Ry(pitch) Rx(roll), roll applied first (calibration-file.md)."""
    r, p, y = 0.1, -0.2, 0.3
    expect = so3.exp([0, 0, y]) @ so3.exp([0, p, 0]) @ so3.exp([r, 0, 0])
    np.testing.assert_allclose(so3.from_rpy([r, p, y]), expect, atol=1e-15)


def test_batches_keep_their_shape() -> None:
    """Leading batch dimensions pass through every map."""
    phi = np.random.default_rng(0).normal(size=(4, 5, 3))
    assert so3.exp(phi).shape == (4, 5, 3, 3)
    assert so3.log(so3.exp(phi)).shape == (4, 5, 3)
    assert so3.right_jacobian_inv(phi).shape == (4, 5, 3, 3)
    assert so3.as_quat(so3.exp(phi)).shape == (4, 5, 4)


@settings(max_examples=30)
@given(st.integers(0, 10_000))
def test_wahba_recovers_a_rotation_from_noiseless_pairs(seed: int) -> None:
    """Two or more non-parallel vector pairs determine the rotation exactly."""
    rng = np.random.default_rng(seed)
    r = so3.exp(rng.normal(size=3))
    body = rng.normal(size=(3, 3))
    np.testing.assert_allclose(so3.wahba(body, body @ r.T), r, atol=1e-10)


@settings(max_examples=30)
@given(st.integers(0, 10_000))
def test_polar_factors(seed: int) -> None:
    """m = U P with U a rotation and P symmetric, also for det(m) < 0 (then P is indefinite)."""
    m = np.random.default_rng(seed).normal(size=(3, 3))
    u, p = so3.polar(m)
    np.testing.assert_allclose(u @ p, m, atol=1e-12)
    np.testing.assert_allclose(u @ u.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(u) == pytest.approx(1.0)
    np.testing.assert_allclose(p, p.T, atol=1e-12)


def test_cumulative_product_matches_a_sequential_product() -> None:
    """The log-depth scan equals R_0 R_1 ... R_k for every k."""
    rots = so3.exp(np.random.default_rng(1).normal(size=(777, 3)) * 0.2)
    out = so3.cumulative_product(rots)
    acc = np.eye(3)
    for k in range(len(rots)):
        acc = acc @ rots[k]
        np.testing.assert_allclose(out[k], acc, atol=1e-12)


def test_slerp_follows_the_geodesic_between_neighbours() -> None:
    """At the given times the rotations themselves; between two, the rotation a fraction w along the geodesic
    (angle w times theirs, same axis); outside the span held at the ends."""
    rng = np.random.default_rng(8)
    rots = so3.exp(rng.normal(size=(5, 3)))
    t = np.array([0.0, 1.0, 2.5, 3.0, 4.0])
    np.testing.assert_allclose(so3.slerp(rots, t, t), rots, atol=1e-12)
    mid = so3.slerp(rots, t, np.array([1.0 + 0.3 * 1.5]))[0]
    rel = so3.log(rots[1].T @ rots[2])
    np.testing.assert_allclose(so3.log(rots[1].T @ mid), 0.3 * rel, atol=1e-12)
    ends = so3.slerp(rots, t, np.array([-1.0, 9.0]))
    np.testing.assert_allclose(ends, rots[[0, -1]], atol=1e-12)


def test_conversions_equal_scipys() -> None:
    """Quaternions, roll-pitch-yaw and Log against scipy's Rotation, which they replace (issue 27: it costs 0.2 s to
    import): from_quat, from_rpy and as_quat to the last digit, log and as_rpy to 1e-15 (numpy's and the C
    library's atan2 and sin differ in the last bit), over random rotations, angles near 0 and pi, the gimbal lock
    and matrices 1e-7 from orthogonal (projected first)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    locked = [Rotation.from_euler("ZYX", [y, p, r]).as_matrix() for y in (0.2, -3.0, np.pi)
              for p in (np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-8, np.pi / 2 - 1e-6) for r in (0.5, -2.9)]
    special = [so3.exp(v) for v in ([0, 0, 0], [1e-9, 0, 0], [np.pi, 0, 0], [0, np.pi - 1e-9, 0],
                                     np.array([1.0, 1, 1]) / np.sqrt(3) * np.pi)]
    m = np.concatenate([Rotation.random(3000, rng=rng).as_matrix(), locked, special,
                        [np.diag([-1.0, -1, 1]), np.diag([1.0, -1, -1])]])
    for rot in (m, m + rng.normal(scale=1e-7, size=m.shape)):
        r = Rotation.from_matrix(rot)
        assert np.array_equal(so3.as_quat(rot), r.as_quat(canonical=True, scalar_first=True))
        np.testing.assert_allclose(so3.log(rot), r.as_rotvec(), rtol=0, atol=2e-15)
        with pytest.warns(UserWarning, match="Gimbal lock"):
            want = r.as_euler("ZYX")[:, ::-1]
        np.testing.assert_allclose(so3.as_rpy(rot), want, rtol=0, atol=2e-15)
    q = rng.normal(size=(3000, 4))
    assert np.array_equal(so3.from_quat(q), Rotation.from_quat(q, scalar_first=True).as_matrix())
    rpy = rng.uniform(-4.0, 4.0, size=(3000, 3))
    assert np.array_equal(so3.from_rpy(rpy), Rotation.from_euler("ZYX", rpy[:, ::-1]).as_matrix())


def test_a_reflection_or_a_zero_quaternion_is_no_rotation() -> None:
    """det <= 0 has no rotation vector or quaternion, and a zero quaternion no matrix: ValueError, as scipy's
    from_matrix and from_quat raised (a NaN quaternion gives NaN, as there)."""
    with pytest.raises(ValueError, match="not a rotation"):
        so3.log(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="not a rotation"):
        so3.from_quat([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    assert np.isnan(so3.from_quat([np.nan, 0.0, 0.0, 1.0])).all()


def test_a_matrix_times_a_hat_is_the_product() -> None:
    """`times_hat` (m [v_k]x through one product) equals the products one at a time."""
    rng = np.random.default_rng(5)
    m, v = rng.normal(size=(3, 3)), rng.normal(size=(7, 3))
    np.testing.assert_allclose(so3.times_hat(m, v), np.stack([m @ so3.hat(vk) for vk in v]), rtol=1e-14, atol=1e-14)
