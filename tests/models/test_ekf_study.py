"""benchmarks/paper_study.py: one command writes the comparison table, the raw numbers and the plots."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

STUDY = Path(__file__).resolve().parents[2] / "benchmarks" / "paper_study.py"


def test_study_writes_table_numbers_and_plots(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A reduced run (1 dataset of 30 s, two rates, two ratios, the two fast methods): the Markdown table has a
    row per configuration, method and the CRLB, the checks section, and both PNG figures exist."""
    spec = importlib.util.spec_from_file_location("paper_study", STUDY)
    assert spec is not None and spec.loader is not None
    study = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "paper_study", study)          # dataclasses look their module up there
    spec.loader.exec_module(study)
    md = study.main(["--datasets", "1", "--duration", "30", "--rates", "10,20", "--ratios", "1,2",
                     "--methods", "map,ekf-aug", "--out", str(tmp_path)])
    text = md.read_text()
    for row in ("| 10 | map |", "| 20 | ekf-aug |", "| 2 | crlb |", "## Checks", "lowest RMSE in o"):
        assert row in text, row
    data = json.loads((tmp_path / "paper_study.json").read_text())
    assert data["rate"]["x"] == [10.0, 20.0] and data["ratio"]["x"] == [1.0, 2.0]
    assert data["rate"]["cells"]["ekf-aug"][1]["rmse"]["D"] < 1e-6      # tesla: well under 1 uT
    for name in ("paper_study_rate.png", "paper_study_ratio.png"):
        assert (tmp_path / name).stat().st_size > 10_000
