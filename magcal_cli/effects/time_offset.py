"""`time_offset`: the magnetometer sample stamped t measured the field at t - tau (mismatch.md E3).

R(t - tau) = R(t) E^T with E = R(t - tau)^T R(t) the body rotation over [t - tau, t], integrated from the gyro
samples themselves (zero-order hold, as the preintegration takes them), so the sensor saw m_b' = E m_b and the
term is D (E - I) m_b: exact in the rotation, not a linearisation in tau omega. d m_b' / d tau =
omega(t - tau) x m_b' (the rate at the time the field was sensed).
"""

from __future__ import annotations

from typing import Any, ClassVar, NamedTuple

import numpy as np
import numpy.typing as npt

from magcal_cli import so3, stacks
from magcal_cli.effects.base import Effect, Inputs, Kinematics, NotTestable, Point, Target, Term
from magcal_cli.params import ParamBlock
from magcal_cli.streams import FloatArray, Stream

#: the rotation rate must change by at least this (rad/s, std of |omega|): a constant rate about a fixed axis
#: turns a delay into a constant rotation that D absorbs
MIN_RATE_SPREAD = 0.05


#: gyro samples per kept attitude: the attitude at a sample between two kept ones is integrated on from the one before
#: it when a term needs it. Keeping it at every sample cost 72 B per IMU sample for every start bias the diagnosis
#: binds, and its log-depth scan over the whole log most of an hour-long log's diagnosis (issue 39)
KEY = 8


class Gyro(NamedTuple):
    """The gyro samples as logged (the problem's arrays, not copied: t (N,) s, raw (N, 3) rad/s, each held over
    [t_j, t_j+1)) and the bias to remove from them."""

    t: FloatArray
    raw: FloatArray
    bias: FloatArray

    def rate(self, j: npt.NDArray[np.int64]) -> FloatArray:
        """The body rate (rad/s) of samples j: what a bias-free copy of the whole log would hold there."""
        out: FloatArray = self.raw[j] - self.bias
        return out

    def step(self, j: npt.NDArray[np.int64], on: npt.NDArray[np.bool_]) -> FloatArray:
        """The rotation (3, 3, M) over sample j's whole interval where `on`, the identity elsewhere."""
        phi = np.zeros((j.size, 3))
        phi[on] = self.rate(j[on]) * (self.t[j[on] + 1] - self.t[j[on]])[:, None]
        return stacks.exp(phi)


def keyframes(g: Gyro) -> FloatArray:
    """The body attitude (ceil(N / KEY), 3, 3) at gyro samples 0, KEY, 2 KEY, ... relative to the first: products
    within each run of KEY samples, then their prefix."""
    n = g.t.size
    runs = -(-n // KEY)
    block = np.broadcast_to(np.eye(3)[:, :, None], (3, 3, runs)).copy()      # component-major (stacks.py)
    for i in range(KEY):                             # the i-th step of every run at once: KEY passes, not N
        s = np.arange(runs) * KEY + i
        block = stacks.mul(block, g.step(np.minimum(s, n - 1), s < n - 1))
    if runs == 1:
        return np.eye(3)[None].copy()
    rel = stacks.rm(block[:, :, :-1])
    del block                                        # each log-sized stack goes as soon as the next is made
    first = np.empty((runs, 3, 3))
    first[0] = np.eye(3)
    first[1:] = so3.cumulative_product(rel)
    return first


def _attitude_cm(g: Gyro, keys: FloatArray, t: FloatArray, memo: dict[str, Any] | None = None
                 ) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """Body attitude Q(t) as a component-major stack (3, 3, M) (stacks.py) relative to the first gyro sample,
    Q_j Exp(w_j (t - t_j)) with t_j <= t, Q_j integrated on from its kept attitude (`keyframes`); and the gyro
    sample j holding at each t.

    `memo` keeps the last call's Q_j: a fit moves tau a little per step, so most times keep their sample and
    only the others are integrated again (each Q_j depends on its own j alone: the same digits either way)."""
    j = np.clip(np.searchsorted(g.t, t, side="right") - 1, 0, g.t.size - 1)
    last = memo.get("_last") if memo is not None else None
    if last is not None and last[0].shape == j.shape:
        q_j = last[1].copy()
        redo = np.flatnonzero(last[0] != j)
    else:
        q_j, redo = np.empty((3, 3, j.size)), np.arange(j.size)
    if redo.size:
        q_j[:, :, redo] = _at_samples(g, keys, j[redo])
    if memo is not None:
        memo["_last"] = (j, q_j)         # one assignment: threads sharing the inputs see the old or the new pair
    return stacks.mul(q_j, stacks.exp(g.rate(j) * (t - g.t[j])[:, None])), j


def _at_samples(g: Gyro, keys: FloatArray, j: npt.NDArray[np.int64]) -> FloatArray:
    """The attitude Q_j (3, 3, M) at gyro samples j: the kept one before each, times the steps up to j."""
    k = j // KEY
    at = stacks.cm(keys[k])
    for i in range(KEY - 1):                         # the samples from the kept one up to j, masked past j
        s = k * KEY + i
        at = _product(at, g.step(np.minimum(s, j), s < j))
    return at


def _product(a: FloatArray, b: FloatArray) -> FloatArray:
    """a b of component-major stacks, entry by entry: einsum's digits depend on where a column sits in memory, and
    a Q_j kept by `_attitude_cm`'s memo must not depend on which other times were integrated with it."""
    out = np.empty_like(a)
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]
    return out


