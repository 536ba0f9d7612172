"""Effect terms in the EKF baselines: the additive magnetometer terms (`Effect.additive`: current, throttle,
temperature), y = D R^T m_n + o + t(beta; channels), evaluated by the plug-in's own `inputs` and `term`.

`ekf-ml` appends beta to the parameters whose likelihood it maximises (its sensitivities get d e_k / d beta = -d t /
d beta, the term's `d_beta`); `ekf-aug` appends beta to its state with a prior. Effects that need the orientation,
the trajectory or row weights (time offset, gyro/accelerometer scale, lever arm, non-gravity acceleration,
transient windows) are for the joint MAP only (docs/effects.md "Methods").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli import effects as registry
from magcal_cli.effects.base import Point
from magcal_cli.models.map.effects import Bound, results
from magcal_cli.models.result import EffectFit
from magcal_cli.params import BASE, Layout
from magcal_cli.streams import FloatArray

BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: an effect parameter without a plausibility limit starts with this prior std (scaled field units per unit of its
#: channel, or the entry's own unit)
DEFAULT_PRIOR_STD = 1.0


def _carries(method: str, effect_id: str) -> bool:
    """Whether `method` ("ekf-ml", "ekf-aug") carries the effect: an additive magnetometer term; for the augmented
    EKF also without a parameter that exists only under the alternative (a plug-in `prior`, the throttle
    exponent). The filter linearises the term at the base model, where such a parameter has no influence: started
    at c = 0 its column c u^p ln u is zero, and the pass ended at p = 1.15 +- 0.02 on a log with p = 1.5 (a second
    pass from there did not converge either), while `ekf-ml`'s likelihood gives 1.51 +- 0.20 (docs/effects.md)."""
    effect = registry.get(effect_id)
    return effect.additive and (method != "ekf-aug" or effect.prior() is None)


def not_carried(ids: Sequence[str], method: str) -> tuple[str, ...]:
    """The effects among `ids` that `method` ("ekf-ml", "ekf-aug") cannot carry."""
    return tuple(i for i in ids if not _carries(method, i))


def carried(method: str) -> tuple[str, ...]:
    """The ids of every registered effect `method` ("ekf-ml", "ekf-aug") carries."""
    return tuple(i for i in registry.EFFECTS if _carries(method, i))


def layout_of(bound: Sequence[Bound]) -> Layout:
    """The effect blocks of one filter, named '<id>.<param>', in the order the effects were requested."""
    return Layout(b for e in bound for b in e.blocks())


def start(bound: Sequence[Bound]) -> FloatArray:
    """The effect parameters' start values (the base model) in layout order."""
    parts = [e.effect.start() for e in bound]
    return np.concatenate(parts) if parts else np.zeros(0)


