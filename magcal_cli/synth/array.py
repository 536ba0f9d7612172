"""Several magnetometers on one IMU, simulated: Huang et al. 2025's board of 30 magnetometers (issue 14 item 3).

`simulate` draws one magnetometer; here the same IMU and trajectory carry `n_mags` of them, each with its own
soft iron, misalignment and hard iron drawn as `synth.truth.draw_truth` draws them (methods.md section 5), all
in the one field (the same dip and strength: they sit on one board) and with the simulation's magnetometer
noise, which `noise_factors` can raise per magnetometer (a bad compass). Readings come from their own
generator, so the IMU and the first magnetometer are exactly `simulate`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from magcal_cli.streams import FloatArray, Kind, Recording, Sampling
from magcal_cli.synth.simulate import Truth, at_home, draw_truth, simulate


@dataclass(frozen=True, eq=False)
class ArraySimulation:
    """A recording with one IMU (`/imu/data`) and magnetometers `/mag/0` ... `/mag/{n-1}` (all at the stamps of
    `simulate`'s magnetometer), the truth of each (same dip, declination and IMU biases; noise_std["magnetometer"]
    is that magnetometer's), the true rotations at the IMU stamps, the scenario and the seed."""

    recording: Recording
    truths: tuple[Truth, ...]
    rotations: FloatArray
    scenario: str
    seed: int


def mag_id(i: int) -> str:
    """The stream id of the i-th simulated magnetometer."""
    return f"/mag/{i}"


def simulate_array(scenario: str, seed: int, n_mags: int, rate: float | None = None, mag_rate: float | None = None,
                   duration: float | None = None, noise_factors: Sequence[float] = (),
                   imu_sampling: Sampling = Sampling.INSTANT, mag_phase_s: float | None = None) -> ArraySimulation:
    """`n_mags` magnetometers on the IMU of `simulate(scenario, seed, rate, mag_rate, duration, imu_sampling=...,
    mag_phase_s=...)`; magnetometer i's noise std is multiplied by noise_factors[i] (1 where not given)."""
    if n_mags < 1:
        msg = f"simulate_array: n_mags must be >= 1, got {n_mags}"
        raise ValueError(msg)
    sim = simulate(scenario, seed, rate, mag_rate, duration, imu_sampling=imu_sampling, mag_phase_s=mag_phase_s)
    base = sim.truth
    first = sim.recording.select(Kind.MAGNETOMETER)
    imu = [s for s in sim.recording.streams if s.kind is not Kind.MAGNETOMETER]
    assert sim.trajectory is not None                      # simulate always returns its continuous truth
    m_b = np.einsum("kji,j->ki", sim.trajectory.at(first.t), base.m_n)     # the field at the readings' own stamps
    rng = np.random.default_rng([seed, n_mags, 14])
    factors = [float(f) for f in noise_factors] + [1.0] * max(0, n_mags - len(noise_factors))
    sd = base.noise_std["magnetometer"]
    truths, streams = [], []
    for i in range(n_mags):
        if i == 0:
            d, o = base.D, base.o
            y = first.xyz + (factors[0] - 1.0) * (first.xyz - m_b @ d.T - o)      # simulate's own noise, scaled
        else:
            drawn = draw_truth(rng, 1.0, 1.0)
            # the board's field: simulate's strength (27 uT in `paper`, the World Magnetic Model's elsewhere)
            d, o = (drawn.D if scenario == "paper" else at_home(drawn).D), drawn.o
            y = m_b @ d.T + o + factors[i] * sd * rng.standard_normal(m_b.shape)
        truths.append(replace(base, D=d, o=o, noise_std=base.noise_std | {"magnetometer": factors[i] * sd}))
        streams.append(replace(first, id=mag_id(i), values=y, source=f"{first.source}#mag{i}"))
    rec = replace(sim.recording, streams=(*imu, *streams))
    return ArraySimulation(rec, tuple(truths), sim.rotations, scenario, seed)
