"""Synthetic recordings with known truth: the `paper` (Huang et al. 2025), `handheld`, `multirotor`, `rover` scenarios.

Truth and noise are drawn as in methods.md section 5 (the authors' simulate/simulate.m), in NED.
Gyro samples are exact constant-rate increments, y_g,k = Log(R_k^T R_k+1)/dt + b_g + noise, so they agree
with preintegration; accelerometers see y_a = R^T (a_n - g_n) + b_a + noise, with a_n = 0 (pure rotation) in
paper and handheld and the vehicle's own translation in multirotor and rover (synth_scenarios.py), which
then also log their GNSS position and list it as the nongravity_acceleration effect in the truth.
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
from .streams import Kind, Recording, Stream
from .synth_effects import EffectSpec
from .synth_inject import Base, InjectedEffect, inject, truth_entry
from .synth_physics import POWER_PROFILES, Motion
from .synth_scenarios import MIN_DURATION, min_jerk, multirotor, rover

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
#: a level ROS (FLU) body in NED: x north, y west, z up
FLU_LEVEL = np.diag([1.0, -1.0, -1.0])


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
    """A simulated recording, its truth, the true trajectory at the IMU epochs, the still intervals (s) and the
    injected effects (SI parameters)."""

    recording: Recording
    truth: Truth
    rotations: FloatArray
    still: tuple[tuple[float, float], ...]
    scenario: str
    seed: int
    effects: tuple[InjectedEffect, ...] = ()


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
                "mag_rate_hz": mag_sim.rate_hz, "still_intervals_s": [list(s) for s in sim.still]}
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


def paper_trajectory(rng: np.random.Generator, rate: float, duration: float | None) -> FloatArray:
    """Rotations at v + 0.05 randn(3) rad/s for 2 pi/|v| s each, v in 0.1 {x, y, z, x+y, x+z, y+z}, from I."""
    axes = 0.1 * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1]], dtype=float)
    spans = 2.0 * np.pi / np.linalg.norm(axes, axis=1)
    if duration is not None:
        spans = np.full(6, duration / 6.0)
    counts = np.ceil(spans * rate).astype(int)
    omega = np.repeat(axes, counts, axis=0) + 0.05 * rng.standard_normal((counts.sum(), 3))
    steps = so3.exp(omega / rate)
    return np.concatenate([np.eye(3)[None], so3.cumulative_product(steps)])


def _pose_with_up(up_body: FloatArray, yaw: float) -> FloatArray:
    """A body->NED rotation that maps the body vector `up_body` to up, then turned by `yaw` about down."""
    up = up_body / np.linalg.norm(up_body)
    axis = np.cross(up, [0.0, 0.0, -1.0])
    s, c = float(np.linalg.norm(axis)), float(-up[2])
    if s < 1e-9:
        align = np.eye(3) if c > 0 else so3.exp([np.pi, 0.0, 0.0])
    else:
        align = so3.exp(axis / s * np.arctan2(s, c))
    return so3.exp([0.0, 0.0, yaw]) @ align


def handheld_trajectory(rng: np.random.Generator, rate: float,
                        duration: float | None) -> tuple[FloatArray, tuple[tuple[float, float], ...]]:
    """10 s still, then moves about varying axes between >= 12 still poses of 2-4 s, then 10 s still.

    The poses point the body's up direction at the 6 faces and 8 corners of a cube (plus random ones),
    each with a random heading, in random order.
    """
    n_poses = 16 if duration is None else max(12, int((duration - 20.0) / 6.0))
    ups = np.concatenate([np.eye(3), -np.eye(3), np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T])
    extra = rng.standard_normal((max(0, n_poses - len(ups)), 3))
    ups = np.concatenate([ups, extra])[rng.permutation(max(n_poses, len(ups)))][:n_poses]
    start = FLU_LEVEL @ so3.exp([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    poses = [start] + [_pose_with_up(u_, rng.uniform(-np.pi, np.pi)) for u_ in ups] + [start]
    holds = [10.0] + list(rng.uniform(2.0, 4.0, n_poses)) + [10.0]
    pieces, still, t = [], [], 0.0
    for k, (pose, hold) in enumerate(zip(poses, holds, strict=True)):
        n = int(round(hold * rate))
        pieces.append(np.broadcast_to(pose, (n, 3, 3)))
        still.append((t, t + (n - 1) / rate))
        t += n / rate
        if k + 1 < len(poses):
            n_move = int(round(rng.uniform(2.0, 3.5) * rate))
            s = (np.arange(1, n_move + 1) / (n_move + 1))[:, None]
            phi = so3.log(pose.T @ poses[k + 1])
            wobble = rng.standard_normal(3) * 0.4
            pieces.append(pose @ so3.exp(min_jerk(s) * phi) @ so3.exp(np.sin(np.pi * min_jerk(s)) * wobble))
            t += n_move / rate
    return np.concatenate(pieces), tuple(still)


def _trajectory(scenario: str, rng: np.random.Generator, rate: float, duration: float | None,
                trajectory: FloatArray | None) -> tuple[FloatArray, Motion | None, tuple[tuple[float, float], ...]]:
    """Rotations (N+1, 3, 3), translation (None: pure rotation) and still intervals of the scenario or `trajectory`."""
    if trajectory is not None:
        rot = np.asarray(trajectory, dtype=np.float64)
        if rot.ndim != 3 or rot.shape[1:] != (3, 3) or len(rot) < 3:
            msg = f"simulate: trajectory must be (N+1, 3, 3) rotations with N >= 2, got {rot.shape}"
            raise MagcalError(msg)
        return rot, None, ()
    if scenario == "paper":
        return paper_trajectory(rng, rate, duration), None, ()
    if scenario == "handheld":
        rot, still = handheld_trajectory(rng, rate, duration)
        return rot, None, still
    length = DEFAULT_DURATION[scenario] if duration is None else duration
    if not length >= MIN_DURATION[scenario]:
        msg = (f"simulate: the {scenario} scenario needs --duration >= {MIN_DURATION[scenario]:g} s "
               f"(its still, start and stop phases alone take most of that), got {length:g}")
        raise MagcalError(msg)
    made = (multirotor if scenario == "multirotor" else rover)(rng, rate, length)
    return made.rotations, made.motion, made.still


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
             power_profile: str = "flight") -> Simulation:
    """Simulate one recording (IMU stream `/imu/data`, magnetometer `/imu/mag`) with seeded truth.

    `truth` replaces the drawn calibration (its noise_std is still set from the rates). `effects` are injected
    (auxiliary channels join the recording); `noise_scale` multiplies every noise std (0: noise-free);
    `trajectory` (N+1, 3, 3) body->NED rotations at the IMU rate replaces the scenario's rotations and
    translation (then there is none). `power_profile`
    (synth_physics.POWER_PROFILES) shapes the throttle and current of the power effects (default "flight").
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
    rate = rate or DEFAULT_RATES[scenario][0]
    mag_rate = mag_rate or min(DEFAULT_RATES[scenario][1], rate)
    ratio = rate / mag_rate
    if abs(ratio - round(ratio)) > 1e-9 or ratio < 1:
        msg = f"simulate: --rate {rate:g} must be a whole multiple of --mag-rate {mag_rate:g}"
        raise MagcalError(msg)
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
    rot, motion, still = _trajectory(scenario, rng, rate, duration, trajectory)
    n = rot.shape[0] - 1                    # gyro k covers [t_k, t_k+1], so keep N+1 rotations
    t = np.arange(n) / rate
    sd = truth.noise_std
    omega = so3.log(rot[:-1].transpose(0, 2, 1) @ rot[1:]) * rate
    noise_g = sd["gyroscope"] * rng.standard_normal((n, 3))
    knots, rot = rot, rot[:-1]
    force = -np.einsum("nji,j->ni", rot, np.array([0.0, 0.0, G]))
    noise_a = sd["accelerometer"] * rng.standard_normal((n, 3))
    step = int(round(ratio))
    m_n = truth.m_n
    mb = np.einsum("nji,j->ni", rot[::step], m_n)
    noise_m = sd["magnetometer"] * rng.standard_normal(mb.shape)
    src = f"simulate:{scenario}:seed={seed}"
    done = inject(tuple(effects), Base(knots, rate, step, m_n, truth.field_strength, seed, noise_scale, src,
                                       power_profile, motion), omega, force)
    gyro = done.omega + truth.gyro_bias
    gyro += noise_g
    acc = done.force + truth.accel_bias
    acc += noise_a
    mag = (mb if done.mag_body is None else done.mag_body) @ truth.D.T + truth.o
    if done.mag_extra is not None:
        mag = mag + done.mag_extra
    mag = mag + noise_m
    streams = (
        Stream(Kind.ACCELEROMETER, "/imu/data", t, acc, f"{src}#/imu/data", "m/s^2"),
        Stream(Kind.GYROSCOPE, "/imu/data", t, gyro, f"{src}#/imu/data", "rad/s"),
        Stream(Kind.MAGNETOMETER, "/imu/mag", t[::step], mag, f"{src}#/imu/mag", "tesla"),
        *done.streams,
    )
    rec = Recording(Path(f"{scenario}-{seed}.sim"), "simulation", streams, t0=T0_ROS)
    return Simulation(rec, truth, rot, still, scenario, seed, done.effects)
