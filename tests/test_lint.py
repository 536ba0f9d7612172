"""The package passes ruff and mypy --strict (STYLE: CI runs tests, ruff and mypy)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(module: str, *args: str) -> subprocess.CompletedProcess[str]:
    if importlib.util.find_spec(module) is None:
        pytest.skip(f"{module} is not installed (pip install -e '.[test]' brings it)")
    return subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, capture_output=True, text=True,
                          check=False)


def test_ruff() -> None:
    """ruff with the rules in pyproject.toml over the package, tests and benchmarks."""
    out = _run("ruff", "check", "--output-format", "concise", "magcal_cli", "tests", "benchmarks")
    assert out.returncode == 0, out.stdout + out.stderr


def test_mypy_strict() -> None:
    """mypy --strict (pyproject.toml) over the package."""
    out = _run("mypy", "magcal_cli")
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr
