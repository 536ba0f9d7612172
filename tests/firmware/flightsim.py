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