def attitude_at(g: Gyro, t: FloatArray) -> FloatArray:
    """Body attitude Q(t) (M, 3, 3) relative to the first gyro sample."""
    return stacks.rm(_attitude_cm(g, keyframes(g), t)[0])


class TimeOffset(Effect):
    """y = D R(t - tau)^T m_n + o; tau > 0: the magnetometer lags the IMU."""

    id = "time_offset"
    target = Target.MAG
    params = (ParamBlock("tau_s", 1, "none", "time offset"),)
    units: ClassVar[dict[str, str]] = {"tau_s": "s"}
    limits: ClassVar[dict[str, float]] = {"tau_s": 0.3}
    separating_experiment = ("fast rotations in both directions about each axis (a few rad/s), then a pause")
    physics_left_out = ("The magnetometer's time stamps lag (or lead) the IMU's, so during rotation it reports "
                        "the field of a slightly earlier orientation.")

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """The integrated body attitude at the gyro samples; needs rotation whose rate changes."""
        spread = float(np.std(np.linalg.norm(kin.omega, axis=1)))
        if spread < MIN_RATE_SPREAD:
            msg = (f"the rotation rate hardly changes (std {spread:.3f} rad/s): a delay cannot be told from a "
                   "mounting rotation")
            raise NotTestable(msg)
        g = Gyro(kin.gyr_t, kin.gyr, kin.gyr_bias)
        keys = keyframes(g)
        q_t = stacks.rm(_attitude_cm(g, keys, kin.t)[0])
        # per-sample tables are constants, not channels: channels are per epoch
        return Inputs(kin.t, kin.omega, kin.omega_dot, {"q_t": q_t}, constants={"_keys": keys, "_gyro": g})

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """D (E - I) m_b; d/dtau = D (omega(t - tau) x E m_b); d/dphi_k = D (E - I) [m_b]x."""
        c, k = inp.channels, inp.constants
        sensed = inp.t - float(beta[0])
        g: Gyro = k["_gyro"]
        q_s, j = _attitude_cm(g, k["_keys"], sensed, k)
        e = stacks.tmul(q_s, stacks.cm(c["q_t"]))                      # R(t - tau)^T R(t), (3, 3, M)
        mb_s = np.einsum("ijn,nj->ni", e, at.m_b)
        v = mb_s - at.m_b                                                # (E - I) m_b
        d_tau = (np.cross(g.rate(j), mb_s) @ at.D.T)[:, :, None]
        e_i = stacks.minus_identity(e)
        m = v.shape[0]
        d_d = np.zeros((m, 3, 3, 3))                                    # d (D v) / d vec(D), column-major:
        for i in range(3):                                               # entry (i, j + 3 k) is v_j when k = i
            d_d[:, i, :, i] = v                                          # (a fill: an einsum with I took 7x longer)
        d_dip = (np.einsum("ijn,nj->ni", e_i, at.dm_b_ddip) @ at.D.T)[:, :, None]
        d_state = stacks.rm(stacks.mul(np.einsum("ik,kjn->ijn", at.D, e_i), stacks.hat(at.m_b)))
        return Term(v @ at.D.T, d_tau, d_state, {"D": d_d.reshape(m, 3, 9), "dip": d_dip})

    def correct(self, params: dict[str, Any], t: FloatArray, y: FloatArray,
                channels: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
        """Re-stamp: the reading stamped t belongs to t - tau."""
        return t - float(params["tau_s"]), y


EFFECT = TimeOffset()
