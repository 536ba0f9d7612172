"""Screening candidate effects with robust score (Lagrange-multiplier) tests at the base optimum.

mismatch.md section 3.5: the score g = K^T eps of an effect's parameters at beta = 0 and its efficient
information F = K^T P K (P projects out the base unknowns) come from one linearisation of the extended model at
the base optimum: the trajectory is eliminated by the solver (Schur complement S over theta), the base theta by
a small dense Schur step. The robust statistic replaces F by a Newey-West variance of the per-second efficient
scores taken after the candidate's own Gauss-Newton step (to first order, from the per-cluster information), so
the signal itself is not counted as noise, and residuals coloured by other unmodelled physics do not inflate the
test's size. The step is each candidate's alone: a step with every candidate free is wild on a weakly determined
flight (an accelerometer scale standing in for a held D), and its residuals hid the 2015 logs' motor current.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli import effects as registry
from magcal_cli.models.epochs import Epochs
from magcal_cli.models.gyro import Preintegrated, preintegrate_epochs
from magcal_cli.models.map.effects import Bound, bind, layout_for
from magcal_cli.models.map.estimate import MapEstimate
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import EffectFit
from magcal_cli.models.sandwich import (
    bartlett_dof,
    cluster_scores_and_information,
    factor_clusters,
    newey_west,
    time_clusters,
)
from magcal_cli.models.solve import Options, Solution, solve
from magcal_cli.params import Layout
from magcal_cli.streams import FloatArray, Stream

IntArray = npt.NDArray[np.int64]

#: length (s) of the blocks whose summed scores are treated as one observation of the robust variance
CLUSTER_S = 1.0


@dataclass(frozen=True)
class Score:
    """One candidate's score test: robust statistic (F-referred), classical statistic, dof, p-value."""

    id: str
    robust: float
    classical: float
    dof: int
    p_value: float


@dataclass(frozen=True, eq=False)
class Screen:
    """The scores of the testable candidates, those the log cannot test, and the largest canonical
    correlation between every pair of candidates (1: the log cannot tell them apart)."""

    scores: tuple[Score, ...]
    untestable: tuple[EffectFit, ...]
    correlation: dict[frozenset[str], float]
    unscored: tuple[str, ...] = ()

    def of(self, eid: str) -> Score | None:
        """The score of effect `eid` (None if it was not scored)."""
        return next((s for s in self.scores if s.id == eid), None)


@dataclass(frozen=True, eq=False)
class _Extended:
    """The extended model's solution at the base optimum and where each candidate's columns are."""

    sol: Solution
    layout: Layout
    tested: dict[str, IntArray]
    held: dict[str, IntArray]
    clusters: list[IntArray]


def _extend(problem: Problem, mag: Stream, est: MapEstimate, bound: Sequence[Bound]) -> _Extended:
    """Linearise base + candidates at the base optimum (candidates at zero); no iterations."""
    ctx = est.context
    assert ctx is not None
    all_bound = (*ctx.bound, *bound)
    layout = layout_for(all_bound)
    theta = layout.zeros()
    layout.carry(theta, ctx.layout, ctx.theta)
    tested, held = {}, {}
    for b in bound:
        cols = layout.cols(*b.names())
        theta[cols] = b.effect.start()
        prior = b.effect.prior()
        free = np.ones(cols.size, bool) if prior is None else ~np.isfinite(prior[1])
        tested[b.effect.id], held[b.effect.id] = cols[free], cols[~free]
    pre = ctx.pre
    if any(b.effect.target.value == "gyro" for b in bound) and pre.d_scale is None:
        pre = _with_scale_jacobian(problem, mag, ctx.ep, pre)
    lin = ctx.linearize(layout, all_bound, pre=pre, holdout=ctx.holdout)
    sol = solve(lin, ctx.states, theta, Options(max_iterations=0))
    t = ctx.ep.t
    ids = time_clusters(t, count=max(1, int((t[-1] - t[0]) / CLUSTER_S)), min_length_s=CLUSTER_S)
    if ctx.holdout is not None:             # held-out seconds carry no readings: not observations of the variance
        ids = np.where(ctx.holdout > 0, ids, -1)
        kept = np.unique(ids[ids >= 0])
        ids = np.where(ids >= 0, np.searchsorted(kept, ids), -1)
    clusters = factor_clusters(sol.factors, ids)
    return _Extended(sol, layout, tested, held, clusters)


#: each problem's preintegrations with the gyro-scale Jacobian by epochs, bias and noise: every screen of a
#: magnetometer (each forward round, each fold) asks for the same one (2015 logs: 18 calls, 2 different)
_SCALE_JACOBIAN: weakref.WeakKeyDictionary[Problem, dict[bytes, Preintegrated]] = weakref.WeakKeyDictionary()
_LOCK = threading.Lock()


def _with_scale_jacobian(problem: Problem, mag: Stream, ep: Epochs, pre: Preintegrated) -> Preintegrated:
    """`pre` integrated again with the gyro-scale Jacobian (models/gyro.py), once per epochs, bias and noise."""
    key = ep.t.tobytes() + pre.bias.tobytes() + pre.noise_std.tobytes()
    with _LOCK:
        memo = _SCALE_JACOBIAN.setdefault(problem, {})
    hit = memo.get(key)
    if hit is None:
        hit = preintegrate_epochs(problem, ep, pre.bias, pre.noise_std, f"{problem.where}: {mag.id}", True)
        memo[key] = hit
    return hit


def _lags(clusters: int) -> int:
    """Newey-West bandwidth: the usual 4 (C/100)^(2/9), and at least 5 blocks (5 s) of residual memory."""
    return max(5, int(np.ceil(4.0 * (clusters / 100.0) ** (2.0 / 9.0))))


def screen(problem: Problem, mag: Stream, est: MapEstimate, ids: Sequence[str],
           declination: float = 0.0) -> Screen:
    """Score-test each candidate effect against the fitted base model `est` (which must carry its context)."""
    from scipy.special import fdtrc  # scipy.stats.f.sf computes it; scipy.stats costs 0.2-1.2 s (issue 27)

    ctx = est.context
    assert ctx is not None
    bias = ctx.pre.bias + ctx.layout.get(ctx.theta, "gyroscope_bias")
    unscored = tuple(i for i in ids if not registry.get(i).params)     # no parameters: nothing to score
    bound, untestable = bind(problem, mag, ctx.ep.t_obs, bias, [i for i in ids if i not in unscored], declination)
    scored = list(bound)
    if not scored:
        return Screen((), tuple(untestable), {}, unscored)
    ext = _extend(problem, mag, est, scored)
    s_inv = ext.sol.cov_theta
    if not np.all(np.isfinite(s_inv)):
        return Screen((), tuple(untestable), {}, unscored)
    info = np.asarray(np.linalg.pinv(s_inv, hermitian=True), dtype=np.float64)
    scores, hessians = cluster_scores_and_information(ext.sol, ext.clusters)
    lags = _lags(scores.shape[0])
    nu = bartlett_dof(scores.shape[0], lags)
    cand = set(np.concatenate([*ext.tested.values(), *ext.held.values()]).tolist())
    base = np.array([c for c in range(info.shape[0]) if c not in cand], dtype=np.int64)
    out = []
    for b in scored:
        a = ext.tested[b.effect.id]
        rest = np.concatenate([base, ext.held[b.effect.id]])
        f_eff, e_eff = _efficient(info, scores, a, rest)
        g = e_eff.sum(axis=0)
        classical = float(g @ np.linalg.lstsq(f_eff, g, rcond=None)[0])
        # the variance from the residuals with the candidate fitted (a robust Wald form): under the alternative
        # the scores at beta = 0 carry the signal, whose spread would pass for noise and cost the test its power
        _, e_noise = _efficient(info, _after_step(info, scores, hessians, a, rest), a, rest)
        meat = newey_west(e_noise, lags)
        robust = float(g @ np.linalg.lstsq(meat, g, rcond=None)[0])
        q = a.size
        # Hotelling-type reference: T^2 (nu - q + 1) / (q nu) ~ F(q, nu - q + 1)
        dfd = max(nu - q + 1.0, 1.0)
        p = float(fdtrc(q, dfd, robust * dfd / (q * nu)))
        out.append(Score(b.effect.id, robust, classical, q, p))
    corr = {}
    for i, b1 in enumerate(scored):
        for b2 in scored[i + 1:]:
            a1, a2 = ext.tested[b1.effect.id], ext.tested[b2.effect.id]
            rest = np.concatenate([base, ext.held[b1.effect.id], ext.held[b2.effect.id]])
            f_eff, _ = _efficient(info, scores, np.concatenate([a1, a2]), rest)
            corr[frozenset((b1.effect.id, b2.effect.id))] = _canonical(f_eff, a1.size)
    return Screen(tuple(out), tuple(untestable), corr, unscored)


#: clusters whose columns `_after_step` gathers at once
AFTER_STEP_CLUSTERS = 256


def _after_step(info: FloatArray, scores: FloatArray, hessians: FloatArray, a: IntArray,
                rest: IntArray) -> FloatArray:
    """Per-cluster scores after one Gauss-Newton step in columns a and rest only (E_c + H_c d, d = -S^-1 g), the
    gradient being the data's on a (the base optimum's total gradient on `rest` is zero)."""
    sub = np.concatenate([rest, a])
    g = np.zeros(sub.size)
    g[rest.size:] = scores[:, a].sum(axis=0)
    d = -np.linalg.lstsq(info[np.ix_(sub, sub)], g, rcond=None)[0]
    out = np.empty_like(scores)
    # a block of clusters at a time: the (C, p, |sub|) copy of every cluster's columns was 18 MB of a 60-min
    # flight's training-fold peak (issue 39); each cluster's product is its own, so the digits are the same
    for c in range(0, scores.shape[0], AFTER_STEP_CLUSTERS):
        block = slice(c, c + AFTER_STEP_CLUSTERS)
        out[block] = scores[block] + hessians[block][:, :, sub] @ d
    return out


def _efficient(info: FloatArray, scores: FloatArray, a: IntArray, rest: IntArray) -> tuple[FloatArray, FloatArray]:
    """Efficient information of columns a given `rest`, and the efficient per-cluster scores."""
    s_aa, s_ar, s_rr = info[np.ix_(a, a)], info[np.ix_(a, rest)], info[np.ix_(rest, rest)]
    proj = np.linalg.lstsq(s_rr, s_ar.T, rcond=None)[0]            # S_rr^-1 S_ra
    return s_aa - s_ar @ proj, scores[:, a] - scores[:, rest] @ proj


def _canonical(f: FloatArray, split: int) -> float:
    """Largest canonical correlation between the first `split` columns and the others of information f."""
    f11, f12, f22 = f[:split, :split], f[:split, split:], f[split:, split:]

    def inv_sqrt(m: FloatArray) -> FloatArray:
        w, v = np.linalg.eigh(m)
        return np.asarray(v @ np.diag(1.0 / np.sqrt(np.maximum(w, 1e-300))) @ v.T, dtype=np.float64)

    k = inv_sqrt(f11) @ f12 @ inv_sqrt(f22)
    return float(np.clip(np.linalg.svd(k, compute_uv=False).max(), 0.0, 1.0))
