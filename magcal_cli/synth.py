"""Synthetic recordings with known truth: the `paper` (Huang et al. 2025), `handheld`, `multirotor`, `rover` scenarios.

Truth and noise are drawn as in methods.md section 5 (the authors' simulate/simulate.m), in NED. The trajectory
is a continuous-time truth (synth_motion.py: attitude knots at OVERSAMPLE times the IMU rate, C1 in between;
a translation whose acceleration is continuous), and every sensor samples it as real sensors do, at its own
stamps (synth_sampling.py): IMU sample k at t_k = k / rate is the instantaneous body rate and specific force
R^T (a_n - g_n) (Sampling.INSTANT) or their means over [t_k - 1/rate, t_k] (Sampling.PRECEDING, a delta-angle
IMU), plus bias and noise; the magnetometer reads D R(t_j)^T m_n + o + noise at its own stamps
t_j = phase + j / mag_rate. a_n = 0 (pure rotation) in paper and handheld; multirotor and rover carry their own
translation (synth_scenarios.py), log their GNSS position and list it as the nongravity_acceleration effect.
`effects` adds physics the base model leaves out (synth_effects.py, synth_inject.py); they draw from their
own generators, so a simulation with effects has the same trajectory and noise as one without.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from . import so3, units
from .calibration import Calibration, ImuCalibration, MagCalibration, Source
from .errors import MagcalError
from .models.accel import G
from .models.params import BASE, MAG
from .streams import Kind, Recording, Sampling, Stream
from .synth_effects import EffectSpec
from .synth_inject import Base, InjectedEffect, inject, truth_entry
from .synth_motion import OVERSAMPLE, Trajectory
from .synth_physics import POWER_PROFILES
from .synth_rotation import handheld, paper
from .synth_rotation import paper_trajectory as paper_trajectory  # re-exported: tests build records from it
from .synth_sampling import (
    check_phase,
    check_rates,
    check_sampling,
    draw_phase,
    imu_stamps,
    mag_stamps,
    sample_imu,
)
from .synth_scenarios import MIN_DURATION, Scenario, multirotor, rover

FloatArray = npt.NDArray[np.float64]

SCENARIOS = ("paper", "handheld", "multirotor", "rover")
#: default IMU and magnetometer rates (Hz) per scenario; the vehicles log like handheld so 5 minutes stay small
DEFAULT_RATES = {"paper": (80.0, 80.0), "handheld": (100.0, 50.0), "multirotor": (100.0, 50.0),
                 "rover": (100.0, 50.0)}
#: default length (s) of the vehicle scenarios (paper and handheld follow their protocols)
DEFAULT_DURATION = {"multirotor": 300.0, "rover": 300.0}
#: noise densities of methods.md section 5: accelerometer m/s^2/sqrt(Hz), gyro rad/s/sqrt(Hz), field T/sqrt(Hz)
NOISE_DENSITY = {"accelerometer": 0.02, "gyroscope": 8.7e-4, "magnetometer": 0.003e-6}
#: a vehicle compass's noise against the paper's lab magnetometer: 0.1-0.3 uT RMS (1-3 mG, a count or more of
#: an ArduPilot log) instead of 0.015-0.03 uT, so that a logged count does not turn the noise into a staircase
COMPASS_NOISE_FACTOR = 7.0
#: the field strength (T) of methods.md section 5's draw
PAPER_FIELD = 27e-6
#: ROS time of the first sample, so that simulated logs carry realistic absolute stamps
T0_ROS = 1_763_700_000.0


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


@dataclass(frozen=True, eq=False)
class Simulation:
    """A simulated recording, its truth, the true attitude at the IMU stamps (N, 3, 3), the still intervals (s),
    the injected effects (SI parameters), how the IMU sampled, the magnetometer's phase (s), the fine grid's
    knots per IMU period and the continuous-time attitude R(t) itself (None only for hand-built simulations)."""

    recording: Recording
    truth: Truth
    rotations: FloatArray
    still: tuple[tuple[float, float], ...]
    scenario: str
    seed: int
    effects: tuple[InjectedEffect, ...] = ()
    imu_sampling: Sampling = Sampling.INSTANT
    mag_phase_s: float = 0.0
    oversample: int = OVERSAMPLE
    trajectory: Trajectory | None = None


def truth_calibration(sim: Simulation, log: Recording, version: str, created_utc: str) -> Calibration:
    """The truth as a calibration document (method "truth", zero uncertainty) plus the simulation settings.

    Ids and the magnetometer unit are those a reader reports for the written `log`, so the truth compares
    directly with what `magcal fit` produces from it (e.g. MAG[0] in milligauss for a .bin).
    """
    tr = sim.truth
    mag_sim, acc_sim = sim.recording.select(Kind.MAGNETOMETER), sim.recording.select(Kind.ACCELEROMETER)
    mag = log.select(Kind.MAGNETOMETER)
    gyro_ids = set(log.ids(Kind.GYROSCOPE))
    imu_id = next((i for i in log.ids(Kind.ACCELEROMETER) if i in gyro_ids), acc_sim.id)
    f = units.from_si(mag.native_unit)
    cal = MagCalibration(mag.id, units.canonical(mag.native_unit), tr.D * f, tr.o * f,
                         float(np.rad2deg(tr.dip)), np.zeros((MAG.size, MAG.size)), tr.field_strength * f, "data")
    imu = ImuCalibration(imu_id, tr.accel_bias, tr.gyro_bias, np.zeros(3), np.zeros(3))
    source = Source(str(log.path), log.format, "", 0.0, float(acc_sim.t[-1]))
    sim_info = {"scenario": sim.scenario, "seed": sim.seed, "rate_hz": acc_sim.rate_hz,
                "mag_rate_hz": mag_sim.rate_hz, "still_intervals_s": [list(s) for s in sim.still],
                "imu_sampling": sim.imu_sampling.value, "mag_phase_s": sim.mag_phase_s, "oversample": sim.oversample}
    noise = {f"{k}_std": [v] * 3 for k, v in tr.noise_std.items()} | {"source": "simulation (per-sample std, SI)"}
    effects = tuple(truth_entry(e, log, imu_id) for e in sim.effects)
    return Calibration(source, "truth", imu, (cal,), version, created_utc, noise, effects,
                       extra={"simulation": sim_info})


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


def _scenario(scenario: str, rng: np.random.Generator, rate: float, duration: float | None,
              trajectory: FloatArray | None) -> Scenario:
    """The continuous-time truth of the scenario, or of `trajectory` (knots at the IMU rate; no translation)."""
    if trajectory is not None:
        rot = np.asarray(trajectory, dtype=np.float64)
        if rot.ndim != 3 or rot.shape[1:] != (3, 3) or len(rot) < 3:
            msg = f"simulate: trajectory must be (N+1, 3, 3) rotations with N >= 2, got {rot.shape}"
            raise MagcalError(msg)
        return Scenario(Trajectory.from_knots(rot, 1.0 / rate), None, ())
    if scenario in ("paper", "handheld"):
        return (paper if scenario == "paper" else handheld)(rng, rate, duration)
    length = DEFAULT_DURATION[scenario] if duration is None else duration
    if not length >= MIN_DURATION[scenario]:
        msg = (f"simulate: the {scenario} scenario needs --duration >= {MIN_DURATION[scenario]:g} s "
               f"(its still, start and stop phases alone take most of that), got {length:g}")
        raise MagcalError(msg)
    return (multirotor if scenario == "multirotor" else rover)(rng, rate, length)


def rates(scenario: str, rate: float | None, mag_rate: float | None) -> tuple[float, float]:
    """The IMU and magnetometer rates (Hz) a simulation uses: given ones, else the scenario's (DEFAULT_RATES;
    the magnetometer never faster than the IMU by default)."""
    rate = rate or DEFAULT_RATES[scenario][0]
    return rate, mag_rate or min(DEFAULT_RATES[scenario][1], rate)


def at_home(drawn: Truth) -> Truth:
    """`drawn` moved to the place and date the written logs claim (HOME, T0_ROS): the WMM's dip, declination and
    field strength (D rescaled from the paper's 27 uT), so that a fit comparing with the WMM finds agreement."""
    import datetime as dt

    from .synth_physics import HOME
    from .wmm import reference_field

    ref = reference_field(HOME[0], HOME[1], HOME[2], dt.datetime.fromtimestamp(T0_ROS, dt.timezone.utc).date())
    noise = drawn.noise_std | {"magnetometer": drawn.noise_std["magnetometer"] * COMPASS_NOISE_FACTOR}
    return replace(drawn, D=drawn.D * (ref.intensity / PAPER_FIELD), dip=ref.dip, declination=ref.declination,
                   noise_std=noise)


def simulate(scenario: str, seed: int, rate: float | None = None, mag_rate: float | None = None,
             duration: float | None = None, truth: Truth | None = None, effects: tuple[EffectSpec, ...] = (),
             noise_scale: float = 1.0, trajectory: FloatArray | None = None,
             power_profile: str = "flight", imu_sampling: Sampling = Sampling.INSTANT,
             mag_phase_s: float | None = None) -> Simulation:
    """Simulate one recording (IMU stream `/imu/data`, magnetometer `/imu/mag`) with seeded truth.

    `truth` replaces the drawn calibration (its noise_std is still set from the rates). `effects` are injected
    (auxiliary channels join the recording); `noise_scale` multiplies every noise std (0: noise-free);
    `trajectory` (N+1, 3, 3) body->NED rotations at the IMU rate (the knots of the C1 truth) replaces the
    scenario's rotations and translation (then there is none). `power_profile` (synth_physics.POWER_PROFILES)
    shapes the throttle and current of the power effects (default "flight"). `imu_sampling` says what an IMU
    sample stands for (INSTANT or PRECEDING, synth_sampling.py); `mag_phase_s` is the magnetometer's first
    stamp, 0 <= phase < 1/mag_rate (default: drawn from the seed in [0, min(5 ms, 1/mag_rate))).
    """
    if scenario not in SCENARIOS:
        msg = f"simulate: unknown scenario {scenario!r}; choose one of {', '.join(SCENARIOS)}"
        raise MagcalError(msg)
    if power_profile not in POWER_PROFILES:
        msg = f"simulate: unknown power profile {power_profile!r}; choose one of {', '.join(POWER_PROFILES)}"
        raise MagcalError(msg)
    if not np.isfinite(noise_scale) or noise_scale < 0:
        msg = f"simulate: noise_scale must be a finite number >= 0, got {noise_scale}"
        raise MagcalError(msg)
    check_sampling(imu_sampling)
    rate, mag_rate = rates(scenario, rate, mag_rate)
    check_rates(rate, mag_rate)
    phase = draw_phase(seed, mag_rate) if mag_phase_s is None else float(mag_phase_s)
    check_phase(phase, mag_rate)
    rng = np.random.default_rng(seed)
    drawn = draw_truth(rng, rate, mag_rate)
    if noise_scale != 1.0:
        drawn = replace(drawn, noise_std={k: v * noise_scale for k, v in drawn.noise_std.items()})
    if truth is None and scenario != "paper":
        # the written logs claim a place and date (GPS at HOME, stamps from T0_ROS): the field must be the one the
        # World Magnetic Model gives there, or a fit that compares with the WMM (or takes the dip from it) disagrees;
        # the paper scenario keeps methods.md's draw (27 uT, dip 72 +- 5 deg) for the replication
        drawn = at_home(drawn)
    truth = drawn if truth is None else replace(truth, noise_std=drawn.noise_std)
    made = _scenario(scenario, rng, rate, duration, trajectory)
    t = imu_stamps(round(made.trajectory.end * rate), rate)     # the truth runs one IMU period past the last
    t_mag = mag_stamps(phase, mag_rate, float(t[-1]))
    sd = truth.noise_std
    noise_g = sd["gyroscope"] * rng.standard_normal((len(t), 3))
    noise_a = sd["accelerometer"] * rng.standard_normal((len(t), 3))
    noise_m = sd["magnetometer"] * rng.standard_normal((len(t_mag), 3))
    src = f"simulate:{scenario}:seed={seed}"
    done = inject(tuple(effects), Base(made.trajectory, t, t_mag, np.array([0.0, 0.0, G]), truth.m_n,
                                       truth.field_strength, seed, noise_scale, src, power_profile, made.motion))
    gyro, acc = sample_imu(done, t, rate, imu_sampling)
    gyro += truth.gyro_bias + noise_g
    acc += truth.accel_bias + noise_a
    mag = done.field(t_mag) @ truth.D.T + truth.o + done.extra(t_mag) + noise_m
    window = None if imu_sampling is Sampling.INSTANT else 1.0 / rate
    streams = (
        Stream(Kind.ACCELEROMETER, "/imu/data", t, acc, f"{src}#/imu/data", "m/s^2", sampling=imu_sampling,
               window_s=window),
        Stream(Kind.GYROSCOPE, "/imu/data", t, gyro, f"{src}#/imu/data", "rad/s", sampling=imu_sampling,
               window_s=window),
        Stream(Kind.MAGNETOMETER, "/imu/mag", t_mag, mag, f"{src}#/imu/mag", "tesla"),
        *done.streams,
    )
    rec = Recording(Path(f"{scenario}-{seed}.sim"), "simulation", streams, t0=T0_ROS)
    oversample = 1 if trajectory is not None else OVERSAMPLE
    return Simulation(rec, truth, made.trajectory.at(t), made.still, scenario, seed, done.effects, imu_sampling,
                      phase, oversample, made.trajectory)
