"""A field normalised to unit length upstream (issue 6): auto falls back to Kok 2012 and says so; MAP refuses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from click.testing import CliRunner

from magcal_cli.streams import Kind
from magcal_cli.synth.logs.csvfile import write_csv
from magcal_cli.synth.simulate import Simulation

from .test_robustness import edited, fit, one_error


def test_normalised_field(runner: CliRunner, tmp_path: Path, sim: Simulation) -> None:
    """A field normalised upstream: auto falls back to Kok 2012 (directions only) and says so; MAP refuses."""
    write_csv(edited(sim, Kind.MAGNETOMETER, lambda t, v: (t, v / np.linalg.norm(v, axis=1, keepdims=True) * 1e-6)),
              tmp_path / "n.csv")
    result = fit(runner, tmp_path / "n.csv", tmp_path / "o")
    assert result.exit_code == 0, result.stderr
    assert result.stdout.startswith("mag: kok2012, ")
    assert ("magcal: warning: mag: the field was normalised to unit length upstream, so auto chose Kok 2012 "
            "(directions only) over the joint MAP method (which needs the field's magnitude); only the misalignment "
            "and dip are meaningful") in result.stderr
    assert one_error(fit(runner, tmp_path / "n.csv", tmp_path / "o2", "--method", "map")) == (
        "n.csv: mag: the field was normalised to unit length upstream, so --method map cannot determine the "
        "calibration (it needs the raw field's magnitude); use --method kok2012 for the misalignment and dip only, "
        "or log the raw magnetometer readings")


def test_real_normalised_bag(runner: CliRunner, tmp_path: Path, realdata: Path) -> None:
    """ardrone_imu.bag logs a unit-vector field: auto runs Kok 2012 and says why (MAP stopped at the gyro bias)."""
    result = fit(runner, realdata / "ros" / "ardrone_imu.bag", tmp_path / "o")
    assert result.exit_code == 0, result.stderr
    assert "/ardrone/mag: the field was normalised to unit length upstream, so auto chose Kok 2012" in result.stderr
