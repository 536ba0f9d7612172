"""Shared fixtures: real logs from ../shared/realdata (skipped when absent) and the --update-golden switch."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
REALDATA = Path(os.environ.get("MAGCAL_REALDATA", ROOT.parent / "shared" / "realdata"))


def pytest_addoption(parser: pytest.Parser) -> None:
    """--update-golden rewrites golden files instead of comparing with them."""
    parser.addoption("--update-golden", action="store_true", help="Rewrite the golden files under tests/golden.")


@pytest.fixture
def update_golden(request: pytest.FixtureRequest) -> bool:
    """True when the run should rewrite golden files."""
    return bool(request.config.getoption("--update-golden"))


@pytest.fixture
def realdata() -> Path:
    """The folder of real third-party logs; tests using it skip when it is absent (e.g. on a bare clone)."""
    if not REALDATA.is_dir():
        pytest.skip(f"real logs not available at {REALDATA} (set MAGCAL_REALDATA to their folder)")
    return REALDATA
