"""Effect plug-ins inside the joint MAP: inputs at the epochs, the extended layout, terms added to factors.

The layout puts each effect's blocks next to the base block its factor already touches (accelerometer effects
before b_a, gyro effects after b_g, magnetometer effects after the dip), so every factor's theta columns stay one
contiguous run and the solver keeps its compact Jacobians.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli import effects as registry
from magcal_cli.align import columns
from magcal_cli.effects.base import Effect, Inputs, Kinematics, NotTestable, Point, Recent, Target, Term
from magcal_cli.models.factor import Factor, gaussian_factor, run_start, whiten
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import EffectFit
from magcal_cli.params import ACCEL_BIAS, D_BLOCK, DIP, GYRO_BIAS, O_BLOCK, Estimate, Layout, ParamBlock
from magcal_cli.streams import FloatArray, Stream

IntArray = npt.NDArray[np.int64]

#: an effect whose Wald test of "zero" has a p-value below this is `accepted` (significant), else `rejected`
ALPHA = 0.01
#: window (s) over which the gyro is differentiated for omega_dot (noise would dominate a 1-sample difference)
OMEGA_DOT_WINDOW_S = 0.05


@dataclass(frozen=True, eq=False)
class Bound:
    """An effect with its inputs at one magnetometer's epochs."""

    effect: Effect
    inputs: Inputs

    def blocks(self) -> tuple[ParamBlock, ...]:
        """The effect's parameter blocks named '<id>.<param>' for the shared layout."""
        return tuple(ParamBlock(f"{self.effect.id}.{b.name}", b.size, b.si_scale, b.group or self.effect.id,
                                b.labels) for b in self.effect.params)

    def names(self) -> tuple[str, ...]:
        """Its block names in the layout."""
        return tuple(b.name for b in self.blocks())


def kinematics(problem: Problem, t: FloatArray, bias: FloatArray) -> Kinematics:
    """Body rate (gyro minus `bias`) and its derivative at times t (rad/s, rad/s^2).

    Computed on the gyro rows the interpolation at t reads (each time's neighbours, and both ends) rather than on
    every sample: the same digits (np.interp finds the same pair of rows), without four arrays the size of the log
    per binding (an hour at 400 Hz: 0.1 GB each time the diagnosis binds a fold, issue 39)."""
    g = problem.gyr
    n = g.t.size
    dt = float(np.median(np.diff(g.t)))
    half = max(1, int(round(OMEGA_DOT_WINDOW_S / dt / 2)))
    # a gyro sample holds over [t_k, t_k+1) (zero-order hold, as the preintegration takes it): its rate is
    # the one at the middle of that interval
    j = np.searchsorted(g.t, t - 0.5 * dt, side="right")        # each time's interval, to a row (the +-3 below)
    rows = np.unique(np.concatenate([[0, n - 1], *(np.clip(j + d, 0, n - 1) for d in range(-3, 3))]))
    w = g.xyz[rows] - bias
    lo, hi = np.clip(rows - half, 0, n - 1), np.clip(rows + half, 0, n - 1)
    wdot = ((g.xyz[hi] - bias) - (g.xyz[lo] - bias)) / np.maximum(g.t[hi] - g.t[lo], 1e-12)[:, None]
    mid = g.t[rows] + 0.5 * dt
    omega = columns(t, mid, w)
    omega_dot = columns(t, mid, wdot)
    still = np.zeros(t.size, dtype=bool)
    for seg in () if problem.still is None else problem.still.segments:     # tests build problems without one
        still |= (t >= seg.start) & (t <= seg.end)
    return Kinematics(t, omega, omega_dot, g.t, g.xyz, still, np.asarray(bias, dtype=np.float64))


def bind(problem: Problem, mag: Stream, t: FloatArray, bias: FloatArray, ids: Sequence[str],
         declination: float = 0.0) -> tuple[list[Bound], list[EffectFit]]:
    """The effects this log can test, with their inputs; the others as `not_testable` results."""
    if not ids:
        return [], []
    kin: Kinematics | None = None
    epochs = (mag.id, declination, hashlib.blake2b(t.tobytes() + bias.tobytes(), digest_size=16).digest())
    bound, untestable = [], []
    for eid in ids:
        eff = registry.get(eid)
        sensor = mag.id if eff.target is Target.MAG else problem.imu_id
        # the diagnosis refits the same epochs with the same start bias dozens of times (log171: 52 fits, 3.2 s
        # of time_offset's attitude integration alone); inputs are read-only, so one computation serves them all
        key = (eid, *epochs)
        got = _INPUTS.get(problem, key)
        if got is None:
            kin = kin or kinematics(problem, t, bias)
            try:
                got = eff.inputs(problem.aux, mag, kin, declination)
            except NotTestable as exc:
                got = str(exc)
            _INPUTS.put(problem, key, got)
        if isinstance(got, str):
            untestable.append(EffectFit(eid, sensor, "not_testable", reason=got))
        else:
            bound.append(Bound(eff, got))
    return bound, untestable


#: the inputs kept per effect, magnetometer and declination: the most recently used epochs and start biases. A
#: diagnosis binds at each fit's own gyro bias, and time_offset's inputs hold an attitude per KEY IMU samples: with
#: every bias kept, 6 sets (155 MB) were alive at a two-hour log's peak (issue 39). Repeats come in runs (a round's
#: fits share their start), so the latest few serve them
KEEP = 2
#: each problem's effect inputs by (effect, magnetometer, declination, epochs and start bias digest); the reason
#: as a string where the effect was not testable. Dropped with the problem. A magnetometer's readings are the
#: problem's own (or a thinned copy, whose epochs differ): its id and epochs name them. KEEP per effect and magnetometer
_INPUTS: Recent[Problem, tuple[object, ...], Inputs | str] = Recent(KEEP, lambda key: key[:3])


def forget(problem: Problem, keep: Sequence[str] = ()) -> None:
    """Drop the inputs kept for `problem`'s effects other than `keep`: a screening's are not asked again once it is
    decided (each training fold binds at its own start bias), and time_offset's hold 26 MB per 60 min of 400 Hz
    gyro, carried through the held-out folds (issue 39)."""
    _INPUTS.drop(problem, lambda key: key[0] not in keep)


def reported(inputs: Inputs) -> dict[str, object]:
    """An effect's constants that its result keeps: not a term's private "_" tables, which can hold a value per IMU
    sample (time_offset's gyro) and would travel with every result a diagnosis worker sends back (issue 39)."""
    return {k: v for k, v in inputs.constants.items() if not k.startswith("_")}


def layout_for(bound: Sequence[Bound]) -> Layout:
    """Accelerometer effects, b_a, b_g, gyro effects, D, o, dip, magnetometer effects."""
    def of(target: Target) -> list[ParamBlock]:
        return [b for e in bound if e.effect.target is target for b in e.blocks()]

    return Layout((*of(Target.ACCEL), ACCEL_BIAS, GYRO_BIAS, *of(Target.GYRO), D_BLOCK, O_BLOCK, DIP,
                   *of(Target.MAG)))


def terms(bound: Sequence[Bound], layout: Layout, theta: FloatArray, at: Point,
          target: Target) -> list[tuple[Term, IntArray]]:
    """Each bound effect's term for one factor, with the theta columns of its parameters."""
    out = []
    for e in bound:
        if e.effect.target is target:
            cols = layout.cols(*e.names())
            out.append((e.effect.term(e.inputs, theta[cols], at), cols))
    return out


def with_terms(f: Factor, l_inv: FloatArray, extra: Sequence[tuple[Term, IntArray]], layout: Layout) -> Factor:
    """A factor r = L^-1 (y - prediction) with the terms added to the prediction (Jacobians included).

    Columns are merged and sorted, so that a layout from `layout_for` keeps them contiguous.
    """
    if not extra:
        return f
    r = f.r.copy()
    for term, _ in extra:
        r -= term.value @ l_inv.T
    if f.J_theta is None or f.theta_cols is None:
        return Factor(f.name, r)
    jx = None if f.J_x is None else f.J_x.copy()
    cols = f.theta_cols
    all_c = np.concatenate([cols, *(c for _, c in extra)])
    # the base columns first, then each term's beta columns: filled in place (no copy-and-concatenate)
    jt = np.empty(f.J_theta.shape[:2] + (all_c.size,))
    jt[:, :, :cols.size] = f.J_theta
    at = cols.size
    for term, beta_cols in extra:
        if term.d_state is not None and jx is not None:
            jx -= whiten(l_inv, term.d_state)
        for name, d in term.d_base.items():
            pos = np.searchsorted(cols, layout.cols(name))        # theta_cols are sorted
            start = run_start(pos)
            run = pos if start is None else slice(start, start + pos.size)
            jt[:, :, run] -= whiten(l_inv, d)
        np.negative(whiten(l_inv, term.d_beta), out=jt[:, :, at:at + beta_cols.size])
        at += beta_cols.size
    order = np.argsort(all_c, kind="stable")
    if np.any(order != np.arange(order.size)):          # a layout from `layout_for` is already in order
        jt, all_c = jt[:, :, order], all_c[order]
    return Factor(f.name, r, f.idx, jx, f.J_next, jt, all_c.astype(np.int64))


