"""Simulation versus recording: replicates simulated from the fitted model, refitted, and a residual battery.

mismatch.md section 3.4. Each replicate keeps the recording's epochs, its auxiliary channels and the fitted
trajectory; the readings are the fitted model's predictions plus noise at the fitted levels, and the gyro's
preintegrated rotations are the fitted relative rotations perturbed by their noise. Refitting the replicate (one
Gauss-Newton step from the optimum: the problem is nearly linear there) reproduces how the fit absorbs
structure; the step uses the fit's own Jacobians, factorised once for all replicates (they depend on the data
only at second order). Every statistic of the battery is standardised by its spread over the replicates; the
largest |z| is compared with the replicates' own largest |z| (a max-statistic test, so the many statistics need
no further correction, and trending channels carry their own null).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.align import columns
from magcal_cli.diagnose.parallel import pmap
from magcal_cli.models.epochs import Epochs
from magcal_cli.models.factor import Factor
from magcal_cli.models.map.cost import point_at
from magcal_cli.models.map.estimate import FitContext, MapEstimate
from magcal_cli.models.problem import Problem
from magcal_cli.models.solve import linearised
from magcal_cli.progress import Hook, current
from magcal_cli.streams import FloatArray, Kind, Stream

REPLICATES = 19
#: windows (s) of the windowed NIS that locates mismatches in time, and the z that flags one
WINDOW_S = 5.0
WINDOW_Z = 4.0
#: moving-average span (s) separating the low band (below ~1/span Hz) from the rest
LOW_BAND_S = 10.0
#: |z| above which a statistic counts as located
LOCATE_Z = 3.0
AXES = "xyz"
#: regressors computed from the motion, not logged channels
DERIVED = ("rotation rate",)
AUX_KINDS = (Kind.BATTERY_CURRENT, Kind.THROTTLE, Kind.BATTERY_VOLTAGE, Kind.TEMPERATURE)


@dataclass(frozen=True, eq=False)
class Check:
    """The battery on the recording, standardised by the replicates, the global p-value and flagged windows."""

    names: tuple[str, ...]
    z: FloatArray
    global_p: float
    replicates: int
    windows: tuple[tuple[float, float], ...]
    logged: tuple[str, ...] = ()

    def top(self, n: int = 5) -> list[tuple[str, float]]:
        """The n largest |z| statistics."""
        order = np.argsort(-np.abs(self.z))[:n]
        return [(self.names[i], float(self.z[i])) for i in order]

    def document(self) -> dict[str, Any]:
        """The document's `ppc` block."""
        return {"replicates": self.replicates, "global_p": self.global_p,
                "top": [{"statistic": s, "z": round(z, 2)} for s, z in self.top()]}

    def located(self, sensor: str) -> dict[str, Any]:
        """Where the recording departs from the replicates: axes, time windows, band and channels."""
        hot = [s for s, z in self.top(len(self.names)) if abs(z) > LOCATE_Z]
        axes = sorted({s[4] for s in hot if s.startswith("mag_") and s[4] in AXES})
        channels = sorted({c for s in hot if " ~ " in s and (c := s.split(" ~ ", 1)[1]) in self.logged})
        band = [0.0, round(1.0 / LOW_BAND_S, 3)] if any("low band" in s for s in hot) else None
        return {"sensor": sensor, "axes": axes, "time_windows_s": [list(w) for w in self.windows],
                "band_hz": band, "channels": channels}


def regressors(problem: Problem, ctx: FitContext) -> dict[str, FloatArray]:
    """The logged channels and motion features the residuals are compared with, at the epochs."""
    t = ctx.ep.t
    out: dict[str, FloatArray] = {"time": t - t[0]}
    for s in problem.aux:
        if s.kind in AUX_KINDS and s.values.shape[1] >= 1 and len(s) >= 2:
            ok = np.isfinite(s.values[:, 0])
            if ok.sum() >= 2 and np.ptp(s.values[ok, 0]) > 0:
                out[s.id] = np.interp(t, s.t[ok], s.values[ok, 0])
    g = problem.gyr
    w = columns(t, g.t, g.xyz) - ctx.pre.bias
    out["rotation rate"] = np.linalg.norm(w, axis=1)
    return out


def _corr(a: FloatArray, b: FloatArray) -> float:
    """Pearson correlation (0 for a constant input)."""
    a, b = a - a.mean(), b - b.mean()
    den = float(np.sqrt(np.sum(a * a) * np.sum(b * b)))
    return float(np.sum(a * b) / den) if den > 0 else 0.0


def _corrs(a: FloatArray, b: FloatArray) -> FloatArray:
    """Pearson correlations of every row of a (m, K) with every row of b (n, K), as `_corr` (0 for a constant row),
    in one product: the battery runs on every replicate."""
    a, b = a - a.mean(axis=1, keepdims=True), b - b.mean(axis=1, keepdims=True)
    den = np.sqrt(np.outer(np.sum(a * a, axis=1), np.sum(b * b, axis=1)))
    out: FloatArray = np.where(den > 0, (a @ b.T) / np.where(den > 0, den, 1.0), 0.0)
    return out


def _low(x: FloatArray, n: int) -> float:
    """Fraction of x's variance below the moving-average band (n samples)."""
    if x.size <= n or n < 2:
        return 0.0
    c = np.cumsum(np.insert(x - x.mean(), 0, 0.0))
    smooth = (c[n:] - c[:-n]) / n
    return float(np.var(smooth) / max(np.var(x), 1e-300))


def battery(ctx: FitContext, factors: Sequence[Factor], states: FloatArray, theta: FloatArray,
            reg: dict[str, FloatArray]) -> tuple[tuple[str, ...], FloatArray, FloatArray]:
    """The statistics (names, values) and the windowed magnetometer NIS (one value per WINDOW_S window)."""
    fa, fm, fg = factors[0], factors[1], factors[2]
    at = point_at(states, theta, ctx.layout, ctx.pre)
    e = fm.r * ctx.noise.mag                                          # unwhitened (scaled units)
    h = at.m_b + e @ np.linalg.inv(at.D).T
    rho = np.linalg.norm(h, axis=1) - 1.0
    rotated = so3.log_small(ctx.pre.delta)                            # rotation vector of each interval
    omega = rotated / np.maximum(ctx.pre.duration, 1e-9)[:, None]     # its mean body rate
    rate_x_field = np.cross(np.concatenate([omega, omega[-1:]]), at.m_b) @ at.D.T
    dt = float(np.median(np.diff(ctx.ep.t)))
    n_low = max(2, int(round(LOW_BAND_S / dt)))
    names, vals = [], []

    def add(name: str, v: float) -> None:
        names.append(name)
        vals.append(v)

    series = {f"mag_{a}": fm.r[:, i] for i, a in enumerate(AXES)} | {"field_norm": rho}
    with_reg = _corrs(np.stack(list(series.values())), np.stack(list(reg.values())))
    for (sname, x), row in zip(series.items(), with_reg, strict=True):
        for cname, c in zip(reg, row, strict=True):
            add(f"{sname} ~ {cname}", float(c))
        add(f"{sname} lag-1 autocorrelation", _corr(x[:-1], x[1:]))
        add(f"{sname} low band", _low(x, n_low))
    for i, a in enumerate(AXES):
        add(f"mag_{a} ~ rotation x field", _corr(fm.r[:, i], rate_x_field[:, i]))
        add(f"acc_{a} ~ rotation rate", _corr(fa.r[:, i], reg["rotation rate"] ** 2))
        add(f"acc_{a} ~ gravity_{a}", _corr(fa.r[:, i], at.g_b[:, i]))
        add(f"gyro_{a} ~ rotation_{a}", _corr(fg.r[:, i], rotated[:, i]))
        add(f"acc_{a} lag-1 autocorrelation", _corr(fa.r[:-1, i], fa.r[1:, i]))
    for f in (fa, fm, fg):
        add(f"{f.name} NIS", float(np.mean(f.r**2)))
    _, which = _windows_of(ctx.ep.t)
    nis = np.bincount(which, np.sum(fm.r**2, axis=1)) / np.bincount(which)
    return tuple(names), np.array(vals), nis


def _windows_of(t: FloatArray) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The WINDOW_S windows from t[0] that hold epochs (their numbers, increasing) and each epoch's place among
    them. Only occupied ones: a corrupt stamp years away once asked for 1.4e8 windows per replicate (21 GB)."""
    occupied, which = np.unique(np.floor((t - t[0]) / WINDOW_S).astype(np.int64), return_inverse=True)
    return occupied, which.reshape(-1)


def replicate(ctx: FitContext, factors: Sequence[Factor], rng: np.random.Generator
              ) -> tuple[Epochs, Any]:
    """Data simulated from the fitted model at the fitted trajectory: predictions plus fresh noise."""
    fa, fm, fg = factors[0], factors[1], factors[2]
    ep, pre, noise = ctx.ep, ctx.pre, ctx.noise
    s_acc = 1.0 / ep.acc_factor if np.any(ep.acc_factor < 1.0 - 1e-12) else np.ones(ep.t.size)
    acc_pred = ep.acc - fa.r / s_acc[:, None] * noise.acc
    s_mag = 1.0 if ep.mag_factor is None else 1.0 / ep.mag_factor[:, None]     # a group's mean reading
    mag_pred = ep.mag - fm.r / s_mag * noise.mag
    k = ep.t.size
    if ep.acc_at is None:
        e_acc = rng.standard_normal((k, 3)) / s_acc[:, None]
    else:                   # noise at the IMU samples, interpolated as the accelerometer was: shared samples correlate
        j, w = ep.acc_at
        z = rng.standard_normal((int(j.max()) + 2 - int(j.min()), 3))
        e_acc = (1.0 - w)[:, None] * z[j - j.min()] + w[:, None] * z[j + 1 - j.min()]
    acc = acc_pred + e_acc * noise.acc
    mag = mag_pred + rng.standard_normal((k, 3)) / s_mag * noise.mag
    chol = np.linalg.cholesky(pre.cov)          # not inv(l_inv): a broken interval has l_inv = 0 (gyro.py)
    r = (chol @ fg.r[:, :, None])[:, :, 0]
    xi = (chol @ rng.standard_normal((k - 1, 3, 1)))[:, :, 0]
    delta = pre.delta @ so3.exp(r - xi)
    return replace(ep, acc=acc, mag=mag), replace(pre, delta=delta)


def gumbel_fit(x: FloatArray) -> tuple[float, float]:
    """Maximum-likelihood Gumbel (right) location and scale: scipy.stats.gumbel_r.fit's equations, bracket and
    tolerances (Evans, Hastings & Peacock 2000, p. 101), without importing scipy.stats (0.2-1.2 s, issue 27)."""
    from scipy.special import logsumexp

    def slope(scale: float) -> float:
        w = np.exp(-x / scale - np.max(-x / scale))
        return float(x.mean() - np.average(x, weights=w) - scale)

    lo, hi = 0.5, 2.0
    while np.sign(slope(lo)) == np.sign(slope(hi)) and (lo > 0 or hi < np.inf):
        lo, hi = lo / 2, hi * 2
    scale = brentq(slope, lo, hi, rtol=1e-14, xtol=1e-14)
    return float(-scale * (logsumexp(-x / scale) - np.log(len(x)))), scale


def brentq(f: Callable[[float], float], a: float, b: float, xtol: float, rtol: float, maxiter: int = 100) -> float:
    """A root of f in [a, b], where f changes sign (else ValueError): Brent's method as scipy's brentq
    (optimize/Zeros/brentq.c) step for step, so the same digits, without importing scipy.optimize (0.09 s per
    process, issue 27); after `maxiter` steps the last estimate, as scipy's root_scalar gives it."""
    xpre, xcur = a, b
    fpre, fcur = f(xpre), f(xcur)
    if fpre * fcur > 0:
        msg = f"f({a:g}) and f({b:g}) have the same sign: no root is bracketed"
        raise ValueError(msg)
    if fpre == 0 or fcur == 0:
        return xpre if fpre == 0 else xcur
    xblk, fblk, spre, scur = 0.0, 0.0, 0.0, 0.0
    for _ in range(maxiter):
        if fpre * fcur < 0:
            xblk, fblk = xpre, fpre
            spre = scur = xcur - xpre
        if abs(fblk) < abs(fcur):                       # xcur: the end with the smaller |f|
            xpre, xcur, xblk = xcur, xblk, xcur
            fpre, fcur, fblk = fcur, fblk, fcur
        delta = (xtol + rtol * abs(xcur)) / 2
        sbis = (xblk - xcur) / 2
        if fcur == 0 or abs(sbis) < delta:
            return xcur
        if abs(spre) > delta and abs(fcur) < abs(fpre):
            if xpre == xblk:                            # secant
                stry = -fcur * (xcur - xpre) / (fcur - fpre)
            else:                                       # inverse quadratic
                dpre = (fpre - fcur) / (xpre - xcur)
                dblk = (fblk - fcur) / (xblk - xcur)
                stry = -fcur * (fblk * dblk - fpre * dpre) / (dblk * dpre * (fblk - fpre))
            if 2 * abs(stry) < min(abs(spre), 3 * abs(sbis) - delta):
                spre, scur = scur, stry
            else:
                spre = scur = sbis
        else:
            spre = scur = sbis
        xpre, fpre = xcur, fcur
        xcur += scur if abs(scur) > delta else (delta if sbis > 0 else -delta)
        fcur = f(xcur)
    return xcur                                         # root_scalar's answer too when it does not converge


