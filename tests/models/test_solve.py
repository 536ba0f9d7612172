"""The banded-Schur Levenberg-Marquardt solver against dense linear algebra on small problems; `linearised` (one
factorisation, steps for other residuals) against the solver's own first step and the dense Gauss-Newton step."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.models import solve as solve_module
from magcal_cli.models.factor import Factor
from magcal_cli.models.solve import Options, linearised, solve


def _chain_problem(rng: np.random.Generator, n: int):  # noqa: ANN202
    """Rotations observed through noisy body vectors (unary), linked by noisy relative rotations (binary),
    plus a global 2-vector theta that biases the unary observations: the MAP problem's structure in miniature."""
    truth = so3.exp(rng.normal(size=(n, 3)))
    theta_true = np.array([0.3, -0.2])
    nav = np.array([[1.0, 0, 0], [0, 0, 1.0]])
    obs = np.einsum("nji,mj->nmi", truth, nav) + 0.01 * rng.normal(size=(n, 2, 3))
    obs[:, 0, :2] += theta_true
    rel = so3.log(truth[:-1].transpose(0, 2, 1) @ truth[1:]) + 0.01 * rng.normal(size=(n - 1, 3))

    def linearize(states: np.ndarray, theta: np.ndarray, jac: bool) -> list[Factor]:
        factors = []
        for j in range(2):
            pred = np.einsum("nji,j->ni", states, nav[j])
            shift = np.zeros(3)
            if j == 0:
                shift[:2] = theta
            r = (obs[:, j] - pred - shift) / 0.01
            jt = np.zeros((n, 3, 2))
            if j == 0:
                jt[:, :2, :] = -np.eye(2) / 0.01
            factors.append(Factor(f"obs{j}", r, np.arange(n), -so3.hat(pred) / 0.01, None, jt) if jac
                           else Factor(f"obs{j}", r))
        d = so3.log(so3.exp(rel).transpose(0, 2, 1) @ states[:-1].transpose(0, 2, 1) @ states[1:])
        r = d / 0.01
        if jac:
            jinv = so3.right_jacobian_inv(d)
            ji = -jinv @ (states[1:].transpose(0, 2, 1) @ states[:-1]) / 0.01
            factors.append(Factor("rel", r, np.arange(n - 1), ji, jinv / 0.01, None))
        else:
            factors.append(Factor("rel", r))
        return factors

    return truth, theta_true, linearize


def _dense(factors, n: int, p: int) -> np.ndarray:  # noqa: ANN001
    """The full Jacobian (rows of every factor) over (3N trajectory, p theta)."""
    rows = []
    for f in factors:
        block = np.zeros((f.r.shape[0], f.r.shape[1], 3 * n + p))
        for i, k in enumerate(f.idx):
            block[i, :, 3 * k:3 * k + 3] = f.J_x[i]
            if f.J_next is not None:
                block[i, :, 3 * k + 3:3 * k + 6] = f.J_next[i]
            if f.J_theta is not None:
                block[i, :, 3 * n:] = f.J_theta[i]
        rows.append(block.reshape(-1, 3 * n + p))
    return np.concatenate(rows)


def test_converges_to_truth_with_tridiagonal_structure() -> None:
    """Unary + consecutive binary factors + a global parameter: the estimate matches truth within noise."""
    rng = np.random.default_rng(3)
    truth, theta_true, linearize = _chain_problem(rng, 40)
    start = truth @ so3.exp(0.05 * rng.normal(size=(40, 3)))
    sol = solve(linearize, start, np.zeros(2))
    assert sol.converged
    err = so3.angle(sol.states.transpose(0, 2, 1) @ truth)
    assert err.max() < 0.02
    z = (sol.theta - theta_true) / np.sqrt(np.diag(sol.cov_theta))
    assert np.all(np.abs(z) < 4)


def test_covariance_is_the_dense_inverse_block() -> None:
    """cov_theta equals the theta block of the inverse of the full dense J^T J at the optimum."""
    rng = np.random.default_rng(4)
    truth, _, linearize = _chain_problem(rng, 12)
    sol = solve(linearize, truth, np.zeros(2))
    n, p = 12, 2
    j = _dense(sol.factors, n, p)
    dense = np.linalg.inv(j.T @ j)
    np.testing.assert_allclose(sol.cov_theta, dense[3 * n:, 3 * n:], rtol=1e-8)


