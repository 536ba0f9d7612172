"""The MAP fit's noise levels re-estimated from its residuals (variance components, leverage-corrected dof)."""

from __future__ import annotations

import numpy as np

from magcal_cli.models.epochs import Noise
from magcal_cli.models.factor import Factor
from magcal_cli.models.gyro import Preintegrated
from magcal_cli.models.solve import Solution
from magcal_cli.streams import FloatArray

#: rounds of (solve, re-estimate the noise levels); stop when no level changes by more than NOISE_TOL
NOISE_ROUNDS = 6
NOISE_TOL = 0.03
#: slope of the gyro's variance-factor fixed point (d log factor / d log variance) assumed for the first step
FIRST_GYRO_SLOPE = -0.7
#: the gyro variance never drops below this factor (log) of its start value (100x lower std)
MIN_GYRO_LOG_VARIANCE = float(np.log(1e-4))


def variance_ratios(sol: Solution, loss: str = "l2", c: float = 3.0) -> FloatArray:
    """Variance factors sum(r^2) / (rows - leverage): accelerometer (3 axes), gyro (1), magnetometer (3).

    The leverage (trace of the hat matrix over a group's rows) counts the degrees of freedom the unknowns take
    from that group (Foerstner's variance-component estimation); a factor of 1 means the assumed noise level
    fits. With a robust loss each row's |r|^2 is truncated at c^2 and divided by its expectation under the
    model (E min(chi2_m, c^2) / m), one factor per group: outliers then cannot inflate the levels.
    """
    marg = sol.marginals()
    out = {f.name: group_ratio(f, sol.leverage(f, marg).sum(axis=0), loss, c) for f in sol.factors}
    return np.concatenate([out["accel"], out["gyro"], out["mag"]])


def group_ratio(f: Factor, leverage: FloatArray, loss: str = "l2", c: float = 3.0) -> FloatArray:
    """One factor group's variance factor per axis (one for the gyro), sum(r^2) / (rows - leverage), from its
    leverage summed over rows per axis (`variance_ratios`)."""
    m = f.r.shape[1]
    # rows weighted to zero (excluded readings) carry no information and no residual: do not count them
    rows = f.r.shape[0] if f.J_theta is None else int(np.count_nonzero(np.any(f.J_theta != 0.0, axis=(1, 2))))
    if loss != "l2":
        from scipy import special  # on use: a robust fit's only need, 9 MB of module an l2 fit does without

        s2 = np.minimum(np.sum(f.r**2, axis=1), c * c)
        # E[min(X, c^2)] for X ~ chi2_m: m F_(m+2)(c^2) + c^2 (1 - F_m(c^2))
        # chdtr/chdtrc are what scipy.stats.chi2.cdf/sf compute for x >= 0, without importing scipy.stats (issue 27)
        kappa = (m * special.chdtr(m + 2, c * c) + c * c * special.chdtrc(m, c * c)) / m
        width = 1 if f.name == "gyro" else m
        ss = np.full(width, s2.sum() / kappa / m)
        dof = np.full(width, (rows * m - leverage.sum()) / m)
    else:
        ss, dof = np.sum(f.r**2, axis=0), rows - leverage
        if f.name == "gyro":
            ss, dof = ss.sum(keepdims=True), dof.sum(keepdims=True)
    out: FloatArray = np.where(dof > 10.0, ss / np.maximum(dof, 1e-300), 1.0)
    return out


def as_levels(noise: Noise) -> FloatArray:
    """The 7 noise levels in variance_ratios order (accelerometer 3, gyro 1, magnetometer 3)."""
    return np.concatenate([noise.acc, noise.gyr[:1], noise.mag])


def secant(history: list[tuple[float, float]], x: float, f: float) -> float:
    """Next step for the gyro log-variance x whose fixed-point residual is f (the log variance factor).

    The plain update x += f converges linearly with rate 1 + slope, slowly for the weakly determined gyro
    level; a secant step on f(x) = 0 (slope clipped to [-1, -0.1], so at most 10 plain steps) converges in a
    few rounds. The first step assumes the slope the paper protocol shows from below (FIRST_GYRO_SLOPE).
    """
    slope = FIRST_GYRO_SLOPE
    if history:
        x0, f0 = history[-1]
        if abs(x - x0) > 1e-12:
            slope = (f - f0) / (x - x0)
    if slope > -0.1:           # not a fixed-point slope: the other levels moved the factor (coupling)
        slope = FIRST_GYRO_SLOPE
    return -f / float(max(slope, -1.0))


def noise_step(step: FloatArray, floor: FloatArray | None, levels: FloatArray, history: list[tuple[float, float]],
               applied: float) -> tuple[FloatArray, bool, float]:
    """One noise round's log-variance step (gyro at index 3) from the measured factors `step`: whether it is small
    enough to stop, and the gyro's measured factor (for the secant history)."""
    if floor is not None:
        # still data measured the sensors' white noise: levels never go below it, and the gyro keeps it; where it
        # moves, the gyro's own noise is measured sample by sample (Problem.gyr_scale: a flight's vibration).
        # Estimated from the residuals instead, the gyro level absorbs every misfit of the other factors and runs
        # away (x 280 on the x-io log), docs/method-map.md
        step[3] = 0.0
        step = np.maximum(step, 2.0 * np.log(floor / levels))
    small = float(np.max(np.abs(step))) < 2.0 * NOISE_TOL
    measured = float(step[3])
    step[3] = secant(history, applied, measured) if floor is None else 0.0
    # without still data the gyro level is weakly determined: when the other factors misfit (flight, too
    # little rotation) its fixed point runs away toward zero and the trajectory becomes numerically rigid
    step[3] = max(step[3], MIN_GYRO_LOG_VARIANCE - applied)
    return step, small, measured


def rescaled(noise: Noise, pre: Preintegrated, log_var: FloatArray) -> tuple[Noise, Preintegrated]:
    """Noise levels (and the preintegration whitening) with variances multiplied by exp(log_var) (7,)."""
    f = np.exp(0.5 * log_var)
    new = Noise(noise.acc * f[:3], noise.gyr * f[3], noise.mag * f[4:])
    return new, pre.scaled(float(np.exp(log_var[3])))
