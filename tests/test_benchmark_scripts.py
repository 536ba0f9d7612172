"""Every script in benchmarks/ imports: three had named a module the house move emptied and failed at their first
line, unnoticed until one was run (issue 39)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.mark.parametrize("script", sorted(p.name for p in BENCH.glob("*.py")))
def test_benchmark_script_imports(script: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Loading the module (not running its main) resolves every import it makes."""
    monkeypatch.syspath_prepend(str(BENCH))
    name = f"_bench_{script[:-3]}"
    spec = importlib.util.spec_from_file_location(name, BENCH / script)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)          # dataclasses look their module up by name
    spec.loader.exec_module(module)
