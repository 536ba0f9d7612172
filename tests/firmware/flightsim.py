"""A simulated ArduPilot flight as a Recording, built in code with a known flown calibration (for check tests).

Slow full turns with +-20 deg of roll and pitch at 10 Hz; the compass sees y = D m + o + c I (body frame,
mGauss) and the vehicle flies with COMPASS_OFS/DIA/ODI that miss the truth, so the heading error it leaves
is known exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magcal_cli import so3
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Source
from magcal_cli.firmware.split import heading_errors_deg
from magcal_cli.streams import Kind, Recording, Sampling, Stream


@dataclass
class Flight:
    """The recording and its truth."""

    recording: Recording
    D: np.ndarray          # mGauss per unit field
    o: np.ndarray          # mGauss
    c: np.ndarray          # mGauss per ampere
    dip_deg: float
    current: np.ndarray    # A at the magnetometer samples
    M: np.ndarray          # the flown iron matrix
    ofs: np.ndarray        # the flown COMPASS_OFS

    def truth(self) -> Calibration:
        """The true calibration as a document (id MAG[0], milligauss, field strength |D| scale)."""
        F = float(np.cbrt(np.linalg.det(self.D)))
        mag = MagCalibration("MAG[0]", "milligauss", self.D, self.o, self.dip_deg, np.zeros((13, 13)), F)
        return Calibration(Source("sim.bin", "dataflash", "", 0.0, 1.0), "truth", ImuCalibration("IMU[0]"),
                           (mag,), "0", "2026-01-01T00:00:00Z")

    def heading_error_deg(self) -> float:
        """Worst level heading error (mean over headings removed) of the flown field, over the current range."""
        worst = 0.0
        for s in (self.current.min(), self.current.max()):
            e = heading_errors_deg(self.M @ self.D, self.M @ (self.o + self.ofs + self.c * s), self.dip_deg)
            worst = max(worst, float(np.max(np.abs(e - np.mean(e)))))
        return worst

    def interference_pct(self) -> float:
        """|M c| I_max as a share of the flown field's strength."""
        F = float(np.cbrt(np.linalg.det(self.M @ self.D)))
        return float(100 * np.linalg.norm(self.M @ self.c) * np.abs(self.current).max() / F)


