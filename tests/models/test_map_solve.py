"""Solver features the joint MAP method relies on, against dense linear algebra: the O(N) selected inverse,
leverage of binary factors on a tridiagonal trajectory, compact theta columns, the Cramer-Rao helper."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.models.factor import Factor
from magcal_cli.models.normal import marginal_covariance, selected_inverse
from magcal_cli.models.solve import solve


def _chain(rng: np.random.Generator, n: int, compact: bool):  # noqa: ANN202
    """Unary body-vector factors (theta[0:3] biases them) and consecutive relative-rotation factors (theta[3]
    scales their rate): the structure of the MAP problem, with theta columns given compactly or densely."""
    truth = so3.exp(rng.normal(size=(n, 3)))
    nav = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    bias = np.array([0.2, -0.1, 0.3, 0.0, 0.0, 0.0])
    obs = np.einsum("nji,mj->nmi", truth, nav).reshape(n, 6) + bias + 0.01 * rng.normal(size=(n, 6))
    rel = so3.log(truth[:-1].transpose(0, 2, 1) @ truth[1:]) * 1.1 + 0.01 * rng.normal(size=(n - 1, 3))
    p = 5

    def linearize(states: np.ndarray, theta: np.ndarray, jac: bool) -> list[Factor]:
        pred = np.einsum("nji,mj->nmi", states, nav)                 # (n, 2, 3)
        r1 = (obs - pred.reshape(n, 6) - np.concatenate([theta[0:3], np.zeros(3)])) / 0.01
        d = so3.log(so3.exp(rel / theta[3]).transpose(0, 2, 1) @ states[:-1].transpose(0, 2, 1) @ states[1:])
        r2 = d / 0.01
        if not jac:
            return [Factor("obs", r1), Factor("rel", r2)]
        jt1 = np.zeros((n, 6, 3))
        jt1[:, :3, :] = -np.eye(3) / 0.01
        jx1 = (-so3.hat(pred) / 0.01).reshape(n, 6, 3)
        jinv = so3.right_jacobian_inv(d)
        # d r2 / d theta[3] by central differences (exact enough for a structure test)
        eps = 1e-7
        rel_states = states[:-1].transpose(0, 2, 1) @ states[1:]
        dp = so3.log(so3.exp(rel / (theta[3] + eps)).transpose(0, 2, 1) @ rel_states)
        dm = so3.log(so3.exp(rel / (theta[3] - eps)).transpose(0, 2, 1) @ rel_states)
        jt2 = ((dp - dm) / (2 * eps) / 0.01)[:, :, None]
        ji = -jinv @ (states[1:].transpose(0, 2, 1) @ states[:-1]) / 0.01
        if compact:
            return [Factor("obs", r1, np.arange(n), jx1, None, jt1, np.arange(3)),
                    Factor("rel", r2, np.arange(n - 1), ji, jinv / 0.01, jt2, np.array([3]))]
        full1, full2 = np.zeros((n, 6, p)), np.zeros((n - 1, 3, p))
        full1[:, :, :3], full2[:, :, 3:4] = jt1, jt2
        return [Factor("obs", r1, np.arange(n), jx1, None, full1),
                Factor("rel", r2, np.arange(n - 1), ji, jinv / 0.01, full2)]

    return truth, linearize, p


def _dense_jacobian(factors: tuple[Factor, ...], n: int, p: int) -> np.ndarray:
    """The full Jacobian [J_states, J_theta] of the factors, row by row."""
    rows = []
    for f in factors:
        jt = f.full_theta(p)
        block = np.zeros(f.r.shape + (3 * n + p,))
        for i, k in enumerate(f.idx):
            block[i, :, 3 * k:3 * k + 3] = f.J_x[i]
            if f.J_next is not None:
                block[i, :, 3 * k + 3:3 * k + 6] = f.J_next[i]
            block[i, :, 3 * n:] = jt[i]
        rows.append(block.reshape(-1, 3 * n + p))
    return np.concatenate(rows)


@pytest.mark.parametrize("block", [8192, 7, 1])
def test_selected_inverse_equals_dense_inverse_blocks(block: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Diagonal and super-diagonal 3x3 blocks of A^-1 for a random SPD block-tridiagonal A, whatever the blocks of
    pairs it is computed in."""
    from magcal_cli.models import normal

    monkeypatch.setattr(normal, "PAIR_BLOCK", block)
    rng = np.random.default_rng(0)
    n = 30
    b = rng.normal(size=(n - 1, 3, 3))
    a = rng.normal(size=(n, 3, 3))
    diag = a @ a.transpose(0, 2, 1) + 8.0 * np.eye(3)
    dense = np.zeros((3 * n, 3 * n))
    for k in range(n):
        dense[3 * k:3 * k + 3, 3 * k:3 * k + 3] = diag[k]
    for k in range(n - 1):
        dense[3 * k:3 * k + 3, 3 * k + 3:3 * k + 6] = b[k]
        dense[3 * k + 3:3 * k + 6, 3 * k:3 * k + 3] = b[k].T
    inv = np.linalg.inv(dense)
    xx, nxt = selected_inverse(diag, b)
    for k in range(n):
        np.testing.assert_allclose(xx[k], inv[3 * k:3 * k + 3, 3 * k:3 * k + 3], rtol=1e-9, atol=1e-12)
    for k in range(n - 1):
        np.testing.assert_allclose(nxt[k], inv[3 * k:3 * k + 3, 3 * k + 3:3 * k + 6], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("chunk", [8192, 4])
def test_leverage_and_marginals_on_a_tridiagonal_trajectory(chunk: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Hat-matrix diagonal of unary and binary factors and the marginal blocks equal the dense inverse, whatever
    the row blocks the leverage is computed in; the leverages sum to the number of unknowns."""
    from magcal_cli.models import solve as solve_module

    monkeypatch.setattr(solve_module, "LEVERAGE_ROWS", chunk)
    rng = np.random.default_rng(1)
    n = 15
    truth, linearize, p = _chain(rng, n, compact=True)
    sol = solve(linearize, truth, np.array([0.0, 0.0, 0.0, 1.0, 0.0]))
    j = _dense_jacobian(sol.factors, n, p)[:, :3 * n + 4]            # theta[4] is not observed: drop it
    # theta[4] never enters: the information is singular there, so compare on the observed block only
    assert not np.all(np.isfinite(sol.cov_theta)) or sol.cov_theta[4, 4] > 1e6
    sol2 = solve(lambda s, t, jac: linearize(s, np.concatenate([t, [0.0]]), jac), truth,
                 np.array([0.0, 0.0, 0.0, 1.0]))
    inv = np.linalg.inv(j.T @ j)
    h = np.concatenate([sol2.leverage(f).ravel() for f in sol2.factors])
    np.testing.assert_allclose(h, np.einsum("ij,jk,ik->i", j, inv, j), atol=1e-9)
    assert abs(h.sum() - (3 * n + 4)) < 1e-8
    z = sol2.marginals()
    np.testing.assert_allclose(z.tt, inv[3 * n:, 3 * n:], rtol=1e-8)
    np.testing.assert_allclose(z.xx(np.array([4]))[0], inv[12:15, 12:15], rtol=1e-8)
    np.testing.assert_allclose(z.x_next(slice(4, 5), slice(5, 6))[0], inv[12:15, 15:18], rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(z.xt(np.array([4]))[0], inv[12:15, 3 * n:], rtol=1e-8, atol=1e-14)


def test_compact_theta_columns_change_nothing() -> None:
    """Factors with theta_cols give the same optimum, covariance and leverage as their dense form."""
    rng = np.random.default_rng(2)
    truth, lin_c, _ = _chain(rng, 20, compact=True)
    _, lin_d, _ = _chain(np.random.default_rng(2), 20, compact=False)
    start = truth @ so3.exp(0.05 * rng.normal(size=(20, 3)))
    theta0 = np.array([0.0, 0.0, 0.0, 1.0])

    def cut(lin):  # noqa: ANN001, ANN202
        return lambda s, t, jac: [f if not jac else Factor(f.name, f.r, f.idx, f.J_x, f.J_next,
                                                           f.J_theta if f.theta_cols is not None
                                                           else f.J_theta[:, :, :4], f.theta_cols)
                                  for f in lin(s, np.concatenate([t, [0.0]]), jac)]
    a, b = solve(cut(lin_c), start, theta0), solve(cut(lin_d), start, theta0)
    np.testing.assert_allclose(a.theta, b.theta, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(a.cov_theta, b.cov_theta, rtol=1e-8)
    np.testing.assert_allclose(a.leverage(a.factors[1]), b.leverage(b.factors[1]), atol=1e-10)


def test_marginal_covariance_at_a_point_is_the_solvers_covariance_at_the_optimum() -> None:
    """marginal_covariance (used for the Cramer-Rao bound) equals Solution.cov_theta at the same point."""
    rng = np.random.default_rng(3)
    truth, lin, _ = _chain(rng, 12, compact=True)

    def lin4(s: np.ndarray, t: np.ndarray, jac: bool) -> list[Factor]:
        return lin(s, np.concatenate([t, [0.0]]), jac)
    sol = solve(lin4, truth, np.array([0.0, 0.0, 0.0, 1.0]))
    np.testing.assert_allclose(marginal_covariance(lin4, sol.states, sol.theta), sol.cov_theta, rtol=1e-10)
