"""Partial calibration (models/partial.py): which entries a log's information leaves to the prior, the priors
themselves, and the held factor's Jacobian."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.models import partial
from magcal_cli.params import BASE


def _yaw_only_information(tilt_deg: float, dip: float = 1.1, sigma: float = 0.01) -> np.ndarray:
    """Information of the base theta for y = D m_b + o with m_b known (a known trajectory) turning about the
    body z axis with +-tilt; IMU biases well known (they do not enter this linear model)."""
    psi = np.linspace(0.0, 4 * np.pi, 400)
    tilt = np.deg2rad(tilt_deg) * np.sin(3.1 * psi)
    rot = so3.exp(np.stack([0 * psi, 0 * psi, psi], 1)) @ so3.exp(np.stack([tilt, 0 * psi, 0 * psi], 1))
    m_b = np.einsum("nji,j->ni", rot, [np.cos(dip), 0.0, np.sin(dip)])
    jac = np.zeros((3 * len(psi), BASE.size))
    for k in range(3):                                     # row k of y depends on D[k, :] and o[k]
        rows = np.arange(len(psi)) * 3 + k
        for j in range(3):
            jac[rows, BASE.slice("D").start + k + 3 * j] = m_b[:, j]
        jac[rows, BASE.slice("o").start + k] = 1.0
    info = jac.T @ jac / sigma**2
    for name in ("accelerometer_bias", "gyroscope_bias", "dip"):
        sl = BASE.slice(name)
        info[sl, sl] += np.eye(sl.stop - sl.start) * 1e8
    return info


def _prior_std() -> np.ndarray:
    return partial.prior_of(BASE, BASE.zeros(), partial.MagPrior(np.eye(3), np.zeros(3), "test", 0.05), 1.0,
                            None).prior_std


def test_level_yaw_holds_the_vertical_column_not_the_offsets() -> None:
    """Level turns cannot separate D[:, z] sin(dip) from o: the column gives way, the offsets stay free."""
    held = {BASE.entry_names()[c] for c in partial.choose(_yaw_only_information(0.0), _prior_std())}
    assert held == {"D.02", "D.12", "D.22"}


def test_enough_tilt_holds_nothing() -> None:
    """+-20 deg of tilt determines D's vertical column: nothing is held."""
    assert partial.choose(_yaw_only_information(20.0), _prior_std()).size == 0


def test_already_held_entries_stay_and_effect_columns_stay_free() -> None:
    """`already` entries are kept; an appended (effect) column without a prior is never held."""
    info = _yaw_only_information(0.0)
    p = info.shape[0]
    big = np.zeros((p + 1, p + 1))
    big[:p, :p] = info
    big[p, p] = 1e-6                                        # an effect the data hardly know: still free
    dip = BASE.slice("dip").start
    held = partial.choose(big, _prior_std(), np.array([dip]))
    assert dip in held and p not in held


def test_posterior_std_is_finite_or_infinite_never_nan() -> None:
    """An entry without information is infinitely uncertain until it is held, then its prior's std bounds it."""
    info = np.diag([4.0, 0.0, 1.0])
    info[0, 2] = info[2, 0] = 1.0
    prior = np.array([1.0, 0.5, 1.0])
    sd = partial.posterior_std(info, prior, np.zeros(0, np.int64))
    assert np.isinf(sd[1]) and np.all(np.isfinite(sd[[0, 2]]))
    assert partial.posterior_std(info, prior, np.array([1]))[1] == pytest.approx(0.5)


def test_flown_prior_inverts_the_firmware_correction() -> None:
    """field = M raw + t  ->  raw = D m_b + o with D = |field| M^-1, o = -M^-1 t."""
    rng = np.random.default_rng(1)
    m = np.eye(3) + 0.05 * rng.standard_normal((3, 3))
    t = rng.normal(size=3) * 30.0
    field = 450.0 * rng.normal(size=(500, 3))
    field *= 450.0 / np.linalg.norm(field, axis=1, keepdims=True)
    raw = (field - t) @ np.linalg.inv(m).T
    prior = partial.flown_prior(raw, field, 1e-7, "COMPASS_*")
    assert prior is not None
    np.testing.assert_allclose(prior.D, 450.0 * np.linalg.inv(m) * 1e-7, rtol=1e-9)
    np.testing.assert_allclose(prior.o, -np.linalg.inv(m) @ t * 1e-7, rtol=1e-9, atol=1e-15)
    assert prior.rel_std == partial.ONBOARD_REL_STD