def flight(seed: int = 0, n: int = 1500, rate: float = 10.0, dip_deg: float = 65.0, field: float = 550.0,
           tilt_deg: tuple[float, float] = (2.0, -3.0), ofs_miss: tuple[float, float, float] = (25.0, -15.0, 10.0),
           c: tuple[float, float, float] = (0.8, -0.4, 1.5), turns: float = 3.0, noise: float = 2.0,
           params: dict[str, float] | None = None) -> Flight:
    """Simulate the flight; `params` are added to the COMPASS_* set the vehicle flies with."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    yaw = 2 * np.pi * turns * t / t[-1] + 0.2 * np.sin(t / 7.0)
    roll = np.deg2rad(20) * np.sin(t / 5.0)
    pitch = np.deg2rad(20) * np.sin(t / 3.7 + 1.0)
    R = so3.from_rpy(np.stack([roll, pitch, yaw], axis=1))
    dip = np.deg2rad(dip_deg)
    m_b = np.einsum("nji,j->ni", R, [np.cos(dip), 0.0, np.sin(dip)])
    S = np.array([[0.03, 0.01, 0.005], [0.01, -0.02, -0.01], [0.005, -0.01, -0.01]])
    D = field * so3.exp(np.deg2rad([tilt_deg[0], tilt_deg[1], 0.0])) @ (np.eye(3) + S)
    o = np.array([120.0, -80.0, 60.0])
    cvec = np.asarray(c, dtype=float)
    current = 8.0 + 6.0 * np.sin(t / 11.0) ** 2
    raw = m_b @ D.T + o + current[:, None] * cvec + rng.normal(0.0, noise, (n, 3))
    M = np.array([[1.01, 0.004, -0.003], [0.004, 0.99, 0.002], [-0.003, 0.002, 1.0]])
    ofs = -o + np.asarray(ofs_miss)
    gyro = np.vstack([so3.log(np.swapaxes(R[:-1], 1, 2) @ R[1:]) * rate, np.zeros((1, 3))])
    streams = [
        Stream(Kind.MAGNETOMETER, "MAG[0]", t, raw * 1e-7, "sim#MAG", "milligauss"),
        Stream(Kind.ATTITUDE, "ATT", t, so3.as_quat(R), "sim#ATT", "quaternion wxyz"),
        Stream(Kind.BATTERY_CURRENT, "BAT[0]", t, current, "sim#BAT.Curr", "A"),
        Stream(Kind.ACCELEROMETER, "IMU[0]", t, np.einsum("nji,j->ni", R, [0, 0, -9.81]), "sim#IMU", "m/s^2"),
        Stream(Kind.GYROSCOPE, "IMU[0]", t, gyro, "sim#IMU", "rad/s", sampling=Sampling.FOLLOWING),  # R_k^T R_k+1
    ]
    p = {f"COMPASS_OFS_{a}": float(v) for a, v in zip("XYZ", ofs, strict=True)}
    p |= {f"COMPASS_DIA_{a}": float(M[i, i]) for i, a in enumerate("XYZ")}
    p |= {"COMPASS_ODI_X": M[0, 1], "COMPASS_ODI_Y": M[0, 2], "COMPASS_ODI_Z": M[1, 2], "COMPASS_MOTCT": 0.0,
          "COMPASS_USE": 1.0, "COMPASS_EXTERNAL": 1.0, "COMPASS_ORIENT": 0.0, "AHRS_ORIENTATION": 0.0}
    p |= params or {}
    rec = Recording(Path("sim.bin"), "dataflash", tuple(streams), 0.0, p)
    return Flight(rec, D, o, cvec, dip_deg, current, M, ofs)


#: the 3-compass flight of issue 38: hard iron of the uncalibrated compass (mG), a badly calibrated iron matrix (as
#: MAG[1]'s DIA2 in the real log: `dia3=BAD_DIA`), the default flown DIA3 (a few % off), and the per-compass
#: COMPASS_MOT (mG per A, MOTCT=2)
HARD_IRON_MG = (520.0, -410.0, 230.0)          # |o| = 700 mG
BAD_DIA = (1.24, 1.26, 0.63)
FLOWN_DIA3 = (1.04, 0.97, 1.03)
MOT_MG_PER_A = ((1.2, -0.8, 2.0), (-1.5, 1.0, 2.5), (0.9, 1.4, -1.8))
#: per-motor interference of MAG[1], MAG[2] relative to MAG[0]'s (the simulator's default c1..c4)
MOTOR_GAIN = {1: 4.0, 2: 3.0}
#: what a real flight has that the model does not: a disturbance of the internal compasses (mG RMS) that wanders
#: over DRIFT_TAU_S (s) and follows no logged channel, so their residuals are correlated in time and the sandwich
#: widens the data's information (issue 38's MAG[1]: D's uncertainty widened 81x)
DRIFT_MG, DRIFT_TAU_S = 15.0, 6.0


@dataclass(frozen=True)
class ThreeCompass:
    """The truth of `three_compass_flight`: per compass (MAG[0], MAG[1], MAG[2]) D and o in mG, the dip (deg),
    the still interval (s) and the heading the vehicle turned through (deg)."""

    D: tuple[np.ndarray, ...]
    o: tuple[np.ndarray, ...]
    dip_deg: float
    still: tuple[tuple[float, float], ...]
    yaw_deg: float
    tilt_deg: float


def _drift(rng: np.random.Generator, t: np.ndarray, std_mg: float, tau_s: float = DRIFT_TAU_S) -> np.ndarray:
    """(N, 3) tesla: a smooth disturbance of RMS `std_mg` that wanders on a timescale of `tau_s` (white noise
    through a Gaussian window), tied to no channel the log records."""
    if std_mg <= 0:
        return np.zeros((t.size, 3))
    grid = np.arange(t[0] - 3 * tau_s, t[-1] + 3 * tau_s, tau_s / 8)
    k = np.exp(-0.5 * (np.arange(-24, 25) / 8) ** 2)
    w = np.column_stack([np.convolve(rng.standard_normal(grid.size), k, "same") for _ in range(3)])
    w = w / np.sqrt(np.mean(w**2, axis=0))
    return np.column_stack([np.interp(t, grid, w[:, i]) for i in range(3)]) * std_mg * 1e-7


def three_compass_flight(tmp_path: Path, seed: int = 0, duration: float = 110.0, drift_mg: float = DRIFT_MG,
                         dia3: tuple[float, float, float] = FLOWN_DIA3,
                         firmware: tuple[int, int, int] = (3, 5, 5)) -> tuple[Path, ThreeCompass]:
    """An ArduCopter 3.5 DataFlash log of a quad (issue 38's 3-compass flight): 3 compasses, full yaw, tilt within
    16 deg, one still segment (on the pad before take-off; the log ends in the air), per-motor interference on
    MAG[0], COMPASS_MOTCT=2 motor offsets added before the iron matrix (3.5's order). MAG[0] flies with a good
    calibration; MAG[1] is uncalibrated onboard (OFS2 = 0, DIA2 = 1) with 700 mG of hard iron; MAG[2] flies with
    DIA3 = `dia3` and offsets near its 700 mG hard iron. MAG[1] and MAG[2] sit nearer the motors (MOTOR_GAIN) and
    carry a disturbance no logged channel explains (`drift_mg`, DRIFT_MG)."""
    from dataclasses import replace

    from magcal_cli.synth.effects import EffectSpec
    from magcal_cli.synth.firmware import CompassParams, PreviousCalibration
    from magcal_cli.synth.logs.dataflash import write_bin
    from magcal_cli.synth.scenarios import LANDED_S
    from magcal_cli.synth.simulate import simulate

    sim = simulate("multirotor", seed, rate=50.0, mag_rate=10.0, duration=duration, n_mags=3, tilt_limit_deg=16.0,
                   effects=(EffectSpec("motor_interference", {}),))
    end = duration - LANDED_S - 2.0                         # before the descent ends: the pad after it is cut off
    hard = np.array(HARD_IRON_MG) * 1e-7
    truths = list(sim.extra_truths)
    rec0 = sim.recording
    motors = [rec0.select(Kind.MOTOR_OUTPUT, f"motor[{i}]") for i in range(1, 5)]
    volts = rec0.select(Kind.BATTERY_VOLTAGE)
    streams = []
    for s in rec0.streams:
        if s.kind is Kind.MAGNETOMETER and s.id in ("/imu/mag1", "/imu/mag2"):
            k = int(s.id[-1])
            o = hard if k == 1 else hard[[1, 2, 0]] * np.array([-1.0, 1.0, -1.0])
            # the internal compasses sit nearer the motors: per-motor interference MOTOR_GAIN times MAG[0]'s
            u = np.column_stack([np.interp(s.t, m.t, m.values[:, 0]) for m in motors])
            x = u * np.interp(s.t, volts.t, volts.values[:, 0])[:, None]
            c = MOTOR_GAIN[k] * np.array([[3e-7, -1.5e-7, 2e-7], [-2.5e-7, 2e-7, 1e-7], [1e-7, 3e-7, -2e-7],
                                          [-2e-7, -2.5e-7, 2.5e-7]])[:, [k % 3, (k + 1) % 3, (k + 2) % 3]]
            s = replace(s, values=s.values - truths[k - 1].o + o + np.where(x > 0, np.abs(x) ** 0.65, 0.0) @ c
                        + _drift(np.random.default_rng([seed, 38, k]), s.t, drift_mg))
            truths[k - 1] = replace(truths[k - 1], o=o)
        streams.append(s.between(None, end))
    rec = replace(sim.recording, streams=tuple(streams))
    o2 = truths[1].o * 1e7
    prev = PreviousCalibration(
        mot=MOT_MG_PER_A[0], motct=2, current_swing_a=12.0, firmware=firmware,
        more=(CompassParams(ofs=(0.0, 0.0, 0.0), dia=(1.0, 1.0, 1.0), mot=MOT_MG_PER_A[1]),
              CompassParams(ofs=(-o2[0] + 30.0, -o2[1] - 20.0, -o2[2] + 40.0), dia=dia3,
                            odi=(0.02, -0.03, 0.01), mot=MOT_MG_PER_A[2])))
    sim = replace(sim, recording=rec, extra_truths=tuple(truths), previous=prev,
                  still=tuple(iv for iv in sim.still if iv[1] <= end))
    path = tmp_path / f"copter{firmware[0]}{firmware[1]}-{seed}.bin"
    write_bin(sim, path)
    R = sim.trajectory.at(rec.select(Kind.ACCELEROMETER).t) if sim.trajectory is not None else sim.rotations
    heading = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    tilt = np.degrees(np.arccos(np.clip(R[:, 2, 2], -1.0, 1.0)))
    return path, ThreeCompass(tuple(t.D * 1e7 for t in sim.truths), tuple(t.o * 1e7 for t in sim.truths),
                              float(np.degrees(sim.truth.dip)), sim.still, float(np.degrees(np.ptp(heading))),
                              float(tilt.max()))