def gyro_extra(bound: Sequence[Bound], layout: Layout, theta: FloatArray, at: Point
               ) -> tuple[FloatArray, FloatArray, IntArray] | None:
    """The gyro effects' summed perturbation, its Jacobian and columns (None without gyro effects)."""
    parts = terms(bound, layout, theta, at, Target.GYRO)
    if not parts:
        return None
    value = sum((t.value for t, _ in parts), np.zeros_like(parts[0][0].value))
    jac = np.concatenate([t.d_beta for t, _ in parts], axis=2)
    return value, jac, np.concatenate([c for _, c in parts]).astype(np.int64)


def row_weights(bound: Sequence[Bound], target: Target = Target.MAG) -> FloatArray | None:
    """The product of the row weights that the effects entering `target`'s factor ask for (None when none
    does)."""
    ws = [w for e in bound if e.effect.target is target and (w := e.effect.weights(e.inputs)) is not None]
    return None if not ws else np.prod(np.stack(ws), axis=0)


def prior_factor(bound: Sequence[Bound], layout: Layout, theta: FloatArray, jacobians: bool) -> Factor | None:
    """Gaussian priors of parameters that only exist under the alternative (e.g. a throttle exponent)."""
    cols, mean, std = [], [], []
    for e in bound:
        p = e.effect.prior()
        if p is None:
            continue
        c = layout.cols(*e.names())
        keep = np.isfinite(p[1])
        cols.append(c[keep])
        mean.append(p[0][keep])
        std.append(p[1][keep])
    if not cols:
        return None
    return gaussian_factor("prior", np.concatenate(cols), np.concatenate(mean), np.concatenate(std), theta, jacobians)


def results(bound: Sequence[Bound], layout: Layout, theta_si: FloatArray, cov_si: FloatArray, mag_id: str,
            imu_id: str) -> list[EffectFit]:
    """Each fitted effect's estimate (SI, by its short parameter names) and Wald test of beta = 0."""
    out: list[EffectFit] = []
    if not bound:
        return out
    # scipy.stats.chi2.sf computes it so, and importing scipy.stats costs 0.2-1.2 s (issue 27)
    from scipy.special import chdtrc

    for e in bound:
        cols = layout.cols(*e.names())
        sensor = mag_id if e.effect.target is Target.MAG else imu_id
        if cols.size == 0:                   # nothing estimated (e.g. excluded windows): found or not
            w = e.effect.weights(e.inputs)
            n = 0 if w is None else int(np.count_nonzero(w == 0.0))
            out.append(EffectFit(e.effect.id, sensor, "accepted" if n else "rejected", None, e.inputs.channel_ids,
                                 float(n), 0, float("nan"), constants=reported(e.inputs)))
            continue
        short = Layout(e.effect.params)
        est = Estimate(short, theta_si[cols], cov_si[np.ix_(cols, cols)])
        prior = e.effect.prior()
        # the test covers the entries that vanish under the base model (not exponents held by a prior)
        test = np.ones(cols.size, bool) if prior is None else ~np.isfinite(prior[1])
        b, c = est.value[test], est.cov[np.ix_(test, test)]
        try:
            stat = float(b @ np.linalg.solve(c, b))
        except np.linalg.LinAlgError:
            stat = float("nan")
        p = float(chdtrc(b.size, stat)) if np.isfinite(stat) else float("nan")
        status = "accepted" if np.isfinite(p) and p < ALPHA else "rejected"
        out.append(EffectFit(e.effect.id, sensor, status, est, e.inputs.channel_ids, stat, int(b.size), p,
                             constants=reported(e.inputs)))
    return out