def test_sphere_prior_finds_centre_and_radius() -> None:
    rng = np.random.default_rng(2)
    u = rng.normal(size=(1000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    centre = np.array([3e-6, -1e-6, 2e-6])
    prior = partial.sphere_prior(centre + 45e-6 * u)
    np.testing.assert_allclose(prior.o, centre, atol=1e-7)
    np.testing.assert_allclose(prior.D, 45e-6 * np.eye(3), atol=1e-7)


def test_held_factor_jacobian_against_finite_differences() -> None:
    held = partial.prior_of(BASE, BASE.zeros(), partial.MagPrior(np.eye(3), np.zeros(3), "t", 0.1), 1.0, None)
    held = held.holding(BASE.cols("D")[[2, 5, 8]], np.zeros(0, np.int64))
    theta = np.random.default_rng(3).normal(size=BASE.size)
    f = held.factor(theta, True)
    assert f.J_theta is not None
    eps = 1e-7
    for i, c in enumerate(held.cols):
        d = np.zeros(BASE.size)
        d[c] = eps
        fd = (held.factor(theta + d, False).r - held.factor(theta - d, False).r) / (2 * eps)
        np.testing.assert_allclose(fd[:, 0], f.J_theta[:, 0, i], rtol=1e-6)
    assert np.allclose(held.soft().factor(theta, False).r, f.r * partial.PIN)


def test_held_entries_follow_the_layout_when_effect_blocks_come_first() -> None:
    """An accelerometer effect's block sits before the base ones: the held factor, the implausibility check and
    the start values must address the base entries where that layout puts them (they held the gyro biases' and
    dip's neighbours, and a flat rover's D came out 70 % off)."""
    from magcal_cli.effects import get
    from magcal_cli.effects.base import Inputs
    from magcal_cli.models.map.effects import Bound, layout_for

    layout = layout_for([Bound(get("nongravity_acceleration"), Inputs(np.zeros(1), np.zeros((1, 3)),
                                                                      np.zeros((1, 3)), {}, (), {}))])
    assert layout.slice("gyroscope_bias").start == 2 + 3                        # kappa, delay_s, b_a, then b_g
    theta = layout.zeros()
    held = partial.prior_of(layout, theta, partial.MagPrior(np.eye(3), np.zeros(3), "t", 0.1), 1.0, 1.1)
    held = held.holding(BASE.cols("gyroscope_bias")[:2].tolist() + BASE.cols("dip").tolist(), np.zeros(0, np.int64))
    assert layout.entry_names()[held.theta_cols[0]] == "gyroscope_bias.x"
    assert [layout.entry_names()[c] for c in held.theta_cols] == ["gyroscope_bias.x", "gyroscope_bias.y", "dip"]
    f = held.factor(theta, True)
    np.testing.assert_array_equal(f.theta_cols, held.theta_cols)
    assert f.r[-1, 0] == pytest.approx(-1.1 / (partial.DIP_REF_STD * partial.PIN))     # dip's row reads theta's dip
    theta[layout.slice("dip")] = 1.1 + 100 * partial.DIP_REF_STD
    assert partial.implausible(theta, held.holding(np.zeros(0, np.int64), np.zeros(0, np.int64))).tolist() == \
        BASE.cols("dip").tolist()


@pytest.mark.parametrize(("widening", "spread", "says"), [
    (None, 0.10, "the log's motion determines too little for even a partial calibration (D.20 is uncertain to "
                 "20 % of the field"),
    (np.full(BASE.size, 2.0), 0.10, "the log's motion determines too little"),      # residuals nearly white: the motion
    (np.full(BASE.size, 8.0), 0.01, "the log's motion determines too little"),      # readings explained: the motion
    (np.full(BASE.size, 8.0), 0.10, "no calibration explains these readings: the calibrated field strength still varies "
                             "10 % RMS and the residuals drift together in time (D.20's uncertainty widened 8.0x, "
                             "to 20 % of the field), so the field around the sensor was not uniform"),
])
def test_a_useless_partial_fit_names_the_field_or_the_motion(widening: np.ndarray | None, spread: float,
                                                            says: str) -> None:
    """A refused partial calibration blames a non-uniform field only when its residuals drift together and the
    calibrated field strength still varies; otherwise the motion."""
    from magcal_cli.errors import InsufficientDataError
    from magcal_cli.models.observability import check_useful

    cov = np.diag(np.full(BASE.size, 1e-8))
    cov[BASE.cols("D")[2], BASE.cols("D")[2]] = 0.04                          # D.20: 20 % of a unit field
    with pytest.raises(InsufficientDataError) as err:
        check_useful(cov, 1.0, np.zeros(0, np.int64), "log: mag", widening, spread)
    assert str(err.value).startswith(f"log: mag: {says}")
