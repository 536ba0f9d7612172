"""The MAP fit's result: the estimate in SI units, the context it was fitted in, and the conversion to both."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from magcal_cli import so3
from magcal_cli.findings import Finding, Severity
from magcal_cli.models.epochs import Epochs, Noise
from magcal_cli.models.factor import Linearize
from magcal_cli.models.gyro import Preintegrated
from magcal_cli.models.mag import field_nav
from magcal_cli.models.map.cost import mag_layout, make_linearize
from magcal_cli.models.map.effects import Bound
from magcal_cli.models.map.within import reading_residuals
from magcal_cli.models.observability import check_observability, check_useful
from magcal_cli.models.partial import Held
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import EffectFit
from magcal_cli.models.solve import Solution
from magcal_cli.params import BASE, Layout
from magcal_cli.streams import FloatArray


@dataclass(frozen=True, eq=False)
class FitContext:
    """What the solver saw at the optimum, in its internal (scaled) units: the diagnosis re-evaluates, extends
    and simulates the fit from here (diagnose/)."""

    ep: Epochs
    pre: Preintegrated
    noise: Noise
    layout: Layout
    bound: tuple[Bound, ...]
    states: FloatArray
    theta: FloatArray
    holdout: FloatArray | None = None
    held: Held | None = None
    #: (K,) 0 at readings inside windows the IMU did not measure (Problem.unmeasured): never part of any cost
    excluded: FloatArray | None = None

    def linearize(self, layout: Layout | None = None, bound: tuple[Bound, ...] | None = None,
                  ep: Epochs | None = None, pre: Preintegrated | None = None,
                  holdout: FloatArray | None = None) -> Linearize:
        """The fit's cost, optionally with another layout and effects, data or held-out weights."""
        w = self.excluded if holdout is None else holdout if self.excluded is None else holdout * self.excluded
        return make_linearize(self.ep if ep is None else ep, self.pre if pre is None else pre, self.noise,
                              self.layout if layout is None else layout, self.bound if bound is None else bound,
                              w, self.held)

    def with_effects_of(self, other: FitContext) -> FitContext:
        """This fit as a warm start that also carries the effect blocks `other` (a fit of the same magnetometer on
        other epochs, e.g. every k-th reading) found, in this fit's units; the base blocks stay this fit's."""
        theta = other.theta * other.layout.si_factors(other.ep.scale) / other.layout.si_factors(self.ep.scale)
        other.layout.carry(theta, self.layout, self.theta)
        return replace(self, layout=other.layout, theta=theta)


@dataclass(frozen=True, eq=False)
class MapEstimate:
    """One magnetometer's joint MAP result in SI: theta in `layout` (b_a, b_g, D, o, dip and any effect blocks)
    with the *total* gyro bias, its covariance, the noise levels used (SI), the trajectory and the solver's
    record, and the effects fitted or found not testable."""

    mag_id: str
    theta: FloatArray
    cov: FloatArray
    noise: Noise
    states: FloatArray
    epochs: FloatArray
    cost: float
    iterations: int
    converged: bool
    residual_rms: float
    log: tuple[str, ...]
    findings: tuple[Finding, ...] = ()
    notes: tuple[str, ...] = ()
    condition: float = float("nan")
    layout: Layout = BASE
    effects: tuple[EffectFit, ...] = ()
    context: FitContext | None = None
    #: entries the log could not determine, held at a prior (partial calibration, models/partial.py)
    held: Held | None = None

    @property
    def std(self) -> FloatArray:
        """Marginal standard deviations of theta (SI)."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def value(self, name: str) -> FloatArray:
        """Block `name` of theta (SI)."""
        return self.layout.get(self.theta, name)

    def std_of(self, name: str) -> FloatArray:
        """Marginal standard deviations of block `name` (SI)."""
        return self.std[self.layout.slice(name)]

    def base(self) -> tuple[FloatArray, FloatArray]:
        """theta and covariance of the base blocks only, in BASE order."""
        c = self.layout.cols(*BASE.names)
        return self.theta[c], self.cov[np.ix_(c, c)]


class Record(NamedTuple):
    """What a fit did: its Gauss-Newton iterations over every round, its log lines and its notes for the report."""

    iterations: int
    log: tuple[str, ...]
    notes: tuple[str, ...]


def estimate(problem: Problem, ctx: FitContext, sol: Solution, record: Record, cov_theta: FloatArray | None = None,
             widen: FloatArray | None = None, spread: float = 0.0) -> MapEstimate:
    """Convert the scaled solution to SI, with the total gyro bias and the observability findings (`cov_theta`:
    the covariance when not the solver's; `widen`: the sandwich's std factors; `spread`: the calibrated field
    strength's, `hold.explains`)."""
    ep, pre, noise, layout, held = ctx.ep, ctx.pre, ctx.noise, ctx.layout, ctx.held
    s = ep.scale
    jac = layout.si_factors(s)
    theta = sol.theta * jac
    bg, dip_at = layout.slice("gyroscope_bias"), layout.slice("dip")
    theta[bg] += pre.bias
    cov = (sol.cov_theta if cov_theta is None else cov_theta) * np.outer(jac, jac)
    states = sol.states
    dip = float(theta[dip_at][0])
    if abs(dip) > np.pi / 2:
        # (dip, R_k) and (pi - dip, Rz(pi) R_k) explain the data alike (north is only fixed by m_n): report
        # the representative with |dip| <= 90 deg; d dip'/d dip = -1 flips the dip's covariances
        theta[dip_at] = float(np.angle(np.exp(1j * (np.pi - dip))))
        states = so3.exp([0.0, 0.0, np.pi]) @ states
        cov[dip_at, :] *= -1.0
        cov[:, dip_at] *= -1.0
    fm = sol.factors[1]
    resid = fm.r * noise.mag * s
    if ep.groups is not None and ep.mag_factor is not None:   # the readings', not their means (map/within.py)
        d, _, dip_fit = mag_layout(layout).unpack(sol.theta)
        mean = fm.r * ep.mag_factor[:, None] * noise.mag          # the rows were scaled by 1 / mag_factor
        resid = reading_residuals(problem, ep.groups, mean, sol.states, d, field_nav(dip_fit),
                                  pre.bias + sol.theta[bg]) * s
    noise_si = Noise(noise.acc, noise.gyr, noise.mag * s)
    where = f"{problem.where}: {ep.mag_id}"
    # observability is a property of the motion: judge it on the model information of the base blocks, then
    # widen for honesty
    base = layout.cols(*BASE.names)
    condition, findings = check_observability(cov[np.ix_(base, base)], s, ep.acc, where,
                                              None if held is None else held.cols)
    if widen is not None and np.any(widen > 1.0):
        cov = cov * np.outer(widen, widen)
        names = [n for n, c in layout.groups().items() if np.any(widen[c] > 1.0)]
        findings.append(widening_note(where, ep.mag_id, float(widen.max()), names))
    if held is not None:
        check_useful(cov[np.ix_(base, base)], s, held.cols, where,
                     None if widen is None else widen[base], spread)
    return MapEstimate(ep.mag_id, theta, cov, noise_si, states, ep.t, sol.cost, record.iterations, sol.converged,
                       float(np.sqrt(np.mean(resid**2))), record.log, tuple(findings), record.notes, condition,
                       layout, context=ctx, held=held)


def widening_note(where: str, mag_id: str, factor: float, names: list[str] | None = None) -> Finding:
    """The note that a fit's uncertainties were widened for residuals correlated in time: information, not a
    warning (the stated stds already include it, and the verdict judges them; nothing changes what to do)."""
    return Finding(Severity.INFO, "correlated_residuals",
                   f"{where}: the residuals are correlated in time beyond the noise model, so the stated uncertainties "
                   f"are widened up to {factor:.1f}x by a time-clustered sandwich estimate; the cause is quantised "
                   "readings, unmodelled motion or a disturbance, and the stds reported include it",
                   {"max_factor": factor, "sensor": mag_id, "parameters": list(names or [])})