def test_linearised_step_is_the_solvers_first_step_and_the_dense_gauss_newton_step() -> None:
    """On the data it was linearised on, `linearised(...).step` moves exactly as solve's first iteration (same
    damping); undamped, for any other residuals r it is the dense Gauss-Newton step -(J^T J)^-1 J^T r."""
    rng = np.random.default_rng(6)
    n, p = 15, 2
    truth, _, linearize = _chain_problem(rng, n)
    start = truth @ so3.exp(0.02 * rng.normal(size=(n, 3)))
    theta0 = np.array([0.1, 0.0])
    at = linearised(linearize, start, theta0)
    dx, dt = at.step([f.r for f in linearize(start, theta0, False)])
    one = solve(linearize, start, theta0, Options(max_iterations=1, covariance=False))
    np.testing.assert_allclose(start @ so3.exp(dx), one.states, atol=1e-12)
    np.testing.assert_allclose(theta0 + dt, one.theta, atol=1e-12)
    plain = linearised(linearize, start, theta0, lam=0.0)
    other = [rng.normal(size=f.r.shape) for f in plain.factors]
    dx, dt = plain.step(other)
    j = _dense(plain.factors, n, p)
    want = -np.linalg.solve(j.T @ j, j.T @ np.concatenate([r.ravel() for r in other]))
    np.testing.assert_allclose(np.concatenate([dx.ravel(), dt]), want, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("chunk", [8192, 3])
def test_leverage_matches_the_dense_hat_matrix(chunk: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Solution.leverage gives diag(J (J^T J)^-1 J^T) for unary factors on a block-diagonal trajectory, whatever
    the row blocks it is computed in."""
    monkeypatch.setattr(solve_module, "LEVERAGE_ROWS", chunk)
    rng = np.random.default_rng(5)
    n = 10
    truth = so3.exp(rng.normal(size=(n, 3)))
    nav = np.eye(3)[:2]
    obs = np.einsum("nji,mj->nmi", truth, nav) + 0.01 * rng.normal(size=(n, 2, 3))

    def linearize(states: np.ndarray, theta: np.ndarray, jac: bool) -> list[Factor]:
        out = []
        for j in range(2):
            pred = np.einsum("nji,j->ni", states, nav[j]) + theta
            r = obs[:, j] - pred
            out.append(Factor(f"o{j}", r, np.arange(n), -so3.hat(pred - theta), None,
                              np.broadcast_to(-np.eye(3), (n, 3, 3)).copy()) if jac else Factor(f"o{j}", r))
        return out

    sol = solve(linearize, truth, np.zeros(3))
    h = np.concatenate([sol.leverage(f).ravel() for f in sol.factors])
    rows = []
    for f in sol.factors:
        block = np.zeros((n, 3, 3 * n + 3))
        for i in range(n):
            block[i, :, 3 * i:3 * i + 3] = f.J_x[i]
            block[i, :, 3 * n:] = f.J_theta[i]
        rows.append(block.reshape(-1, 3 * n + 3))
    j = np.concatenate(rows)
    dense = np.einsum("ij,jk,ik->i", j, np.linalg.inv(j.T @ j), j)
    np.testing.assert_allclose(h, dense, atol=1e-10)
    assert abs(h.sum() - (3 * n + 3)) < 1e-8           # trace of the hat matrix = number of unknowns


def test_one_blas_thread_limits_blas_inside_the_block_only() -> None:
    """The cached controller limits every loaded BLAS to one thread in the block and restores it after."""
    from threadpoolctl import threadpool_info

    from magcal_cli.models.normal import one_blas_thread

    before = {p["filepath"]: p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}
    assert before, "numpy should have loaded a BLAS"
    with one_blas_thread():
        inside = {p["filepath"]: p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}
        assert set(inside.values()) == {1}
    with one_blas_thread():                          # the second use reuses the scan and still limits
        assert {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"} == {1}
    assert {p["filepath"]: p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"} == before


def test_a_solve_that_stops_on_a_rejected_step_keeps_its_points_jacobians() -> None:
    """The factors drop their Jacobians once assembled (issue 39); a solve whose last step was rejected stops on a
    point whose equations are assembled, and its solution still holds that point's factors with Jacobians."""
    rng = np.random.default_rng(3)
    n = 12
    truth, _, linearize = _chain_problem(rng, n)
    start, theta0 = truth @ so3.exp(0.1 * rng.normal(size=(n, 3))), np.zeros(2)
    calls = []

    def rejecting(states: np.ndarray, theta: np.ndarray, jac: bool) -> list[Factor]:
        calls.append(jac)
        out = linearize(states, theta, jac)
        if len(calls) == 2:                        # the first trial point: a cost that no step can be accepted at
            out = [Factor(f.name, 1e6 + f.r, f.idx, f.J_x, f.J_next, f.J_theta, f.theta_cols) for f in out]
        return out

    sol = solve(rejecting, start, theta0, Options(max_iterations=1))
    assert "rejected" in sol.log[-1] and sol.iterations == 1
    np.testing.assert_array_equal(sol.states, start)
    fresh = linearize(start, theta0, True)
    for got, want in zip(sol.factors, fresh, strict=True):
        assert got.J_x is not None
        np.testing.assert_array_equal(got.J_x, want.J_x)
        np.testing.assert_array_equal(got.r, want.r)
    assert np.all(np.isfinite(sol.cov_theta))
