"""The banded-Schur Levenberg-Marquardt solver against dense linear algebra on small problems; `linearised` (one
factorisation, steps for other residuals) against the solver's own first step and the dense Gauss-Newton step."""

from __future__ import annotations

from dataclasses import replace

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


def _rejecting_first_trial(linearize):  # noqa: ANN001, ANN202
    """`linearize` with a cost no step can be accepted at on its second call (the first trial point), and the list
    of the `jac` it was asked with."""
    calls: list[bool] = []

    def rejecting(states: np.ndarray, theta: np.ndarray, jac: bool) -> list[Factor]:
        calls.append(jac)
        out = linearize(states, theta, jac)
        if len(calls) == 2:
            out = [Factor(f.name, 1e6 + f.r, f.idx, f.J_x, f.J_next, f.J_theta, f.theta_cols) for f in out]
        return out

    return rejecting, calls


def _perturbed_chain(seed: int):  # noqa: ANN202
    """A 12-state `_chain_problem`'s linearize and a start 0.1 rad off its truth (theta 0)."""
    rng = np.random.default_rng(seed)
    truth, _, linearize = _chain_problem(rng, 12)
    return linearize, truth @ so3.exp(0.1 * rng.normal(size=(12, 3))), np.zeros(2)


#: equations solved in place (and released before each trial point), or kept for a rejected step
IN_PLACE = pytest.mark.parametrize(("in_place", "again"), [(0, True), (2**62, False)])


