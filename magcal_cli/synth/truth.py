"""The simulator's calibration truth: D, o, dip, IMU biases and noise, drawn as methods.md section 5 draws them.

`draw_truth` is the authors' simulate/simulate.m draw (27 uT field); `at_home` moves it to the place and date
the written logs claim (the World Magnetic Model's field at HOME on T0_ROS); `more_mags` draws further
magnetometers on the same board, each from a generator of its own.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from magcal_cli import so3
from magcal_cli.params import BASE
from magcal_cli.streams import FloatArray, Kind, Stream

#: noise densities of methods.md section 5: accelerometer m/s^2/sqrt(Hz), gyro rad/s/sqrt(Hz), field T/sqrt(Hz)
NOISE_DENSITY = {"accelerometer": 0.02, "gyroscope": 8.7e-4, "magnetometer": 0.003e-6}
#: a vehicle compass's noise against the paper's lab magnetometer: 0.1-0.3 uT RMS (1-3 mG, a count or more of
#: an ArduPilot log) instead of 0.015-0.03 uT, so that a logged count does not turn the noise into a staircase
COMPASS_NOISE_FACTOR = 7.0
#: the field strength (T) of methods.md section 5's draw
PAPER_FIELD = 27e-6
#: ROS time of the first sample, so that simulated logs carry realistic absolute stamps
T0_ROS = 1_763_700_000.0
#: second entry of the seed of magnetometer k >= 1's generator (its calibration, then its noise)
MAGS_TAG = 0x3A65


@dataclass(frozen=True, eq=False)
class Truth:
    """The calibration the simulator used: D, o in tesla, dip in rad, biases in SI, per-sample noise std."""

    D: FloatArray
    o: FloatArray
    dip: float
    accel_bias: FloatArray
    gyro_bias: FloatArray
    noise_std: dict[str, float]
    #: magnetic declination (rad): the field's east component in the true-north NED frame the trajectory uses
    declination: float = 0.0
    #: per-sample noise std while the motors run (vibration); None: noise_std at all times
    noise_std_flight: dict[str, float] | None = None

    @property
    def m_n(self) -> FloatArray:
        """The unit field direction in the trajectory's (true-north) NED frame."""
        c = np.cos(self.dip)
        return np.array([c * np.cos(self.declination), c * np.sin(self.declination), np.sin(self.dip)])

    @property
    def theta(self) -> FloatArray:
        """The calibration parameters in `params.BASE` order: b_a, b_g, vec(D) column-major, o, dip."""
        theta = BASE.zeros()
        for name, value in (("accelerometer_bias", self.accel_bias), ("gyroscope_bias", self.gyro_bias),
                            ("D", self.D.ravel(order="F")), ("o", self.o), ("dip", self.dip)):
            BASE.put(theta, name, value)
        return theta

    @property
    def field_strength(self) -> float:
        """det(D)^(1/3), the convention magcal reports when no reference field is known."""
        return float(np.cbrt(np.linalg.det(self.D)))


def draw_truth(rng: np.random.Generator, rate: float, mag_rate: float) -> Truth:
    """Calibration drawn as in methods.md section 5 (field magnitude 27 uT)."""
    def u(lim: float, n: int = 3) -> FloatArray:
        out: FloatArray = rng.uniform(-lim, lim, n)
        return out

    acc_bias, mag_bias = u(0.5), u(2.0) * 1e-6
    scale = np.diag(1.0 + u(0.1))
    s1, s2, s3 = u(np.deg2rad(10.0))
    skew = np.array([[1.0, 0.0, 0.0], [np.sin(s1), np.cos(s1), 0.0],
                     [-np.sin(s2), np.cos(s2) * np.sin(s3), np.cos(s2) * np.cos(s3)]])
    a1, a2, a3 = u(np.deg2rad(5.0))
    rot = so3.exp([a1, 0, 0]) @ so3.exp([0, a2, 0]) @ so3.exp([0, 0, a3])
    d = PAPER_FIELD * scale @ skew @ rot
    dip = np.deg2rad(72.0) + float(u(np.deg2rad(5.0), 1)[0])
    gyro_bias = 0.01 + u(np.deg2rad(0.1))
    noise = {"accelerometer": NOISE_DENSITY["accelerometer"] * np.sqrt(rate),
             "gyroscope": NOISE_DENSITY["gyroscope"] * np.sqrt(rate),
             "magnetometer": NOISE_DENSITY["magnetometer"] * np.sqrt(mag_rate)}
    return Truth(d, mag_bias, dip, acc_bias, gyro_bias, noise)


def at_home(drawn: Truth) -> Truth:
    """`drawn` moved to the place and date the written logs claim (HOME, T0_ROS): the WMM's dip, declination and
    field strength (D rescaled from the paper's 27 uT), so that a fit comparing with the WMM finds agreement."""
    import datetime as dt

    from magcal_cli.synth.physics import HOME
    from magcal_cli.wmm import reference_field

    ref = reference_field(HOME[0], HOME[1], HOME[2], dt.datetime.fromtimestamp(T0_ROS, dt.timezone.utc).date())
    noise = drawn.noise_std | {"magnetometer": drawn.noise_std["magnetometer"] * COMPASS_NOISE_FACTOR}
    return replace(drawn, D=drawn.D * (ref.intensity / PAPER_FIELD), dip=ref.dip, declination=ref.declination,
                   noise_std=noise)


def more_mags(scenario: str, seed: int, truth: Truth, n_mags: int, m_b: FloatArray, t_mag: FloatArray,
              src: str) -> tuple[tuple[Truth, ...], tuple[Stream, ...]]:
    """Magnetometers 1 .. n_mags-1: D and o drawn as draw_truth draws them (in the first one's field: its dip,
    declination and strength rule), the first one's noise std, from generators of their own; they read
    D m_b + o + noise at the first one's stamps (`m_b`: the body-frame unit field there, without effects)."""
    truths, streams = [], []
    sd = truth.noise_std["magnetometer"]
    for k in range(1, n_mags):
        rng = np.random.default_rng([seed, MAGS_TAG, k])
        drawn = draw_truth(rng, 1.0, 1.0)
        d = drawn.D if scenario == "paper" else at_home(drawn).D
        truths.append(replace(truth, D=d, o=drawn.o))
        y = m_b @ d.T + drawn.o + sd * rng.standard_normal(m_b.shape)
        sid = f"/imu/mag{k}"
        streams.append(Stream(Kind.MAGNETOMETER, sid, t_mag, y, f"{src}#{sid}", "tesla"))
    return tuple(truths), tuple(streams)