def _cost(factors: Sequence[Factor]) -> float:
    """1/2 the sum of squared (whitened) residuals."""
    return 0.5 * sum(float(np.sum(f.r * f.r)) for f in factors)


def check(problem: Problem, mag: Stream, est: MapEstimate, replicates: int = REPLICATES, seed: int = 0,
          progress: Hook | None = None, stage: str = "replicates") -> Check:
    """Compare the recording with `replicates` simulations from the fit `est`."""
    hook = progress or current()
    ctx = est.context
    assert ctx is not None
    reg = regressors(problem, ctx)
    factors = ctx.linearize(holdout=None)(ctx.states, ctx.theta, False)
    names, obs, nis = battery(ctx, factors, ctx.states, ctx.theta, reg)
    rng = np.random.default_rng(seed)
    seeds = rng.integers(0, 2**32, replicates)
    at_fit = linearised(ctx.linearize(holdout=None), ctx.states, ctx.theta)

    def one(s: int) -> tuple[FloatArray, FloatArray]:
        ep, pre = replicate(ctx, factors, np.random.default_rng(s))
        lin = ctx.linearize(ep=ep, pre=pre, holdout=None)
        start = lin(ctx.states, ctx.theta, False)
        dx, dt = at_fit.step([f.r for f in start])
        states, theta = ctx.states @ so3.exp(dx), ctx.theta + dt
        moved = lin(states, theta, False)
        if not _cost(moved) <= _cost(start):            # a step that does not lower the cost is not taken
            states, theta, moved = ctx.states, ctx.theta, start
        _, v, w = battery(replace(ctx, ep=ep, pre=pre), moved, states, theta, reg)
        return v, w

    sims = pmap(one, [int(s) for s in seeds], done=lambda i, n: hook(f"{mag.id} diagnosis: {stage}", i, n))
    t_sim, w_sim = np.array([v for v, _ in sims]), np.array([w for _, w in sims])
    mean, sd = t_sim.mean(axis=0), np.maximum(t_sim.std(axis=0, ddof=1), 1e-12)
    z = (obs - mean) / sd
    # each replicate standardised by the others: the null distribution of the largest |z|
    b = replicates
    loo_mean = (t_sim.sum(axis=0) - t_sim) / (b - 1)
    loo_sd = np.sqrt(np.maximum((np.sum(t_sim**2, axis=0) - t_sim**2 - (b - 1) * loo_mean**2) / (b - 2), 1e-24))
    null_max = np.max(np.abs((t_sim - loo_mean) / loo_sd), axis=1)
    observed = float(np.max(np.abs(z)))
    exceed = int(np.sum(null_max >= observed))
    p = (1 + exceed) / (b + 1)
    if exceed == 0:                           # beyond every replicate: a Gumbel tail fitted to the null maxima
        from scipy.special import expm1

        loc, scale = gumbel_fit(null_max)
        p = min(p, float(-expm1(-np.exp(-((observed - loc) / scale)))))      # Gumbel's survival function, as scipy
    wz = (nis - w_sim.mean(axis=0)) / np.maximum(w_sim.std(axis=0, ddof=1), 1e-12)
    logged = tuple(k for k in reg if k not in DERIVED)
    return Check(names, z, float(p), b, _windows(ctx.ep.t, wz), logged)


def _windows(t: FloatArray, wz: FloatArray) -> tuple[tuple[float, float], ...]:
    """Merged windows whose magnetometer NIS stands out from every replicate's (wz: one per occupied window)."""
    out: list[list[float]] = []
    occupied, _ = _windows_of(t)
    for i in occupied[np.flatnonzero(wz > WINDOW_Z)].tolist():
        a, b = float(t[0] + i * WINDOW_S), float(min(t[0] + (i + 1) * WINDOW_S, t[-1]))
        if out and abs(out[-1][1] - a) < 1e-9:
            out[-1][1] = b
        else:
            out.append([a, b])
    return tuple((round(a, 1), round(b, 1)) for a, b in out)
