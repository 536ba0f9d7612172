"""Simulated recordings for the joint MAP tests: any trajectory, magnetometer epochs between IMU samples."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magcal_cli import so3
from magcal_cli.config import Config
from magcal_cli.models.accel import G
from magcal_cli.models.problem import Problem
from magcal_cli.pipeline import select_problem
from magcal_cli.streams import Kind, Recording, Sampling, Stream
from magcal_cli.synth.simulate import Truth, draw_truth


def theta_of(truth: Truth) -> np.ndarray:
    """theta = (b_a, b_g, vec D, o, dip) of a truth (SI)."""
    return truth.theta


def record(rot: np.ndarray, rate: float, seed: int, mag_step: int = 1, mag_offset: float = 0.0,
           n_mags: int = 1) -> tuple[Problem, list[Truth], np.ndarray]:
    """IMU at `rate` along rotations rot (N+1, 3, 3) and magnetometers every `mag_step` samples, shifted by
    `mag_offset` sample periods (0 <= offset < 1; the rotation in between follows the constant-rate model the
    gyro measures). Returns the problem, each magnetometer's truth (IMU biases from the first) and the true
    rotations at the magnetometer epochs."""
    rng = np.random.default_rng(seed)
    truths = [draw_truth(rng, rate, rate / mag_step) for _ in range(n_mags)]
    first = truths[0]
    truths = [Truth(t.D, t.o, t.dip, first.accel_bias, first.gyro_bias, first.noise_std) for t in truths]
    tr = truths[0]
    sd = tr.noise_std
    n = rot.shape[0] - 1
    t = np.arange(n) / rate
    inc = so3.log(rot[:-1].transpose(0, 2, 1) @ rot[1:])
    gyro = inc * rate + tr.gyro_bias + sd["gyroscope"] * rng.standard_normal((n, 3))
    acc = -G * rot[:-1, 2, :] + tr.accel_bias + sd["accelerometer"] * rng.standard_normal((n, 3))
    idx = np.arange(0, n - 1, mag_step)
    r_m = rot[idx] @ so3.exp(mag_offset * inc[idx])
    # the gyro sample is the mean rate over [t_k, t_k+1) (the constant-rate model above): say so
    streams = [Stream(Kind.ACCELEROMETER, "imu", t, acc, "sim#imu", "m/s^2"),
               Stream(Kind.GYROSCOPE, "imu", t, gyro, "sim#imu", "rad/s", sampling=Sampling.FOLLOWING)]
    for i, m in enumerate(truths):
        m_n = np.array([np.cos(m.dip), 0.0, np.sin(m.dip)])
        noise = sd["magnetometer"] * rng.standard_normal((idx.size, 3))
        y = (r_m.transpose(0, 2, 1) @ m_n) @ m.D.T + m.o + noise
        t_mag = t[idx] + mag_offset / rate
        streams.append(Stream(Kind.MAGNETOMETER, f"mag{i}", t_mag, y, f"sim#mag{i}", "tesla"))
    rec = Recording(Path(f"sim-{seed}.sim"), "simulation", tuple(streams), t0=0.0)
    return select_problem(rec, Config()), truths, r_m


def noise_of(truth: Truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-axis true noise std: accelerometer, gyro, magnetometer."""
    sd = truth.noise_std
    return (np.full(3, sd["accelerometer"]), np.full(3, sd["gyroscope"]), np.full(3, sd["magnetometer"]))
