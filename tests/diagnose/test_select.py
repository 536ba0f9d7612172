"""Why a candidate effect was rejected, in words that agree with its p-value (issue 30 item 4)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from magcal_cli.diagnose import select as select_module
from magcal_cli.diagnose.score import Score, Screen


def _select(monkeypatch: pytest.MonkeyPatch, p_values: dict[str, float]) -> dict[str, Any]:
    """`select` on a screen whose candidates have these p-values and no significant one: no fit runs."""
    scores = tuple(Score(eid, 1.0, 1.0, 3, p) for eid, p in p_values.items())
    monkeypatch.setattr(select_module, "screen", lambda *a, **k: Screen(scores, (), {}))
    problem = SimpleNamespace(imu_id="IMU[0]", where="log.bin")
    mag = SimpleNamespace(id="MAG[0]")
    base = SimpleNamespace(effects=())
    sel = select_module.select(problem, mag, base, tuple(p_values))  # type: ignore[arg-type]
    return {v.id: v for v in sel.verdicts}


def test_a_p_below_five_percent_is_not_called_no_sign(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 30: 'rejected; score test p = 0.032. the score test found no sign of it (p = 0.032)'. With three
    candidates Holm's first step needs p <= 0.017, so 0.032 is rejected as too weak once corrected for testing three
    effects at once; a p of 0.4 is no sign at all. The reason no longer repeats the p the report prints beside it."""
    verdicts = _select(monkeypatch, {"temperature_drift": 0.032, "current_interference": 0.4,
                                     "throttle_interference": 0.2})
    weak = verdicts["temperature_drift"]
    assert weak.status == "rejected" and weak.p_value == pytest.approx(0.032)
    assert "no sign" not in weak.reason and "p =" not in weak.reason
    assert weak.reason == "too weak once corrected for testing 3 effects at once (Holm's method, 5 % for all of them " \
                          "together)"
    assert verdicts["current_interference"].reason == "the score test found no sign of it"
    assert all(np.isfinite(v.p_value) for v in verdicts.values())