@IN_PLACE
def test_a_solve_that_stops_on_a_rejected_step_keeps_its_points_jacobians(in_place: int, again: bool,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The factors drop their Jacobians once assembled (issue 39); a solve whose last step was rejected stops on a
    point whose equations are assembled (or released), and its solution still holds that point's factors with
    Jacobians."""
    monkeypatch.setattr(solve_module, "IN_PLACE_BYTES", in_place)
    linearize, start, theta0 = _perturbed_chain(3)
    rejecting, _ = _rejecting_first_trial(linearize)
    sol = solve(rejecting, start, theta0, Options(max_iterations=1))
    assert "rejected" in sol.log[-1] and sol.iterations == 1
    np.testing.assert_array_equal(sol.states, start)
    fresh = linearize(start, theta0, True)
    for got, want in zip(sol.factors, fresh, strict=True):
        assert got.J_x is not None
        np.testing.assert_array_equal(got.J_x, want.J_x)
        np.testing.assert_array_equal(got.r, want.r)
    assert np.all(np.isfinite(sol.cov_theta))
    kept = solve(linearize, start, theta0, Options(max_iterations=0))
    np.testing.assert_array_equal(sol.cov_theta, kept.cov_theta)


@IN_PLACE
def test_a_rejected_step_is_solved_again_from_the_same_points_equations(in_place: int, again: bool,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Large equations are solved in place and released before the trial point is linearised (issue 39): a rejected
    step linearises its point again and takes the more damped step that equations kept aside give (small ones)."""
    monkeypatch.setattr(solve_module, "IN_PLACE_BYTES", in_place)
    linearize, start, theta0 = _perturbed_chain(8)
    rejecting, calls = _rejecting_first_trial(linearize)
    sol = solve(rejecting, start, theta0, Options(max_iterations=2, covariance=False))
    assert "rejected" in sol.log[1] and "cost" in sol.log[2] and "rejected" not in sol.log[2]
    # the start, the rejected trial, (in place: the start again), the last trial (no covariance: no Jacobians there)
    assert calls == ([True, True, True, False] if again else [True, True, False])
    # the accepted step is the first step of a solve that starts with the damping the rejection left
    once = solve(linearize, start, theta0, Options(max_iterations=1, covariance=False, lambda0=1e-5))
    np.testing.assert_array_equal(sol.states, once.states)
    np.testing.assert_array_equal(sol.theta, once.theta)


def test_equations_solved_in_place_give_the_same_step_and_cannot_be_solved_twice() -> None:
    """Hxt and gx are views of the Fortran-order [Hxt, gx] the banded solve takes; a step solved in it equals one
    solved in a copy, digit for digit, and the spent equations refuse a second solve."""
    from magcal_cli.models import normal

    rng = np.random.default_rng(9)
    n, p = 14, 2
    truth, _, linearize = _chain_problem(rng, n)
    factors = linearize(truth @ so3.exp(0.05 * rng.normal(size=(n, 3))), np.array([0.1, -0.1]), True)
    weights = [np.ones(f.r.shape[0]) for f in factors]
    ne = normal.assemble(factors, weights, n, p)
    assert np.shares_memory(ne.hxt, ne.xg) and np.shares_memory(ne.gx, ne.xg) and ne.xg.flags.f_contiguous
    np.testing.assert_array_equal(ne.xg[:, :p].reshape(n, 3, p), ne.hxt)
    np.testing.assert_array_equal(ne.xg[:, p].reshape(n, 3), ne.gx)
    copied = normal.step(ne, 1e-3, 5, need_w=True)
    assert not ne.consumed
    in_place = normal.step(ne, 1e-3, 5, need_w=True, consume=True)
    for a, b in zip(copied, in_place, strict=True):
        np.testing.assert_array_equal(a, b)
    assert ne.consumed
    with pytest.raises(ValueError, match="assemble them again"):
        normal.step(ne, 1e-3, 5)
    # assembled while each factor gives up its Jacobians: the same equations
    listed = list(factors)
    stripped = normal.assemble_stripping(listed, weights, n, p)
    assert all(f.J_x is None and f.J_theta is None for f in listed)
    again = normal.assemble(factors, weights, n, p)
    for name in ("diag", "off", "hxt", "htt", "gx", "gt"):
        np.testing.assert_array_equal(getattr(stripped, name), getattr(again, name))


def test_rows_added_a_block_at_a_time_give_the_same_equations(monkeypatch: pytest.MonkeyPatch) -> None:
    """J_x^T J_theta made and added 3 rows at a time (`normal.ADD_BLOCK`) equals all rows at once, digit for digit,
    with states in a run and scattered."""
    from magcal_cli.models import normal

    rng = np.random.default_rng(11)
    n, p = 14, 2
    truth, _, linearize = _chain_problem(rng, n)
    factors = linearize(truth @ so3.exp(0.05 * rng.normal(size=(n, 3))), np.array([0.1, -0.1]), True)
    factors = [*factors, *(replace(f, idx=f.idx[::-1].copy()) for f in factors if f.idx is not None)]
    weights = [rng.uniform(0.5, 2.0, f.r.shape[0]) for f in factors]
    whole = normal.assemble(factors, weights, n, p)
    monkeypatch.setattr(normal, "ADD_BLOCK", 3)
    blocks = normal.assemble(factors, weights, n, p)
    for name in ("diag", "off", "hxt", "htt", "gx", "gt"):
        np.testing.assert_array_equal(getattr(blocks, name), getattr(whole, name))


def test_a_singular_information_solved_in_place_is_assembled_again_for_the_damped_retry() -> None:
    """`undamped` with `remake`: when the undamped Schur complement is singular (theta not determined), the retry with a
    trace of damping works on equations assembled again, and gives what the copy-keeping path gives."""
    from magcal_cli.models import normal

    rng = np.random.default_rng(10)
    n, p = 10, 2
    truth, _, linearize = _chain_problem(rng, n)

    def blind(states: np.ndarray, theta: np.ndarray, jac: bool) -> list[Factor]:
        """theta's second component enters nothing: the information is singular."""
        out = linearize(states, theta, jac)
        return [Factor(f.name, f.r, f.idx, f.J_x, f.J_next, None if f.J_theta is None else
                       np.concatenate([f.J_theta[:, :, :1], np.zeros_like(f.J_theta[:, :, 1:])], axis=2))
                for f in out]

    factors = blind(truth, np.zeros(p), True)
    weights = [np.ones(f.r.shape[0]) for f in factors]
    made = []

    def remake() -> normal.NormalEquations:
        made.append(1)
        return normal.assemble(factors, weights, n, p)

    log: list[str] = []
    kept = normal.undamped(normal.assemble(factors, weights, n, p), 5)
    spent = normal.undamped(normal.assemble(factors, weights, n, p), 5, log, remake=remake)
    assert made and "nearly singular" in log[0]
    for a, b in zip(kept, spent, strict=True):
        np.testing.assert_array_equal(a, b)
