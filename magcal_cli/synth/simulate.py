"""Synthetic recordings with known truth: the `paper` (Huang et al. 2025), `handheld`, `multirotor`, `rover` scenarios.

Truth and noise are drawn as in methods.md section 5 (the authors' simulate/simulate.m), in NED. The trajectory
is a continuous-time truth (synth/motion.py: attitude knots at OVERSAMPLE times the IMU rate, C1 in between;
a translation whose acceleration is continuous), and every sensor samples it as real sensors do, at its own
stamps (synth/sampling.py): IMU sample k at t_k = k / rate is the instantaneous body rate and specific force
R^T (a_n - g_n) (Sampling.INSTANT) or their means over [t_k - 1/rate, t_k] (Sampling.PRECEDING, a delta-angle
IMU), plus bias and noise; the magnetometer reads D R(t_j)^T m_n + o + noise at its own stamps
t_j = phase + j / mag_rate. a_n = 0 (pure rotation) in paper and handheld; multirotor and rover carry their own
translation (synth/scenarios.py), log their GNSS position and list it as the nongravity_acceleration effect.
`effects` adds physics the base model leaves out (synth/effects.py, synth/inject.py); they draw from their
own generators, so a simulation with effects has the same trajectory and noise as one without. `vibration`
makes the IMU noise std a function of time, higher while the motors run (synth/vibration.py); `n_mags` adds
magnetometers `/imu/mag1`.. with their own D, o and noise generator, in the same field and trajectory.
What a firmware does to the field before it logs it is no part of the physics: `Simulation.previous` carries
the onboard calibration the `.bin` writer applies (synth/firmware.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from magcal_cli import units
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Source
from magcal_cli.errors import MagcalError
from magcal_cli.models.accel import G
from magcal_cli.params import MAG
from magcal_cli.streams import FloatArray, Kind, Recording, Sampling, Stream
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.firmware import PreviousCalibration
from magcal_cli.synth.inject import Base, InjectedEffect, inject, truth_entry
from magcal_cli.synth.motion import OVERSAMPLE, Trajectory
from magcal_cli.synth.physics import POWER_PROFILES
from magcal_cli.synth.rotation import handheld, paper
from magcal_cli.synth.rotation import (
    paper_trajectory as paper_trajectory,  # re-exported: tests build records from it
)
from magcal_cli.synth.sampling import (
    check_phase,
    check_rates,
    check_sampling,
    draw_phase,
    imu_stamps,
    mag_stamps,
    sample_imu,
)
from magcal_cli.synth.scenarios import MIN_DURATION, NO_LIMITS, Limits, Scenario, multirotor, rover
from magcal_cli.synth.truth import (
    COMPASS_NOISE_FACTOR as COMPASS_NOISE_FACTOR,  # re-exported, as the names below
)
from magcal_cli.synth.truth import NOISE_DENSITY as NOISE_DENSITY
from magcal_cli.synth.truth import PAPER_FIELD as PAPER_FIELD
from magcal_cli.synth.truth import T0_ROS as T0_ROS
from magcal_cli.synth.truth import Truth as Truth
from magcal_cli.synth.truth import at_home as at_home
from magcal_cli.synth.truth import draw_truth as draw_truth
from magcal_cli.synth.truth import more_mags
from magcal_cli.synth.vibration import SPIN_S, imu_std, levels, motor_weight, motors_of

SCENARIOS = ("paper", "handheld", "multirotor", "rover")
#: default IMU and magnetometer rates (Hz) per scenario; the vehicles log like handheld so 5 minutes stay small
DEFAULT_RATES = {"paper": (80.0, 80.0), "handheld": (100.0, 50.0), "multirotor": (100.0, 50.0),
                 "rover": (100.0, 50.0)}
#: default length (s) of the vehicle scenarios (paper and handheld follow their protocols)
DEFAULT_DURATION = {"multirotor": 300.0, "rover": 300.0}


@dataclass(frozen=True, eq=False)
class Simulation:
    """A simulated recording, its truth, the true attitude at the IMU stamps (N, 3, 3), the still intervals (s),
    the injected effects (SI parameters), how the IMU sampled, the magnetometer's phase (s), the fine grid's
    knots per IMU period and the continuous-time attitude R(t) itself (None only for hand-built simulations).

    `extra_truths` are the truths of magnetometers `/imu/mag1`.. (`truths` lists all); `motors` the intervals (s)
    in which motors run at flight speed and `vibration` whether the IMU noise follows them; `previous` the
    onboard calibration the simulated ArduPilot firmware flies with (None: the writer's default), set with
    `dataclasses.replace`.
    """

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
    extra_truths: tuple[Truth, ...] = ()
    motors: tuple[tuple[float, float], ...] = ()
    vibration: bool = False
    previous: PreviousCalibration | None = None

    @property
    def truths(self) -> tuple[Truth, ...]:
        """The truth of every magnetometer, in stream order (`/imu/mag`, `/imu/mag1`, ...)."""
        return (self.truth, *self.extra_truths)

    def imu_noise_std(self, sensor: str, t: FloatArray) -> FloatArray:
        """(N,) per-sample noise std of "gyroscope" or "accelerometer" at IMU stamps t (constant without
        vibration)."""
        rest = self.truth.noise_std[sensor]
        flight = self.truth.noise_std_flight
        if not self.vibration or flight is None:
            return np.full(len(t), rest)
        return imu_std(rest, flight[sensor], motor_weight(t, self.motors))[:, 0]


def log_mags(sim: Simulation, log: Recording) -> list[tuple[Truth, Stream]]:
    """Each simulated magnetometer with the stream a reader reports for it in the written `log` (the one with its
    id, else the one in its place: MAG[k], sensor_mag[k]); those the format does not carry are left out."""
    found = log.of_kind(Kind.MAGNETOMETER)
    by_id = {s.id: s for s in found}
    out = []
    for i, (tr, sid) in enumerate(zip(sim.truths, sim.recording.ids(Kind.MAGNETOMETER), strict=False)):
        stream = by_id.get(sid, found[i] if i < len(found) else None)
        if stream is not None:
            out.append((tr, stream))
    return out


def truth_calibration(sim: Simulation, log: Recording, version: str, created_utc: str) -> Calibration:
    """The truth as a calibration document (method "truth", zero uncertainty) plus the simulation settings.

    Ids and the magnetometer unit are those a reader reports for the written `log`, so the truth compares
    directly with what `magcal fit` produces from it (e.g. MAG[0] in milligauss for a .bin).
    """
    tr = sim.truth
    mag_sim, acc_sim = sim.recording.select(Kind.MAGNETOMETER), sim.recording.select(Kind.ACCELEROMETER)
    gyro_ids = set(log.ids(Kind.GYROSCOPE))
    imu_id = next((i for i in log.ids(Kind.ACCELEROMETER) if i in gyro_ids), acc_sim.id)
    cals = []
    for t_k, mag in log_mags(sim, log):
        f = units.from_si(mag.native_unit)
        cals.append(MagCalibration(mag.id, units.canonical(mag.native_unit), t_k.D * f, t_k.o * f,
                                   float(np.rad2deg(t_k.dip)), np.zeros((MAG.size, MAG.size)),
                                   t_k.field_strength * f, "data"))
    imu = ImuCalibration(imu_id, tr.accel_bias, tr.gyro_bias, np.zeros(3), np.zeros(3))
    source = Source(str(log.path), log.format, "", 0.0, float(acc_sim.t[-1]))
    sim_info = {"scenario": sim.scenario, "seed": sim.seed, "rate_hz": acc_sim.rate_hz,
                "mag_rate_hz": mag_sim.rate_hz, "still_intervals_s": [list(s) for s in sim.still],
                "imu_sampling": sim.imu_sampling.value, "mag_phase_s": sim.mag_phase_s, "oversample": sim.oversample}
    noise: dict[str, Any] = {f"{k}_std": [v] * 3 for k, v in tr.noise_std.items()}
    if sim.vibration and tr.noise_std_flight is not None:
        # the keys above stay the rest level; the flight level holds while the motors run (motors_s, ramps spin_s)
        noise |= {f"{k}_std_rest": [v] * 3 for k, v in tr.noise_std.items()}
        noise |= {f"{k}_std_flight": [v] * 3 for k, v in tr.noise_std_flight.items()}
        sim_info |= {"vibration": True, "motors_s": [list(m) for m in sim.motors], "spin_s": SPIN_S}
    noise |= {"source": "simulation (per-sample std, SI)"}
    effects = tuple(truth_entry(e, log, imu_id) for e in sim.effects)
    return Calibration(source, "truth", imu, tuple(cals), version, created_utc, noise, effects,
                       extra={"simulation": sim_info})


def _scenario(scenario: str, rng: np.random.Generator, rate: float, duration: float | None,
              trajectory: FloatArray | None, limits: Limits = NO_LIMITS) -> Scenario:
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
    return multirotor(rng, rate, length, limits) if scenario == "multirotor" else rover(rng, rate, length)


def rates(scenario: str, rate: float | None, mag_rate: float | None) -> tuple[float, float]:
    """The IMU and magnetometer rates (Hz) a simulation uses: given ones, else the scenario's (DEFAULT_RATES;
    the magnetometer never faster than the IMU by default)."""
    rate = rate or DEFAULT_RATES[scenario][0]
    return rate, mag_rate or min(DEFAULT_RATES[scenario][1], rate)


def _check_options(scenario: str, n_mags: int, limits: Limits, trajectory: FloatArray | None) -> None:
    """n_mags a whole number >= 1; flight limits only for the multirotor's own flight, within sense."""
    if isinstance(n_mags, bool) or not isinstance(n_mags, (int, np.integer)) or n_mags < 1:
        msg = f"simulate: n_mags must be a whole number >= 1, got {n_mags!r}"
        raise MagcalError(msg)
    if not limits.active:
        return
    if scenario != "multirotor" or trajectory is not None:
        msg = "simulate: tilt_limit_deg and accel_limit_mps2 shape the multirotor's own flight; leave them out here"
        raise MagcalError(msg)
    if limits.tilt_deg is not None and not 3.0 <= limits.tilt_deg <= 45.0:
        msg = f"simulate: tilt_limit_deg must be within 3..45 deg (the pad alone tilts up to 1.4), got {limits.tilt_deg}"
        raise MagcalError(msg)
    if limits.accel_mps2 is not None and not 0.2 <= limits.accel_mps2 <= 20.0:
        msg = f"simulate: accel_limit_mps2 must be within 0.2..20 m/s^2, got {limits.accel_mps2}"
        raise MagcalError(msg)


def simulate(scenario: str, seed: int, rate: float | None = None, mag_rate: float | None = None,
             duration: float | None = None, truth: Truth | None = None, effects: tuple[EffectSpec, ...] = (),
             noise_scale: float = 1.0, trajectory: FloatArray | None = None,
             power_profile: str = "flight", imu_sampling: Sampling = Sampling.INSTANT,
             mag_phase_s: float | None = None, vibration: bool | None = None, n_mags: int = 1,
             log_power: bool = False, tilt_limit_deg: float | None = None,
             accel_limit_mps2: float | None = None, truth_noise: bool = False) -> Simulation:
    """Simulate one recording (IMU stream `/imu/data`, magnetometer `/imu/mag`) with seeded truth.

    `truth` replaces the drawn calibration (its noise_std is still set from the rates). `effects` are injected
    (auxiliary channels join the recording); `noise_scale` multiplies every noise std (0: noise-free);
    `trajectory` (N+1, 3, 3) body->NED rotations at the IMU rate (the knots of the C1 truth) replaces the
    scenario's rotations and translation (then there is none). `power_profile` (physics.POWER_PROFILES)
    shapes the throttle and current of the power effects (default "flight"). `imu_sampling` says what an IMU
    sample stands for (INSTANT or PRECEDING, synth/sampling.py); `mag_phase_s` is the magnetometer's first
    stamp, 0 <= phase < 1/mag_rate (default: drawn from the seed in [0, min(5 ms, 1/mag_rate))).

    `vibration` (default: True for the multirotor's own flight, else False) draws the IMU noise at the rest
    level with the motors off and the flight level while they run (vibration.VIBRATION_STD, times
    noise_scale). `n_mags` magnetometers read the field (`/imu/mag`, `/imu/mag1`, ...; effects act on the first
    alone). `log_power` logs the power model's current, voltage and throttle without any magnetic term.
    `tilt_limit_deg` and `accel_limit_mps2` bound the multirotor's tilt and horizontal acceleration
    (scenarios.Limits; None, None: the original flight). `truth_noise` keeps a given `truth`'s own noise std
    (a vehicle file's truth, drawn as a vehicle's compass: synth/vehicle.py).
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
    limits = Limits(tilt_limit_deg, accel_limit_mps2)
    _check_options(scenario, n_mags, limits, trajectory)
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
    truth = drawn if truth is None else truth if truth_noise else replace(truth, noise_std=drawn.noise_std)
    made = _scenario(scenario, rng, rate, duration, trajectory, limits)
    t = imu_stamps(round(made.trajectory.end * rate), rate)     # the truth runs one IMU period past the last
    t_mag = mag_stamps(phase, mag_rate, float(t[-1]))
    vibrates = (scenario == "multirotor" and trajectory is None) if vibration is None else bool(vibration)
    motors = made.motors
    sd_g: float | FloatArray = truth.noise_std["gyroscope"]
    sd_a: float | FloatArray = truth.noise_std["accelerometer"]
    if vibrates:
        motors = motors_of(made.motors, [e.id for e in effects], log_power, float(t[-1]), scenario)
        rest, flight = levels(noise_scale)
        truth = replace(truth, noise_std=truth.noise_std | rest, noise_std_flight=truth.noise_std | flight)
        weight = motor_weight(t, motors)
        sd_g, sd_a = (imu_std(rest[k], flight[k], weight) for k in ("gyroscope", "accelerometer"))
    noise_g = sd_g * rng.standard_normal((len(t), 3))
    noise_a = sd_a * rng.standard_normal((len(t), 3))
    noise_m = truth.noise_std["magnetometer"] * rng.standard_normal((len(t_mag), 3))
    src = f"simulate:{scenario}:seed={seed}"
    done = inject(tuple(effects), Base(made.trajectory, t, t_mag, np.array([0.0, 0.0, G]), truth.m_n,
                                       truth.field_strength, seed, noise_scale, src, power_profile, made.motion,
                                       log_power))
    gyro, acc = sample_imu(done, t, rate, imu_sampling)
    gyro += truth.gyro_bias + noise_g
    acc += truth.accel_bias + noise_a
    del noise_g, noise_a                    # an hour at 400 Hz: 35 MB each, and the streams copy gyro and acc
    mag = done.field(t_mag) @ truth.D.T + truth.o + done.extra(t_mag) + noise_m
    more: tuple[tuple[Truth, ...], tuple[Stream, ...]] = ((), ())
    if n_mags > 1:
        m_b = np.einsum("nji,j->ni", made.trajectory.at(t_mag), truth.m_n)
        more = more_mags(scenario, seed, truth, n_mags, m_b, t_mag, src)
    window = None if imu_sampling is Sampling.INSTANT else 1.0 / rate
    streams = (
        Stream(Kind.ACCELEROMETER, "/imu/data", t, acc, f"{src}#/imu/data", "m/s^2", sampling=imu_sampling,
               window_s=window),
        Stream(Kind.GYROSCOPE, "/imu/data", t, gyro, f"{src}#/imu/data", "rad/s", sampling=imu_sampling,
               window_s=window),
        Stream(Kind.MAGNETOMETER, "/imu/mag", t_mag, mag, f"{src}#/imu/mag", "tesla"),
        *more[1],
        *done.streams,
    )
    del gyro, acc, mag
    rec = Recording(Path(f"{scenario}-{seed}.sim"), "simulation", streams, t0=T0_ROS)
    oversample = 1 if trajectory is not None else OVERSAMPLE
    return Simulation(rec, truth, made.trajectory.at(t), made.still, scenario, seed, done.effects, imu_sampling,
                      phase, oversample, made.trajectory, more[0], motors, vibrates)