def prior(bound: Sequence[Bound], scale: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The plug-ins' priors in layout order and scaled units: mean, std (inf where a parameter has none), and the
    start std of an augmented state: that prior where there is one, else the parameter's plausibility limit
    (`Effect.limits`), so that the start admits every plausible value and carries little information."""
    mean, std, std0 = [], [], []
    for e in bound:
        factors = Layout(e.effect.params).si_factors(scale)
        p = e.effect.prior()
        m, s = (e.effect.start(), np.full(factors.size, np.inf)) if p is None else (p[0] / factors, p[1] / factors)
        lim = np.concatenate([np.full(b.size, e.effect.limits.get(b.name, np.nan)) for b in e.effect.params])
        mean.append(m)
        std.append(s)
        std0.append(np.where(np.isfinite(s), s, np.where(np.isfinite(lim), lim / factors, DEFAULT_PRIOR_STD)))
    if not mean:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return np.concatenate(mean), np.concatenate(std), np.concatenate(std0)


@dataclass(frozen=True, eq=False)
class Terms:
    """The bound additive effects of B filters that share one effect layout (`layout`, width p), with their priors
    (`prior`, scaled units): mean, std (inf: none) and start std (B, p)."""

    bound: tuple[tuple[Bound, ...], ...]
    layout: Layout
    mean: FloatArray
    std: FloatArray
    std0: FloatArray
    cols: tuple[IntArray, ...]                  # each effect's columns in `layout` (the same in every filter)

    @classmethod
    def of(cls, bound: Sequence[Sequence[Bound]], scales: Sequence[float]) -> Terms | None:
        """None when no filter carries an effect; the filters must carry the same effects (same layout) and have
        field scales `scales`."""
        layouts = {layout_of(b) for b in bound}
        if len(layouts) != 1:
            msg = "filters with different effects cannot share a batch"
            raise ValueError(msg)
        layout = layouts.pop()
        if layout.size == 0:
            return None
        mean, std, std0 = (np.array(x) for x in zip(*(prior(b, s) for b, s in zip(bound, scales, strict=True)),
                                                      strict=True))
        cols = tuple(layout.cols(*e.names()) for e in bound[0])
        return cls(tuple(tuple(b) for b in bound), layout, mean, std, std0, cols)

    @property
    def size(self) -> int:
        """p, the number of effect parameters per filter."""
        return self.layout.size

    def start(self) -> FloatArray:
        """Start values (B, p): the base model."""
        return np.array([start(b) for b in self.bound])

    def at(self, k: int, beta: FloatArray, rot: FloatArray, m_b: FloatArray, dm_b: FloatArray, g_b: FloatArray,
           d: FloatArray, valid: BoolArray) -> tuple[FloatArray, FloatArray]:
        """Summed term value (B, 3) and its Jacobian by beta (B, 3, p) at epoch k, for the filters whose epoch k is
        `valid`, from each plug-in's `term` at parameters beta (B, p) and the model point (rot (B, 3, 3), the
        predicted unit body field m_b and its dip derivative dm_b, g_b = R^T g_n (B, 3), D (B, 3, 3))."""
        b = beta.shape[0]
        value, jac = np.zeros((b, 3)), np.zeros((b, 3, self.size))
        one = slice(k, k + 1)
        for i in np.flatnonzero(valid):
            at = Point(rot[i:i + 1], m_b[i:i + 1], dm_b[i:i + 1], g_b[i:i + 1], d[i])
            for e, cols in zip(self.bound[i], self.cols, strict=True):
                term = e.effect.term(e.inputs.rows(one), beta[i, cols], at)
                value[i] += term.value[0]
                jac[i][:, cols] = term.d_beta[0]
        return value, jac

    def table(self, beta: FloatArray, k_all: int) -> tuple[FloatArray, FloatArray]:
        """The summed term (B, K, 3) and its Jacobian by beta (B, K, 3, p) at every epoch, for parameters beta
        (B, p) that stay fixed over a filter pass: one `term` call per plug-in over all epochs, at a point of
        unknowns (an additive term reads no model quantity; one that did would give NaN, refused here)."""
        b = beta.shape[0]
        value, jac = np.zeros((b, k_all, 3)), np.zeros((b, k_all, 3, self.size))
        for i in range(b):
            for e, cols in zip(self.bound[i], self.cols, strict=True):
                n = min(k_all, e.inputs.t.size)
                term = e.effect.term(e.inputs.rows(slice(0, n)), beta[i, cols], Point.unknown(n))
                if not (np.all(np.isfinite(term.value)) and np.all(np.isfinite(term.d_beta))):
                    msg = f"effect {e.effect.id} is declared additive but its term depends on the model point"
                    raise ValueError(msg)
                value[i, :n] += term.value
                jac[i, :n][:, :, cols] = term.d_beta
        return value, jac


def fitted(bound: Sequence[Bound], theta_si: FloatArray, cov_si: FloatArray, mag_id: str, imu_id: str
           ) -> list[EffectFit]:
    """Each effect's estimate and Wald test (as the joint MAP reports it) from theta and covariance (SI) in the
    layout BASE + the effect blocks."""
    layout = BASE.extended(layout_of(bound).blocks)
    return results(bound, layout, theta_si, cov_si, mag_id, imu_id)

