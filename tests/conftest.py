"""Shared fixtures: real logs from ../shared/realdata (skipped when absent) and the --update-golden switch."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest
from click.testing import CliRunner

from magcal_cli.streams import Sampling
from magcal_cli.synth.simulate import Simulation, simulate

ROOT = Path(__file__).resolve().parents[1]
REALDATA = Path(os.environ.get("MAGCAL_REALDATA", ROOT.parent / "shared" / "realdata"))

# a suite started from a background job (`cmd &`, nohup) inherits SIGINT ignored, so the Ctrl-C tests' signals
# would never arrive: give each test process Python's own handler, as a terminal does (its children then start
# with the default disposition)
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_addoption(parser: pytest.Parser) -> None:
    """--update-golden rewrites golden files instead of comparing with them."""
    parser.addoption("--update-golden", action="store_true", help="Rewrite the golden files under tests/golden.")


@pytest.fixture
def update_golden(request: pytest.FixtureRequest) -> bool:
    """True when the run should rewrite golden files."""
    return bool(request.config.getoption("--update-golden"))


@pytest.fixture(scope="module")
def sim() -> Simulation:
    """A handheld simulation at 25 Hz IMU / 12.5 Hz field (about 90 s): accurate enough, fast to fit.

    Its IMU samples are instantaneous and its field is read on IMU stamps (phase 0: a CSV log has one row per IMU
    sample), so it writes to every format but .ulg (`sim_ulg`). Modules with a `sim` fixture of their own use theirs
    (pytest prefers the nearer definition)."""
    return simulate("handheld", 1, rate=25.0, mag_rate=12.5, mag_phase_s=0.0)


@pytest.fixture(scope="module")
def sim_ulg() -> Simulation:
    """`sim` with the IMU sampled as a .ulg holds it: each sample the mean over the period ending at its stamp."""
    return simulate("handheld", 1, rate=25.0, mag_rate=12.5, mag_phase_s=0.0, imu_sampling=Sampling.PRECEDING)


@pytest.fixture
def runner() -> CliRunner:
    """A click test runner (stdout and stderr kept apart)."""
    return CliRunner()


@pytest.fixture
def realdata() -> Path:
    """The folder of real third-party logs; tests using it skip when it is absent (e.g. on a bare clone)."""
    if not REALDATA.is_dir():
        pytest.skip(f"real logs not available at {REALDATA} (set MAGCAL_REALDATA to their folder)")
    return REALDATA
