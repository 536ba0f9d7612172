"""The package passes ruff, mypy --strict, its import contract and the house rules (STYLE; issue 26)."""

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


def test_import_contract() -> None:
    """lint-imports: the layers and the no-circles contract of pyproject.toml (docs/architecture.md)."""
    if importlib.util.find_spec("importlinter") is None:
        pytest.skip("import-linter is not installed (pip install -e '.[test]' brings it)")
    code = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    out = subprocess.run([sys.executable, "-c", code, "--no-cache"], cwd=ROOT, capture_output=True, text=True,
                         check=False)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr


def test_house_rules() -> None:
    """benchmarks/house.py --check: module sizes, top-level count, one FloatArray, no circles or knots, no private
    name across modules, every module tested (its figures are printed with -s)."""
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "house.py"), "--check"], cwd=ROOT,
                         capture_output=True, text=True, check=False)
    print(out.stdout)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr
