"""Held-out evidence: interleaved blocked cross-validation, with the screening also run on each training fold.

mismatch.md section 3.9. The log is cut into contiguous blocks; fold f holds out every K-th block. The training
fits see no accelerometer or magnetometer reading of the held-out blocks (their gyro still carries the
trajectory through). The base model and the model with the chosen effects are fitted on each training fold;
the held-out readings are scored by their negative log-likelihood with the parameters and noise levels frozen
and only the trajectory refitted to them. The screening run on each training fold alone says how often the
training data would have chosen each effect (the nested check).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import partial
from typing import cast

import numpy as np

from magcal_cli.diagnose.parallel import Outcome, captured, pmap
from magcal_cli.errors import InsufficientDataError
from magcal_cli.models.factor import Factor, Linearize
from magcal_cli.models.map.effects import row_weights
from magcal_cli.models.map.estimate import FitContext, MapEstimate
from magcal_cli.models.map.fit import fit_map
from magcal_cli.models.problem import Problem
from magcal_cli.models.solve import Options, solve
from magcal_cli.progress import Hook, current
from magcal_cli.streams import FloatArray, Stream

#: shortest held-out block (s): long against the residuals' memory, short against gyro drift in the block
BLOCK_S = 10.0
FOLDS = 5
#: noise-level rounds of a fold's fit: it starts from the full fit's levels, which barely move
FOLD_NOISE_ROUNDS = 0
#: bootstrap resamples of the held-out blocks for the gain's interval
BOOTSTRAP = 2000

#: what a refit on a weakly determined log (a partial calibration) raises: that fold, or that effect, is left out
REFIT_ERRORS = (InsufficientDataError, np.linalg.LinAlgError)

@dataclass(frozen=True)
class Heldout:
    """Per held-out block: NLL drop per reading (base minus the model chosen in its fold), and the magnetometer
    residual RMS (SI) before and after over all held-out readings; the effects chosen in each fold."""

    gain: FloatArray
    rms_before: float
    rms_after: float
    chosen: tuple[tuple[str, ...], ...]
    protocol: str

    def ci95(self, seed: int = 0) -> tuple[float, float]:
        """Block-bootstrap 95 % interval of the mean gain per reading."""
        if self.gain.size < 2:
            return float("nan"), float("nan")
        rng = np.random.default_rng(seed)
        means = self.gain[rng.integers(0, self.gain.size, (BOOTSTRAP, self.gain.size))].mean(axis=1)
        lo, hi = np.quantile(means, [0.025, 0.975])
        return float(lo), float(hi)

    def share(self, eid: str) -> float:
        """Fraction of the folds whose training data chose effect `eid`."""
        return sum(eid in c for c in self.chosen) / max(len(self.chosen), 1)


def blocks(t: FloatArray, length: float = BLOCK_S) -> list[tuple[float, float]]:
    """Contiguous windows of about `length` s covering t (the last short one merged into its neighbour)."""
    t0, t1 = float(t[0]), float(t[-1]) + 1e-9
    n = max(1, int((t1 - t0) // length))
    edges = np.linspace(t0, t1, n + 1)
    return [(float(a), float(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def folds(windows: Sequence[tuple[float, float]], k: int = FOLDS) -> list[tuple[tuple[float, float], ...]]:
    """Fold f holds out every k-th window starting at f (interleaved, so every fold spans the log)."""
    k = min(k, len(windows))
    return [tuple(windows[f::k]) for f in range(k)]


def _frozen(lin: Linearize, theta: FloatArray) -> Linearize:
    """The cost as a function of the trajectory alone, with theta held at `theta`."""
    def linearize(states: FloatArray, _: FloatArray, jac: bool) -> list[Factor]:
        return [Factor(f.name, f.r, f.idx, f.J_x, f.J_next) for f in lin(states, theta, jac)]
    return linearize


def scores_in(ctx: FitContext, windows: Sequence[tuple[float, float]], keep: FloatArray
              ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per window: the held-out NLL (accelerometer, magnetometer and gyro rows) and the reading count, with the
    parameters and noise levels frozen and the trajectory refitted to the held-out readings alone; and the
    summed squared magnetometer residual (SI^2)."""
    t = ctx.ep.t
    inside = np.zeros(t.size, bool)
    for a, b in windows:
        inside |= (t >= a) & (t < b)
    w = (inside & (keep > 0)).astype(np.float64)
    if ctx.excluded is not None:                 # readings the IMU's motion did not cover are nobody's score
        w = w * ctx.excluded
    lin = _frozen(ctx.linearize(holdout=w), ctx.theta)
    sol = solve(lin, ctx.states, np.zeros(0), Options(max_iterations=3, abs_cost_tol=1e-2, covariance=False))
    fa, fm, fg = sol.factors[0], sol.factors[1], sol.factors[2]
    logdet = float(np.sum(np.log(ctx.noise.acc)) + np.sum(np.log(ctx.noise.mag)))
    det = np.abs(np.linalg.det(ctx.pre.l_inv))
    g_logdet = -np.log(np.where(det > 0, det, 1.0))       # a broken interval (l_inv = 0, gyro.py) scores nothing
    nll = 0.5 * (np.sum(fa.r**2, axis=1) + np.sum(fm.r**2, axis=1)) + logdet
    nll[:-1] += (0.5 * np.sum(fg.r**2, axis=1) + g_logdet) * w[:-1] * w[1:]
    sq = np.sum((fm.r * ctx.noise.mag * ctx.ep.scale) ** 2, axis=1)
    out = np.zeros((3, len(windows)))
    for i, (a, b) in enumerate(windows):
        m = (t >= a) & (t < b) & (w > 0)
        out[:, i] = nll[m].sum(), m.sum(), sq[m].sum()
    return out[0], out[1], out[2]


#: a fold's held-out NLL gains per window, squared residual sums before and after, readings, effects it chose
FoldScores = tuple[FloatArray, float, float, float, tuple[str, ...]]
#: a selection procedure: (base fit of a training fold, its held-out windows) -> the effects it chooses
Procedure = Callable[[MapEstimate, tuple[tuple[float, float], ...]], tuple[str, ...]]


def crossvalidate(problem: Problem, mag: Stream, est: MapEstimate, procedure: Procedure, model: MapEstimate,
                  declination: float = 0.0, loss: str = "l2", dip_prior: float | None = None,
                  progress: Hook | None = None, beside: Sequence[Callable[[], object]] = ()
                  ) -> tuple[Heldout, tuple[Outcome[object], ...]]:
    """Blocked cross-validation of the base model plus the effects `model` against the base model, both fitted
    on each training fold (each fit starts from its whole-log counterpart, `est` or `model`); inside each fold
    `procedure` also chooses effects from the training data alone (the fraction of folds choosing an effect is the
    nested check that the whole log did not choose it by chance). The work `beside` (what follows if the check
    confirms the model) runs side by side with the folds: five folds keep two cores busy only for four."""
    ctx = est.context
    assert ctx is not None
    windows = blocks(ctx.ep.t)
    ids = tuple(f.id for f in model.effects if f.estimate is not None)

    def fold(hold: tuple[tuple[float, float], ...]) -> FoldScores | None:
        try:
            return scored(hold)
        except REFIT_ERRORS:
            # a weakly determined flight (a partial calibration) may not be determined without a tenth of its
            # readings: that fold is left out; the check stands on the others
            return None

    def scored(hold: tuple[tuple[float, float], ...]) -> FoldScores:
        base = fit_map(problem, mag, loss, dip_prior, FOLD_NOISE_ROUNDS, declination=declination, holdout=hold,
                       warm=ctx)
        picked = procedure(base, hold)
        assert base.context is not None and model.context is not None
        # both models score with the noise levels of the fold's base fit: levels estimated on the whole log
        # would carry the held-out readings into the comparison
        ratio = float(base.context.noise.gyr[0] / model.context.noise.gyr[0])
        start = replace(model.context, noise=base.context.noise, pre=model.context.pre.scaled(ratio**2))
        ext = fit_map(problem, mag, loss, dip_prior, FOLD_NOISE_ROUNDS, effects=ids, declination=declination,
                      holdout=hold, warm=start)
        assert base.context is not None and ext.context is not None
        w = row_weights(ext.context.bound)
        keep = np.ones(ctx.ep.t.size) if w is None else w
        nb, n, sb = scores_in(base.context, hold, keep)
        ne, _, se = scores_in(ext.context, hold, keep)
        ok = n > 0
        return (nb - ne)[ok] / n[ok], float(sb.sum()), float(se.sum()), float(n.sum()), picked

    hook = progress or current()
    # the longest first: each core takes the next item when it is free
    items: list[Callable[[], object]] = [*beside, *(partial(fold, hold) for hold in folds(windows))]
    outcomes = pmap(captured, items, done=lambda i, n: hook(f"{mag.id} diagnosis: held-out folds", i, n))
    ahead = tuple(outcomes[:len(beside)])
    every = [cast(FoldScores | None, o.get()) for o in outcomes[len(beside):]]
    parts = [p for p in every if p is not None]
    if not parts:
        msg = (f"{problem.where}: {mag.id}: no training fold of the held-out check could be fitted (the log determines "
               "the calibration only with all of its readings)")
        raise InsufficientDataError(msg)
    gains = np.concatenate([p[0] for p in parts])
    before, after, count = sum(p[1] for p in parts), sum(p[2] for p in parts), sum(p[3] for p in parts)
    chosen = [p[4] for p in parts]
    left_out = len(every) - len(parts)
    protocol = (f"interleaved blocked cross-validation: {len(windows)} blocks of {windows[0][1] - windows[0][0]:.0f} s, "
                f"{min(FOLDS, len(windows))} folds"
                + (f" ({left_out} could not be fitted and {'was' if left_out == 1 else 'were'} left out)"
                   if left_out else "")
                + "; parameters fitted without the held-out block, whose readings are scored with the parameters "
                "frozen; effects also chosen inside each training fold")
    rms = (np.sqrt(before / max(count, 1.0)), np.sqrt(after / max(count, 1.0)))
    return Heldout(np.array(gains), float(rms[0]), float(rms[1]), tuple(chosen), protocol), ahead
