"""`time_offset`: the magnetometer sample stamped t measured the field at t - tau (mismatch.md E3).

R(t - tau) = R(t) E^T with E = R(t - tau)^T R(t) the body rotation over [t - tau, t], integrated from the gyro
samples themselves (zero-order hold, as the preintegration takes them), so the sensor saw m_b' = E m_b and the
term is D (E - I) m_b: exact in the rotation, not a linearisation in tau omega. d m_b' / d tau =
omega(t - tau) x m_b' (the rate at the time the field was sensed).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from magcal_cli import so3, stacks
from magcal_cli.effects.base import Effect, Inputs, Kinematics, NotTestable, Point, Target, Term
from magcal_cli.params import ParamBlock
from magcal_cli.streams import FloatArray, Stream

#: the rotation rate must change by at least this (rad/s, std of |omega|): a constant rate about a fixed axis
#: turns a delay into a constant rotation that D absorbs
MIN_RATE_SPREAD = 0.05


def attitude_at(t_gyr: FloatArray, q: FloatArray, w: FloatArray, t: FloatArray
                ) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """Body attitude Q(t) (M, 3, 3) relative to the first gyro sample, Q_j Exp(w_j (t - t_j)) with t_j <= t, and
    the gyro sample j holding at each t."""
    at, j = _attitude_cm(t_gyr, q, w, t)
    return stacks.rm(at), j


def _attitude_cm(t_gyr: FloatArray, q: FloatArray, w: FloatArray, t: FloatArray
                 ) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """`attitude_at` on component-major stacks (3, 3, M) (stacks.py): the term evaluates it at every
    linearisation (~700 times on log171), where np.matmul would loop over its 2 383 tiny products."""
    j = np.clip(np.searchsorted(t_gyr, t, side="right") - 1, 0, t_gyr.size - 1)
    return stacks.mul(stacks.cm(q[j]), stacks.exp(w[j] * (t - t_gyr[j])[:, None])), j


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
        steps = so3.exp(kin.gyr[:-1] * np.diff(kin.gyr_t)[:, None])
        q = np.concatenate([np.eye(3)[None], so3.cumulative_product(steps)])
        q_t, _ = attitude_at(kin.gyr_t, q, kin.gyr, kin.t)
        return Inputs(kin.t, kin.omega, kin.omega_dot, {"q": q, "q_t": q_t, "gyr_t": kin.gyr_t, "gyr": kin.gyr})

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """D (E - I) m_b; d/dtau = D (omega(t - tau) x E m_b); d/dphi_k = D (E - I) [m_b]x."""
        c = inp.channels
        sensed = inp.t - float(beta[0])
        q_s, j = _attitude_cm(c["gyr_t"], c["q"], c["gyr"], sensed)
        e = stacks.tmul(q_s, stacks.cm(c["q_t"]))                      # R(t - tau)^T R(t), (3, 3, M)
        mb_s = np.einsum("ijn,nj->ni", e, at.m_b)
        v = mb_s - at.m_b                                                # (E - I) m_b
        d_tau = (np.cross(c["gyr"][j], mb_s) @ at.D.T)[:, :, None]
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
